use super::*;

use Action::*;

fn secs(s: u64) -> Duration {
    Duration::from_secs(s)
}

fn intensity(max_restarts: u32, period: u64) -> Intensity {
    Intensity {
        max_restarts,
        period: secs(period),
    }
}

/// A machine with children 0, 1, 2 of `restart`, all started at `at`.
fn three(machine: Machine<usize>, restart: RestartType, at: Instant) -> Machine<usize> {
    let mut machine = machine;
    for child in 0..3 {
        assert_eq!(
            machine.handle(Event::Added { child, restart }, at),
            [Start(child)]
        );
    }
    machine
}

fn failed<K>(child: K) -> Event<K> {
    Event::Exited {
        child,
        normally: false,
        why: "crashed".into(),
    }
}

fn ended<K>(child: K) -> Event<K> {
    Event::Exited {
        child,
        normally: true,
        why: "returned".into(),
    }
}

#[test]
fn one_for_one_restarts_only_the_failed_child() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::OneForOne, Intensity::default()),
        RestartType::Permanent,
        now,
    );
    assert_eq!(m.handle(failed(1), now), [Start(1)]);
}

#[test]
fn one_for_all_stops_the_others_last_first_and_starts_all_in_order() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::OneForAll, Intensity::default()),
        RestartType::Permanent,
        now,
    );
    assert_eq!(
        m.handle(failed(1), now),
        [Stop(vec![2, 0]), Start(0), Start(1), Start(2)]
    );
    assert_eq!(m.handle(Event::RestartDue { child: 1 }, now), [], "running");
}

#[test]
fn rest_for_one_restarts_the_failed_child_and_those_after_it() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::RestForOne, Intensity::default()),
        RestartType::Permanent,
        now,
    );
    assert_eq!(
        m.handle(failed(1), now),
        [Stop(vec![2]), Start(1), Start(2)]
    );
    assert_eq!(
        m.handle(failed(0), now),
        [Stop(vec![2, 1]), Start(0), Start(1), Start(2)]
    );
    assert_eq!(m.handle(failed(2), now), [Start(2)]);
}

#[test]
fn a_group_restart_leaves_done_children_alone() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::OneForAll, Intensity::default()),
        RestartType::Transient,
        now,
    );
    assert_eq!(m.handle(ended(0), now), [Done(0)]);
    assert_eq!(
        m.handle(failed(2), now),
        [Stop(vec![1]), Start(1), Start(2)]
    );
}

#[test]
fn restart_types_decide_whether_an_exit_is_restarted() {
    let now = Instant::now();
    let mut m = Machine::new(Strategy::OneForOne, Intensity::default());
    for (child, restart) in [
        ("permanent", RestartType::Permanent),
        ("transient", RestartType::Transient),
        ("temporary", RestartType::Temporary),
    ] {
        m.handle(Event::Added { child, restart }, now);
    }
    assert_eq!(m.handle(ended("permanent"), now), [Start("permanent")]);
    assert_eq!(m.handle(failed("permanent"), now), [Start("permanent")]);
    assert_eq!(m.handle(failed("transient"), now), [Start("transient")]);
    assert_eq!(m.handle(ended("transient"), now), [Done("transient")]);
    assert_eq!(m.handle(failed("temporary"), now), [Done("temporary")]);
    // Done children stay done.
    assert_eq!(m.handle(failed("temporary"), now), []);
    assert_eq!(m.len(), 3);
}

#[test]
fn past_the_whole_intensity_the_supervisor_gives_up_and_stops_the_rest() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::OneForOne, intensity(2, 60)),
        RestartType::Permanent,
        now,
    );
    assert_eq!(m.handle(failed(2), now), [Start(2)]);
    assert_eq!(m.handle(failed(0), now), [Start(0)]);
    let error = GaveUp {
        max_restarts: 2,
        period: secs(60),
        child: "2".into(),
        failure: "crashed".into(),
    };
    assert_eq!(
        m.handle(failed(2), now),
        [
            GiveUp {
                child: 2,
                error: error.clone()
            },
            Stop(vec![1, 0])
        ]
    );
    assert_eq!(
        error.to_string(),
        "more than 2 restarts within 60s (last failure: 2: crashed)"
    );
    assert_eq!(m.handle(failed(1), now), [], "nothing after giving up");
}

#[test]
fn restarts_outside_the_period_are_forgotten() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::OneForOne, intensity(1, 10)),
        RestartType::Permanent,
        now,
    );
    for s in [0, 11, 22, 33] {
        assert_eq!(m.handle(failed(0), now + secs(s)), [Start(0)]);
    }
}

#[test]
fn simple_one_for_one_with_intensity_per_child_gives_up_on_that_child_only() {
    let now = Instant::now();
    let mut m = Machine::new(Strategy::SimpleOneForOne, intensity(1, 60)).scope(Scope::PerChild);
    for child in ["o-1", "o-2"] {
        let restart = RestartType::Transient;
        assert_eq!(
            m.handle(Event::Added { child, restart }, now),
            [Start(child)]
        );
    }
    assert_eq!(m.handle(failed("o-1"), now), [Start("o-1")]);
    assert_eq!(
        m.handle(failed("o-2"), now),
        [Start("o-2")],
        "a window of its own"
    );
    let actions = m.handle(failed("o-1"), now);
    assert!(
        matches!(&actions[..], [GiveUp { child: "o-1", error }] if error.max_restarts == 1),
        "{actions:?}"
    );
    assert_eq!(m.len(), 1, "the order given up on is forgotten");
    assert_eq!(m.handle(ended("o-2"), now), [Done("o-2")]);
    assert!(m.is_empty(), "a dynamic child that is done is forgotten");
}

#[test]
fn a_backoff_pauses_restarts_and_starts_over_after_a_whole_period() {
    let ms = Duration::from_millis;
    let now = Instant::now();
    let mut m =
        Machine::new(Strategy::OneForOne, intensity(10, 5)).backoff(Backoff::new(ms(100), ms(300)));
    let restart = RestartType::Permanent;
    m.handle(Event::Added { child: 0, restart }, now);
    assert_eq!(m.handle(failed(0), now), [RestartAfter(0, ms(100))]);
    assert_eq!(m.handle(failed(0), now), [], "waiting: not running");
    assert_eq!(m.handle(Event::RestartDue { child: 0 }, now), [Start(0)]);
    assert_eq!(m.handle(Event::RestartDue { child: 0 }, now), [], "stale");
    assert_eq!(m.handle(failed(0), now), [RestartAfter(0, ms(200))]);
    // A start that fails pauses again, without counting against the intensity.
    let why = "no such file".to_string();
    assert_eq!(
        m.handle(Event::StartFailed { child: 0, why }, now),
        [RestartAfter(0, ms(300))]
    );
    let later = now + secs(1);
    assert_eq!(m.handle(Event::RestartDue { child: 0 }, later), [Start(0)]);
    // It ran for a whole period: its backoff starts over.
    let after_a_period = later + secs(5);
    assert_eq!(
        m.handle(failed(0), after_a_period),
        [RestartAfter(0, ms(100))]
    );
    assert_eq!(
        m.handle(Event::RestartDue { child: 0 }, after_a_period),
        [Start(0)]
    );
    assert_eq!(
        m.handle(failed(0), after_a_period),
        [RestartAfter(0, ms(200))]
    );
    // A successor took over: its backoff starts over too.
    m.handle(Event::RestartDue { child: 0 }, after_a_period);
    m.handle(
        Event::Replaced {
            child: 0,
            started_at: after_a_period,
        },
        after_a_period,
    );
    assert_eq!(
        m.handle(failed(0), after_a_period),
        [RestartAfter(0, ms(100))]
    );
}

#[test]
fn without_a_backoff_a_failed_start_is_a_failure() {
    let now = Instant::now();
    let mut m = Machine::new(Strategy::OneForOne, intensity(1, 60));
    let restart = RestartType::Permanent;
    m.handle(Event::Added { child: 0, restart }, now);
    let why = "cannot start".to_string();
    assert_eq!(
        m.handle(
            Event::StartFailed {
                child: 0,
                why: why.clone()
            },
            now
        ),
        [Start(0)]
    );
    let actions = m.handle(Event::StartFailed { child: 0, why }, now);
    assert!(
        matches!(&actions[..], [GiveUp { child: 0, .. }]),
        "{actions:?}"
    );
}

#[test]
fn a_removed_child_is_forgotten() {
    let now = Instant::now();
    let mut m = three(
        Machine::new(Strategy::OneForAll, Intensity::default()),
        RestartType::Permanent,
        now,
    );
    assert_eq!(m.handle(Event::Removed { child: 1 }, now), []);
    assert_eq!(m.handle(failed(1), now), []);
    assert_eq!(
        m.handle(failed(0), now),
        [Stop(vec![2]), Start(0), Start(2)]
    );
}

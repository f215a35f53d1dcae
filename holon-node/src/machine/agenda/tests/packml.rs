//! The PackML rows of the agenda's table: what Hold, Stop, Abort, a controller fault and
//! a long hold do to bookings and the running step.

use super::*;
use schemas::unix_ms;
use schemas::{PackmlCommand, PackmlRequest, Refusal};

fn command(m: &mut AgendaMachine, command: PackmlCommand) -> Vec<AgendaAction> {
    m.handle(
        AgendaEvent::Packml(PackmlRequest::command(command, "op")),
        unix_ms(),
    )
}

fn packml_reply(actions: &[AgendaAction]) -> &PackmlReply {
    match actions.first() {
        Some(AgendaAction::PackmlReply(r)) => r,
        other => panic!("expected a PackML reply first, got {other:?}"),
    }
}

/// The withdrawn results handed back, by conversation.
fn handed_back(actions: &[AgendaAction]) -> Vec<String> {
    actions
        .iter()
        .filter_map(|a| match a {
            AgendaAction::Deliver(r)
                if r.reason.as_ref().map(|r| r.as_str()) == Some("withdrawn") =>
            {
                Some(r.conversation_id.clone())
            }
            _ => None,
        })
        .collect()
}

/// robot1 running c1 with c2 and c3 booked.
fn busy_with_two_booked() -> AgendaMachine {
    let mut m = manager();
    for c in ["c1", "c2", "c3"] {
        assert_accepted(&m.handle(AgendaEvent::Request(book("o-1", c)), unix_ms()));
    }
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()));
    m
}

#[test]
fn hold_keeps_the_bookings_and_lets_the_running_step_finish() {
    let mut m = busy_with_two_booked();
    let actions = command(&mut m, PackmlCommand::Hold);
    assert_eq!(packml_reply(&actions).state, PackmlState::Holding);
    assert!(handed_back(&actions).is_empty());
    // No new work while holding: proposals and bookings are refused, naming the state.
    let proposal = m.handle(
        AgendaEvent::Request(msg(MessageType::ProposalReq, "o-2", "p")),
        unix_ms(),
    );
    let r = reply(&proposal);
    assert_eq!(r.reason.as_ref().map(|r| r.as_str()), Some("unavailable"));
    assert_eq!(r.info["packml_state"], 10);
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-2", "c9")), unix_ms()),
        "unavailable",
    );
    m.handle(done("c1"), unix_ms());
    assert_eq!(m.packml().state(), PackmlState::Held);
    // Held: the next booking does not start.
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-1", "c2")), unix_ms()),
        "unavailable",
    );
    assert_eq!(m.bookings().len(), 2);
    let actions = command(&mut m, PackmlCommand::Unhold);
    assert_eq!(packml_reply(&actions).state, PackmlState::Execute);
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c2")), unix_ms()));
}

#[test]
fn a_long_hold_hands_the_bookings_back() {
    let mut m = busy_with_two_booked();
    command(&mut m, PackmlCommand::Hold);
    m.handle(done("c1"), unix_ms());
    let since = m.packml().since();
    assert!(m.wants_tick());
    assert_eq!(m.handle(AgendaEvent::Tick, since + 29_000), vec![]);
    let actions = m.handle(AgendaEvent::Tick, since + 30_000);
    assert_eq!(handed_back(&actions), ["c2", "c3"]);
    assert!(m.bookings().is_empty());
    assert!(!m.wants_tick());
    assert_eq!(m.packml().state(), PackmlState::Held);
}

#[test]
fn stop_hands_every_booking_back_and_reset_start_bring_it_back() {
    let mut m = busy_with_two_booked();
    let actions = command(&mut m, PackmlCommand::Stop);
    assert_eq!(packml_reply(&actions).state, PackmlState::Stopping);
    assert_eq!(handed_back(&actions), ["c2", "c3"]);
    assert!(!actions.contains(&AgendaAction::Abort), "the step finishes");
    m.handle(done("c1"), unix_ms());
    assert_eq!(m.packml().state(), PackmlState::Stopped);
    command(&mut m, PackmlCommand::Reset);
    assert_eq!(m.packml().state(), PackmlState::Idle);
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-2", "c9")), unix_ms()),
        "unavailable",
    );
    command(&mut m, PackmlCommand::Start);
    assert_eq!(m.packml().state(), PackmlState::Execute);
    assert_accepted(&m.handle(AgendaEvent::Request(book("o-2", "c9")), unix_ms()));
}

#[test]
fn abort_aborts_the_running_step_and_hands_the_bookings_back() {
    let mut m = busy_with_two_booked();
    let actions = command(&mut m, PackmlCommand::Abort);
    assert_eq!(packml_reply(&actions).state, PackmlState::Aborting);
    assert!(actions.contains(&AgendaAction::Abort));
    assert_eq!(handed_back(&actions), ["c2", "c3"]);
    m.handle(
        AgendaEvent::ExecutionFinished {
            conversation_id: "c1".into(),
            outcome: Outcome::Failed {
                reason: "aborted".into(),
                detail: "aborted by an operator".into(),
            },
        },
        unix_ms(),
    );
    assert_eq!(m.packml().state(), PackmlState::Aborted);
    assert_eq!(m.packml().status().defective, 1);
    command(&mut m, PackmlCommand::Clear);
    assert_eq!(m.packml().state(), PackmlState::Stopped);
}

#[test]
fn abort_with_nothing_running_goes_straight_to_aborted() {
    let mut m = manager();
    let actions = command(&mut m, PackmlCommand::Abort);
    assert!(!actions.contains(&AgendaAction::Abort));
    assert_eq!(packml_reply(&actions).state, PackmlState::Aborted);
}

#[test]
fn a_controller_fault_aborts_and_hands_the_bookings_back() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    let actions = m.handle(
        AgendaEvent::ExecutionUnavailable(ControllerStatus::Estop, None),
        unix_ms(),
    );
    assert_eq!(handed_back(&actions), ["c1"]);
    assert_eq!(m.packml().state(), PackmlState::Aborted);
    // Ready again: still Aborted until an operator clears, resets and starts it.
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    assert_eq!(m.packml().state(), PackmlState::Aborted);
    assert!(!m.takes_work());
    for c in [
        PackmlCommand::Clear,
        PackmlCommand::Reset,
        PackmlCommand::Start,
    ] {
        command(&mut m, c);
    }
    assert!(m.takes_work());
}

#[test]
fn a_refused_command_names_the_state_and_changes_nothing() {
    let mut m = busy_with_two_booked();
    let before = m.record();
    let actions = command(&mut m, PackmlCommand::Unhold);
    let r = packml_reply(&actions);
    assert_eq!(
        r.refused,
        Some(Refusal::NotInState {
            command: PackmlCommand::Unhold,
            state: PackmlState::Execute
        })
    );
    assert_eq!(
        r.detail.as_deref(),
        Some("Unhold is not allowed in Execute")
    );
    assert_eq!(actions.len(), 1);
    assert_eq!(m.record(), before);
    let mode = m.handle(
        AgendaEvent::Packml(PackmlRequest::mode(UnitMode::Maintenance, "op")),
        unix_ms(),
    );
    assert!(packml_reply(&mode).refused.is_some());
}

#[test]
fn maintenance_mode_takes_no_orders() {
    let mut m = manager();
    command(&mut m, PackmlCommand::Stop);
    let actions = m.handle(
        AgendaEvent::Packml(PackmlRequest::mode(UnitMode::Maintenance, "op")),
        unix_ms(),
    );
    assert_eq!(packml_reply(&actions).mode, UnitMode::Maintenance);
    command(&mut m, PackmlCommand::Reset);
    command(&mut m, PackmlCommand::Start);
    assert_eq!(m.packml().state(), PackmlState::Execute);
    let refused = m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    assert_refused(&refused, "unavailable");
    assert!(reply(&refused).info["detail"]
        .as_str()
        .unwrap()
        .contains("Maintenance"));
}

#[test]
fn a_held_resource_comes_back_held_from_its_journal() {
    let mut m = busy_with_two_booked();
    command(&mut m, PackmlCommand::Hold);
    let record = m.record();
    let text = serde_json::to_string(&record).unwrap();
    let restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        serde_json::from_str(&text).unwrap(),
        Inheritance::Restarted,
        unix_ms(),
    )
    .with_packml(PackmlSettings::default());
    // The step ran at the crash: reported interrupted; Holding resumes as Held.
    assert_eq!(restored.packml().state(), PackmlState::Held);
    assert_eq!(restored.bookings().len(), 2);
    // A journal from before PackML: the settings' initial state.
    let old = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        AgendaRecord::default(),
        Inheritance::Restarted,
        unix_ms(),
    )
    .with_packml(PackmlSettings {
        initial_state: PackmlState::Idle,
        ..PackmlSettings::default()
    });
    assert_eq!(old.packml().state(), PackmlState::Idle);
}

/// robot1 stopped, put in Maintenance, reset and started: Execute in Maintenance.
fn in_maintenance() -> AgendaMachine {
    let mut m = manager();
    command(&mut m, PackmlCommand::Stop);
    m.handle(
        AgendaEvent::Packml(PackmlRequest::mode(UnitMode::Maintenance, "op")),
        unix_ms(),
    );
    command(&mut m, PackmlCommand::Reset);
    command(&mut m, PackmlCommand::Start);
    assert_eq!(m.packml().state(), PackmlState::Execute);
    m
}

fn operator_job(m: &mut AgendaMachine, info: Map<String, Value>) -> Vec<AgendaAction> {
    m.handle(
        AgendaEvent::Packml(PackmlRequest::job(
            schemas::packml::JobRequest {
                service_type: "pick_n_place".into(),
                info,
            },
            "alice",
        )),
        unix_ms(),
    )
}

#[test]
fn an_operator_runs_a_single_job_in_maintenance_and_it_goes_to_no_inbox() {
    let mut m = in_maintenance();
    let actions = operator_job(&mut m, poses());
    let reply = packml_reply(&actions);
    assert_eq!(reply.refused, None, "{reply:?}");
    assert_eq!(reply.job.as_deref(), Some("maintenance/1"));
    let Some(AgendaAction::Execute(job)) = actions.get(1) else {
        panic!("{actions:?}")
    };
    assert_eq!(job.operator.as_deref(), Some("alice"));
    assert_eq!(m.packml().status().operator_job.unwrap().outcome, None);
    // One at a time.
    let again = operator_job(&mut m, poses());
    assert!(
        matches!(&packml_reply(&again).refused, Some(Refusal::JobNotAllowed { why, .. }) if why.contains("a job runs")),
        "{again:?}"
    );
    let ended = m.handle(done("maintenance/1"), unix_ms());
    assert_eq!(ended, vec![AgendaAction::StateChanged], "no delivery");
    let status = m.packml().status();
    let job = status.operator_job.unwrap();
    assert!(job.done && job.outcome.unwrap().starts_with("done"));
    assert_eq!(status.processed, 0, "an operator's job is not production");
    assert!(m.undelivered().is_empty());
    assert_eq!(
        packml_reply(&operator_job(&mut m, poses())).job.as_deref(),
        Some("maintenance/2")
    );
}

#[test]
fn an_operator_job_is_refused_outside_maintenance_and_when_it_does_not_fit() {
    let mut m = manager();
    let refused = operator_job(&mut m, poses());
    assert!(
        matches!(
            &packml_reply(&refused).refused,
            Some(Refusal::JobNotAllowed {
                state: PackmlState::Execute,
                mode: UnitMode::Production,
                ..
            })
        ),
        "{refused:?}"
    );
    assert_eq!(refused.len(), 1, "nothing changed");
    let mut m = in_maintenance();
    let refused = operator_job(&mut m, Map::new());
    assert!(
        matches!(
            &packml_reply(&refused).refused,
            Some(Refusal::InvalidJob { .. })
        ),
        "{refused:?}"
    );
    assert!(m.current().is_none());
}

#[test]
fn an_operator_job_running_at_a_crash_is_reported_interrupted_not_delivered() {
    let mut m = in_maintenance();
    operator_job(&mut m, poses());
    let record = m.record();
    let restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        record,
        Inheritance::Restarted,
        unix_ms(),
    );
    assert!(restored.undelivered().is_empty());
    let job = restored.packml().status().operator_job.unwrap();
    assert!(!job.done);
    assert!(job.outcome.unwrap().contains("interrupted"));
}

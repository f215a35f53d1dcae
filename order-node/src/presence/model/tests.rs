use super::*;
use schemas::{BookingView, CurrentJobView};

fn robot() -> HolonId {
    HolonId::resource("robot1").unwrap()
}

fn published(length: usize, ready: bool) -> Option<Published> {
    Some(Published {
        length,
        held: 0,
        carriers_out: 0,
        ready,
    })
}

fn snapshot(state: &str, controller: &str, agenda: &[&str]) -> ResourceSnapshot {
    snapshot_of(&robot(), state, controller, agenda)
}

/// A snapshot of `resource` in `state` with its `controller`, its agenda the bookings
/// of these conversations (the presence's task tests publish it too).
pub(in crate::presence) fn snapshot_of(
    resource: &HolonId,
    state: &str,
    controller: &str,
    agenda: &[&str],
) -> ResourceSnapshot {
    ResourceSnapshot {
        state: serde_json::from_value(state.into()).expect("a resource state"),
        controller: serde_json::from_value(controller.into()).expect("a controller status"),
        agenda: agenda
            .iter()
            .map(|c| {
                BookingView::waiting(
                    HolonId::new(schemas::HolonKind::Order, "o-1").unwrap(),
                    c,
                    "pick_n_place",
                )
            })
            .collect(),
        current: None,
        services: vec!["pick_n_place".into()],
        ..ResourceSnapshot::blank(resource.clone())
    }
}

#[test]
fn a_free_resource_gives_the_turn_to_the_first_booking() {
    let (news, now) = read_state(
        published(2, true),
        &snapshot("free", "ready", &["a/1/1", "b/1/1"]),
    );
    assert_eq!(news.turn.as_deref(), Some("a/1/1"));
    assert!(!news.became_ready);
    assert_eq!(news.places_freed, 0);
    assert_eq!(now, published(2, true).unwrap());
}

#[test]
fn a_busy_or_empty_resource_gives_no_turn() {
    let (busy, _) = read_state(published(1, true), &snapshot("busy", "ready", &["a/1/1"]));
    assert_eq!(busy.turn, None);
    let (empty, _) = read_state(published(0, true), &snapshot("free", "ready", &[]));
    assert_eq!(empty.turn, None);
}

#[test]
fn bookings_leaving_the_agenda_free_places() {
    let (news, now) = read_state(published(3, true), &snapshot("busy", "ready", &["c/1/1"]));
    assert_eq!(news.places_freed, 2);
    assert_eq!(now, published(1, true).unwrap());
    let (grew, _) = read_state(
        published(1, true),
        &snapshot("busy", "ready", &["c/1/1", "d/1/1"]),
    );
    assert_eq!(grew.places_freed, 0);
}

#[test]
fn readiness_is_news_once() {
    let (first, now) = read_state(None, &snapshot("free", "ready", &[]));
    assert!(first.became_ready, "a resource seen ready the first time");
    let (again, _) = read_state(Some(now), &snapshot("free", "ready", &[]));
    assert!(!again.became_ready);
    let (fault, now) = read_state(Some(now), &snapshot("init", "fault", &[]));
    assert!(!fault.became_ready);
    assert_eq!(fault.turn, None);
    let (back, _) = read_state(Some(now), &snapshot("free", "ready", &[]));
    assert!(back.became_ready, "back from a fault");
}

#[test]
fn a_held_resource_gives_no_turn_and_its_unhold_is_news() {
    let mut held = snapshot("free", "ready", &["a/1/1"]);
    let mut unit = packml(schemas::PackmlState::Held);
    held.packml = Some(unit.clone());
    let (news, now) = read_state(published(1, true), &held);
    assert_eq!(news.turn, None, "nobody's turn on a held resource");
    assert!(!news.became_ready);
    unit.state = schemas::PackmlState::Execute;
    let mut back = snapshot("free", "ready", &["a/1/1"]);
    back.packml = Some(unit.clone());
    let (news, _) = read_state(Some(now), &back);
    assert_eq!(news.turn.as_deref(), Some("a/1/1"));
    assert!(news.became_ready, "the unhold is news");
    unit.mode = schemas::UnitMode::Maintenance;
    back.packml = Some(unit);
    let (news, _) = read_state(Some(now), &back);
    assert_eq!(news.turn, None, "maintenance takes no orders");
}

/// A resource's PackML figures in `state`, in Production.
fn packml(state: schemas::PackmlState) -> schemas::PackmlStatus {
    schemas::PackmlStatus {
        state,
        state_number: state.number(),
        state_requested: state,
        mode: schemas::UnitMode::Production,
        processed: 0,
        defective: 0,
        stop_reason: None,
        since: 0,
        cumulative_ms: Default::default(),
        commands: vec![],
        operator_job: None,
    }
}

#[test]
fn a_new_booking_counts_the_jobs_of_its_priority_or_higher_ahead() {
    let queue = PublishedQueue {
        running: true,
        waiting: vec![100, 100, 0, 0, -5],
    };
    assert_eq!(queue.ahead_of(0), 5, "behind the running job and c1..c4");
    assert_eq!(queue.ahead_of(100), 3);
    assert_eq!(queue.ahead_of(1000), 1);
    assert_eq!(queue.ahead_of(-1000), 6);
    assert_eq!(PublishedQueue::default().ahead_of(0), 0);
}

fn token(holon: &HolonId, alive: bool) -> Event {
    Event::Token {
        holon: holon.clone(),
        alive,
    }
}

#[test]
fn a_token_appears_once_and_vanishes() {
    let mut model = PresenceModel::default();
    let r = robot();
    assert_eq!(
        model.apply(token(&r, true)),
        vec![Notice::Appeared(r.clone())]
    );
    assert!(model.is_alive(&r));
    assert_eq!(model.apply(token(&r, true)), vec![], "a repeat is no news");
    let version = model.version();
    assert_eq!(
        model.apply(token(&r, false)),
        vec![Notice::Vanished {
            holon: r.clone(),
            handover: false
        }]
    );
    assert!(!model.is_alive(&r));
    assert!(model.version() > version, "orders read the change");
}

#[test]
fn a_resource_handed_over_vanishes_as_planned_until_it_is_back() {
    let mut model = PresenceModel::default();
    let r = robot();
    model.apply(token(&r, true));
    let mut leaving = snapshot("free", "ready", &[]);
    leaving.handing_over = true;
    model.apply(Event::Snapshot(Box::new(leaving)));
    assert!(model.handing_over().contains(&r));
    assert_eq!(
        model.apply(token(&r, false)),
        vec![Notice::Vanished {
            holon: r.clone(),
            handover: true
        }]
    );
    assert!(model.handing_over().contains(&r), "kept while it is away");
    assert_eq!(
        model.apply(token(&r, true)),
        vec![Notice::Appeared(r.clone())]
    );
    assert!(
        !model.handing_over().contains(&r),
        "back: the hand-over is over"
    );
}

#[test]
fn a_snapshot_gives_the_turn_readiness_and_freed_places() {
    let mut model = PresenceModel::default();
    let r = robot();
    let mut busy = snapshot("busy", "ready", &["b/1/1", "c/1/1"]);
    busy.current = Some(CurrentJobView {
        requester: HolonId::new(schemas::HolonKind::Order, "o-1").unwrap(),
        conversation_id: "a/1/1".into(),
        service_type: "pick_n_place".into(),
        step: None,
        program: None,
        started_at: None,
    });
    let notices = model.apply(Event::Snapshot(Box::new(busy)));
    assert_eq!(
        notices,
        vec![
            Notice::Turn {
                resource: r.clone(),
                turns: Turns {
                    turn: None,
                    running: Some("a/1/1".into()),
                    epoch: None,
                }
            },
            Notice::BecameReady(r.clone()),
        ]
    );
    assert_eq!(model.queues()[&r].ahead_of(0), 3);
    let notices = model.apply(Event::Snapshot(Box::new(snapshot(
        "free",
        "ready",
        &["c/1/1"],
    ))));
    assert_eq!(
        notices,
        vec![
            Notice::Turn {
                resource: r.clone(),
                turns: Turns {
                    turn: Some("c/1/1".into()),
                    running: None,
                    epoch: None,
                }
            },
            Notice::PlacesFreed {
                resource: r.clone(),
                places: 1
            },
        ]
    );
    let version = model.version();
    let again = model.apply(Event::Snapshot(Box::new(snapshot(
        "free",
        "ready",
        &["c/1/1"],
    ))));
    assert_eq!(
        again.len(),
        1,
        "a republished turn is told again: {again:?}"
    );
    assert_eq!(model.version(), version, "nothing orders read changed");
}

/// A carrier put back in service is room for a part waiting for a home, as a place
/// released is (docs/material-flow.md, "Carriers out of service").
#[test]
fn a_carrier_back_in_service_is_a_place_freed() {
    let mut free = snapshot("free", "ready", &[]);
    free.carriers_out = vec!["p3".into(), "p4".into()];
    let (news, now) = read_state(published(0, true), &free);
    assert_eq!(news.places_freed, 0, "a carrier taken out frees nothing");
    free.carriers_out = vec!["p4".into()];
    let (news, _) = read_state(Some(now), &free);
    assert_eq!(news.places_freed, 1, "p3 is back");
}

#[test]
fn a_query_of_the_tokens_makes_the_alive_set_what_it_found() {
    let mut model = PresenceModel::default();
    let (r1, r2, r3) = (
        HolonId::resource("r1").unwrap(),
        HolonId::resource("r2").unwrap(),
        HolonId::resource("r3").unwrap(),
    );
    model.apply(token(&r1, true));
    model.apply(token(&r2, true));
    let notices = model.apply(Event::Tokens(vec![r2.clone(), r3.clone()]));
    assert_eq!(
        notices,
        vec![
            Notice::Vanished {
                holon: r1.clone(),
                handover: false
            },
            Notice::Appeared(r3.clone()),
        ]
    );
    assert!(!model.is_alive(&r1) && model.is_alive(&r2) && model.is_alive(&r3));
}

#[test]
fn staff_come_and_go_once() {
    let mut model = PresenceModel::default();
    let (s1, s2) = (
        HolonId::new(schemas::HolonKind::Staff, "s1").unwrap(),
        HolonId::new(schemas::HolonKind::Staff, "s2").unwrap(),
    );
    let staff = |holon: &HolonId, alive| Event::Staff {
        holon: holon.clone(),
        alive,
    };
    assert_eq!(
        model.apply(staff(&s2, true)),
        vec![Notice::StaffChanged {
            holon: s2.clone(),
            alive: true
        }]
    );
    assert_eq!(model.apply(staff(&s2, true)), vec![]);
    model.apply(staff(&s1, true));
    assert_eq!(model.staff().first(), Some(&s1), "the first by name");
    assert_eq!(
        model.apply(Event::StaffTokens(vec![s2.clone()])),
        vec![Notice::StaffChanged {
            holon: s1.clone(),
            alive: false
        }]
    );
    assert_eq!(model.apply(staff(&s1, false)), vec![], "already gone");
    assert_eq!(model.staff().iter().collect::<Vec<_>>(), vec![&s2]);
}

#[test]
fn a_deposed_holders_state_is_not_read() {
    let mut model = PresenceModel::default();
    let r = robot();
    let of = |epoch: u64, agenda: &[&str]| {
        let mut s = snapshot("free", "ready", agenda);
        s.epoch = Some(epoch);
        Box::new(s)
    };
    // The holder at epoch 2 gives c the turn.
    let notices = model.apply(Event::Snapshot(of(2, &["c/1/1"])));
    assert!(
        matches!(&notices[0], Notice::Turn { turns, .. } if turns.turn.as_deref() == Some("c/1/1")),
        "{notices:?}"
    );
    let version = model.version();
    // The deposed holder of epoch 1, thawed, publishes its old agenda: not read.
    assert_eq!(model.apply(Event::Snapshot(of(1, &["b/1/1"]))), vec![]);
    assert_eq!(model.version(), version);
    assert_eq!(model.queues()[&r].waiting.len(), 1);
    // The holder goes on; a later holder (epoch 3) is read.
    assert!(!model.apply(Event::Snapshot(of(2, &[]))).is_empty());
    assert!(!model.apply(Event::Snapshot(of(3, &["d/1/1"]))).is_empty());
    assert_eq!(model.apply(Event::Snapshot(of(2, &[]))), vec![]);
}

#[test]
fn a_place_released_at_a_location_is_room_for_a_waiting_order() {
    let mut held = snapshot("free", "ready", &[]);
    held.places
        .insert("robot1.port".into(), vec!["o-1".into(), "o-2".into()]);
    let (news, before) = read_state(published(0, true), &held);
    assert_eq!(news.places_freed, 0);
    assert_eq!(before.held, 2);
    let mut released = snapshot("free", "ready", &[]);
    released
        .places
        .insert("robot1.port".into(), vec!["o-2".into()]);
    let (news, _) = read_state(Some(before), &released);
    assert_eq!(news.places_freed, 1, "one place released");
}

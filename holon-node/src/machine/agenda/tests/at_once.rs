//! A controller that runs several jobs at once (`[controller] jobs_at_once`): bookings
//! begin while there is room beside the running jobs, and each job ends on its own.

use super::*;
use schemas::unix_ms;

fn two_at_once() -> AgendaMachine {
    let mut m = AgendaMachine::new(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        8,
        unix_ms(),
    )
    .with_jobs_at_once(2);
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    m
}

#[test]
fn bookings_on_turn_begin_while_there_is_room_and_wait_when_there_is_none() {
    let mut m = two_at_once();
    let first = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    assert!(reply(&first).started());
    // One runs, one more may: still free, and the second begins beside the first.
    assert_eq!(m.state(), ResourceState::Free);
    let second = m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    assert!(reply(&second).started());
    assert_eq!(executed(&second), ["c2"]);
    assert_eq!(m.state(), ResourceState::Busy);
    let third = m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")), unix_ms());
    assert!(!reply(&third).started());
    assert_eq!(reply(&third).info["queue_position"], 2);
    // A start of a booking while both run is refused busy; the booking stays.
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-3", "c3")), unix_ms()),
        "busy",
    );
    // The second ends first: its result goes out and the third begins in its place.
    let actions = m.handle(done("c2"), unix_ms());
    assert!(matches!(actions[0], AgendaAction::Deliver(ref r) if r.conversation_id == "c2"));
    assert_eq!(executed(&actions), ["c3"]);
    let running: Vec<&str> = m
        .running()
        .iter()
        .map(|j| j.conversation_id.as_str())
        .collect();
    assert_eq!(running, ["c1", "c3"]);
    // The snapshot shows the first begun as current, the other beside it.
    let snapshot = m.snapshot();
    assert_eq!(snapshot.current.unwrap().conversation_id, "c1");
    assert_eq!(snapshot.more_running.len(), 1);
    assert_eq!(snapshot.more_running[0].conversation_id, "c3");
    // A repeated booking of a running job is told it began, and is not run again.
    let again = m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")), unix_ms());
    assert!(reply(&again).started());
    assert!(executed(&again).is_empty());
}

#[test]
fn the_controller_ready_again_begins_as_many_waiting_bookings_as_there_is_room_for() {
    let mut m = two_at_once();
    for (order, conversation) in [("o-1", "c1"), ("o-2", "c2"), ("o-3", "c3"), ("o-4", "c4")] {
        m.handle(
            AgendaEvent::Request(book_on_turn(order, conversation)),
            unix_ms(),
        );
    }
    assert_eq!(m.running().len(), 2);
    // The controller goes away: the execution ends both jobs; nothing begins.
    m.handle(
        AgendaEvent::ExecutionUnavailable(ControllerStatus::Disconnected, None),
        unix_ms(),
    );
    for conversation in ["c1", "c2"] {
        let failed = AgendaEvent::ExecutionFinished {
            conversation_id: conversation.into(),
            outcome: Outcome::Failed {
                reason: Reason::ControllerDisconnected,
                detail: "gone".into(),
            },
        };
        assert!(executed(&m.handle(failed, unix_ms())).is_empty());
    }
    assert_eq!(m.state(), ResourceState::Init);
    // Back: both waiting bookings begin in the one transition.
    let actions = m.handle(AgendaEvent::ExecutionReady, unix_ms());
    assert_eq!(executed(&actions), ["c3", "c4"]);
    assert_eq!(m.state(), ResourceState::Busy);
}

#[test]
fn a_proposal_counts_the_wait_on_the_first_lane_to_be_free() {
    let mut m = two_at_once();
    // Nothing runs: no wait.
    let ask = msg(MessageType::ProposalReq, "o-9", "p1").with_info(poses());
    let wait = |m: &mut AgendaMachine| {
        let actions = m.handle(AgendaEvent::Request(ask.clone()), unix_ms());
        reply(&actions).info["expected_wait_ms"].as_u64().unwrap()
    };
    assert_eq!(wait(&mut m), 0);
    let nominal = pick_n_place()
        .get("pick_n_place")
        .unwrap()
        .nominal_duration
        .as_millis() as u64;
    // One runs: the other lane is free, no wait.
    m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    assert_eq!(wait(&mut m), 0);
    // Both run: one job's time. A third waiting: still one (it takes the first free
    // lane, the new one the second).
    m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    assert_eq!(wait(&mut m), nominal);
    m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")), unix_ms());
    assert_eq!(wait(&mut m), nominal);
    m.handle(AgendaEvent::Request(book_on_turn("o-4", "c4")), unix_ms());
    assert_eq!(wait(&mut m), 2 * nominal);
}

#[test]
fn a_restart_reports_every_job_that_ran_interrupted() {
    let mut m = two_at_once();
    m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    let record = m.record();
    assert_eq!(record.more_running.len(), 1);
    assert!(m.keeps(&record));
    // Written and read back as the journal does.
    let written = serde_json::to_value(m.record_ref()).unwrap();
    assert_eq!(written, serde_json::to_value(&record).unwrap());
    let record: AgendaRecord = serde_json::from_value(written).unwrap();
    let restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        8,
        record,
        Inheritance::Restarted,
        unix_ms(),
    );
    let interrupted: Vec<(&str, Option<&str>)> = restored
        .undelivered()
        .iter()
        .map(|r| {
            (
                r.conversation_id.as_str(),
                r.reason.as_ref().map(|r| r.as_str()),
            )
        })
        .collect();
    assert_eq!(
        interrupted,
        [("c1", Some("interrupted")), ("c2", Some("interrupted"))]
    );
    assert!(restored.running().is_empty());
}

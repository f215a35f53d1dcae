//! The agenda restored from its journal: after a restart, and in a successor that was
//! handed the bookings over.

use super::*;
use schemas::unix_ms;

fn restored_with_bookings_on_turn(inheritance: Inheritance) -> (AgendaMachine, Vec<String>) {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")), unix_ms());
    let json = serde_json::to_string(&m.record()).unwrap();
    let mut restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        serde_json::from_str(&json).unwrap(),
        inheritance,
        unix_ms(),
    );
    let started = executed(&restored.handle(AgendaEvent::ExecutionReady, unix_ms()));
    (restored, started)
}

#[test]
fn bookings_handed_over_start_on_their_turn_in_the_successor() {
    let (_, started) = restored_with_bookings_on_turn(Inheritance::HandedOver);
    assert_eq!(started, ["c2"]);
}

#[test]
fn after_a_restart_a_booking_on_turn_waits_for_its_requesters_start() {
    let (mut m, started) = restored_with_bookings_on_turn(Inheritance::Restarted);
    assert!(started.is_empty(), "{started:?}");
    assert_eq!(m.state(), ResourceState::Free);
    // Its order gave up on it while the resource was away: the cancel is taken.
    let cancel = msg(MessageType::BookingCancel, "o-2", "c2");
    let actions = m.handle(AgendaEvent::Request(cancel), unix_ms());
    assert_accepted(&actions);
    assert!(executed(&actions).is_empty(), "{actions:?}");
    // The other order still holds its booking and asks to start.
    let actions = m.handle(AgendaEvent::Request(start("o-3", "c3")), unix_ms());
    assert_accepted(&actions);
    assert_eq!(executed(&actions), ["c3"]);
}

#[test]
fn restore_reports_the_interrupted_job_and_redelivers_results() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-3", "c3")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    m.handle(done("c1"), unix_ms());
    m.handle(AgendaEvent::Request(start("o-2", "c2")), unix_ms());
    let record = m.record();
    let json = serde_json::to_string(&record).unwrap();
    let record: AgendaRecord = serde_json::from_str(&json).unwrap();
    let restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        record,
        Inheritance::Restarted,
        unix_ms(),
    );
    assert_eq!(restored.bookings().len(), 1);
    assert_eq!(restored.bookings()[0].conversation_id, "c3");
    assert_eq!(
        restored.status(),
        Status::Init,
        "no job runs after a restart"
    );
    let delivered: Vec<(&str, MessageType, Option<&str>)> = restored
        .undelivered()
        .iter()
        .map(|s| {
            (
                s.conversation_id.as_str(),
                s.message_type,
                s.reason.as_ref().map(|r| r.as_str()),
            )
        })
        .collect();
    assert_eq!(
        delivered,
        vec![
            ("c1", MessageType::Done, None),
            ("c2", MessageType::Failed, Some("interrupted"))
        ]
    );
}

#[test]
fn a_journal_keeps_no_parameters_and_its_bookings_are_read_again_when_it_opens() {
    let (m, _) = restored_with_bookings_on_turn(Inheritance::HandedOver);
    let json = serde_json::to_value(m.record()).unwrap();
    // The journal's form is as before: a booking's info, not what was read from it.
    let booking = &json["bookings"][0];
    assert!(booking.get("parameters").is_none(), "{booking}");
    assert!(booking["info"]["pick"].is_object(), "{booking}");
    // Opened again, each booking has what its steps need, read from its info.
    let restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        serde_json::from_value(json).unwrap(),
        Inheritance::HandedOver,
        unix_ms(),
    );
    let parameters = restored.bookings()[0].parameters.as_ref().unwrap();
    assert_eq!(parameters.poses.len(), 2);
}

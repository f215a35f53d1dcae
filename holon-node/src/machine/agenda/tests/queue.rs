//! The waiting queue: the capacity, the expected wait in proposals, priorities and
//! the overtakes a waiting booking allows.

use super::*;
use schemas::unix_ms;

#[test]
fn the_agenda_has_a_capacity() {
    let mut m = manager();
    for i in 0..3 {
        assert_accepted(&m.handle(
            AgendaEvent::Request(book("o-1", &format!("c{i}"))),
            unix_ms(),
        ));
    }
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-1", "c3")), unix_ms()),
        "agenda_full",
    );
    let mut proposal = book("o-2", "p");
    proposal.message_type = MessageType::ProposalReq;
    let actions = m.handle(AgendaEvent::Request(proposal), unix_ms());
    assert_eq!(
        reply(&actions).reason.as_ref().map(|r| r.as_str()),
        Some("agenda_full")
    );
}

#[test]
fn proposals_report_the_expected_wait() {
    let mut m = manager();
    let mut proposal = book("o-9", "p1");
    proposal.message_type = MessageType::ProposalReq;
    let actions = m.handle(AgendaEvent::Request(proposal.clone()), unix_ms());
    let r = reply(&actions);
    assert_eq!(r.message_type, MessageType::Proposal);
    assert_eq!(r.result, Some(true));
    assert_eq!(r.info["expected_wait_ms"], 0);
    assert_eq!(r.info["state"], "free");
    assert_eq!(actions.len(), 1, "a proposal books nothing");
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    let actions = m.handle(AgendaEvent::Request(proposal.clone()), unix_ms());
    assert_eq!(reply(&actions).info["expected_wait_ms"], 2000);
    assert_eq!(reply(&actions).info["queue_position"], 2);
    m.handle(
        AgendaEvent::ExecutionUnavailable(ControllerStatus::Disconnected, None),
        unix_ms(),
    );
    let actions = m.handle(AgendaEvent::Request(proposal), unix_ms());
    assert_eq!(
        reply(&actions).reason.as_ref().map(|r| r.as_str()),
        Some("unavailable")
    );
}

/// A ready agenda of room for 16 bookings, running `c0` so the others wait.
fn busy_manager(max_overtakes: u32) -> AgendaMachine {
    let mut m = AgendaMachine::new(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        16,
        unix_ms(),
    )
    .with_max_overtakes(max_overtakes);
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    m.handle(AgendaEvent::Request(book("o-0", "c0")), unix_ms());
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-0", "c0")), unix_ms()));
    m
}

fn urgent(order: &str, conversation: &str, priority: i32) -> Service {
    book(order, conversation).with_urgency(priority, None)
}

fn waiting(m: &AgendaMachine) -> Vec<(&str, i32, u32)> {
    m.bookings()
        .iter()
        .map(|b| (b.conversation_id.as_str(), b.priority, b.overtaken))
        .collect()
}

#[test]
fn bookings_wait_by_priority_then_in_the_order_they_came() {
    let mut m = busy_manager(4);
    m.handle(AgendaEvent::Request(urgent("o-1", "c1", 0)), unix_ms());
    m.handle(AgendaEvent::Request(urgent("o-2", "c2", 0)), unix_ms());
    let rush = m.handle(AgendaEvent::Request(urgent("o-3", "c3", 100)), unix_ms());
    assert_accepted(&rush);
    assert_eq!(
        reply(&rush).info["queue_position"],
        2,
        "behind the running job only"
    );
    m.handle(AgendaEvent::Request(urgent("o-4", "c4", 100)), unix_ms());
    m.handle(AgendaEvent::Request(urgent("o-5", "c5", 50)), unix_ms());
    m.handle(AgendaEvent::Request(urgent("o-6", "c6", -5)), unix_ms());
    assert_eq!(
        waiting(&m),
        vec![
            ("c3", 100, 0),
            ("c4", 100, 0),
            ("c5", 50, 0),
            ("c1", 0, 3),
            ("c2", 0, 3),
            ("c6", -5, 0)
        ]
    );
    // A proposal says where a booking of its priority would stand: a rush order
    // waits for the running job and the two rush bookings only.
    let mut ask = urgent("o-9", "p1", 100);
    ask.message_type = MessageType::ProposalReq;
    let r = m.handle(AgendaEvent::Request(ask.clone()), unix_ms());
    assert_eq!(reply(&r).info["queue_position"], 3);
    assert_eq!(reply(&r).info["expected_wait_ms"], 3000);
    ask.info.remove(schemas::info_key::PRIORITY);
    let r = m.handle(AgendaEvent::Request(ask), unix_ms());
    assert_eq!(
        reply(&r).info["queue_position"],
        6,
        "priority 0 waits behind c2"
    );
    // The snapshot shows each booking's priority and how often it was passed.
    let view = m.snapshot();
    assert_eq!(view.agenda[3].priority, 0);
    assert_eq!(view.agenda[3].overtaken, 3);
    assert_eq!(view.agenda[0].priority, 100);
}

#[test]
fn a_waiting_booking_is_passed_at_most_max_overtakes_times() {
    let mut m = busy_manager(2);
    m.handle(AgendaEvent::Request(urgent("o-1", "c1", 0)), unix_ms());
    for (order, conversation) in [("o-2", "c2"), ("o-3", "c3"), ("o-4", "c4")] {
        m.handle(
            AgendaEvent::Request(urgent(order, conversation, 10)),
            unix_ms(),
        );
    }
    // c2 and c3 passed c1; c4 may not (c1 was passed twice), nor can anything later.
    assert_eq!(
        waiting(&m),
        vec![("c2", 10, 0), ("c3", 10, 0), ("c1", 0, 2), ("c4", 10, 0)]
    );
    m.handle(AgendaEvent::Request(urgent("o-5", "c5", 1000)), unix_ms());
    assert_eq!(
        waiting(&m)[2..],
        [("c1", 0, 2), ("c5", 1000, 0), ("c4", 10, 1)],
        "the bound holds for every priority"
    );
    // With no overtakes allowed, bookings wait in the order they came.
    let mut fifo = busy_manager(0);
    fifo.handle(AgendaEvent::Request(urgent("o-1", "c1", -1000)), unix_ms());
    fifo.handle(AgendaEvent::Request(urgent("o-2", "c2", 1000)), unix_ms());
    assert_eq!(waiting(&fifo), vec![("c1", -1000, 0), ("c2", 1000, 0)]);
}

#[test]
fn a_priority_or_due_time_that_is_not_one_is_refused_and_changes_nothing() {
    let mut m = busy_manager(4);
    for (key, bad) in [
        (schemas::info_key::PRIORITY, json!("high")),
        (schemas::info_key::PRIORITY, json!(1001)),
        (schemas::info_key::PRIORITY, json!(1.5)),
        (schemas::info_key::DUE, json!(-1)),
        (schemas::info_key::DUE, json!("tomorrow")),
    ] {
        let mut request = book("o-1", "c1");
        request.info.insert(key.into(), bad.clone());
        let actions = m.handle(AgendaEvent::Request(request.clone()), unix_ms());
        assert_refused(&actions, "invalid_info");
        let detail = reply(&actions).info["detail"].as_str().unwrap().to_string();
        assert!(detail.contains(key), "{bad}: {detail}");
        if key == schemas::info_key::PRIORITY {
            request.message_type = MessageType::ProposalReq;
            assert_refused(
                &m.handle(AgendaEvent::Request(request), unix_ms()),
                "invalid_info",
            );
        }
    }
    assert!(m.bookings().is_empty());
    let ok = m.handle(
        AgendaEvent::Request(book("o-1", "c1").with_urgency(-1000, Some(1_700_000_000_000))),
        unix_ms(),
    );
    assert_accepted(&ok);
    assert_eq!(m.bookings()[0].due, Some(1_700_000_000_000));
}

#[test]
fn a_booking_journalled_before_priorities_reads_as_priority_zero() {
    let old = json!({"requester": "order/o-1", "conversation_id": "c1",
        "service_type": "pick_n_place", "reply_to": INBOX, "info": {}});
    let booking: Booking = serde_json::from_value(old).unwrap();
    assert_eq!(
        (booking.priority, booking.due, booking.overtaken),
        (0, None, 0)
    );
}

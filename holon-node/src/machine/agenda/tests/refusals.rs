//! What the agenda refuses, and in which order: proposals against the tables, a booking
//! for the running conversation, repeated withdrawals and acknowledgements, requests that
//! are not the agenda's.

use super::*;
use schemas::unix_ms;

fn proposal_req(order: &str, service_type: &str) -> Service {
    Service::request(
        MessageType::ProposalReq,
        service_type,
        "c0",
        HolonId::order(order).unwrap(),
    )
}

#[test]
fn proposal_refusals_come_in_the_tables_order() {
    let mut m = AgendaMachine::new(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        1,
        unix_ms(),
    );
    // Not offered beats unavailable.
    let r = m.handle(AgendaEvent::Request(proposal_req("o-1", "weld")), unix_ms());
    assert_eq!(
        reply(&r).reason.as_ref().map(|r| r.as_str()),
        Some("unknown_service")
    );
    let r = m.handle(
        AgendaEvent::Request(proposal_req("o-1", "pick_n_place")),
        unix_ms(),
    );
    assert_eq!(
        reply(&r).reason.as_ref().map(|r| r.as_str()),
        Some("unavailable")
    );
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    let r = m.handle(
        AgendaEvent::Request(proposal_req("o-2", "pick_n_place")),
        unix_ms(),
    );
    assert_eq!(
        reply(&r).reason.as_ref().map(|r| r.as_str()),
        Some("agenda_full")
    );
    assert_eq!(reply(&r).message_type, MessageType::Proposal);
    // A proposal changes nothing.
    assert_eq!(r.len(), 1);
}

#[test]
fn a_booking_request_for_the_running_conversation_is_refused_busy() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms()),
        "busy",
    );
}

#[test]
fn a_repeated_withdraw_and_an_unknown_acknowledgement_change_nothing() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    assert!(!m.handle(AgendaEvent::Withdraw, unix_ms()).is_empty());
    assert_eq!(m.handle(AgendaEvent::Withdraw, unix_ms()), vec![]);
    assert_eq!(
        m.handle(
            AgendaEvent::ResultAcknowledged {
                conversation_id: "nobody".into()
            },
            unix_ms()
        ),
        vec![]
    );
    assert_eq!(
        m.handle(
            AgendaEvent::RequesterGone {
                requester: HolonId::order("o-9").unwrap()
            },
            unix_ms()
        ),
        vec![]
    );
}

#[test]
fn requests_that_are_not_for_the_agenda_are_refused() {
    let mut m = manager();
    for kind in [
        MessageType::Status,
        MessageType::Done,
        MessageType::Proposal,
    ] {
        assert_refused(
            &m.handle(AgendaEvent::Request(msg(kind, "o-1", "c1")), unix_ms()),
            "unknown_service",
        );
    }
}

//! Bookings that start on their turn: at once on a free resource, after the running
//! job, never passing one that waits for its start, and never while withdrawing.

use super::*;
use schemas::unix_ms;

#[test]
fn a_booking_on_turn_starts_at_once_on_a_free_resource() {
    let mut m = manager();
    let actions = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    assert_accepted(&actions);
    assert!(reply(&actions).started(), "{actions:?}");
    assert_eq!(executed(&actions), ["c1"]);
    assert_eq!(actions.last(), Some(&AgendaAction::StateChanged));
    assert!(
        matches!(m.status(), Status::Busy(ref j) if j.conversation_id == "c1" && j.reply_to == INBOX)
    );
    assert!(m.bookings().is_empty());
    // Asked again (a lost reply): begun, not begun twice.
    let again = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    assert!(reply(&again).started());
    assert_eq!(again.len(), 1, "{again:?}");
    // A start (the order's fallback) finds it running.
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()));
    // Finished, its result not yet acknowledged: still begun, never run again.
    m.handle(done("c1"), unix_ms());
    let after = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    assert!(reply(&after).started());
    assert!(executed(&after).is_empty());
    assert!(m.bookings().is_empty());
}

#[test]
fn a_booking_on_turn_waits_for_the_running_job_and_starts_when_it_ends() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    let second = m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    assert_accepted(&second);
    assert!(!reply(&second).started());
    assert_eq!(reply(&second).info["queue_position"], 2);
    let third = m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")), unix_ms());
    assert_eq!(reply(&third).info["queue_position"], 3);
    // The first ends: its result goes out and the next starts, in one transition.
    let actions = m.handle(done("c1"), unix_ms());
    assert!(matches!(actions[0], AgendaAction::Deliver(ref r) if r.conversation_id == "c1"));
    assert_eq!(executed(&actions), ["c2"]);
    assert_eq!(m.bookings().len(), 1);
    // Not while the controller is away; again when it is back.
    m.handle(
        AgendaEvent::ExecutionUnavailable(ControllerStatus::Disconnected, None),
        unix_ms(),
    );
    assert!(executed(&m.handle(done("c2"), unix_ms())).is_empty());
    assert_eq!(m.status(), Status::Init);
    assert_eq!(
        executed(&m.handle(AgendaEvent::ExecutionReady, unix_ms())),
        ["c3"]
    );
}

#[test]
fn a_booking_on_turn_does_not_pass_one_that_waits_for_its_start() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    let actions = m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    assert!(!reply(&actions).started());
    assert!(executed(&actions).is_empty());
    // The booking ahead is cancelled: the one on turn is first, and starts.
    let actions = m.handle(
        AgendaEvent::Request(msg(MessageType::BookingCancel, "o-1", "c1")),
        unix_ms(),
    );
    assert_accepted(&actions);
    assert_eq!(executed(&actions), ["c2"]);
}

#[test]
fn a_booking_on_turn_without_what_its_start_needs_is_refused() {
    let mut m = manager();
    let no_poses = book("o-1", "c1").with_start_on_turn();
    assert_refused(
        &m.handle(AgendaEvent::Request(no_poses), unix_ms()),
        Reason::InvalidInfo,
    );
    let mut no_reply_to = book_on_turn("o-1", "c1");
    no_reply_to.reply_to = None;
    assert_refused(
        &m.handle(AgendaEvent::Request(no_reply_to), unix_ms()),
        Reason::InvalidInfo,
    );
    assert!(m.bookings().is_empty());
    assert_eq!(m.status(), Status::Free);
}

#[test]
fn a_withdrawing_resource_starts_nothing_on_its_turn() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")), unix_ms());
    m.handle(AgendaEvent::Withdraw, unix_ms());
    assert!(executed(&m.handle(done("c1"), unix_ms())).is_empty());
    assert_eq!(m.status(), Status::Free);
}

//! Requests of an order-node on etcd carry its epoch: a booking keeps the highest it
//! was asked at, and a request of a lower one (a deposed holder) changes nothing.

use super::*;
use schemas::unix_ms;

fn at(request: Service, epoch: u64) -> Service {
    request.with_epoch(Some(epoch))
}

#[test]
fn a_request_of_a_lower_epoch_than_its_booking_is_refused_stale_and_changes_nothing() {
    let mut m = manager();
    assert_accepted(&m.handle(AgendaEvent::Request(at(book("o-1", "c1"), 2)), unix_ms()));
    assert_eq!(m.bookings[0].requester_epoch, Some(2));
    // The deposed holder (epoch 1) can neither start nor cancel it.
    assert_refused(
        &m.handle(AgendaEvent::Request(at(start("o-1", "c1"), 1)), unix_ms()),
        "stale_epoch",
    );
    let cancel = msg(MessageType::BookingCancel, "o-1", "c1");
    assert_refused(
        &m.handle(AgendaEvent::Request(at(cancel.clone(), 1)), unix_ms()),
        "stale_epoch",
    );
    assert_refused(
        &m.handle(AgendaEvent::Request(at(book("o-1", "c1"), 1)), unix_ms()),
        "stale_epoch",
    );
    assert_eq!(m.bookings.len(), 1);
    assert!(m.current().is_none());
    // A newer holder books again (idempotent): the booking keeps its epoch, and that
    // change is journalled.
    let again = m.handle(AgendaEvent::Request(at(book("o-1", "c1"), 3)), unix_ms());
    assert_accepted(&again);
    assert!(again.contains(&AgendaAction::StateChanged), "{again:?}");
    assert_eq!(m.bookings[0].requester_epoch, Some(3));
    // The same epoch again is no change.
    let same = m.handle(AgendaEvent::Request(at(book("o-1", "c1"), 3)), unix_ms());
    assert_eq!(same.len(), 1, "{same:?}");
    assert_refused(
        &m.handle(AgendaEvent::Request(at(cancel, 2)), unix_ms()),
        "stale_epoch",
    );
    // The holder's start carries only its epoch: it runs with the booking's info.
    let booked_with_poses = at(book("o-2", "c2"), 3).with_info(poses());
    let booked_with_poses = at(booked_with_poses, 3);
    assert_accepted(&m.handle(AgendaEvent::Request(booked_with_poses), unix_ms()));
    let started = m.handle(AgendaEvent::Request(at(start("o-1", "c1"), 3)), unix_ms());
    assert_accepted(&started);
    let bare = at(msg(MessageType::Start, "o-2", "c2"), 3);
    assert!(!bare.has_service_data());
    assert_refused(&m.handle(AgendaEvent::Request(bare), unix_ms()), "busy");
}

#[test]
fn requests_without_an_epoch_are_not_fenced() {
    // A SQLite order-node says no epoch: nothing is compared.
    let mut m = manager();
    assert_accepted(&m.handle(AgendaEvent::Request(at(book("o-1", "c1"), 2)), unix_ms()));
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()));
    // Booked with its poses and no epoch; a start that carries only an epoch runs
    // with the booking's poses.
    let mut n = manager();
    let booked = book("o-1", "c1").with_info(poses());
    assert_accepted(&n.handle(AgendaEvent::Request(booked), unix_ms()));
    assert_eq!(n.bookings[0].requester_epoch, None);
    let bare = at(msg(MessageType::Start, "o-1", "c1"), 1);
    let started = n.handle(AgendaEvent::Request(bare), unix_ms());
    assert_accepted(&started);
    assert!(n.current().is_some());
}

#[test]
fn an_epoch_that_is_not_a_whole_number_is_invalid_info() {
    let mut m = manager();
    let mut request = book("o-1", "c1");
    request
        .info
        .insert(schemas::info_key::EPOCH.into(), json!("two"));
    assert_refused(
        &m.handle(AgendaEvent::Request(request), unix_ms()),
        "invalid_info",
    );
    assert!(m.bookings.is_empty());
}

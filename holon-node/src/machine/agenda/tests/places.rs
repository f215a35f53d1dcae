//! Places at a resource's own locations: reserved by a booking of `place`, released by
//! its cancel; physical, so they outlast withdrawals, absences and restarts.

use super::*;
use schemas::unix_ms;

/// robot1 with one port of capacity 1.
fn station() -> AgendaMachine {
    let part = schemas::layout::part_from_toml(
        "robot1",
        "[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ncapacity = 1\ndock = \"conveyor1.s1\"\n",
    )
    .unwrap();
    manager().with_locations(Some(&part))
}

fn place(kind: MessageType, order: &str, location: &str) -> Service {
    let info = json!({"part": order, "location": location});
    Service::request(
        kind,
        schemas::PLACE_SERVICE,
        &format!("{order}/place/{location}"),
        HolonId::order(order).unwrap(),
    )
    .with_info(info.as_object().unwrap().clone())
}

#[test]
fn a_place_is_held_for_one_part_until_its_requester_releases_it() {
    let mut m = station();
    let held = m.handle(
        AgendaEvent::Request(place(MessageType::BookingReq, "o-1", "robot1.port")),
        unix_ms(),
    );
    assert_accepted(&held);
    assert!(
        held.contains(&AgendaAction::StateChanged),
        "journalled: {held:?}"
    );
    // Asked again (a lost reply): the same place, no second one.
    let again = m.handle(
        AgendaEvent::Request(place(MessageType::BookingReq, "o-1", "robot1.port")),
        unix_ms(),
    );
    assert_eq!(again.len(), 1, "{again:?}");
    assert_accepted(&again);
    // Full: another part is refused, told who holds it; the agenda is not touched.
    let refused = m.handle(
        AgendaEvent::Request(place(MessageType::BookingReq, "o-2", "robot1.port")),
        unix_ms(),
    );
    assert_refused(&refused, "no_place");
    let detail = reply(&refused).info["detail"].as_str().unwrap().to_string();
    assert!(
        detail.contains("robot1.port is full") && detail.contains("o-1"),
        "{detail}"
    );
    assert!(m.bookings().is_empty(), "a place is not a booking");
    assert_eq!(m.snapshot().places["robot1.port"], ["o-1"]);

    // A withdrawal hands bookings back, not places: the part is physically there.
    m.handle(AgendaEvent::Withdraw, unix_ms());
    let record = m.record();
    assert_eq!(record.places[&id("robot1.port")].len(), 1, "{record:?}");
    let restored = AgendaMachine::restore(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        record,
        Inheritance::Restarted,
        unix_ms(),
    );
    let mut m = restored.with_locations(Some(
        &schemas::layout::part_from_toml(
            "robot1",
            "[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"conveyor1.s1\"\n",
        )
        .unwrap(),
    ));
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    assert_eq!(
        m.snapshot().places["robot1.port"],
        ["o-1"],
        "kept over a restart"
    );

    // Its cancel releases it; then the other part gets it.
    let released = m.handle(
        AgendaEvent::Request(place(MessageType::BookingCancel, "o-1", "robot1.port")),
        unix_ms(),
    );
    assert_accepted(&released);
    assert!(m.snapshot().places.is_empty());
    assert_accepted(&m.handle(
        AgendaEvent::Request(place(MessageType::BookingReq, "o-2", "robot1.port")),
        unix_ms(),
    ));
}

/// A part reserves a place again under a newer conversation while its earlier
/// reservation's cancel is still on its way (its resource had not answered it): the
/// hold is the newer one's, and the late cancel releases nothing.
#[test]
fn a_late_cancel_of_an_earlier_reservation_does_not_release_a_newer_one() {
    let mut m = station();
    let first = place(MessageType::BookingReq, "o-1", "robot1.port");
    assert_accepted(&m.handle(AgendaEvent::Request(first.clone()), unix_ms()));
    let mut newer = first.clone();
    newer.conversation_id = "o-1/place/robot1.port/7".into();
    let again = m.handle(AgendaEvent::Request(newer.clone()), unix_ms());
    assert_accepted(&again);
    assert!(
        again.contains(&AgendaAction::StateChanged),
        "re-keyed, journalled: {again:?}"
    );
    let mut late = first.clone();
    late.message_type = MessageType::BookingCancel;
    let late_cancel = m.handle(AgendaEvent::Request(late), unix_ms());
    assert_refused(&late_cancel, "not_booked");
    assert_eq!(m.snapshot().places["robot1.port"], ["o-1"], "still held");
    let mut cancel = newer;
    cancel.message_type = MessageType::BookingCancel;
    assert_accepted(&m.handle(AgendaEvent::Request(cancel), unix_ms()));
    assert!(m.snapshot().places.is_empty());
}

#[test]
fn a_place_elsewhere_or_without_its_part_is_refused_saying_which_places_there_are() {
    let mut m = station();
    let elsewhere = m.handle(
        AgendaEvent::Request(place(MessageType::BookingReq, "o-1", "robot2.port")),
        unix_ms(),
    );
    assert_refused(&elsewhere, "invalid_info");
    let detail = reply(&elsewhere).info["detail"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(
        detail.contains("one of robot1's locations (robot1.port)"),
        "{detail}"
    );
    let mut no_part = place(MessageType::BookingReq, "o-1", "robot1.port");
    no_part.info.remove("part");
    assert_refused(
        &m.handle(AgendaEvent::Request(no_part), unix_ms()),
        "invalid_info",
    );
    // A resource states no locations: every place is refused.
    let mut plain = manager();
    assert_refused(
        &plain.handle(
            AgendaEvent::Request(place(MessageType::BookingReq, "o-1", "robot1.port")),
            unix_ms(),
        ),
        "invalid_info",
    );
}

fn id(s: &str) -> schemas::layout::LocationId {
    schemas::layout::LocationId::try_from(s.to_string()).unwrap()
}

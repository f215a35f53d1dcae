use super::*;

fn id(s: &str) -> LocationId {
    LocationId::try_from(s.to_string()).unwrap()
}

fn order() -> HolonId {
    HolonId::order("o-1").unwrap()
}

fn conveyor() -> HolonId {
    HolonId::resource("conveyor1").unwrap()
}

#[test]
fn a_part_enters_rides_to_a_station_and_leaves_with_every_place_released() {
    let mut part = PartProgress {
        home: Some(id("conveyor1.buffer")),
        ..PartProgress::default()
    };
    part.held
        .insert(id("conveyor1.buffer"), "o-1/place/conveyor1.buffer".into());
    part.held
        .insert(id("robot1.port"), "o-1/place/robot1.port".into());
    part.begin_move(
        &order(),
        id("conveyor1.load"),
        id("robot1.port"),
        MoveGoal::Station,
    );
    assert_eq!(part.moving.as_ref().unwrap().conversation_id, "o-1/m1/1");
    part.move_phase(Phase::Booked(conveyor()));
    assert_eq!(
        part.place,
        PartPlace::Outside,
        "not moving before it starts"
    );
    part.move_phase(Phase::Started(conveyor()));
    assert!(
        matches!(part.place, PartPlace::InTransit { .. }),
        "{part:?}"
    );
    let released = part.end_move(MoveEnd::Done, Some(conveyor()));
    assert!(
        released.is_empty(),
        "the entry holds no place: {released:?}"
    );
    assert_eq!(part.place.location(), Some(&id("robot1.port")));

    // To the exit: the station's place and the home go. No layout is needed to know
    // it left: the move was begun to an exit (a conveyor restarted mid-move may be
    // out of the layout while its end is learnt).
    part.begin_move(
        &order(),
        id("robot1.port"),
        id("conveyor1.load"),
        MoveGoal::Exit,
    );
    part.move_phase(Phase::Started(conveyor()));
    let mut released: Vec<_> = part
        .end_move(MoveEnd::Done, Some(conveyor()))
        .into_iter()
        .map(|(l, _)| l.to_string())
        .collect();
    released.sort();
    assert_eq!(released, ["conveyor1.buffer", "robot1.port"]);
    assert_eq!(
        part.place,
        PartPlace::Shipped {
            exit: id("conveyor1.load")
        }
    );
    assert!(!part.in_cell());
}

#[test]
fn a_move_that_may_have_run_leaves_the_part_lost_until_its_transporter_says() {
    let mut part = PartProgress {
        place: PartPlace::At {
            location: id("robot1.port"),
        },
        home: Some(id("conveyor1.buffer")),
        ..PartProgress::default()
    };
    part.held
        .insert(id("robot1.port"), "o-1/place/robot1.port".into());
    part.begin_move(
        &order(),
        id("robot1.port"),
        id("conveyor1.buffer"),
        MoveGoal::Home,
    );
    part.move_phase(Phase::Started(conveyor()));
    let released = part.end_move(
        MoveEnd::Unknown {
            why: "the resource vanished".into(),
        },
        Some(conveyor()),
    );
    assert!(released.is_empty(), "nothing is released while lost");
    assert_eq!(
        part.place.to_string(),
        "in transit on resource/conveyor1, last seen at robot1.port (the resource vanished)"
    );
    assert!(part.moving.is_some(), "kept to be asked about");

    // Its transporter says the move never reached the controller: where it was.
    let released = part.found(false);
    assert!(released.is_empty());
    assert_eq!(part.place.location(), Some(&id("robot1.port")));
    assert!(part.moving.is_none());
}

/// A part at its home `conveyor1.buffer`, the places `held` held for it, its move from
/// home to `robot1.port` begun.
fn moving_from_home(held: &[&str]) -> PartProgress {
    let mut part = PartProgress {
        place: PartPlace::At {
            location: id("conveyor1.buffer"),
        },
        home: Some(id("conveyor1.buffer")),
        ..PartProgress::default()
    };
    for place in held {
        part.held.insert(id(place), format!("o-1/place/{place}"));
    }
    part.begin_move(
        &order(),
        id("conveyor1.buffer"),
        id("robot1.port"),
        MoveGoal::Station,
    );
    part
}

#[test]
fn a_move_that_never_began_releases_the_place_reserved_for_it() {
    let mut part = moving_from_home(&["robot1.port"]);
    let released = part.end_move(MoveEnd::Unattempted, None);
    assert_eq!(
        released,
        [(id("robot1.port"), "o-1/place/robot1.port".to_string())]
    );
    assert_eq!(part.place.location(), Some(&id("conveyor1.buffer")));
}

#[test]
fn an_operators_word_places_a_lost_part_at_one_end_of_its_move_and_is_kept() {
    let lost = || {
        let mut part = PartProgress {
            place: PartPlace::At {
                location: id("conveyor1.buffer"),
            },
            home: Some(id("conveyor1.buffer")),
            ..PartProgress::default()
        };
        part.held
            .insert(id("robot1.port"), "o-1/place/robot1.port".into());
        part.begin_move(
            &order(),
            id("conveyor1.buffer"),
            id("robot1.port"),
            MoveGoal::Station,
        );
        part.move_phase(Phase::Started(conveyor()));
        part.end_move(
            MoveEnd::Unknown {
                why: "the resource vanished".into(),
            },
            Some(conveyor()),
        );
        part
    };

    // A location that is neither end of the move changes nothing.
    let mut part = lost();
    let before = part.clone();
    assert!(part
        .found_by_operator(&id("robot2.port"), "kim", 7)
        .is_empty());
    assert_eq!(part, before);

    // At its destination: it arrived, and the place there stays held for the step.
    let released = part.found_by_operator(&id("robot1.port"), "kim", 7);
    assert!(released.is_empty(), "its home is kept: {released:?}");
    assert_eq!(part.place.location(), Some(&id("robot1.port")));
    assert!(part.moving.is_none());
    assert_eq!(part.found.len(), 1);
    assert_eq!(
        part.found[0].to_string(),
        "found at robot1.port by kim (lost on resource/conveyor1, move o-1/m1/1)"
    );
    // Said again, once it is no longer lost: nothing changes.
    let before = part.clone();
    part.found_by_operator(&id("robot1.port"), "kim", 8);
    assert_eq!(part, before);

    // At its origin: it never left, and the place reserved at the destination is
    // released.
    let mut part = lost();
    let released = part.found_by_operator(&id("conveyor1.buffer"), "lee", 9);
    assert_eq!(
        released,
        [(id("robot1.port"), "o-1/place/robot1.port".to_string())]
    );
    assert_eq!(part.place.location(), Some(&id("conveyor1.buffer")));
    assert_eq!(part.found[0].by, "lee");
}

/// A part at `robot1.port` (held), its home `conveyor1.buffer` (held), a place held at
/// `robot2.port`, and its move from the first port to the second begun.
fn moving_between_ports() -> PartProgress {
    let mut part = PartProgress {
        place: PartPlace::At {
            location: id("robot1.port"),
        },
        home: Some(id("conveyor1.buffer")),
        ..PartProgress::default()
    };
    for place in ["conveyor1.buffer", "robot1.port", "robot2.port"] {
        part.held.insert(id(place), format!("o-1/place/{place}"));
    }
    part.begin_move(
        &order(),
        id("robot1.port"),
        id("robot2.port"),
        MoveGoal::Station,
    );
    part
}

#[test]
fn a_departed_move_releases_the_port_it_left_once_and_its_done_nothing_more() {
    let mut part = moving_between_ports();
    part.move_phase(Phase::Started(conveyor()));
    let released = part.departed("o-1/m1/1", &conveyor());
    assert_eq!(
        released,
        Some((id("robot1.port"), "o-1/place/robot1.port".to_string()))
    );
    assert!(
        matches!(part.place, PartPlace::InTransit { .. }),
        "still in transit: {part:?}"
    );
    assert!(!part.held.contains_key(&id("robot1.port")));
    assert_eq!(
        part.released_at_departure(),
        Some((id("robot1.port"), "o-1/place/robot1.port".to_string())),
        "kept with the move, for a restarted order-node to send its cancel again"
    );

    // Idempotent: a second departure releases nothing.
    assert_eq!(part.departed("o-1/m1/1", &conveyor()), None);

    // Survives the journal: a restarted order-node sees the same.
    let journalled: PartProgress =
        serde_json::from_value(serde_json::to_value(&part).unwrap()).unwrap();
    assert_eq!(journalled, part);
    assert_eq!(
        journalled.clone().departed("o-1/m1/1", &conveyor()),
        None,
        "released already"
    );

    // Its done puts the part at the destination and releases nothing more.
    let released = part.end_move(MoveEnd::Done, Some(conveyor()));
    assert!(released.is_empty(), "released once: {released:?}");
    assert_eq!(part.place.location(), Some(&id("robot2.port")));
    assert_eq!(part.released_at_departure(), None, "the move is over");
    let mut held: Vec<_> = part.held.keys().map(|l| l.to_string()).collect();
    held.sort();
    assert_eq!(held, ["conveyor1.buffer", "robot2.port"]);
}

#[test]
fn a_move_that_never_says_it_departed_releases_its_origin_at_done() {
    let mut part = moving_between_ports();
    part.move_phase(Phase::Started(conveyor()));
    assert_eq!(part.released_at_departure(), None);
    let released = part.end_move(MoveEnd::Done, Some(conveyor()));
    assert_eq!(
        released,
        [(id("robot1.port"), "o-1/place/robot1.port".to_string())]
    );
}

#[test]
fn a_departure_never_releases_the_home() {
    let mut part = moving_from_home(&["conveyor1.buffer", "robot1.port"]);
    part.move_phase(Phase::Started(conveyor()));
    assert!(!part.has_left());
    assert_eq!(part.departed("o-1/m1/1", &conveyor()), None);
    assert_eq!(part.held.len(), 2, "both kept: {:?}", part.held);
    assert_eq!(part.released_at_departure(), None);
    // Marked left all the same (recorded by the order): a refusal after it does not
    // put the part back at its home.
    assert!(part.has_left());
    let released = part.end_move(MoveEnd::Done, Some(conveyor()));
    assert!(released.is_empty(), "the home stays held: {released:?}");
}

#[test]
fn a_departure_of_another_move_or_transporter_or_before_the_start_releases_nothing() {
    let mut part = moving_between_ports();
    let untouched = part.clone();
    // Booked, its start not recorded yet: the place is released at done.
    part.move_phase(Phase::Booked(conveyor()));
    assert_eq!(part.departed("o-1/m1/1", &conveyor()), None);
    part.move_phase(Phase::Started(conveyor()));
    assert_eq!(part.departed("o-1/m0/1", &conveyor()), None, "another move");
    let other = HolonId::resource("mover1").unwrap();
    assert_eq!(
        part.departed("o-1/m1/1", &other),
        None,
        "another transporter"
    );
    assert_eq!(part.held, untouched.held);
    assert_eq!(part.moving.as_ref().unwrap().departed, None);
    assert!(!part.has_left(), "not this move's word: {part:?}");

    // No move under way.
    let mut still = untouched.clone();
    still.moving = None;
    assert_eq!(still.departed("o-1/m1/1", &conveyor()), None);
}

#[test]
fn a_departed_move_that_then_fails_is_lost_and_found_without_a_second_release() {
    let mut part = moving_between_ports();
    part.move_phase(Phase::Started(conveyor()));
    assert!(part.departed("o-1/m1/1", &conveyor()).is_some());
    let released = part.end_move(
        MoveEnd::Unknown {
            why: "fault".into(),
        },
        Some(conveyor()),
    );
    assert!(released.is_empty());
    assert!(
        part.released_at_departure().is_some(),
        "kept with the lost move"
    );
    // Found at its destination: the origin was released at departure already.
    let released = part.found(true);
    assert!(released.is_empty(), "{released:?}");
    assert_eq!(part.place.location(), Some(&id("robot2.port")));
}

#[test]
fn an_operators_word_on_a_departed_part_at_its_origin_needs_the_origin_reserved_again() {
    let lost_after_departing = || {
        let mut part = moving_between_ports();
        part.move_phase(Phase::Started(conveyor()));
        assert!(part.departed("o-1/m1/1", &conveyor()).is_some());
        part.end_move(
            MoveEnd::Unknown {
                why: "fault".into(),
            },
            Some(conveyor()),
        );
        part
    };
    let mut part = lost_after_departing();
    assert!(part.needs_origin_again(&id("robot1.port")));
    assert!(
        !part.needs_origin_again(&id("robot2.port")),
        "its place at the destination is held"
    );
    // Reserved again (the order's task journals it before it asks): asked again all the
    // same, as the journal cannot tell whether it was granted.
    part.held
        .insert(id("robot1.port"), "o-1/place/robot1.port".into());
    assert!(part.needs_origin_again(&id("robot1.port")));
    // Then found there: the origin kept, the destination released.
    let released = part.found_by_operator(&id("robot1.port"), "kim", 7);
    assert_eq!(
        released,
        vec![(id("robot2.port"), "o-1/place/robot2.port".to_string())]
    );
    assert!(part.held.contains_key(&id("robot1.port")), "{part:?}");

    // A word on a lost move that never departed: its origin is still held.
    let mut never_left = moving_between_ports();
    never_left.move_phase(Phase::Started(conveyor()));
    never_left.end_move(
        MoveEnd::Unknown {
            why: "fault".into(),
        },
        Some(conveyor()),
    );
    assert!(!never_left.needs_origin_again(&id("robot1.port")));
    // Nor a part that is not lost.
    assert!(!moving_between_ports().needs_origin_again(&id("robot1.port")));
    // Found at its destination after the origin was reserved again: released there.
    let mut part = lost_after_departing();
    part.held
        .insert(id("robot1.port"), "o-1/place/robot1.port".into());
    let released = part.found(true);
    assert_eq!(
        released,
        vec![(id("robot1.port"), "o-1/place/robot1.port".to_string())]
    );
}

#[test]
fn a_journalled_move_of_before_departures_reads_as_not_departed() {
    let mut part = moving_between_ports();
    part.move_phase(Phase::Started(conveyor()));
    let mut value = serde_json::to_value(&part).unwrap();
    assert!(
        value["moving"].get("departed").is_none(),
        "not written while it has not departed: {value}"
    );
    assert!(value["moving"].get("left").is_none(), "{value}");
    value["moving"].as_object_mut().unwrap().remove("departed");
    let read: PartProgress = serde_json::from_value(value).unwrap();
    assert_eq!(read, part);
}

#[test]
fn each_reservation_has_a_conversation_of_its_own() {
    let mut part = PartProgress::default();
    let first = part.place_conversation(&order(), &id("robot1.port"));
    let again = part.place_conversation(&order(), &id("robot1.port"));
    assert_ne!(
        first, again,
        "a late cancel of the first must not release the second"
    );
    let value = serde_json::to_value(&part).unwrap();
    let read: PartProgress = serde_json::from_value(value.clone()).unwrap();
    assert_eq!(read.reservations, 2, "journalled with the part");
    let mut old = value;
    old.as_object_mut().unwrap().remove("reservations");
    let read: PartProgress = serde_json::from_value(old).unwrap();
    assert_eq!(
        read.reservations, 0,
        "a journal of before reads as none yet"
    );
}

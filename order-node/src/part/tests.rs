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

#[test]
fn a_move_that_never_began_releases_the_place_reserved_for_it() {
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

use super::*;

fn part(holon: &str, toml_text: &str) -> schemas::layout::LayoutPart {
    schemas::layout::part_from_toml(holon, toml_text).unwrap_or_else(|e| panic!("{e}"))
}

fn id(s: &str) -> LocationId {
    LocationId::try_from(s.to_string()).unwrap()
}

fn dock(s: &str) -> Dock {
    Dock::try_from(s.to_string()).unwrap()
}

/// A loop of 3 m at 1 m/s with stoppers load (0), s1 (1000) and s2 (2000), each track
/// holding `queue` pallets; `pallets` pallets; an entry and exit at load, robot1's port
/// at s1, robot2's at s2 (one place each); a transfer robot between the two ports, and
/// another between robot1's port and a shelf off the loop (two places).
fn plant_of(pallets: u32, queue: u32, dock_ms: u64) -> Plant {
    let station = |dock: &str| {
        format!("[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n")
    };
    let transfer =
        |between: &str| format!("[layout.transfer]\nbetween = {between}\nmove_ms = 500\n");
    let conveyor = format!(
        r#"
[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"
[layout.conveyor]
length_mm = 3000
speed_mm_s = 1000
pallets = {pallets}
dock_ms = {dock_ms}
stoppers = [{{ name = "load", at_mm = 0, queue = {queue} }}, {{ name = "s1", at_mm = 1000, queue = {queue} }}, {{ name = "s2", at_mm = 2000, queue = {queue} }}]
"#
    );
    Plant::new(CellLayout::assemble([
        part("conveyor1", &conveyor),
        part("robot1", &station("conveyor1.s1")),
        part("robot2", &station("conveyor1.s2")),
        part(
            "shelf1",
            "[[layout.locations]]\nname = \"shelf\"\nrole = \"buffer\"\ncapacity = 2\n",
        ),
        part("mover1", &transfer("[\"robot1.port\", \"robot2.port\"]")),
        part("mover2", &transfer("[\"robot1.port\", \"shelf1.shelf\"]")),
    ]))
}

/// Two pallets, tracks of two.
fn plant() -> Plant {
    plant_of(2, 2, 0)
}

#[test]
fn a_part_rides_a_pallet_from_the_entry_through_the_stations_and_leaves() {
    let mut plant = plant();
    assert_eq!(
        plant.check_work("robot1", None),
        Err(PhysicalError::Empty {
            ports: "robot1.port".into()
        })
    );
    let took = plant
        .begin_move(
            "conveyor1",
            "o-1",
            &id("conveyor1.load"),
            &id("robot1.port"),
        )
        .unwrap();
    assert_eq!(took, Duration::from_millis(1000));
    assert_eq!(
        plant.where_is("o-1"),
        "on conveyor1 from conveyor1.load to robot1.port"
    );
    assert_eq!(plant.view().free_pallets["conveyor1"].len(), 1);
    // On the track to s1, riding.
    plant.advance(999);
    let pallet = plant.carrier_of("o-1").unwrap();
    let view = &plant.view().pallets[&pallet];
    assert_eq!(
        (
            view.at,
            view.track.as_deref(),
            view.queue_position,
            view.riding
        ),
        ("track", Some("s1"), Some(0), true),
        "{view:?}"
    );
    // Not there yet: nothing to pick.
    assert!(plant.check_work("robot1", Some("o-1")).is_err());
    assert!(plant.on_its_way("o-1", "conveyor1").is_some());
    let happened = plant.advance(1000);
    assert!(
        happened.contains(&Happening::Arrived {
            part: "o-1".into(),
            at: id("robot1.port"),
            transporter: "conveyor1".into()
        }),
        "{happened:?}"
    );
    assert_eq!(plant.on_its_way("o-1", "conveyor1"), None);
    assert_eq!(plant.where_is("o-1"), "at robot1.port");
    plant.check_work("robot1", Some("o-1")).unwrap();
    plant.check_work("robot1", None).unwrap();
    assert!(matches!(
        plant.check_work("robot1", Some("o-2")),
        Err(PhysicalError::NotAtStation { .. })
    ));
    // The transfer takes it off its pallet, which is parked again.
    let took = plant
        .begin_move("mover1", "o-1", &id("robot1.port"), &id("robot2.port"))
        .unwrap();
    assert_eq!(took, Duration::from_millis(500));
    assert_eq!(plant.view().free_pallets["conveyor1"].len(), 2);
    plant.advance(1499);
    assert!(plant.on_its_way("o-1", "mover1").is_some());
    plant.advance(1500);
    assert_eq!(plant.where_is("o-1"), "at robot2.port");
    // Back on the conveyor (a parked pallet comes for it) to the exit: it leaves.
    let took = plant
        .begin_move(
            "conveyor1",
            "o-1",
            &id("robot2.port"),
            &id("conveyor1.load"),
        )
        .unwrap();
    assert_eq!(took, Duration::from_millis(1000));
    plant.advance(2500);
    let view = plant.view();
    assert_eq!(view.shipped, 1);
    assert_eq!(view.free_pallets["conveyor1"].len(), 2);
    assert!(view.locations.values().all(Vec::is_empty), "{view:?}");
    assert_eq!(plant.where_is("o-1"), "not in the plant");
    assert!(!view.deadlocked);
    assert_eq!(view.longest_wait_ms, 0);
}

#[test]
fn a_move_takes_the_layouts_travel_track_by_track_docking_included() {
    let mut plant = plant_of(2, 2, 150);
    let (load, r2) = (id("conveyor1.load"), id("robot2.port"));
    let took = plant.begin_move("conveyor1", "o-1", &load, &r2).unwrap();
    assert_eq!(took, Duration::from_millis(2300));
    // Coming back onto the loop and the track to s1, then the track to s2, then docking.
    plant.advance(1149);
    assert_eq!(
        plant.view().pallets["conveyor1/p1"].track.as_deref(),
        Some("s1")
    );
    plant.advance(1150);
    assert_eq!(
        plant.view().pallets["conveyor1/p1"].track.as_deref(),
        Some("s2")
    );
    plant.advance(2150);
    assert_eq!(plant.view().pallets["conveyor1/p1"].at, "docking");
    plant.advance(2299);
    assert!(plant.on_its_way("o-1", "conveyor1").is_some());
    plant.advance(2300);
    assert_eq!(plant.where_is("o-1"), "at robot2.port");
    assert_eq!(plant.view().pallets["conveyor1/p1"].at, "docked");
    // Time never goes back.
    plant.advance(5);
    assert_eq!(plant.now_ms(), 2300);
}

#[test]
fn a_pallet_waits_at_a_full_port_blocking_the_pallets_behind_it_until_there_is_a_place() {
    let mut plant = plant_of(3, 2, 0);
    let (load, r1, r2, shelf) = (
        id("conveyor1.load"),
        id("robot1.port"),
        id("robot2.port"),
        id("shelf1.shelf"),
    );
    plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
    plant.advance(1000);
    // The port is full: the move is not refused; the pallet goes and waits there.
    plant.begin_move("conveyor1", "o-2", &load, &r1).unwrap();
    plant.begin_move("conveyor1", "o-3", &load, &r2).unwrap();
    plant.advance(2500);
    let (p2, p3) = (
        plant.carrier_of("o-2").unwrap(),
        plant.carrier_of("o-3").unwrap(),
    );
    let view = plant.view();
    let waiting = &view.pallets[&p2];
    assert_eq!(
        (waiting.track.as_deref(), waiting.queue_position),
        (Some("s1"), Some(0))
    );
    assert_eq!(waiting.waits.as_deref(), Some("robot1.port full"));
    assert_eq!(waiting.waits_since_ms, Some(2000));
    let behind = &view.pallets[&p3];
    assert_eq!(behind.queue_position, Some(1));
    assert_eq!(behind.waits, Some(format!("behind {p2}")));
    assert!(!view.deadlocked, "a part at rest holds the port: {view:?}");
    assert_eq!(view.longest_wait_ms, 500);
    assert_eq!(plant.waits().len(), 2);
    assert_eq!(
        plant.on_its_way("o-2", "conveyor1"),
        Some(format!("{p2} waits: robot1.port full"))
    );
    plant.advance(2600);
    // The port is emptied (a transfer takes its part to the shelf): the pallet docks at
    // once, and the one behind goes on to robot2.
    plant.begin_move("mover2", "o-1", &r1, &shelf).unwrap();
    plant.advance(2600);
    assert_eq!(plant.where_is("o-2"), "at robot1.port");
    plant.advance(3599);
    assert!(plant.on_its_way("o-3", "conveyor1").is_some());
    plant.advance(3600);
    assert_eq!(plant.where_is("o-3"), "at robot2.port");
    assert_eq!(plant.where_is("o-1"), "at shelf1.shelf");
    let view = plant.view();
    assert!(plant.waits().is_empty(), "{view:?}");
    assert_eq!(view.longest_wait_ms, 600);
}

#[test]
fn a_pallet_leaves_only_onto_a_track_with_room_and_passes_a_stopper_only_so() {
    // Tracks of one: the second pallet waits docked at the loading point until the first
    // has left the track to s1.
    let mut plant = plant_of(2, 1, 0);
    let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
    plant.begin_move("conveyor1", "o-1", &load, &r2).unwrap();
    plant.begin_move("conveyor1", "o-2", &load, &r1).unwrap();
    let p2 = plant.carrier_of("o-2").unwrap();
    let view = plant.view();
    assert_eq!(view.pallets[&p2].at, "docked");
    assert_eq!(view.pallets[&p2].waits.as_deref(), Some("track s1 full"));
    // At 1000 the first passes s1 onto the track to s2, and the second leaves.
    plant.advance(1000);
    assert_eq!(plant.view().pallets[&p2].at, "track");
    plant.advance(2000);
    assert_eq!(plant.where_is("o-1"), "at robot2.port");
    assert_eq!(plant.where_is("o-2"), "at robot1.port");
    assert_eq!(plant.view().longest_wait_ms, 1000);
}

#[test]
fn a_move_has_left_its_origin_once_its_pallet_is_off_the_origins_port() {
    // Tracks of one: the second pallet waits docked at the loading point.
    let mut plant = plant_of(2, 1, 0);
    let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
    plant.begin_move("conveyor1", "o-1", &load, &r2).unwrap();
    plant.begin_move("conveyor1", "o-2", &load, &r1).unwrap();
    // No pallet is free: the third part waits at the loading point for one.
    plant.begin_move("conveyor1", "o-3", &load, &r1).unwrap();
    plant.advance(1);
    assert!(plant.left_origin("o-1"), "{:?}", plant.view());
    let p2 = plant.carrier_of("o-2").unwrap();
    assert_eq!(plant.view().pallets[&p2].at, "docked");
    assert!(!plant.left_origin("o-2"), "docked, waiting to leave");
    assert!(!plant.left_origin("o-3"), "waiting for a pallet");
    assert!(!plant.left_origin("o-9"), "unknown");
    plant.advance(999);
    assert!(!plant.left_origin("o-2"));
    // At 1000 the first passes s1, and the second leaves onto the track to s1.
    plant.advance(1000);
    assert_eq!(plant.view().pallets[&p2].at, "track");
    assert!(plant.left_origin("o-2"));
    assert!(plant.on_its_way("o-2", "conveyor1").is_some());
    // Arrived: the move is over, nothing is leaving any more.
    plant.advance(2000);
    assert_eq!(plant.where_is("o-2"), "at robot1.port");
    assert!(!plant.left_origin("o-2"));
    // A transfer's move leaves on no pallet.
    let shelf = id("shelf1.shelf");
    plant.begin_move("mover2", "o-2", &r1, &shelf).unwrap();
    assert!(plant.on_its_way("o-2", "mover2").is_some());
    assert!(!plant.left_origin("o-2"));
}

#[test]
fn a_jammed_track_holds_the_pallets_and_a_silent_pallet_goes_unreported() {
    let mut plant = plant();
    let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
    assert!(plant.jam(dock("conveyor1.s9"), true).is_err());
    plant.jam(dock("conveyor1.s2"), true).unwrap();
    // load -> s1 does not ride the track to s2; load -> s2 does: it waits at s1.
    plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
    plant.begin_move("conveyor1", "o-2", &load, &r2).unwrap();
    plant.advance(1500);
    assert_eq!(plant.where_is("o-1"), "at robot1.port");
    let p2 = plant.carrier_of("o-2").unwrap();
    assert_eq!(
        plant.on_its_way("o-2", "conveyor1"),
        Some(format!("{p2} waits: track s2 jammed"))
    );
    assert!(!plant.view().deadlocked);
    plant.jam(dock("conveyor1.s2"), false).unwrap();
    plant.advance(2499);
    assert!(plant.on_its_way("o-2", "conveyor1").is_some());
    plant.advance(2500);
    assert_eq!(plant.where_is("o-2"), "at robot2.port");
    let pallet = plant.view().locations["robot2.port"][0]
        .carrier
        .clone()
        .unwrap();
    assert!(plant.silence("conveyor1/p9", true).is_err());
    plant.silence(&pallet, true).unwrap();
    assert!(plant.is_silent(&pallet));
    plant.begin_move("conveyor1", "o-2", &r2, &load).unwrap();
    assert_eq!(plant.carrier_of("o-2"), Some(pallet.clone()));
    assert_eq!(plant.view().silent, vec![pallet]);
}

#[test]
fn an_estop_stands_the_pallets_still_and_they_go_on_with_the_time_they_had_left() {
    let mut plant = plant();
    let (load, r1) = (id("conveyor1.load"), id("robot1.port"));
    plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
    plant.advance(400);
    plant.estop("conveyor1", true);
    plant.advance(5000);
    assert_eq!(
        plant.on_its_way("o-1", "conveyor1").as_deref(),
        Some("conveyor1 is e-stopped")
    );
    plant.estop("conveyor1", false);
    plant.advance(5599);
    assert!(plant.on_its_way("o-1", "conveyor1").is_some());
    plant.advance(5600);
    assert_eq!(plant.where_is("o-1"), "at robot1.port");
}

#[test]
fn the_plant_refuses_what_cannot_happen() {
    let mut plant = plant();
    let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
    plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
    // A full port does not refuse a pallet (it waits there).
    plant.begin_move("conveyor1", "o-2", &load, &r1).unwrap();
    plant.advance(1000);
    // A part is moved from where it is, by a transporter that reaches both ends.
    assert!(matches!(
        plant.begin_move("conveyor1", "o-1", &r2, &load),
        Err(PhysicalError::NotThere { .. })
    ));
    assert!(matches!(
        plant.begin_move("mover1", "o-1", &r1, &load),
        Err(PhysicalError::NoRoute { .. })
    ));
    assert!(matches!(
        plant.begin_move("conveyor1", "o-2", &r1, &r2),
        Err(PhysicalError::Moving { .. })
    ));
    let refused = plant.begin_move("conveyor1", "o-3", &load, &load);
    assert!(refused.is_err(), "{refused:?}");
    // A transfer does not wait at a full port: it refuses to go.
    plant.begin_move("mover1", "o-1", &r1, &r2).unwrap();
    plant.advance(1500);
    assert!(matches!(
        plant.begin_move("mover1", "o-1", &r2, &r1),
        Err(PhysicalError::Full { held: 1, .. })
    ));
    // Aborted on the way, a part stays on its transporter, stopped, its pallet where it
    // stopped.
    plant.advance(1600);
    plant.begin_move("conveyor1", "o-1", &r2, &load).unwrap();
    plant.advance(1800);
    plant.stop_move("o-1");
    assert_eq!(
        plant.where_is("o-1"),
        "on conveyor1 from robot2.port to conveyor1.load, stopped"
    );
    plant.advance(60_000);
    let pallet = plant.carrier_of("o-1").unwrap();
    let view = plant.view();
    assert_eq!(
        (
            view.pallets[&pallet].track.as_deref(),
            view.pallets[&pallet].stopped
        ),
        (Some("load"), true),
        "{view:?}"
    );
    assert!(matches!(
        plant.begin_move("conveyor1", "o-1", &r2, &load),
        Err(PhysicalError::Moving { .. })
    ));
}

/// The orders of [`crossing`]: each part's stops, and how long its station works on it
/// at each.
type Orders<'a> = [(&'a str, &'a [&'a str], &'a [u64])];

/// Runs `orders` from time 0 in steps of 100 ms, as a control would: a part's next
/// move is begun once it is at rest at its stop and worked on; with `reserve`, only
/// once its destination has a free place (nothing held there, nothing on its way: the
/// control's reservation). Returns whether the plant ever deadlocked, and the plant.
fn run(mut plant: Plant, orders: &Orders, reserve: bool) -> (bool, Plant) {
    let mut next = vec![1usize; orders.len()];
    let mut arrived_at = vec![0u64; orders.len()];
    let mut deadlocked = false;
    for now in (0..=20_000).step_by(100) {
        plant.advance(now);
        let view = plant.view();
        deadlocked |= view.deadlocked;
        for (i, (part, stops, work)) in orders.iter().enumerate() {
            if next[i] >= stops.len() || plant.transit.contains_key(*part) {
                continue;
            }
            let (from, to) = (id(stops[next[i] - 1]), id(stops[next[i]]));
            let at_rest = next[i] == 1 || plant.where_is(part) == format!("at {from}");
            if !at_rest {
                continue;
            }
            if arrived_at[i] == 0 {
                arrived_at[i] = now;
            }
            let worked = now >= arrived_at[i] + work[next[i] - 1];
            let taken = view.locations[to.as_str()].len()
                + view.in_transit.iter().filter(|t| t.to == to).count();
            let free = plant.is_exit(&to) || taken == 0;
            if worked && (!reserve || free) {
                plant.begin_move("conveyor1", part, &from, &to).unwrap();
                next[i] += 1;
                arrived_at[i] = 0;
            }
        }
    }
    (deadlocked, plant)
}

/// Two parts cross at robot2's stopper: o-1 goes from robot1 to robot2 while robot2
/// still works on o-2, which then leaves for the exit. Without the control's
/// reservation o-1's pallet waits at s2 for robot2's place, and o-2's pallet cannot
/// come back onto the loop at s2, where o-1's stands: each waits on the other, for ever.
/// With it, o-1 waits at rest in robot1 (blocking nobody) until robot2 has a place.
#[test]
fn parts_crossing_deadlock_the_plant_without_reservation_and_never_with_it() {
    let orders: &Orders = &[
        (
            "o-2",
            &["conveyor1.load", "robot2.port", "conveyor1.load"],
            &[0, 2000, 0],
        ),
        (
            "o-1",
            &[
                "conveyor1.load",
                "robot1.port",
                "robot2.port",
                "conveyor1.load",
            ],
            &[0, 0, 0, 0],
        ),
    ];
    for queue in [1, 2] {
        let (deadlocked, plant) = run(plant_of(2, queue, 0), orders, false);
        assert!(deadlocked, "queue {queue}: {:?}", plant.view());
        let view = plant.view();
        let (p1, p2) = (
            plant.carrier_of("o-1").unwrap(),
            plant.carrier_of("o-2").unwrap(),
        );
        let mut both = vec![p1.clone(), p2.clone()];
        both.sort();
        assert_eq!(view.deadlock, both, "{view:?}");
        assert_eq!(view.pallets[&p1].waits.as_deref(), Some("robot2.port full"));
        assert_eq!(
            view.pallets[&p2].waits,
            Some(format!("stopper s2 taken by {p1}"))
        );
        assert_eq!(view.shipped, 0);

        let (deadlocked, plant) = run(plant_of(2, queue, 0), orders, true);
        let view = plant.view();
        assert!(!deadlocked, "queue {queue}: {view:?}");
        assert_eq!(view.shipped, 2, "queue {queue}: {view:?}");
    }
}

/// The same crossing between two stations each way (o-1 from robot1 to robot2, o-2
/// from robot2 to robot1): without the reservation, the plant deadlocks.
#[test]
fn parts_crossing_between_two_ports_each_way_deadlock_without_reservation() {
    let orders: &Orders = &[
        (
            "o-2",
            &["conveyor1.load", "robot2.port", "robot1.port"],
            &[0, 2000, 0],
        ),
        (
            "o-1",
            &["conveyor1.load", "robot1.port", "robot2.port"],
            &[0, 0, 0],
        ),
    ];
    let (deadlocked, plant) = run(plant_of(2, 2, 0), orders, false);
    assert!(deadlocked, "{:?}", plant.view());
    // With it, neither is sent while the other's port is full: each part waits at rest
    // in its port, and nothing waits on the loop (the crossing is the control's to
    // break, through a buffer).
    let (deadlocked, plant) = run(plant_of(2, 2, 0), orders, true);
    assert!(!deadlocked);
    assert!(plant.waits().is_empty(), "{:?}", plant.view());
}

#[test]
fn a_part_waits_for_a_free_pallet_and_a_retired_pallet_takes_none() {
    let mut plant = plant();
    let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
    assert!(plant.retire("conveyor1/p9", true).is_err());
    // One of the two pallets is taken out: it is free, so at once.
    plant.retire("conveyor1/p2", true).unwrap();
    let view = plant.view();
    assert_eq!(view.pallets["conveyor1/p2"].at, "retired");
    assert_eq!(view.free_pallets["conveyor1"], ["conveyor1/p1"]);
    plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
    assert_eq!(plant.carrier_of("o-1").as_deref(), Some("conveyor1/p1"));
    // No pallet is free: the second part waits at the entry for one.
    plant.begin_move("conveyor1", "o-2", &load, &r2).unwrap();
    assert_eq!(plant.carrier_of("o-2"), None);
    assert_eq!(
        plant.on_its_way("o-2", "conveyor1").as_deref(),
        Some("waits at conveyor1.load for a free pallet")
    );
    assert!(plant.view().in_transit.iter().any(|t| t.awaits_pallet));
    // o-1 arrives, is worked, and leaves by the exit: its pallet is freed there, and
    // the waiting part takes it (brought to the entry).
    plant.advance(1000);
    assert_eq!(plant.where_is("o-1"), "at robot1.port");
    // The pallet carrying a part is to be retired: it finishes what it carries.
    plant.retire("conveyor1/p1", true).unwrap();
    plant.begin_move("conveyor1", "o-1", &r1, &load).unwrap();
    plant.advance(3000);
    assert_eq!(plant.view().shipped, 1);
    assert_eq!(plant.view().pallets["conveyor1/p1"].at, "retired");
    assert_eq!(
        plant.on_its_way("o-2", "conveyor1").as_deref(),
        Some("waits at conveyor1.load for a free pallet"),
        "a retired pallet takes no part"
    );
    // Put back: the waiting part takes it at once and rides.
    let happened = {
        plant.retire("conveyor1/p2", false).unwrap();
        plant.advance(3000)
    };
    assert!(
        happened.contains(&Happening::Retired {
            pallet: "conveyor1/p2".into(),
            out: false
        }),
        "{happened:?}"
    );
    assert_eq!(plant.carrier_of("o-2").as_deref(), Some("conveyor1/p2"));
    plant.advance(5000);
    assert_eq!(plant.where_is("o-2"), "at robot2.port");
}

#[test]
fn a_plant_resumed_from_its_memory_goes_on_as_the_one_that_wrote_it() {
    let mut plant = plant_of(3, 2, 100);
    plant
        .begin_move(
            "conveyor1",
            "o-1",
            &id("conveyor1.load"),
            &id("robot2.port"),
        )
        .unwrap();
    plant.note_command("o-1", "move", Some("c-1#0"));
    plant
        .begin_move(
            "conveyor1",
            "o-2",
            &id("conveyor1.load"),
            &id("robot1.port"),
        )
        .unwrap();
    plant.advance(700);
    plant.silence("conveyor1/p1", true).unwrap();
    let json = serde_json::to_string(&plant.memory()).unwrap();
    let memory: PlantMemory = serde_json::from_str(&json).unwrap();
    let mut resumed = Plant::resume(plant.layout().clone(), memory.clone()).unwrap();
    let view = |p: &Plant| serde_json::to_value(p.view()).unwrap();
    assert_eq!(view(&resumed), view(&plant));
    assert_eq!(resumed.moves_under_way().len(), 2);
    // Both go on alike.
    for now in [1500, 2600, 4000] {
        assert_eq!(resumed.advance(now), plant.advance(now), "at {now} ms");
        assert_eq!(view(&resumed), view(&plant), "at {now} ms");
    }
    assert_eq!(resumed.where_is("o-1"), "at robot2.port");
    assert_eq!(resumed.where_is("o-2"), "at robot1.port");
    assert!(resumed.is_silent("conveyor1/p1"));
    // o-1's end is not told yet: the plant knows its step is done.
    assert!(resumed.arrived_untold("conveyor1", "c-1#0"));
    resumed.end_told("conveyor1", "c-1#0");
    assert!(!resumed.arrived_untold("conveyor1", "c-1#0"));
    // A memory that does not fit the layout is refused, naming what does not fit.
    let smaller = plant_of(2, 2, 100);
    let problems = Plant::resume(smaller.layout().clone(), memory).unwrap_err();
    assert!(
        problems.iter().any(|p| p.contains("conveyor1/p3")),
        "{problems:?}"
    );
}

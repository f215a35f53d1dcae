//! Chaos with material flow (docs/material-flow.md): 200 orders of the demo's breaker
//! ride pallets through the demo's layout on the plant simulator, while a driver kills
//! holon processes with SIGKILL (the stations, a transporter while a part is on it, the
//! order-node) and starts them again on their journals, kills the plant simulator
//! itself (every controller at once; it resumes from its memory) and cuts the links of
//! the plant's controllers. An operator's duty is played too: a part the control has
//! lost is looked up in the plant and its place said (`cell part`).
//!
//! At the end: every order ended done (each step once, in order, with its reworks) or
//! with a stated reason; the control's view of every part equals the plant's physical
//! truth (every part that entered left by the exit, the plant holds none, every pallet
//! is free, no place is held); the controllers executed no step recorded done twice
//! (the plant's trace, across its lives);
//! the plant never deadlocked, and no part waited beyond the dashboard's bound (its
//! `part_waits` alarm, which the run counts as a failure).
//!
//! `HOLARCHY_MATERIAL_CHAOS_ORDERS=N` runs fewer orders; the seed is printed and
//! `HOLARCHY_CHAOS_SEED=N` replays one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use holarchy_tests::chaos::{Rng, Victim};
use holarchy_tests::web::Web;
use holarchy_tests::*;
use schemas::{HolonId, HolonKind, OrderSnapshot, OrderStatus, PartPlace};

/// SIGKILLs of holon processes, at least.
const KILLS: usize = 24;
/// Cut links of the plant's controllers, at least.
const CUTS: usize = 3;
/// SIGKILLs of the plant simulator (all its controllers at once), at least.
const PLANT_KILLS: usize = 3;
/// The dashboard's bound on a part's wait in one place, in seconds.
const WAIT_BOUND_S: u64 = 90;
/// The longest the cell may go without an order ending.
const STALL_BOUND: Duration = Duration::from_secs(180);
/// The whole run's limit.
const RUN_LIMIT: Duration = Duration::from_secs(1500);

/// The demo's plant, on free ports; the conveyor's controller fenced, so that a
/// conveyor restarted mid-move learns what became of it.
const PLANT: &str = r#"
layout = ["conveyor1.toml", "robot1.toml", "robot2.toml", "inspect1.toml", "transfer1.toml"]

[[controller]]
resource = "robot1"
listen = "127.0.0.1:0"
delay_ms = 300

[[controller]]
resource = "robot2"
listen = "127.0.0.1:0"
delay_ms = 300

[[controller]]
resource = "inspect1"
listen = "127.0.0.1:0"
delay_ms = 100
inspect_fail_every = 7

[[controller]]
resource = "conveyor1"
listen = "127.0.0.1:0"
fenced_lease_ms = 1000

[[controller]]
resource = "transfer1"
listen = "127.0.0.1:0"
fenced_lease_ms = 1000
"#;

/// The cell on its plant, and what the driver did to it.
struct Run {
    dir: PathBuf,
    plant: PlantProcess,
    victims: BTreeMap<String, Victim>,
    kills: usize,
    /// Kills of a transporter (the conveyor, the transfer robot) while the plant had a
    /// part on it.
    mid_move: usize,
    cuts: usize,
    /// SIGKILLs of the plant simulator.
    plant_kills: usize,
    /// Operators' words said on lost parts.
    words: usize,
}

/// Copies the demo's config `file` into `dir`, with `edit` applied.
fn demo_copy(dir: &Path, file: &str, edit: impl Fn(String) -> String) -> PathBuf {
    let text = std::fs::read_to_string(demo_config(file)).unwrap();
    let path = dir.join(file);
    std::fs::write(&path, edit(text)).unwrap();
    path
}

impl Run {
    async fn start(dir: &Path, cell: &Cell) -> Run {
        let conveyor = demo_copy(dir, "conveyor1.toml", |t| {
            t.replace(
                "address = \"127.0.0.1:7621\"",
                "address = \"127.0.0.1:7621\"\nfenced = true",
            )
        });
        let transfer = demo_copy(dir, "transfer1.toml", |t| {
            t.replace(
                "address = \"127.0.0.1:7622\"",
                "address = \"127.0.0.1:7622\"\nfenced = true",
            )
        });
        let mut configs = vec![("conveyor1", conveyor), ("transfer1", transfer)];
        for name in ["robot1", "robot2", "inspect1"] {
            configs.push((name, demo_copy(dir, &format!("{name}.toml"), |t| t)));
        }
        let plant = PlantProcess::start(dir, PLANT);
        let data = dir.join("data").to_str().unwrap().to_string();
        let mut victims = BTreeMap::new();
        for (name, config) in configs {
            let extra = vec![
                "--controller".to_string(),
                plant.controllers[name].clone(),
                "--data-dir".to_string(),
                data.clone(),
            ];
            let key = cell.keys.alive(&HolonId::resource(name).unwrap());
            victims.insert(name.to_string(), (config, extra, key, "holon-node"));
        }
        let orders = demo_copy(dir, "orders1.toml", |t| {
            t.replace("max_attempts = 3", "max_attempts = 20").replace(
                "durability = \"power_loss\"",
                "durability = \"process_crash\"",
            )
        });
        victims.insert(
            "orders1".into(),
            (
                orders,
                vec!["--data-dir".into(), data],
                cell.keys.host("order-node", "orders1"),
                "order-node",
            ),
        );
        let product = HolonId::new(HolonKind::Product, "breaker").unwrap();
        victims.insert(
            "breaker".into(),
            (
                demo_config("breaker.toml"),
                vec![],
                cell.keys.alive(&product),
                "holon-node",
            ),
        );
        let mut started = BTreeMap::new();
        for (name, (config, extra, ready_key, program)) in victims {
            let victim = Victim::start(dir, cell, &name, program, config, extra, ready_key);
            cell.wait_token(&victim.ready_key).await.unwrap();
            started.insert(name, victim);
        }
        for resource in ["conveyor1", "transfer1", "robot1", "robot2", "inspect1"] {
            cell.wait_serving(resource).await.unwrap();
        }
        Run {
            dir: dir.to_path_buf(),
            plant,
            victims: started,
            kills: 0,
            mid_move: 0,
            cuts: 0,
            plant_kills: 0,
            words: 0,
        }
    }

    /// SIGKILLs `name` and starts it again on its journal once `pause` has passed.
    async fn kill(&mut self, cell: &Cell, name: &str, pause: Duration, started: Instant) {
        let victim = self.victims.get_mut(name).unwrap();
        victim.process.kill();
        victim.kills += 1;
        self.kills += 1;
        println!("{:7.2}s kill -9 {name}", started.elapsed().as_secs_f64());
        tokio::time::sleep(pause).await;
        victim.restart(&self.dir, cell);
        cell.wait_token(&victim.ready_key).await.unwrap();
    }

    /// Kills the plant simulator with SIGKILL (every controller of the cell at once,
    /// whatever it was doing) and starts it again on its state file after `pause`.
    fn kill_plant(&mut self, pause: Duration, started: Instant) {
        let moving = self.plant.state()["in_transit"]
            .as_array()
            .map_or(0, |m| m.len());
        self.plant.kill_and_restart_after(&self.dir, pause);
        self.kills += 1;
        self.plant_kills += 1;
        println!(
            "{:7.2}s kill -9 plant-sim ({moving} parts in transit), started again",
            started.elapsed().as_secs_f64()
        );
    }

    /// Kills the conveyor while the plant has a part on it (waiting at most 20 s for
    /// one).
    async fn kill_mid_move(&mut self, cell: &Cell, pause: Duration, started: Instant) {
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut victim = "conveyor1";
        while Instant::now() < deadline {
            let truth = self.plant.state();
            let moving = truth["in_transit"].as_array().and_then(|moves| {
                moves
                    .iter()
                    .filter(|m| m["stopped"] != true)
                    .find_map(|m| m["transporter"].as_str().map(str::to_string))
            });
            if let Some(transporter) = moving {
                victim = if transporter == "transfer1" {
                    "transfer1"
                } else {
                    "conveyor1"
                };
                self.mid_move += 1;
                break;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        self.kill(cell, victim, pause, started).await;
    }

    /// The operator's duty: each lost part is looked up in the plant and, once it is at
    /// rest at one end of its lost move, its place is said.
    fn find_lost_parts(&mut self, cell: &Cell, orders: &BTreeMap<HolonId, OrderSnapshot>) {
        let truth = self.plant.state();
        for order in orders.values() {
            let Some(PartPlace::Lost { from, to, .. }) = &order.part else {
                continue;
            };
            let name = order.holon.name();
            let Some(at) = resting_place(&truth, name) else {
                continue;
            };
            assert!(
                at == from.as_str() || at == to.as_str(),
                "{name}: lost between {from} and {to}, the plant has it at {at}"
            );
            let said = std::process::Command::new(bin("cell"))
                .args(["part", name, "--at", &at, "--cell", cell.keys.cell()])
                .args(["--connect", &cell.endpoint])
                .output()
                .unwrap();
            println!(
                "operator: {name} is at {at}: {}{}",
                String::from_utf8_lossy(&said.stdout).trim(),
                String::from_utf8_lossy(&said.stderr).trim()
            );
            self.words += usize::from(said.status.success());
        }
    }
}

/// Where the plant has `part` at rest (at a location, not on its way), if it does.
fn resting_place(truth: &serde_json::Value, part: &str) -> Option<String> {
    let moving = truth["in_transit"]
        .as_array()
        .is_some_and(|m| m.iter().any(|m| m["load"]["part"] == part));
    if moving {
        return None;
    }
    truth["locations"]
        .as_object()?
        .iter()
        .find(|(_, parts)| {
            parts
                .as_array()
                .is_some_and(|p| p.iter().any(|p| p["part"] == part))
        })
        .map(|(location, _)| location.clone())
}

async fn all_orders(cell: &Cell) -> BTreeMap<HolonId, OrderSnapshot> {
    // None while the listing is incomplete (the order-node restarting): asked again.
    ::cell::client::listing::all_orders(&cell.session, &cell.keys, Duration::from_secs(3))
        .await
        .map(|orders| orders.into_iter().map(|o| (o.holon.clone(), o)).collect())
        .unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread")]
async fn parts_and_orders_survive_kills_mid_move() {
    let count: u32 = std::env::var("HOLARCHY_MATERIAL_CHAOS_ORDERS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(200);
    let (mut rng, seed) = Rng::seeded();
    println!("material chaos seed {seed} (HOLARCHY_CHAOS_SEED={seed} replays it), {count} orders");
    for program in ["holon-node", "order-node", "plant-sim", "cell"] {
        bin(program);
    }
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    println!("material chaos in {}", dir.path().display());
    let cell = Cell::open("t-mchaos").await.unwrap();
    let mut run = Run::start(dir.path(), &cell).await;
    let wait_bound = WAIT_BOUND_S.to_string();
    let (_dashboard, address) = start_dashboard(
        dir.path(),
        cell.keys.cell(),
        &cell.endpoint,
        &["--part-wait-alarm-s", &wait_bound],
    );
    let ids = cell.submit("breaker", count).await.unwrap();
    assert_eq!(ids.len(), count as usize);

    // The driver: a kill (or a cut) every 3 to 7 s until its quota is met, then the
    // cell finishes on its own; the operator's duty and the deadlock check every round.
    let mut round = 0usize;
    // The cell makes progress: some order ends every STALL_BOUND at least.
    let mut progress = (0usize, Instant::now());
    let orders = loop {
        tokio::time::sleep(Duration::from_millis(3000 + rng.below(4000))).await;
        let orders = all_orders(&cell).await;
        let waits: serde_json::Value = serde_json::from_str(&run.plant.command("waits")).unwrap();
        assert_eq!(
            waits["deadlocked"], false,
            "the plant deadlocked: {waits:#}"
        );
        run.find_lost_parts(&cell, &orders);
        if orders.len() == count as usize && orders.values().all(|o| o.status.is_final()) {
            break orders;
        }
        let ended = orders.values().filter(|o| o.status.is_final()).count();
        if ended != progress.0 {
            progress = (ended, Instant::now());
        }
        if started.elapsed() > RUN_LIMIT || progress.1.elapsed() > STALL_BOUND {
            let kept = dir.keep();
            panic!(
                "after {:?}: {} of {count} orders ended (the run's files kept in {}); plant: {}",
                started.elapsed(),
                orders.values().filter(|o| o.status.is_final()).count(),
                kept.display(),
                run.plant.command("waits")
            );
        }
        if run.kills >= KILLS && run.cuts >= CUTS && run.plant_kills >= PLANT_KILLS {
            continue;
        }
        let pause = Duration::from_millis(50 + rng.below(400));
        round += 1;
        match round % 6 {
            0 if run.plant_kills < run.cuts => run.kill_plant(pause, started),
            0 => {
                let resource = ["conveyor1", "transfer1", "robot1", "robot2", "inspect1"]
                    [rng.below(5) as usize];
                assert_eq!(run.plant.command(&format!("cut {resource}")), "ok");
                run.cuts += 1;
                println!(
                    "{:7.2}s cut {resource}'s links",
                    started.elapsed().as_secs_f64()
                );
            }
            1 | 4 => run.kill_mid_move(&cell, pause, started).await,
            3 => run.kill(&cell, "orders1", pause, started).await,
            _ => {
                let victim =
                    ["robot1", "robot2", "inspect1", "transfer1", "breaker"][rng.below(5) as usize];
                run.kill(&cell, victim, pause, started).await
            }
        }
    };

    every_order_ended_properly(&orders, &ids);
    let truth = run.plant.state();
    the_control_agrees_with_the_plant(&cell, &orders, &truth).await;
    no_done_step_ran_twice(dir.path(), &run.plant, &orders);
    let alarms = Web::plain(&address).call("GET", "/api/alarms", "").json();
    let waited: Vec<&serde_json::Value> = alarms
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| a["kind"] == "part_waits")
        .collect();
    if !waited.is_empty() {
        let kept = dir.keep();
        panic!(
            "parts waited beyond {WAIT_BOUND_S} s (the run's files kept in {}): {waited:#?}",
            kept.display()
        );
    }

    let count_of = |status| orders.values().filter(|o| o.status == status).count();
    let rebooks: u32 = orders.values().map(|o| o.rebooks).sum();
    let kills: Vec<String> = run
        .victims
        .values()
        .map(|v| format!("{}={}", v.name, v.kills))
        .collect();
    println!(
        "material chaos figures: orders {count}, done {}, scrapped {}, failed {}, kills {} ({} plant-sim={}), of them a transporter mid-move {}, cuts {}, operators' words {}, rebooks {rebooks}, parts shipped {}, took {:.1}s",
        count_of(OrderStatus::Done),
        count_of(OrderStatus::Scrapped),
        count_of(OrderStatus::Failed),
        run.kills,
        kills.join(" "),
        run.plant_kills,
        run.mid_move,
        run.cuts,
        run.words,
        truth["shipped"],
        started.elapsed().as_secs_f64()
    );
    assert!(
        run.kills >= 20 && run.mid_move >= 4 && run.cuts >= CUTS && run.plant_kills >= PLANT_KILLS,
        "the driver did too little: {} kills, {} mid-move, {} cuts, {} of the plant",
        run.kills,
        run.mid_move,
        run.cuts,
        run.plant_kills
    );
}

/// Every submitted order is there; a done one did each step once, in order, with each
/// rework (back to the first step) doing both again; any other says why it ended.
fn every_order_ended_properly(orders: &BTreeMap<HolonId, OrderSnapshot>, ids: &[String]) {
    let names: Vec<String> = orders.keys().map(|h| h.name().to_string()).collect();
    let mut expected = ids.to_vec();
    expected.sort();
    assert_eq!(names, expected, "an order is missing");
    for order in orders.values() {
        let steps: Vec<&str> = order.completed.iter().map(|(s, _)| s.as_str()).collect();
        match order.status {
            OrderStatus::Done => {
                let rounds = 1 + order.reworks as usize;
                let expected: Vec<&str> = ["pick_n_place", "inspect"].repeat(rounds);
                assert_eq!(steps, expected, "a step done twice or missing: {order:#?}");
            }
            _ => assert!(
                order.reason.as_deref().is_some_and(|r| !r.is_empty()),
                "no reason: {order:#?}"
            ),
        }
    }
}

/// The control's view of every part equals the plant's: each part that entered the
/// cell left it by the exit (the plant counted it shipped), the plant holds no part and
/// moves none, every pallet is free, and no resource holds a place.
async fn the_control_agrees_with_the_plant(
    cell: &Cell,
    orders: &BTreeMap<HolonId, OrderSnapshot>,
    truth: &serde_json::Value,
) {
    let mut shipped = 0;
    for order in orders.values() {
        match &order.part {
            Some(PartPlace::Shipped { exit }) => {
                assert_eq!(exit.as_str(), "conveyor1.load", "{order:#?}");
                shipped += 1;
            }
            Some(PartPlace::Outside) => {}
            other => panic!("{} ended with its part {other:?}", order.holon),
        }
    }
    assert_eq!(truth["shipped"], shipped, "{truth:#}");
    assert!(
        truth["in_transit"].as_array().unwrap().is_empty(),
        "{truth:#}"
    );
    for (location, parts) in truth["locations"].as_object().unwrap() {
        assert!(
            parts.as_array().unwrap().is_empty(),
            "the plant still has parts at {location}: {truth:#}"
        );
    }
    assert_eq!(free_pallets(truth, "conveyor1"), 4, "{truth:#}");
    for resource in ["conveyor1", "robot1", "robot2", "inspect1"] {
        let status = cell.status(resource).await.unwrap();
        assert!(
            status.get("places").is_none(),
            "{resource} still holds places: {status:#}"
        );
    }
}

/// What the controllers ran, from the plant's trace (every action a controller ran
/// to its end, written before its reply, across the plant's lives): every step
/// recorded as done was executed, and nothing beyond the attempts the orders abandoned
/// (interrupted, failed, rebooked) ran.
fn no_done_step_ran_twice(
    dir: &Path,
    plant: &PlantProcess,
    orders: &BTreeMap<HolonId, OrderSnapshot>,
) {
    let executed = |resources: &[&str], action: &str| -> u64 {
        let done = PlantProcess::done_in_trace(dir, action);
        resources.iter().filter_map(|r| done.get(*r)).sum()
    };
    let done = |service: &str| -> u64 {
        orders
            .values()
            .flat_map(|o| &o.completed)
            .filter(|(s, _)| s == service)
            .count() as u64
    };
    let abandoned: u64 = orders
        .values()
        .map(|o| (o.rebooks + o.failed_attempts) as u64)
        .sum();
    for (what, executed, recorded) in [
        (
            "place",
            executed(&["robot1", "robot2"], "place"),
            done("pick_n_place"),
        ),
        (
            "inspect",
            executed(&["inspect1"], "inspect"),
            done("inspect"),
        ),
    ] {
        assert!(
            executed >= recorded,
            "{what}: {executed} executed < {recorded} recorded done"
        );
        assert!(
            executed <= recorded + abandoned,
            "{what}: {executed} executed > {recorded} done + {abandoned} abandoned attempts"
        );
    }
    println!(
        "controllers (this life of the plant): {}",
        plant.command("counts")
    );
}

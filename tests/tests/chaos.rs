//! Chaos: a cell processes 100 orders while a driver kills holon processes with SIGKILL
//! at random moments (resources, the product and the order-node, several times) and
//! restarts them on the same data directories, kills controller simulators (restarted on
//! their addresses), and starts a twin of a resource (which must be refused). At the end every order has completed or
//! failed with a stated reason, none is missing, and the controllers' command counts
//! show no step acknowledged as done was executed again.
//!
//! Bounded: at most `KILLS` kills, at most `RUN_LIMIT` for the whole run. The seed is
//! printed; `HOLARCHY_CHAOS_SEED=N` replays one.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

use holarchy_tests::chaos::{Rng, Victim};
use holarchy_tests::*;
use schemas::{HolonId, HolonKind, OrderSnapshot, OrderStatus};

const ORDERS: u32 = 100;
const KILLS: usize = 12;
const RUN_LIMIT: Duration = Duration::from_secs(240);

async fn all_orders(cell: &Cell) -> BTreeMap<HolonId, OrderSnapshot> {
    // Every order, finished ones too, a page at a time; none while the listing is
    // incomplete (an order-node restarting), and the caller asks again.
    ::cell::client::listing::all_orders(&cell.session, &cell.keys, Duration::from_secs(3))
        .await
        .map(|orders| orders.into_iter().map(|o| (o.holon.clone(), o)).collect())
        .unwrap_or_default()
}

/// The controller simulators' pauses per step, in ms.
const SIMULATORS: [(&str, &str); 4] = [
    ("robot1", "60"),
    ("robot2", "60"),
    ("inspect1", "20"),
    ("conveyor1", "30"),
];

#[tokio::test(flavor = "multi_thread")]
async fn orders_survive_random_kills() {
    let (mut rng, seed) = Rng::seeded();
    println!("chaos seed {seed} (HOLARCHY_CHAOS_SEED={seed} replays it)");
    // The binaries are built (if they need it) before the clock starts: a build must
    // not eat the run's time limit and leave the driver no time to kill anything.
    for program in ["holon-node", "order-node", "robot-sim"] {
        bin(program);
    }
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-chaos").await.unwrap();
    let mut chaos = Chaos::start(dir.path(), &cell).await;

    let ids = cell.submit("breaker", ORDERS).await.unwrap();
    assert_eq!(ids.len(), ORDERS as usize);

    chaos.drive(&cell, &mut rng, started).await;
    chaos.the_twin_was_refused();
    let orders = every_order_ends(&cell, started).await;
    no_order_is_missing_and_each_ended_properly(&orders, &ids);
    chaos.no_done_step_ran_twice(&orders);
    chaos.report(&orders, started);
}

/// The cell under attack: its controllers, its holons, and what the driver did.
struct Chaos<'a> {
    dir: &'a Path,
    /// The controllers are the hardware: they count what they execute.
    sims: BTreeMap<&'static str, Sim>,
    /// Killed simulators: their counts stay in their files.
    retired: Vec<(&'static str, Sim)>,
    /// The holon processes: four resources, the product, the order-node (last).
    victims: Vec<Victim>,
    kills: usize,
    sim_kills: usize,
    /// A twin of a resource (same name, its own data dir), which must be refused.
    twin: Option<(String, Process)>,
}

impl<'a> Chaos<'a> {
    /// Starts the simulators, then the holons on one data directory, and waits for all.
    async fn start(dir: &'a Path, cell: &Cell) -> Chaos<'a> {
        let mut sims = BTreeMap::new();
        for (name, delay) in SIMULATORS {
            let sim = Sim::start(
                dir,
                &format!("{name}-sim"),
                "127.0.0.1:0",
                &["--delay-ms", delay],
            );
            sims.insert(name, sim.unwrap());
        }
        // The order-node retries a step more often than the demo's, as kills interrupt
        // steps.
        let orders_config = dir.join("orders-chaos.toml");
        std::fs::write(
            &orders_config,
            std::fs::read_to_string(demo_config("orders1.toml"))
                .unwrap()
                .replace("max_attempts = 3", "max_attempts = 20")
                .replace(
                    "durability = \"power_loss\"",
                    "durability = \"process_crash\"",
                ),
        )
        .unwrap();
        let data_arg = dir.join("data").to_str().unwrap().to_string();
        let mut victims = Vec::new();
        for (name, config) in [
            ("robot1", "robot1.toml"),
            ("robot2", "robot1.toml"),
            ("inspect1", "inspect1.toml"),
            ("conveyor1", "conveyor1.toml"),
        ] {
            let extra = vec![
                "--controller".into(),
                sims[name].address.clone(),
                "--data-dir".into(),
                data_arg.clone(),
            ];
            let key = cell.keys.alive(&HolonId::resource(name).unwrap());
            victims.push(Victim::start(
                dir,
                cell,
                name,
                "holon-node",
                demo_config(config),
                extra,
                key,
            ));
        }
        let product_key = cell
            .keys
            .alive(&HolonId::new(HolonKind::Product, "breaker").unwrap());
        victims.push(Victim::start(
            dir,
            cell,
            "breaker",
            "holon-node",
            stationary_breaker(),
            vec![],
            product_key,
        ));
        let orders_key = cell.keys.host("order-node", "orders1");
        victims.push(Victim::start(
            dir,
            cell,
            "orders1",
            "order-node",
            orders_config,
            vec!["--data-dir".into(), data_arg],
            orders_key,
        ));
        for victim in &victims {
            cell.wait_token(&victim.ready_key).await.unwrap();
        }
        Chaos {
            dir,
            sims,
            retired: Vec::new(),
            victims,
            kills: 0,
            sim_kills: 0,
            twin: None,
        }
    }

    /// The driver: kill a random holon at a random moment, start it again; every fourth
    /// round a controller simulator instead; once, start a twin of a resource.
    async fn drive(&mut self, cell: &Cell, rng: &mut Rng, started: Instant) {
        let mut rounds = 0;
        while self.kills < KILLS && started.elapsed() < RUN_LIMIT / 2 {
            tokio::time::sleep(Duration::from_millis(200 + rng.below(600))).await;
            let finished = all_orders(cell)
                .await
                .values()
                .filter(|o| o.status.is_final())
                .count();
            if finished == ORDERS as usize {
                break;
            }
            rounds += 1;
            if self.twin.is_none() && rounds == 3 {
                self.start_a_twin(cell, rng, started);
            }
            if rounds % 4 == 0 {
                self.kill_a_simulator(rng, started, finished).await;
            } else {
                self.kill_a_holon(cell, rng, started, finished).await;
            }
        }
    }

    /// A resource's config copied to "another host": same name, its own data dir.
    fn start_a_twin(&mut self, cell: &Cell, rng: &mut Rng, started: Instant) {
        let victim = &self.victims[rng.below(4) as usize];
        let twin_dir = self.dir.join("twin");
        std::fs::create_dir_all(&twin_dir).unwrap();
        let process = start_holon(
            &twin_dir,
            "holon-node",
            &victim.config,
            &victim.name,
            cell,
            &[
                "--controller",
                &self.sims[victim.name.as_str()].address,
                "--data-dir",
                twin_dir.join("data").to_str().unwrap(),
            ],
        )
        .unwrap();
        println!(
            "{:6.2}s twin of {} started",
            started.elapsed().as_secs_f64(),
            victim.name
        );
        self.twin = Some((victim.name.clone(), process));
    }

    /// A controller that reboots: killed, and a new one started on the same address.
    async fn kill_a_simulator(&mut self, rng: &mut Rng, started: Instant, finished: usize) {
        let (name, delay) = SIMULATORS[rng.below(4) as usize];
        let mut old = self.sims.remove(name).unwrap();
        old.process.kill();
        self.sim_kills += 1;
        println!(
            "{:6.2}s kill -9 the controller simulator of {name} ({finished} of {ORDERS} orders finished)",
            started.elapsed().as_secs_f64()
        );
        tokio::time::sleep(Duration::from_millis(50 + rng.below(300))).await;
        let mut restarted = None;
        for _ in 0..50 {
            // The same address: the holon reconnects to it.
            let label = format!("{name}-sim.{}", self.sim_kills);
            match Sim::start(self.dir, &label, &old.address, &["--delay-ms", delay]) {
                Ok(sim) => {
                    restarted = Some(sim);
                    break;
                }
                Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
            }
        }
        self.sims.insert(
            name,
            restarted.expect("the simulator restarts on its address"),
        );
        self.retired.push((name, old));
    }

    /// Every third kill takes the order-node; the others a random holon. It is started
    /// again on its data directory.
    async fn kill_a_holon(
        &mut self,
        cell: &Cell,
        rng: &mut Rng,
        started: Instant,
        finished: usize,
    ) {
        let index = if self.kills % 3 == 2 {
            5
        } else {
            rng.below(6) as usize
        };
        let victim = &mut self.victims[index];
        victim.process.kill();
        victim.kills += 1;
        self.kills += 1;
        println!(
            "{:6.2}s kill -9 {} ({} of {ORDERS} orders finished)",
            started.elapsed().as_secs_f64(),
            victim.name,
            finished
        );
        tokio::time::sleep(Duration::from_millis(50 + rng.below(300))).await;
        victim.restart(self.dir, cell);
        cell.wait_token(&victim.ready_key).await.unwrap();
    }

    /// The twin was refused, and said who holds the name.
    fn the_twin_was_refused(&mut self) {
        if let Some((name, mut process)) = self.twin.take() {
            let status = process.wait_exit(Duration::from_secs(30)).unwrap();
            let stderr = process.stderr();
            assert!(!status.success(), "the twin of {name} ran: {stderr}");
            assert!(stderr.contains("already running"), "{stderr}");
        }
    }

    /// What the controllers executed of `action` (the retired ones included).
    fn executed(&self, names: &[&str], action: &str) -> u64 {
        let current: u64 = names.iter().map(|n| self.sims[n].executed(action)).sum();
        let before: u64 = self
            .retired
            .iter()
            .filter(|(n, _)| names.contains(n))
            .map(|(_, sim)| sim.executed(action))
            .sum();
        current + before
    }

    /// The controllers' counts: every step recorded as done was executed, and nothing
    /// beyond the attempts the orders abandoned (interrupted, failed, rebooked) ran.
    fn no_done_step_ran_twice(&self, orders: &BTreeMap<HolonId, OrderSnapshot>) {
        let done_steps = |service: &str| -> u64 {
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
        let moves = self.executed(&["conveyor1"], "move");
        let picks = self.executed(&["robot1", "robot2"], "pick");
        let places = self.executed(&["robot1", "robot2"], "place");
        let inspections = self.executed(&["inspect1"], "inspect");
        for (what, executed, recorded) in [
            ("move", moves, done_steps("transport")),
            ("place", places, done_steps("pick_n_place")),
            ("inspect", inspections, done_steps("inspect")),
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
        assert!(picks >= places);
        println!(
            "controllers: moves {moves}, picks {picks}, places {places}, inspections {inspections}"
        );
    }

    /// The figures of the run; a run that killed nothing proved nothing.
    fn report(&self, orders: &BTreeMap<HolonId, OrderSnapshot>, started: Instant) {
        let count = |status| orders.values().filter(|o| o.status == status).count();
        let rebooks: u32 = orders.values().map(|o| o.rebooks).sum();
        let retries: u32 = orders.values().map(|o| o.failed_attempts).sum();
        let kills_by: Vec<String> = self
            .victims
            .iter()
            .map(|v| format!("{}={}", v.name, v.kills))
            .collect();
        println!("chaos figures: orders {ORDERS}, done {}, failed {}, kills {} ({}), simulator kills {}, rebooks {rebooks}, retries {retries}, took {:.1}s", count(OrderStatus::Done), count(OrderStatus::Failed), self.kills, kills_by.join(" "), self.sim_kills, started.elapsed().as_secs_f64());
        assert!(
            self.kills >= 3 && self.sim_kills >= 1,
            "the driver killed only {} holons and {} simulators",
            self.kills,
            self.sim_kills
        );
        for failed in orders.values().filter(|o| o.status == OrderStatus::Failed) {
            println!(
                "  failed {}: {}",
                failed.holon,
                failed.reason.as_ref().map_or("", |r| r.as_str())
            );
        }
    }
}

/// Waits until every order has ended (within the run's limit).
async fn every_order_ends(cell: &Cell, started: Instant) -> BTreeMap<HolonId, OrderSnapshot> {
    loop {
        let orders = all_orders(cell).await;
        if orders.len() == ORDERS as usize && orders.values().all(|o| o.status.is_final()) {
            return orders;
        }
        assert!(
            started.elapsed() < RUN_LIMIT,
            "after {:?}: {} orders known, running: {:#?}",
            started.elapsed(),
            orders.len(),
            orders
                .values()
                .filter(|o| !o.status.is_final())
                .take(5)
                .collect::<Vec<_>>()
        );
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
}

/// Every submitted order is there; a done one did each step once, in order; any other
/// says why it ended.
fn no_order_is_missing_and_each_ended_properly(
    orders: &BTreeMap<HolonId, OrderSnapshot>,
    ids: &[String],
) {
    let names: Vec<String> = orders.keys().map(|h| h.name().to_string()).collect();
    let mut expected = ids.to_vec();
    expected.sort();
    assert_eq!(names, expected, "an order is missing");
    for order in orders.values() {
        match order.status {
            OrderStatus::Done => {
                let steps: Vec<&str> = order.completed.iter().map(|(s, _)| s.as_str()).collect();
                assert_eq!(
                    steps,
                    ["transport", "pick_n_place", "inspect"],
                    "a step done twice or missing: {order:#?}"
                );
            }
            _ => assert!(
                order.reason.as_deref().is_some_and(|r| !r.is_empty()),
                "no reason: {order:#?}"
            ),
        }
    }
}

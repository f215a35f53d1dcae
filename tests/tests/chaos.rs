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
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use holarchy_tests::*;
use schemas::{HolonId, HolonKind, OrderSnapshot, OrderStatus};

const ORDERS: u32 = 100;
const KILLS: usize = 12;
const RUN_LIMIT: Duration = Duration::from_secs(240);

/// xorshift64*: enough randomness for choosing victims and moments.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// A holon process the driver may kill, and how to start it again.
struct Victim {
    name: String,
    program: &'static str,
    config: PathBuf,
    extra: Vec<String>,
    ready_key: String,
    process: Process,
    kills: usize,
}

impl Victim {
    fn start(
        dir: &Path,
        cell: &Cell,
        name: &str,
        program: &'static str,
        config: PathBuf,
        extra: Vec<String>,
        ready_key: String,
    ) -> Victim {
        let args: Vec<&str> = extra.iter().map(String::as_str).collect();
        let process = start_holon(dir, program, &config, name, cell, &args).unwrap();
        Victim {
            name: name.into(),
            program,
            config,
            extra,
            ready_key,
            process,
            kills: 0,
        }
    }

    fn restart(&mut self, dir: &Path, cell: &Cell) {
        let args: Vec<&str> = self.extra.iter().map(String::as_str).collect();
        // Keep each incarnation's log.
        let _ = std::fs::rename(
            &self.process.stderr_path,
            dir.join(format!("{}.stderr.{}", self.name, self.kills)),
        );
        self.process =
            start_holon(dir, self.program, &self.config, &self.name, cell, &args).unwrap();
    }
}

async fn all_orders(cell: &Cell) -> BTreeMap<HolonId, OrderSnapshot> {
    let mut orders = BTreeMap::new();
    if let Ok(replies) = cell
        .session
        .get(cell.keys.order_states())
        .timeout(Duration::from_secs(3))
        .await
    {
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                if let Ok(snapshot) =
                    serde_json::from_slice::<OrderSnapshot>(&sample.payload().to_bytes())
                {
                    orders.insert(snapshot.holon.clone(), snapshot);
                }
            }
        }
    }
    orders
}

#[tokio::test(flavor = "multi_thread")]
async fn orders_survive_random_kills() {
    let seed = std::env::var("HOLARCHY_CHAOS_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| schemas::unix_ms() | 1);
    println!("chaos seed {seed} (HOLARCHY_CHAOS_SEED={seed} replays it)");
    let mut rng = Rng(seed);
    // The binaries are built (if they need it) before the clock starts: a build must
    // not eat the run's time limit and leave the driver no time to kill anything.
    for program in ["holon-node", "order-node", "robot-sim"] {
        bin(program);
    }
    let started = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let data = dir.join("data");
    let cell = Cell::open("t-chaos").await.unwrap();

    // The controllers are the hardware: they count what they execute. The driver also
    // kills a simulator now and then (a controller that reboots) and starts a new one on
    // the same address; a killed one's counts stay in its file (`retired`).
    let mut sims = BTreeMap::new();
    let mut retired: Vec<(&str, Sim)> = Vec::new();
    let delays: BTreeMap<&str, &str> = [
        ("robot1", "60"),
        ("robot2", "60"),
        ("inspect1", "20"),
        ("conveyor1", "30"),
    ]
    .into();
    for (name, delay) in [
        ("robot1", "60"),
        ("robot2", "60"),
        ("inspect1", "20"),
        ("conveyor1", "30"),
    ] {
        sims.insert(
            name,
            Sim::start(
                dir,
                &format!("{name}-sim"),
                "127.0.0.1:0",
                &["--delay-ms", delay],
            )
            .unwrap(),
        );
    }
    // The order-node retries a step more often than the demo's, as kills interrupt steps.
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
    let data_arg = data.to_str().unwrap().to_string();
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
            &cell,
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
        &cell,
        "breaker",
        "holon-node",
        demo_config("breaker.toml"),
        vec![],
        product_key,
    ));
    let orders_key = cell.keys.host("order-node", "orders1");
    victims.push(Victim::start(
        dir,
        &cell,
        "orders1",
        "order-node",
        orders_config,
        vec!["--data-dir".into(), data_arg.clone()],
        orders_key,
    ));
    for victim in &victims {
        cell.wait_token(&victim.ready_key).await.unwrap();
    }

    let ids = cell.submit("breaker", ORDERS).await.unwrap();
    assert_eq!(ids.len(), ORDERS as usize);

    // The driver: kill a random holon at a random moment, start it again; every fourth
    // round a controller simulator instead; once, start a twin of a resource (its config
    // copied to "another host": same name, its own data dir), which must be refused.
    let mut kills = 0;
    let mut rounds = 0;
    let mut sim_kills = 0;
    let mut twin: Option<(String, Process)> = None;
    while kills < KILLS && started.elapsed() < RUN_LIMIT / 2 {
        tokio::time::sleep(Duration::from_millis(200 + rng.below(600))).await;
        let finished = all_orders(&cell)
            .await
            .values()
            .filter(|o| o.status.is_final())
            .count();
        if finished == ORDERS as usize {
            break;
        }
        rounds += 1;
        if twin.is_none() && rounds == 3 {
            let victim = &victims[rng.below(4) as usize];
            let twin_dir = dir.join("twin");
            std::fs::create_dir_all(&twin_dir).unwrap();
            let process = start_holon(
                &twin_dir,
                "holon-node",
                &victim.config,
                &victim.name,
                &cell,
                &[
                    "--controller",
                    &sims[victim.name.as_str()].address,
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
            twin = Some((victim.name.clone(), process));
        }
        if rounds % 4 == 0 {
            let name = ["robot1", "robot2", "inspect1", "conveyor1"][rng.below(4) as usize];
            let mut old = sims.remove(name).unwrap();
            old.process.kill();
            sim_kills += 1;
            println!(
                "{:6.2}s kill -9 the controller simulator of {name} ({finished} of {ORDERS} orders finished)",
                started.elapsed().as_secs_f64()
            );
            tokio::time::sleep(Duration::from_millis(50 + rng.below(300))).await;
            let mut restarted = None;
            for _ in 0..50 {
                // The same address: the holon reconnects to it.
                match Sim::start(
                    dir,
                    &format!("{name}-sim.{sim_kills}"),
                    &old.address,
                    &["--delay-ms", delays[name]],
                ) {
                    Ok(sim) => {
                        restarted = Some(sim);
                        break;
                    }
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
            }
            sims.insert(
                name,
                restarted.expect("the simulator restarts on its address"),
            );
            retired.push((name, old));
            continue;
        }
        // Every third kill takes the order-node; the others a random holon.
        let index = if kills % 3 == 2 {
            5
        } else {
            rng.below(6) as usize
        };
        let victim = &mut victims[index];
        victim.process.kill();
        victim.kills += 1;
        kills += 1;
        println!(
            "{:6.2}s kill -9 {} ({} of {ORDERS} orders finished)",
            started.elapsed().as_secs_f64(),
            victim.name,
            finished
        );
        tokio::time::sleep(Duration::from_millis(50 + rng.below(300))).await;
        victim.restart(dir, &cell);
        cell.wait_token(&victim.ready_key).await.unwrap();
    }

    // The twin was refused, and said who holds the name.
    if let Some((name, mut process)) = twin {
        let status = process.wait_exit(Duration::from_secs(30)).unwrap();
        let stderr = process.stderr();
        assert!(!status.success(), "the twin of {name} ran: {stderr}");
        assert!(stderr.contains("already running"), "{stderr}");
    }

    // Every order ends: completed, or failed with a reason.
    let orders = loop {
        let orders = all_orders(&cell).await;
        if orders.len() == ORDERS as usize && orders.values().all(|o| o.status.is_final()) {
            break orders;
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
    };
    let names: Vec<String> = orders.keys().map(|h| h.name().to_string()).collect();
    let mut expected = ids.clone();
    expected.sort();
    assert_eq!(names, expected, "an order is missing");
    let done: Vec<&OrderSnapshot> = orders
        .values()
        .filter(|o| o.status == OrderStatus::Done)
        .collect();
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

    // The controllers' counts: every step recorded as done was executed, and nothing
    // beyond the attempts the orders abandoned (interrupted, failed, rebooked) ran.
    let count = |names: &[&str], action: &str| -> u64 {
        let current: u64 = names.iter().map(|n| sims[n].executed(action)).sum();
        let before: u64 = retired
            .iter()
            .filter(|(n, _)| names.contains(n))
            .map(|(_, sim)| sim.executed(action))
            .sum();
        current + before
    };
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
    let moves = count(&["conveyor1"], "move");
    let picks = count(&["robot1", "robot2"], "pick");
    let places = count(&["robot1", "robot2"], "place");
    let inspections = count(&["inspect1"], "inspect");
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

    let failed = orders
        .values()
        .filter(|o| o.status == OrderStatus::Failed)
        .count();
    let rebooks: u32 = orders.values().map(|o| o.rebooks).sum();
    let retries: u32 = orders.values().map(|o| o.failed_attempts).sum();
    let kills_by: Vec<String> = victims
        .iter()
        .map(|v| format!("{}={}", v.name, v.kills))
        .collect();
    println!("chaos figures: orders {ORDERS}, done {}, failed {failed}, kills {kills} ({}), simulator kills {sim_kills}, rebooks {rebooks}, retries {retries}, took {:.1}s", done.len(), kills_by.join(" "), started.elapsed().as_secs_f64());
    // A chaos run that killed nothing proved nothing.
    assert!(
        kills >= 3 && sim_kills >= 1,
        "the driver killed only {kills} holons and {sim_kills} simulators"
    );
    println!("controllers: moves {moves}, picks {picks}, places {places}, inspections {inspections}; recorded done steps {} per service", done.len());
    for failed in orders.values().filter(|o| o.status == OrderStatus::Failed) {
        println!(
            "  failed {}: {}",
            failed.holon,
            failed.reason.as_deref().unwrap_or("")
        );
    }
}

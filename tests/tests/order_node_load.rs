//! An order-node under an operator's load, as a plant runs it: a journal of 10,000
//! finished orders, 200 orders running on two robots (each with a busy agenda) with a
//! staff holon planning for them, three clients listing the orders every half second
//! (two as an operator's screen does, one the whole history) and a dashboard open and
//! read (it follows every resource's and order's state). Every process must stay on
//! the cell (no transport closed in any log, no token lost: the order-node's, the
//! robots', the staff holon's), every listing must be complete, and every order done.
//! The booking's round trip inside the node is reported beside the same production
//! without listings (read from the node's `booked` log lines, `took_us`); no timing is
//! asserted.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use holarchy_tests::web::Web;
use holarchy_tests::*;
use holon::journal::{Durability, Journal};
use order_node::progress::OrderProgress;
use schemas::{HolonId, OrderStatus};

/// Finished orders in the node's journal before it starts.
const FINISHED: u64 = 10_000;
/// Orders submitted in each phase.
const RUNNING: u32 = 200;
/// How long each phase may take before the test gives up.
const PHASE_LIMIT: Duration = Duration::from_secs(180);

/// Writes `FINISHED` finished orders (every 50th failed, the rest done) and the next
/// order number into the journal `orders1` will open in `data`.
fn seed_journal(data: &Path) {
    let journal = Journal::open(data, "order-node-orders1.sqlite", Durability::ProcessCrash)
        .expect("the journal opens");
    let now = schemas::unix_ms();
    let robot = HolonId::resource("robot1").unwrap();
    let orders: Vec<(String, OrderProgress)> = (1..=FINISHED)
        .map(|n| {
            let name = format!("orders1-{n}");
            let mut p = OrderProgress::new(HolonId::order(&name).unwrap(), "part", 3);
            p.step = 1;
            p.completed = vec![("pick_n_place".to_string(), robot.clone())];
            p.worked_with.insert(robot.clone());
            if n % 50 == 0 {
                p.status = OrderStatus::Failed;
                p.reason = Some("no resource proposed within the step's timeout".into());
            } else {
                p.status = OrderStatus::Done;
            }
            p.finished_at = Some(now - (FINISHED - n) * 10);
            (name, p)
        })
        .collect();
    for chunk in orders.chunks(2_000) {
        journal
            .put_all(chunk.iter().map(|(name, p)| ("order", name.as_str(), p)))
            .expect("the seed is written");
    }
    journal
        .put("meta", "next_order", &(FINISHED + 1))
        .expect("the next number is written");
}

/// The node's counts, asked until it answers (a page of none).
async fn counts(cell: &Cell) -> schemas::OrderCounts {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok(nodes) =
            ::cell::client::listing::counts(&cell.session, &cell.keys, Duration::from_secs(5)).await
        {
            if let Some((_, Ok(counts))) = nodes.into_iter().next() {
                return counts;
            }
        }
        assert!(Instant::now() < deadline, "orders1 gave no counts for 30 s");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Submits `RUNNING` orders and waits until none runs and `total` have finished.
async fn run_phase(cell: &Cell, phase: &str, total: u64) -> Duration {
    let started = Instant::now();
    let orders = cell.submit("part", RUNNING).await.unwrap();
    assert_eq!(
        orders.len(),
        RUNNING as usize,
        "{phase}: every order accepted"
    );
    loop {
        let c = counts(cell).await;
        if c.running == 0 && c.finished() >= total {
            assert_eq!(c.finished(), total, "{phase}: {c:?}");
            assert_eq!(
                c.done,
                total - FINISHED / 50,
                "{phase}: every new order done: {c:?}"
            );
            return started.elapsed();
        }
        assert!(
            started.elapsed() < PHASE_LIMIT,
            "{phase}: orders still running after {PHASE_LIMIT:?}: {c:?}"
        );
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// The `took_us` of the node's `booked` log lines, from line `from` on.
fn bookings(log: &Path, from: usize) -> (Vec<u64>, usize) {
    let text = std::fs::read_to_string(log).unwrap_or_default();
    let lines: Vec<&str> = text.lines().collect();
    let took = lines[from.min(lines.len())..]
        .iter()
        .filter(|l| l.contains("\"booked\""))
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter_map(|v| {
            v["took_us"]
                .as_u64()
                .or_else(|| v["fields"]["took_us"].as_u64())
        })
        .collect();
    (took, lines.len())
}

/// p50 and p99 of `values` in ms.
fn p50_p99(values: &mut [u64]) -> (f64, f64) {
    values.sort_unstable();
    let at = |q: f64| values[((values.len() as f64 - 1.0) * q).round() as usize] as f64 / 1000.0;
    (at(0.5), at(0.99))
}

/// What one lister saw.
#[derive(Default)]
struct Listed {
    runs: u64,
    incomplete: Vec<String>,
    slowest: Duration,
    /// The summary line of its last run.
    last_summary: String,
}

/// Runs `cell orders ARGS` every half second (start to start) until `stop`.
fn lister(
    cell: &Cell,
    args: &'static [&'static str],
    stop: Arc<AtomicBool>,
) -> tokio::task::JoinHandle<Listed> {
    let (cell_name, endpoint) = (cell.keys.cell().to_string(), cell.endpoint.clone());
    tokio::spawn(async move {
        let mut listed = Listed::default();
        while !stop.load(Ordering::SeqCst) {
            let began = Instant::now();
            let output = tokio::process::Command::new(bin("cell"))
                .arg("orders")
                .args(args)
                .args(["--cell", &cell_name, "--connect", &endpoint])
                .output()
                .await
                .expect("cell orders runs");
            let took = began.elapsed();
            let stdout = String::from_utf8_lossy(&output.stdout).to_string();
            listed.runs += 1;
            listed.slowest = listed.slowest.max(took);
            if !output.status.success() || stdout.contains("INCOMPLETE") {
                listed.incomplete.push(format!(
                    "{}{}",
                    stdout.lines().last().unwrap_or(""),
                    String::from_utf8_lossy(&output.stderr)
                ));
            }
            listed.last_summary = stdout.lines().next().unwrap_or("").to_string();
            tokio::time::sleep(Duration::from_millis(500).saturating_sub(took)).await;
        }
        listed
    })
}

/// Lines of the processes' logs that say a link was closed under them.
fn closings(dir: &Path) -> Vec<String> {
    let mut found = Vec::new();
    for file in [
        "orders1.log.json",
        "orders1.stderr",
        "dashboard.stderr",
        "planner.log.json",
        "planner.stderr",
        "robot1.log.json",
        "robot1.node.stderr",
        "robot2.log.json",
        "robot2.node.stderr",
    ] {
        let text = std::fs::read_to_string(dir.join(file)).unwrap_or_default();
        found.extend(
            text.lines()
                .filter(|l| l.contains("Closing transport") || l.contains("non droppable"))
                .map(|l| format!("{file}: {l}")),
        );
    }
    found
}

#[tokio::test(flavor = "multi_thread")]
async fn an_order_node_with_a_long_history_stays_on_the_cell_while_operators_list() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let data = dir.join("data");
    seed_journal(&data);
    let cell = Cell::open("t-load").await.unwrap();
    let mut robots = Vec::new();
    for name in ["robot1", "robot2"] {
        robots.push(
            cell.resource(dir, name)
                .sim_flags(&["--delay-ms", "10"])
                .start()
                .await
                .unwrap(),
        );
    }
    let _planner = start_holon(
        dir,
        "holon-node",
        &demo_config("planner.toml"),
        "planner",
        &cell,
        &[],
    )
    .unwrap();
    cell.wait_alive(&HolonId::staff("planner").unwrap())
        .await
        .unwrap();
    let (_part, _orders1) = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &data)
        .await
        .unwrap();
    // The tokens of the order-node, the robots and the staff holon: every loss of one
    // is recorded, by key.
    let lost = Arc::new(Mutex::new(Vec::<String>::new()));
    let mut token_watches = Vec::new();
    for key in [
        cell.keys.host("order-node", "orders1"),
        cell.keys.alive(&HolonId::resource("robot1").unwrap()),
        cell.keys.alive(&HolonId::resource("robot2").unwrap()),
        cell.keys.alive(&HolonId::staff("planner").unwrap()),
    ] {
        let lost = lost.clone();
        token_watches.push(
            cell.session
                .liveliness()
                .declare_subscriber(key)
                .callback(move |sample| {
                    if sample.kind() == zenoh::sample::SampleKind::Delete {
                        lost.lock().unwrap().push(sample.key_expr().to_string());
                    }
                })
                .await
                .unwrap(),
        );
    }
    let before = counts(&cell).await;
    assert_eq!(
        (before.running, before.finished()),
        (0, FINISHED),
        "the seeded history is read: {before:?}"
    );

    // Phase 1: production alone, the baseline.
    let log = dir.join("orders1.log.json");
    let (_, mark) = bookings(&log, 0);
    let alone = run_phase(&cell, "alone", FINISHED + RUNNING as u64).await;
    let (mut booked_alone, mark) = bookings(&log, mark);

    // Phase 2: the same production with three listers and a dashboard open.
    let dashboard_address = format!("127.0.0.1:{}", free_port());
    let mut dashboard = start_program(
        dir,
        "cell",
        "dashboard",
        &[
            "dashboard",
            "--connect",
            &cell.endpoint,
            "--cell",
            cell.keys.cell(),
            "--listen",
            &dashboard_address,
        ],
    )
    .unwrap();
    wait_listening(&dashboard_address).await.unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let screens = [
        lister(&cell, &[], stop.clone()),
        lister(&cell, &["--status", "running"], stop.clone()),
        lister(&cell, &["--all"], stop.clone()),
    ];
    let read_dashboard = {
        let (stop, web) = (stop.clone(), Web::plain(&dashboard_address));
        let failures = Arc::new(Mutex::new(Vec::new()));
        let seen = failures.clone();
        let task = tokio::task::spawn_blocking(move || {
            let mut reads = 0u64;
            while !stop.load(Ordering::SeqCst) {
                let answer = web.call("GET", "/api/orders", "");
                if answer.status != 200 {
                    seen.lock().unwrap().push(answer.status);
                }
                reads += 1;
                std::thread::sleep(Duration::from_millis(500));
            }
            reads
        });
        (task, failures)
    };
    let loaded = run_phase(&cell, "listed", FINISHED + 2 * RUNNING as u64).await;
    // The listers go on a little after the last order ended.
    tokio::time::sleep(Duration::from_secs(1)).await;
    stop.store(true, Ordering::SeqCst);
    let mut seen = Vec::new();
    for screen in screens {
        seen.push(screen.await.unwrap());
    }
    let dashboard_reads = read_dashboard.0.await.unwrap();
    let (mut booked_listed, _) = bookings(&log, mark);
    dashboard.kill();

    let (a50, a99) = p50_p99(&mut booked_alone);
    let (l50, l99) = p50_p99(&mut booked_listed);
    println!(
        "production alone: {RUNNING} orders in {alone:.1?}, {} bookings, p50 {a50:.2} ms, p99 {a99:.2} ms",
        booked_alone.len()
    );
    println!(
        "with listings: {RUNNING} orders in {loaded:.1?}, {} bookings, p50 {l50:.2} ms, p99 {l99:.2} ms ({:.2}x the p99 alone)",
        booked_listed.len(),
        l99 / a99.max(0.001)
    );
    for (name, listed) in ["default", "running", "all"].iter().zip(&seen) {
        println!(
            "lister {name}: {} listings, slowest {:.2?}, last: {}",
            listed.runs, listed.slowest, listed.last_summary
        );
    }
    println!("dashboard: {dashboard_reads} reads of /api/orders");
    let orders =
        ::cell::client::listing::all_orders(&cell.session, &cell.keys, Duration::from_secs(5))
            .await
            .expect("a complete listing");
    let advised: u32 = orders.iter().map(|o| o.advised).sum();
    println!(
        "staff: {advised} of {} steps booked on its advice",
        2 * RUNNING
    );

    let closed = closings(dir);
    assert!(closed.is_empty(), "links closed under load: {closed:#?}");
    assert!(
        lost.lock().unwrap().is_empty(),
        "tokens lost under load: {:?}",
        lost.lock().unwrap()
    );
    for (name, listed) in ["default", "running", "all"].iter().zip(&seen) {
        assert!(
            listed.runs >= 2,
            "lister {name} listed {} times",
            listed.runs
        );
        assert!(
            listed.incomplete.is_empty(),
            "lister {name}: incomplete listings: {:#?}",
            listed.incomplete
        );
    }
    // The whole-history lister saw every order, counted in its summary.
    let all = &seen[2].last_summary;
    assert!(
        all.contains(&format!("{} orders", FINISHED + 2 * RUNNING as u64)),
        "{all}"
    );
    assert!(
        read_dashboard.1.lock().unwrap().is_empty(),
        "the dashboard refused reads: {:?}",
        read_dashboard.1.lock().unwrap()
    );
    assert!(!booked_alone.is_empty() && !booked_listed.is_empty());
    drop(robots);
}

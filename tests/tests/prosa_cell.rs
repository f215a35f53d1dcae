//! The PROSA cell: product, order and resource holons as real processes, orders
//! negotiated with whichever resources are alive, a robot hot-added and one stopped
//! while production runs.

use std::collections::BTreeMap;
use std::time::Duration;

use holarchy_tests::*;
use nix::sys::signal::Signal;
use schemas::{HolonId, OrderSnapshot, OrderStatus, Plan};

struct Resource {
    sim: Sim,
    node: Process,
}

async fn resource(
    dir: &std::path::Path,
    cell: &Cell,
    name: &str,
    config: &str,
    sim_flags: &[&str],
) -> Resource {
    let sim = Sim::start(dir, &format!("{name}-sim"), "127.0.0.1:0", sim_flags).unwrap();
    let node = start_holon(
        dir,
        "holon-node",
        &demo_config(config),
        name,
        cell,
        &["--controller", &sim.address],
    )
    .unwrap();
    cell.wait_alive(&HolonId::resource(name).unwrap())
        .await
        .unwrap();
    Resource { sim, node }
}

/// Every order's latest snapshot, as published.
struct Orders {
    subscriber:
        zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    latest: BTreeMap<HolonId, OrderSnapshot>,
}

impl Orders {
    async fn watch(cell: &Cell) -> Orders {
        let subscriber = cell
            .session
            .declare_subscriber(cell.keys.order_states())
            .await
            .unwrap();
        Orders {
            subscriber,
            latest: BTreeMap::new(),
        }
    }

    fn finished(&self) -> usize {
        self.latest.values().filter(|o| o.status.is_final()).count()
    }

    /// Waits until at least `n` orders are finished.
    async fn until_finished(&mut self, n: usize, within: Duration) {
        let deadline = tokio::time::Instant::now() + within;
        while self.finished() < n {
            let sample = tokio::time::timeout_at(deadline, self.subscriber.recv_async())
                .await
                .unwrap_or_else(|_| {
                    panic!(
                        "only {} of {n} orders finished: {:#?}",
                        self.finished(),
                        self.latest
                            .values()
                            .filter(|o| !o.status.is_final())
                            .collect::<Vec<_>>()
                    )
                })
                .unwrap();
            let snapshot: OrderSnapshot =
                serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
            self.latest.insert(snapshot.holon.clone(), snapshot);
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn twenty_orders_while_a_robot_is_hot_added_and_another_stopped() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-prosa").await.unwrap();
    let robot1 = resource(
        dir.path(),
        &cell,
        "robot1",
        "robot1.toml",
        &["--delay-ms", "150"],
    )
    .await;
    let robot2 = resource(
        dir.path(),
        &cell,
        "robot2",
        "robot1.toml",
        &["--delay-ms", "150"],
    )
    .await;
    let inspect1 = resource(
        dir.path(),
        &cell,
        "inspect1",
        "inspect1.toml",
        &["--delay-ms", "20"],
    )
    .await;
    let conveyor1 = resource(
        dir.path(),
        &cell,
        "conveyor1",
        "conveyor1.toml",
        &["--delay-ms", "100"],
    )
    .await;
    let _product = start_holon(
        dir.path(),
        "holon-node",
        &stationary_breaker(),
        "breaker",
        &cell,
        &[],
    )
    .unwrap();
    cell.wait_alive(&HolonId::new(schemas::HolonKind::Product, "breaker").unwrap())
        .await
        .unwrap();
    let _orders_node = cell.start_order_node(dir.path(), &[]).await.unwrap();

    let mut orders = Orders::watch(&cell).await;
    let ids = cell.submit("breaker", 20).await.unwrap();
    assert_eq!(ids.len(), 20);
    assert_eq!(ids[0], "orders1-1");

    // Hot-add a third robot while orders run: nothing is restarted.
    orders.until_finished(3, Duration::from_secs(60)).await;
    let robot3 = resource(
        dir.path(),
        &cell,
        "robot3",
        "robot1.toml",
        &["--delay-ms", "150"],
    )
    .await;

    // Stop robot1 with SIGTERM mid-run: it finishes its step, hands its bookings back.
    orders.until_finished(8, Duration::from_secs(60)).await;
    let mut robot1 = robot1;
    robot1.node.signal(Signal::SIGTERM).unwrap();
    let status = robot1.node.wait_exit(Duration::from_secs(40)).unwrap();
    assert!(status.success(), "robot1 exited with {status}");
    let log = robot1.node.stderr();
    assert!(log.contains("withdrawing"), "{log}");

    orders.until_finished(20, Duration::from_secs(120)).await;
    for order in orders.latest.values() {
        assert_eq!(order.status, OrderStatus::Done, "{order:#?}");
        let services: Vec<&str> = order.completed.iter().map(|(s, _)| s.as_str()).collect();
        assert_eq!(
            services,
            ["transport", "pick_n_place", "inspect"],
            "{order:#?}"
        );
    }
    // The added robot received work.
    let robot3_steps = orders
        .latest
        .values()
        .flat_map(|o| &o.completed)
        .filter(|(_, r)| r.name() == "robot3")
        .count();
    assert!(robot3_steps > 0, "robot3 executed nothing");
    assert!(robot3.sim.executed("pick") > 0);
    // No step was started twice: the controllers executed exactly one command per step.
    let robots = [&robot1.sim, &robot2.sim, &robot3.sim];
    let picks: u64 = robots.iter().map(|s| s.executed("pick")).sum();
    let places: u64 = robots.iter().map(|s| s.executed("place")).sum();
    assert_eq!(
        (picks, places),
        (20, 20),
        "robot1 {} robot2 {} robot3 {}",
        robot1.sim.counts(),
        robot2.sim.counts(),
        robot3.sim.counts()
    );
    assert_eq!(conveyor1.sim.executed("move"), 20);
    assert_eq!(inspect1.sim.executed("inspect"), 20);
    // Steps reported by the orders match the controllers, resource by resource.
    for (name, sim) in [
        ("robot1", &robot1.sim),
        ("robot2", &robot2.sim),
        ("robot3", &robot3.sim),
    ] {
        let steps = orders
            .latest
            .values()
            .flat_map(|o| &o.completed)
            .filter(|(_, r)| r.name() == name)
            .count() as u64;
        assert_eq!(steps, sim.executed("pick"), "{name}");
    }
    let rebooks: u32 = orders.latest.values().map(|o| o.rebooks).sum();
    println!("20 orders done; robot3 did {robot3_steps} steps; rebooks {rebooks}");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_rejected_part_is_reworked_and_the_product_serves_its_plan() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-rework").await.unwrap();
    let _robot = resource(dir.path(), &cell, "robot1", "robot1.toml", &[]).await;
    let _conveyor = resource(dir.path(), &cell, "conveyor1", "conveyor1.toml", &[]).await;
    let _product = start_holon(
        dir.path(),
        "holon-node",
        &stationary_breaker(),
        "breaker",
        &cell,
        &[],
    )
    .unwrap();
    cell.wait_alive(&HolonId::new(schemas::HolonKind::Product, "breaker").unwrap())
        .await
        .unwrap();

    // The plan as any holon sees it.
    let replies = cell
        .session
        .get(cell.keys.plan("breaker"))
        .timeout(Duration::from_secs(5))
        .await
        .unwrap();
    let plan: Plan = serde_json::from_slice(
        &replies
            .recv_async()
            .await
            .unwrap()
            .result()
            .unwrap()
            .payload()
            .to_bytes(),
    )
    .unwrap();
    assert_eq!(plan.steps.len(), 3);
    assert_eq!(plan.steps[2].reject_results, ["inspect_fail"]);

    // An inspection station that fails every inspection: the part is reworked twice
    // (max_reworks = 2), then scrapped.
    let failing = resource(
        dir.path(),
        &cell,
        "inspect2",
        "inspect1.toml",
        &["--inspect-fail-every", "1"],
    )
    .await;
    let _orders_node = cell.start_order_node(dir.path(), &[]).await.unwrap();
    let mut orders = Orders::watch(&cell).await;
    cell.submit("breaker", 1).await.unwrap();
    orders.until_finished(1, Duration::from_secs(60)).await;
    let order = orders.latest.values().next().unwrap();
    assert_eq!(order.status, OrderStatus::Scrapped, "{order:#?}");
    assert_eq!(order.reworks, 2);
    assert!(
        order.reason.as_deref().unwrap().contains("after 2 reworks"),
        "{order:#?}"
    );
    assert_eq!(failing.sim.executed("inspect"), 3);

    // The audit trail: every execution with its own conversation, as `cell orders
    // --detail` prints it.
    let ends: Vec<(String, schemas::AttemptEnd)> = order
        .attempts
        .iter()
        .map(|a| (a.conversation_id.clone(), a.end))
        .collect();
    let name = order.holon.name();
    let rejected: Vec<&String> = ends
        .iter()
        .filter(|(_, end)| *end == schemas::AttemptEnd::Rejected)
        .map(|(id, _)| id)
        .collect();
    assert_eq!(
        rejected,
        [
            &format!("{name}/3/1"),
            &format!("{name}/3/2"),
            &format!("{name}/3/3")
        ],
        "{ends:?}"
    );
    let output = tokio::process::Command::new(bin("cell"))
        .args([
            "orders",
            "--detail",
            "--cell",
            cell.keys.cell(),
            "--connect",
            cell.endpoint.as_str(),
        ])
        .output()
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}");
    let trail: Vec<&str> = stdout.lines().filter(|l| l.starts_with("    ")).collect();
    assert_eq!(trail.len(), ends.len(), "{stdout}");
    assert!(
        trail.iter().any(|l| l.contains(&format!("{name}/2/3"))
            && l.contains("pick_n_place")
            && l.contains("done by resource/")),
        "{stdout}"
    );
    assert!(
        trail.iter().any(|l| l.contains(&format!("{name}/3/3"))
            && l.contains("rejected")
            && l.contains("inspect=inspect_fail")),
        "{stdout}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn bad_work_orders_get_an_error_and_create_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-submit").await.unwrap();
    let _orders_node = cell.start_order_node(dir.path(), &[]).await.unwrap();
    for (payload, code) in [
        (b"not json".to_vec(), "malformed"),
        (br#"{"product": "breaker", "count": 0}"#.to_vec(), "invalid"),
        (br#"{"product": "Breaker"}"#.to_vec(), "invalid"),
        (
            br#"{"product": "breaker", "colour": "red"}"#.to_vec(),
            "malformed",
        ),
    ] {
        let error = cell
            .request(&cell.keys.orders_submit(), payload)
            .await
            .unwrap()
            .unwrap_err();
        assert_eq!(error.code.as_str(), code);
    }
    // No product holon runs in this cell: a product nobody serves is refused, saying so.
    let submit = |extra: &'static [&'static str]| {
        tokio::process::Command::new(bin("cell"))
            .args(["submit", "--cell", "t-submit", "--connect", &cell.endpoint])
            .args(extra)
            .output()
    };
    let output = submit(&["widget"]).await.unwrap();
    assert!(!output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains("unknown_product") && stderr.contains("no product holon \"widget\""),
        "{stderr}"
    );
    // The next valid order is the first one created (queued: its product comes later).
    let output = submit(&["breaker", "--count", "2", "--queue"])
        .await
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    assert_eq!(
        String::from_utf8_lossy(&output.stdout).trim(),
        "orders1-1\norders1-2"
    );
}

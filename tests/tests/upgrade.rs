//! Upgrading holons while the cell runs (`--take-over`, `cell upgrade`): real
//! processes, the controller simulator, journals on disk. Nothing acknowledged is lost,
//! no booking is handed back, no step is interrupted or run twice.

use std::path::Path;
use std::time::Duration;

use holarchy_tests::*;
use nix::sys::signal::Signal;
use schemas::HolonId;

/// Every order's state, as its order-node answers (the orders must all be known).
async fn order_states(cell: &Cell, orders: &[String]) -> Vec<serde_json::Value> {
    let mut states = Vec::new();
    for order in orders {
        states.push(cell.order_state(order).await.unwrap_or_default());
    }
    states
}

/// Waits (at most `limit`) until every order is done; the states as they ended.
async fn wait_all_done(
    cell: &Cell,
    orders: &[String],
    limit: Duration,
) -> Vec<serde_json::Value> {
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        let states = order_states(cell, orders).await;
        let open: Vec<_> = states
            .iter()
            .zip(orders)
            .filter(|(s, _)| s["status"] != "done")
            .map(|(s, o)| format!("{o}: {} {}", s["status"], s["reason"]))
            .collect();
        if open.is_empty() {
            return states;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "orders not done within {limit:?}: {open:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Asserts that no order rebooked, failed an attempt or was reworked.
fn assert_undisturbed(states: &[serde_json::Value]) {
    for state in states {
        assert_eq!(state["rebooks"], 0, "an order rebooked: {state}");
        assert_eq!(state["failed_attempts"], 0, "an attempt failed: {state}");
        for attempt in state["attempts"].as_array().unwrap() {
            let detail = attempt["detail"].as_str().unwrap_or_default();
            assert!(
                !detail.contains("withdrawn") && !detail.contains("interrupted"),
                "{detail}"
            );
        }
    }
}

/// A copy of `config` in `dir` (the successor's own log and stderr go there).
fn successor_dir(dir: &Path) -> std::path::PathBuf {
    let next = dir.join("next");
    std::fs::create_dir_all(&next).unwrap();
    next
}

#[tokio::test(flavor = "multi_thread")]
async fn a_resource_hands_over_to_its_successor_without_losing_or_repeating_a_step() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-upgrade-resource").await.unwrap();
    let sim = Sim::start(dir, "sim1", "127.0.0.1:0", &["--delay-ms", "100"]).unwrap();
    let config = resource_config(dir, "robot1", 10_000).unwrap();
    let data = dir.join("robot-data");
    let data_arg = data.to_str().unwrap();
    let mut old = cell
        .start_free_resource(dir, &config, &sim.address, &["--data-dir", data_arg])
        .await
        .unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &dir.join("orders-data"))
        .await
        .unwrap();
    let orders = cell.submit("part", 12).await.unwrap();
    // Mid-run: a step is running and others wait on the agenda.
    sim.wait_executed("pick", 3).await;

    // A successor with another data dir is refused, and the running holon serves on.
    let next = successor_dir(dir);
    let elsewhere = dir.join("elsewhere");
    let mut wrong = start_node(
        &next,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", elsewhere.to_str().unwrap(), "--take-over"],
    )
    .unwrap();
    let status = wrong.wait_exit(Duration::from_secs(20)).unwrap();
    assert!(!status.success(), "a successor on another journal must fail");
    assert!(wrong.stderr().contains("data dir"), "{}", wrong.stderr());

    // The real successor: same config, same data dir.
    let mut successor = start_node(
        &next,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", data_arg, "--take-over"],
    )
    .unwrap();
    let status = old.wait_exit(Duration::from_secs(30)).unwrap();
    assert!(status.success(), "the predecessor ends with 0: {status:?}");
    assert!(
        old.stderr().contains("handed over"),
        "{}",
        old.stderr()
    );
    cell.wait_alive(&HolonId::resource("robot1").unwrap())
        .await
        .unwrap();

    let states = wait_all_done(&cell, &orders, Duration::from_secs(60)).await;
    assert_undisturbed(&states);
    // Every step ran exactly once, on the one controller both processes drove.
    assert_eq!(sim.wait_executed("pick", 12).await, 12);
    assert_eq!(sim.wait_executed("place", 12).await, 12);
    successor.signal(Signal::SIGTERM).unwrap();
    assert!(successor
        .wait_exit(Duration::from_secs(20))
        .unwrap()
        .success());
}

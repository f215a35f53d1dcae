//! Orders that book to start on their turn (the order-node's default), against real
//! processes: one whose job began keeps the resource's grace to come back and report.
//! The order-node here has a grace of 10 minutes.

use std::time::Duration;

use holarchy_tests::*;

/// The demo order-node's config with `vanished_grace_ms` of 10 minutes.
fn patient_orders(dir: &std::path::Path) -> std::path::PathBuf {
    let text = std::fs::read_to_string(demo_config("orders1.toml")).unwrap();
    assert!(text.contains("vanished_grace_ms = 2000"));
    let path = dir.join("orders1.toml");
    std::fs::write(
        &path,
        text.replace("vanished_grace_ms = 2000", "vanished_grace_ms = 600000"),
    )
    .unwrap();
    path
}

#[tokio::test(flavor = "multi_thread")]
async fn a_running_booking_on_turn_keeps_the_grace() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-on-turn-rebook").await.unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &patient_orders(dir), &dir.join("orders-data"))
        .await
        .unwrap();

    // 2. The order's job begins on its turn on a free `held2` and runs: when `held2`
    // dies, the order waits for it to come back and report (the grace), and does not
    // book the step elsewhere.
    // Its controller's actions take 10 minutes.
    let mut held2 = cell
        .resource(dir, "held2")
        .sim_flags(&["--delay-ms", "600000"])
        .command_timeout_ms(600_000)
        .start()
        .await
        .unwrap();
    let second = cell.submit("part", 1).await.unwrap().remove(0);
    cell.wait_state("held2", "the order's job running", |s| {
        s["current"]["requester"] == format!("order/{second}")
    })
    .await
    .unwrap();
    held2.node.kill();
    // A spare whose controller answers at once.
    let _spare2 = cell.resource(dir, "spare2").start().await.unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let state = cell.order_state(&second).await.unwrap();
    assert_eq!(state["status"], "running", "{state}");
    assert_eq!(
        state["resource"], "resource/held2",
        "still waiting for held2: {state}"
    );
    assert_eq!(state["rebooks"], 0, "{state}");
    let spare2 = cell.status("spare2").await.unwrap();
    assert_eq!(spare2["state"], "free", "{spare2}");
    assert_eq!(
        spare2["agenda"].as_array().map(Vec::len),
        Some(0),
        "{spare2}"
    );
}

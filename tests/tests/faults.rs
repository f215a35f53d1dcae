//! Faults that used to break a promise (issue: twins, bookings that never end, ...):
//! each reproduced with the real binaries.

use std::time::Duration;

use holarchy_tests::*;
use schemas::{HolonId, MessageType};

/// A robot-sim and a holon-node `robot1` with `extra` appended to its config.
async fn robot_with(cell: &Cell, dir: &std::path::Path, extra: &str) -> (Sim, Process) {
    let sim = Sim::start(dir, "sim1", "127.0.0.1:0", &[]).unwrap();
    let config = resource_config(dir, "robot1", 5000).unwrap();
    let mut text = std::fs::read_to_string(&config).unwrap();
    text.push_str(extra);
    std::fs::write(&config, text).unwrap();
    let data = dir.join("data-a");
    let node = start_node(
        dir,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", data.to_str().unwrap()],
    )
    .unwrap();
    cell.wait_alive(&HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    cell.wait_state("robot1", "free", |s| s["state"] == "free")
        .await
        .unwrap();
    (sim, node)
}

#[tokio::test(flavor = "multi_thread")]
async fn a_twin_resource_is_refused_and_the_first_keeps_serving() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-twin").await.unwrap();
    let (sim, first) = robot_with(&cell, dir.path(), "").await;

    // The same config on "another host": its own data dir, same name.
    let twin_dir = dir.path().join("twin");
    std::fs::create_dir_all(&twin_dir).unwrap();
    let config = dir.path().join("robot1.toml");
    let mut twin = start_node(
        &twin_dir,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", twin_dir.join("data-b").to_str().unwrap()],
    )
    .unwrap();
    let status = match twin.wait_exit(Duration::from_secs(30)) {
        Ok(status) => status,
        Err(e) => panic!(
            "{e}: {}\n{}",
            twin.stderr(),
            std::fs::read_to_string(twin_dir.join("robot1.log.json")).unwrap_or_default()
        ),
    };
    assert!(!status.success(), "the twin must exit non-zero");
    let stderr = twin.stderr();
    assert!(stderr.contains("already running"), "{stderr}");
    assert!(
        stderr.contains(&format!("pid {}", first.pid())),
        "the message names the process that holds the name: {stderr}"
    );
    assert_eq!(
        stderr.matches("already running").count(),
        1,
        "said once: {stderr}"
    );

    // The first one still serves, and only it moves the robot.
    let mut inbox = cell.inbox("o-1", 0).await.unwrap();
    let book = pick_n_place(&cell.keys, MessageType::BookingReq, "o-1", "o-1/1/1");
    assert_eq!(
        cell.service("robot1", &book).await.unwrap().result,
        Some(true)
    );
    let start = pick_n_place(&cell.keys, MessageType::Start, "o-1", "o-1/1/1");
    assert_eq!(
        cell.service("robot1", &start).await.unwrap().result,
        Some(true)
    );
    let done = inbox.next().await.unwrap();
    assert_eq!(done.message_type, MessageType::Done);
    assert!(inbox.silent_for(Duration::from_millis(1000)).await);
    assert_eq!(sim.executed("pick"), 1);
    drop(first);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_twin_order_node_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-twin-orders").await.unwrap();
    let first_data = dir.path().join("data-a");
    let first = start_holon(
        dir.path(),
        "order-node",
        &demo_config("orders1.toml"),
        "orders1",
        &cell,
        &["--data-dir", first_data.to_str().unwrap()],
    )
    .unwrap();
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await
        .unwrap();
    let twin_dir = dir.path().join("twin");
    std::fs::create_dir_all(&twin_dir).unwrap();
    let mut twin = start_holon(
        &twin_dir,
        "order-node",
        &demo_config("orders1.toml"),
        "orders1",
        &cell,
        &["--data-dir", twin_dir.join("data-b").to_str().unwrap()],
    )
    .unwrap();
    let status = twin.wait_exit(Duration::from_secs(30)).unwrap();
    assert!(!status.success());
    let stderr = twin.stderr();
    assert!(
        stderr.contains("order-node orders1 is already running"),
        "{stderr}"
    );
    assert!(stderr.contains(&format!("pid {}", first.pid())), "{stderr}");
    // The first one still takes orders. No product holon runs here: a work order for
    // an absent product is refused unless queued.
    let refused = cell.submit("breaker", 1).await.unwrap_err().to_string();
    assert!(
        refused.contains("unknown_product") && refused.contains("no product holon"),
        "{refused}"
    );
    let orders = cell
        .submit_work(schemas::WorkOrder {
            product: "breaker".into(),
            count: 1,
            priority: 0,
            queue: true,
        })
        .await
        .unwrap();
    assert_eq!(orders, vec!["orders1-1".to_string()]);
}

#[tokio::test(flavor = "multi_thread")]
async fn bookings_of_a_requester_gone_for_good_are_released() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-lifetime").await.unwrap();
    let (_sim, _node) =
        robot_with(&cell, dir.path(), "\n[agenda]\nrequester_grace_ms = 2000\n").await;
    // o-live holds a token while it wants its booking; o-ghost never had one (a faked
    // or long-gone requester).
    let live = HolonId::order("o-live").unwrap();
    let token = cell
        .session
        .liveliness()
        .declare_token(cell.keys.alive(&live))
        .await
        .unwrap();
    for (order, conversation) in [("o-ghost", "g/1/1"), ("o-live", "l/1/1")] {
        let book = pick_n_place(&cell.keys, MessageType::BookingReq, order, conversation);
        assert_eq!(
            cell.service("robot1", &book).await.unwrap().result,
            Some(true)
        );
    }
    let state = cell.status("robot1").await.unwrap();
    let agenda = state["agenda"].as_array().unwrap();
    assert_eq!(agenda.len(), 2, "{state}");
    assert!(
        agenda[0]["requester_absent_since"].is_u64(),
        "the ghost is shown absent: {state}"
    );
    assert!(
        agenda[1].get("requester_absent_since").is_none(),
        "the live requester is present: {state}"
    );
    let state = cell
        .wait_state("robot1", "the ghost's booking released", |s| {
            s["agenda"].as_array().is_some_and(|a| a.len() == 1)
        })
        .await
        .unwrap();
    assert_eq!(state["agenda"][0]["requester"], "order/o-live");
    // Still there well after the grace while its requester lives.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let state = cell.status("robot1").await.unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 1, "{state}");

    // The requester ends: its booking goes after the grace.
    token.undeclare().await.unwrap();
    cell.wait_state("robot1", "the ended order's booking released", |s| {
        s["agenda"].as_array().is_some_and(|a| a.is_empty())
    })
    .await
    .unwrap();
}

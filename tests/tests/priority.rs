//! Work-order priority against real processes: `cell submit --priority`, the order-node
//! carrying it on every booking, and a resource holon serving its waiting bookings by
//! it, with the bound on how often one booking may be passed.

use holarchy_tests::*;

/// Runs `cell ARGS --cell C --connect ROUTER` and returns its stdout (it must succeed).
async fn cell_command(cell: &Cell, args: &[&str]) -> String {
    let output = tokio::process::Command::new(bin("cell"))
        .args(args)
        .args([
            "--cell",
            cell.keys.cell(),
            "--connect",
            cell.endpoint.as_str(),
        ])
        .output()
        .await
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    assert!(
        output.status.success(),
        "cell {args:?}: {stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    stdout
}

/// The conversation ids' orders on the resource's agenda, with how often each was passed.
fn agenda(state: &serde_json::Value) -> Vec<(String, i64, u64)> {
    state["agenda"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| {
            let requester = b["requester"].as_str().unwrap();
            (
                requester.trim_start_matches("order/").to_string(),
                b["priority"].as_i64().unwrap(),
                b["overtaken"].as_u64().unwrap(),
            )
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn rush_orders_go_first_and_a_passed_booking_is_not_passed_again() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-priority").await.unwrap();
    // Every action takes a second: a job takes two, long enough to queue behind it.
    let robot = cell
        .resource(dir, "robot1")
        .sim_flags(&["--delay-ms", "1000"])
        .command_timeout_ms(10_000)
        .config("\n[agenda]\nmax_overtakes = 1\n")
        .start()
        .await
        .unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &dir.join("orders-data"))
        .await
        .unwrap();

    // One ordinary order runs; a low-priority one waits behind it.
    let first = cell.submit("part", 1).await.unwrap().remove(0);
    cell.wait_state("robot1", "running the first order", |s| {
        s["current"]["requester"] == format!("order/{first}")
    })
    .await
    .unwrap();
    let low = cell
        .submit_work(schemas::WorkOrder {
            product: "part".into(),
            count: 1,
            priority: -10,
            due: None,
            queue: false,
            submit_id: None,
        })
        .await
        .unwrap()
        .remove(0);
    cell.wait_state("robot1", "the low-priority booking waiting", |s| {
        s["agenda"].as_array().is_some_and(|a| a.len() == 1)
    })
    .await
    .unwrap();

    // Three rush orders from the command line: the first passes the low-priority
    // booking; with `max_overtakes = 1` the next two may not, and wait behind it.
    let submitted = cell_command(
        &cell,
        &[
            "submit",
            "part",
            "--count",
            "3",
            "--priority",
            "100",
            "--due-in",
            "10m",
        ],
    )
    .await;
    let rush: Vec<String> = submitted.lines().map(str::to_string).collect();
    assert_eq!(rush.len(), 3, "{submitted}");
    cell.wait_state("robot1", "all four waiting", |s| {
        s["agenda"].as_array().is_some_and(|a| a.len() == 4)
    })
    .await
    .unwrap();
    let waiting = agenda(&cell.status("robot1").await.unwrap());
    assert_eq!(waiting[1], (low.clone(), -10, 1), "{waiting:?}");
    assert_eq!(waiting[0].1, 100, "a rush order is first: {waiting:?}");
    assert_eq!(
        (waiting[2].1, waiting[3].1),
        (100, 100),
        "the later rush orders wait behind the passed booking: {waiting:?}"
    );

    // The orders table shows each order's priority and time to its due.
    let table = cell_command(&cell, &["orders"]).await;
    let row = |order: &str| -> Vec<String> {
        let line = table
            .lines()
            .find(|l| l.starts_with(&format!("{order} ")))
            .unwrap_or_else(|| panic!("{order} not listed: {table}"));
        line.split_whitespace().map(str::to_string).collect()
    };
    assert_eq!(row(&low)[3], "-10", "{table}");
    assert_eq!(row(&rush[0])[3], "100", "{table}");
    assert!(
        row(&rush[0])[4].starts_with("9m"),
        "due in about 10 minutes: {table}"
    );
    assert_eq!(row(&first)[4], "-", "{table}");

    // They finish in the agenda's order (when each recorded its step done).
    let mut finished = Vec::new();
    for order in [&first, &rush[0], &rush[1], &rush[2], &low] {
        cell.wait_order(order, "finished", |s| {
            s.is_some_and(|s| s["status"] == "done")
        })
        .await
        .unwrap();
        let state = cell.order_state(order).await.unwrap();
        let done_at = state["attempts"][0]["at"].as_u64().unwrap();
        finished.push((done_at, order.clone()));
    }
    finished.sort();
    let served: Vec<&String> = finished.iter().map(|(_, order)| order).collect();
    let expected: Vec<&String> = std::iter::once(&first)
        .chain(waiting.iter().map(|(order, _, _)| order))
        .collect();
    assert_eq!(served, expected);
    assert_eq!(robot.sim.executed("pick"), 5);
}

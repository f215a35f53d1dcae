//! The order-node's journal keeps finished orders only for `journal.keep_finished_ms`:
//! they leave the journal and `cell orders`, and a restarted node does not bring them
//! back.

use std::time::Duration;

use holarchy_tests::*;
use nix::sys::signal::Signal;

fn config(dir: &std::path::Path, keep_finished_ms: u64) -> std::path::PathBuf {
    let path = dir.join("orders.toml");
    std::fs::write(
        &path,
        format!(
            r#"
cell = "demo"
name = "orders1"
[orders]
no_resource_timeout_ms = 300
[journal]
durability = "process_crash"
keep_finished_ms = {keep_finished_ms}
"#
        ),
    )
    .unwrap();
    path
}

#[tokio::test(flavor = "multi_thread")]
async fn finished_orders_leave_the_journal_after_the_retention() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-retention").await.unwrap();
    let data = dir.path().join("data");
    let data_arg = data.to_str().unwrap();
    let node = |dir: &std::path::Path| {
        start_holon(
            dir,
            "order-node",
            &config(dir, 1500),
            "orders1",
            &cell,
            &["--data-dir", data_arg],
        )
        .unwrap()
    };
    let mut first = node(dir.path());
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await
        .unwrap();

    // Orders for a product nobody makes fail ("no plan") once the timeout passes.
    let failing = cell
        .submit_work(schemas::WorkOrder {
            product: "nothing".into(),
            count: 3,
            priority: 0,
            due: None,
            queue: true,
        })
        .await
        .unwrap();
    for order in &failing {
        cell.wait_order(order, "failed", |s| {
            s.is_some_and(|s| s["status"] == "failed")
        })
        .await
        .unwrap();
    }
    // Still known right after; gone once the retention has passed.
    assert!(cell.order_state(&failing[0]).await.is_some());
    for order in &failing {
        cell.wait_order(order, "left the journal", |s| s.is_none())
            .await
            .unwrap();
    }
    let log = std::fs::read_to_string(dir.path().join("orders1.log.json")).unwrap();
    assert!(log.contains("finished orders left the journal"), "{log}");

    // A late result for a forgotten order (a resource away for longer than the
    // retention) is acknowledged, so the resource stops sending it; one for an order the
    // node never made is refused.
    let late = |order: &str| {
        let mut done = schemas::Service::request(
            schemas::MessageType::Done,
            "pick_n_place",
            &format!("{order}/1/1"),
            schemas::HolonId::order(order).unwrap(),
        )
        .with_reply_to(cell.keys.inbox(order));
        done.provider = Some(schemas::HolonId::resource("robot1").unwrap());
        done.result = Some(true);
        done
    };
    let answer = |order: String| {
        let cell = &cell;
        let message = late(&order);
        async move {
            let replies = cell
                .session
                .get(cell.keys.inbox(&order))
                .payload(message.to_json())
                .timeout(Duration::from_secs(3))
                .await
                .unwrap();
            let reply = replies.recv_async().await.unwrap();
            match reply.result() {
                Ok(sample) => {
                    Ok(schemas::Service::from_json(&sample.payload().to_bytes()).unwrap())
                }
                Err(e) => Err(e.payload().try_to_string().unwrap_or_default().into_owned()),
            }
        }
    };
    let acknowledged = answer(failing[0].clone()).await.unwrap();
    assert_eq!(acknowledged.result, Some(true), "{acknowledged:?}");
    let refused = answer("orders1-999".into()).await.unwrap_err();
    assert!(refused.contains("unknown_order"), "{refused}");

    // A restarted node does not bring them back.
    first.signal(Signal::SIGTERM).unwrap();
    assert!(first.wait_exit(Duration::from_secs(20)).unwrap().success());
    let second_dir = dir.path().join("second");
    std::fs::create_dir_all(&second_dir).unwrap();
    let mut second = node(&second_dir);
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await
        .unwrap();
    for order in &failing {
        assert_eq!(cell.order_state(order).await, None, "{order} came back");
    }
    second.signal(Signal::SIGTERM).unwrap();
    assert!(second.wait_exit(Duration::from_secs(20)).unwrap().success());
    let journal = holon::journal::Journal::open(
        &data,
        "order-node-orders1.sqlite",
        holon::journal::Durability::ProcessCrash,
    )
    .unwrap();
    let left: Vec<(String, serde_json::Value)> = journal.list("order").unwrap();
    assert!(left.is_empty(), "{left:?}");
}

//! The order-node's journal keeps finished orders only for `journal.keep_finished_ms`:
//! they leave the journal and `cell orders`, and a restarted node does not bring them
//! back. A named work order (`submit_id`) is made once, asked again or not.

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

/// Ends the node `old` with `signal` (SIGTERM: a clean exit), starts it again with
/// `start` in a directory of its own under `dir`, on the same journal, and waits until
/// it is there.
async fn restart(
    cell: &Cell,
    mut old: Process,
    signal: Signal,
    dir: &std::path::Path,
    start: impl Fn(&std::path::Path) -> Process,
) -> Process {
    old.signal(signal).unwrap();
    let exit = old.wait_exit(Duration::from_secs(20)).unwrap();
    assert!(signal != Signal::SIGTERM || exit.success(), "{exit:?}");
    let second = dir.join("second");
    std::fs::create_dir_all(&second).unwrap();
    let new = start(&second);
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await
        .unwrap();
    new
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
    let first = node(dir.path());
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
            submit_id: Some("retained-1".into()),
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
    let mut second = restart(&cell, first, Signal::SIGTERM, dir.path(), node).await;
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
    // Their work order's name left with them.
    let names: Vec<(String, serde_json::Value)> = journal.list("submit").unwrap();
    assert!(names.is_empty(), "{names:?}");
}

/// `cell submit --submit-id NAME` run again makes no more orders: the node answers
/// with those it made under the name, also after a kill -9 and a restart on its
/// journal; the name given to other work is refused and changes nothing.
#[tokio::test(flavor = "multi_thread")]
async fn a_named_work_order_submitted_again_makes_its_orders_once() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-named").await.unwrap();
    let data = dir.path().join("data");
    let data_arg = data.to_str().unwrap().to_string();
    let config = config(dir.path(), 3_600_000);
    let node = |dir: &std::path::Path| {
        start_holon(
            dir,
            "order-node",
            &config,
            "orders1",
            &cell,
            &["--data-dir", &data_arg],
        )
        .unwrap()
    };
    let submit = |extra: &[&str]| {
        let output = std::process::Command::new(bin("cell"))
            .args(["submit", "nothing", "--queue", "--cell", "t-named"])
            .args(["--connect", &cell.endpoint])
            .args(extra)
            .output()
            .unwrap();
        let said = |b: &[u8]| String::from_utf8_lossy(b).into_owned();
        (
            output.status.success(),
            said(&output.stdout)
                .split_whitespace()
                .map(String::from)
                .collect::<Vec<_>>(),
            said(&output.stderr),
        )
    };
    // The node's orders, as `cell orders --all` lists them.
    let orders = || {
        let output = std::process::Command::new(bin("cell"))
            .args(["orders", "--all", "--cell", "t-named"])
            .args(["--connect", &cell.endpoint])
            .output()
            .unwrap();
        let listed = String::from_utf8_lossy(&output.stdout).into_owned();
        let names: Vec<String> = listed
            .lines()
            .filter_map(|l| l.split_whitespace().next())
            .filter(|w| w.starts_with("orders1-"))
            .map(String::from)
            .collect();
        (names, listed)
    };
    let first = node(dir.path());
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await
        .unwrap();

    let (ok, made, said) = submit(&["--count", "2", "--submit-id", "mes-4711"]);
    assert!(ok, "{said}");
    assert_eq!(made, ["orders1-1", "orders1-2"]);
    let again = submit(&["--count", "2", "--submit-id", "mes-4711"]);
    assert_eq!((again.0, &again.1), (true, &made), "{}", again.2);
    // The name given to other work: refused, nothing made.
    let other = submit(&["--count", "3", "--submit-id", "mes-4711"]);
    assert!(!other.0, "{:?}", other.1);
    assert!(
        other.2.contains("invalid") && other.2.contains("mes-4711"),
        "{}",
        other.2
    );
    let (listed, table) = orders();
    assert_eq!(listed, ["orders1-1", "orders1-2"], "{table}");

    // Killed, restarted on its journal: the name is still known.
    let mut second = restart(&cell, first, Signal::SIGKILL, dir.path(), node).await;
    let after = submit(&["--count", "2", "--submit-id", "mes-4711"]);
    assert_eq!((after.0, &after.1), (true, &made), "{}", after.2);
    // Another name, and none, make new orders.
    let new = submit(&["--submit-id", "mes-4712"]);
    assert_eq!(
        (new.0, &new.1[..]),
        (true, &["orders1-3".to_string()][..]),
        "{}",
        new.2
    );
    let unnamed = submit(&[]);
    assert_eq!(unnamed.1, ["orders1-4"], "{}", unnamed.2);
    let (listed, table) = orders();
    assert_eq!(listed.len(), 4, "{table}");
    // A malformed name: refused by the tool before anything is asked.
    let bad = submit(&["--submit-id", "MES 4711"]);
    assert!(!bad.0 && bad.2.contains("submit_id"), "{}", bad.2);
    second.signal(Signal::SIGTERM).unwrap();
    assert!(second.wait_exit(Duration::from_secs(20)).unwrap().success());
}

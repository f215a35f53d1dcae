//! Faults that used to break a promise (issue: twins, bookings that never end, ...):
//! each reproduced with the real binaries.

use std::time::Duration;

use holarchy_tests::*;
use schemas::{HolonId, MessageType};

/// A robot-sim and a holon-node `robot1` with `extra` appended to its config.
async fn robot_with(cell: &Cell, dir: &std::path::Path, extra: &str) -> (Sim, Process) {
    let data = dir.join("data-a");
    let Resource { sim, node, .. } = cell
        .resource(dir, "robot1")
        .config(extra)
        .node_flags(&["--data-dir", data.to_str().unwrap()])
        .start()
        .await
        .unwrap();
    (sim, node)
}

/// Books robot1 for `order` and starts the job; the order's inbox, declared first.
async fn book_and_start(cell: &Cell, order: &str, conversation: &str) -> Inbox {
    let inbox = cell.inbox(order, 0).await.unwrap();
    for kind in [MessageType::BookingReq, MessageType::Start] {
        let request = pick_n_place(&cell.keys, kind, order, conversation);
        let answer = cell.service("robot1", &request).await.unwrap();
        assert_eq!(answer.result, Some(true), "{kind}: {answer:?}");
    }
    inbox
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
    let mut inbox = book_and_start(&cell, "o-1", "o-1/1/1").await;
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
    let first = cell
        .start_order_node(dir.path(), &["--data-dir", first_data.to_str().unwrap()])
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
            due: None,
            queue: true,
            submit_id: None,
        })
        .await
        .unwrap();
    assert_eq!(orders, vec!["orders1-1".to_string()]);
}

/// A fake order-node: answers `host/order-node/tnode/held` with those of the orders
/// asked that are in `holds`, and counts the questions.
async fn fake_node(
    cell: &Cell,
    holds: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    asked: std::sync::Arc<std::sync::atomic::AtomicUsize>,
) -> zenoh::query::Queryable<()> {
    let reply_key = cell.keys.node_held("tnode");
    cell.session
        .declare_queryable(cell.keys.node_held("tnode"))
        .callback(move |query| {
            use zenoh::Wait;
            asked.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let question: schemas::HeldRequest = serde_json::from_slice(
                &query
                    .payload()
                    .map(|p| p.to_bytes().into_owned())
                    .unwrap_or_default(),
            )
            .expect("a held question");
            let holds = holds.lock().unwrap().clone();
            let reply = schemas::HeldReply {
                node: "tnode".into(),
                held: question
                    .orders
                    .into_iter()
                    .filter(|o| holds.contains(o))
                    .collect(),
            };
            query
                .reply(&reply_key, serde_json::to_vec(&reply).unwrap())
                .wait()
                .unwrap();
        })
        .await
        .unwrap()
}

/// An order's bookings last while an order-node holds it (`host/order-node/*/held`),
/// or, for an order of an earlier release, while its token lives; a requester no node
/// holds and without a token (a faked or long-gone one) loses them after the grace.
#[tokio::test(flavor = "multi_thread")]
async fn bookings_of_a_requester_gone_for_good_are_released() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-lifetime").await.unwrap();
    let (_sim, _node) =
        robot_with(&cell, dir.path(), "\n[agenda]\nrequester_grace_ms = 2000\n").await;
    // o-held is held by its node; o-live holds a token (an order-node of an earlier
    // release); o-ghost has neither.
    let holds = std::sync::Arc::new(std::sync::Mutex::new(vec!["o-held".to_string()]));
    let asked = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let node = fake_node(&cell, holds.clone(), asked.clone()).await;
    let live = HolonId::order("o-live").unwrap();
    let token = cell
        .session
        .liveliness()
        .declare_token(cell.keys.alive(&live))
        .await
        .unwrap();
    for (order, conversation) in [
        ("o-ghost", "g/1/1"),
        ("o-live", "l/1/1"),
        ("o-held", "h/1/1"),
    ] {
        let book = pick_n_place(&cell.keys, MessageType::BookingReq, order, conversation);
        assert_eq!(
            cell.service("robot1", &book).await.unwrap().result,
            Some(true)
        );
    }
    let state = cell
        .wait_state("robot1", "the ghost's booking released", |s| {
            s["agenda"].as_array().is_some_and(|a| a.len() == 2)
        })
        .await
        .unwrap();
    let requesters: Vec<&str> = state["agenda"]
        .as_array()
        .unwrap()
        .iter()
        .map(|b| b["requester"].as_str().unwrap())
        .collect();
    assert_eq!(requesters, ["order/o-live", "order/o-held"], "{state}");
    assert!(
        asked.load(std::sync::atomic::Ordering::Relaxed) > 0,
        "the resource asked the node"
    );
    // Still there well after the grace while their requesters are in the cell.
    tokio::time::sleep(Duration::from_secs(3)).await;
    let state = cell.status("robot1").await.unwrap();
    let agenda = state["agenda"].as_array().unwrap();
    assert_eq!(agenda.len(), 2, "{state}");
    assert!(
        agenda
            .iter()
            .all(|b| b.get("requester_absent_since").is_none()),
        "both requesters are present: {state}"
    );

    // The requesters end: the node no longer holds o-held, o-live withdraws its token;
    // their bookings go after the grace.
    holds.lock().unwrap().clear();
    token.undeclare().await.unwrap();
    let state = cell
        .wait_state("robot1", "the absence shown", |s| {
            s["agenda"].as_array().is_some_and(|a| {
                !a.is_empty() && a.iter().all(|b| b["requester_absent_since"].is_u64())
            })
        })
        .await
        .unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 2, "{state}");
    cell.wait_state("robot1", "the ended orders' bookings released", |s| {
        s["agenda"].as_array().is_some_and(|a| a.is_empty())
    })
    .await
    .unwrap();
    drop(node);
}

/// A small tmpfs mounted at a directory for the test's life (needs root, as the
/// network-namespace tests do).
struct SmallDisk {
    path: std::path::PathBuf,
}

impl SmallDisk {
    fn mount(path: &std::path::Path, size: &str) -> SmallDisk {
        std::fs::create_dir_all(path).unwrap();
        let status = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(path)
            .status()
            .expect("run mount");
        assert!(
            status.success(),
            "this test needs root to mount a small tmpfs (a disk that can be filled)"
        );
        SmallDisk {
            path: path.to_path_buf(),
        }
    }

    /// Fills the disk with a file; returns its path.
    fn fill(&self) -> std::path::PathBuf {
        use std::io::Write;
        let filler = self.path.join("filler");
        let mut file = std::fs::File::create(&filler).unwrap();
        let chunk = vec![0u8; 4096];
        while file.write_all(&chunk).and_then(|_| file.flush()).is_ok() {}
        filler
    }
}

/// robot1 (its controller takes 1.5 s a step) with its journal on a 1 MB disk.
struct DiskRobot {
    cell: Cell,
    disk: SmallDisk,
    sim: Sim,
    config: std::path::PathBuf,
    dir: tempfile::TempDir,
}

impl DiskRobot {
    async fn new(cell: &str) -> DiskRobot {
        let dir = tempfile::tempdir().unwrap();
        let disk = SmallDisk::mount(&dir.path().join("data"), "1m");
        let cell = Cell::open(cell).await.unwrap();
        let sim = Sim::start(dir.path(), "sim1", "127.0.0.1:0", &["--delay-ms", "1500"]).unwrap();
        let config = resource_config(dir.path(), "robot1", 10_000).unwrap();
        DiskRobot {
            cell,
            disk,
            sim,
            config,
            dir,
        }
    }

    /// Starts the holon and waits until it is free.
    async fn start(&self) -> Process {
        let data = self.disk.path.to_str().unwrap();
        self.cell
            .start_free_resource(
                self.dir.path(),
                &self.config,
                &self.sim.address,
                &["--data-dir", data],
            )
            .await
            .unwrap()
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.path)
            .status();
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_full_disk_holds_the_result_until_it_is_recorded_and_never_makes_it_interrupted() {
    let disk_robot = DiskRobot::new("t-disk-full").await;
    let DiskRobot {
        cell, disk, sim, ..
    } = &disk_robot;
    let mut node = disk_robot.start().await;
    let robot = HolonId::resource("robot1").unwrap();

    let mut inbox = book_and_start(cell, "o-1", "o-1/1/1").await;
    // The disk fills while the robot works: the job's end cannot be recorded.
    let filler = disk.fill();
    let state = cell
        .wait_state("robot1", "a journal fault", |s| {
            s["journal_fault"].is_string()
        })
        .await
        .unwrap();
    assert_eq!(state["state"], "free", "the job ended: {state}");
    assert!(
        inbox.silent_for(Duration::from_millis(1500)).await,
        "no result goes out before it is recorded"
    );
    let proposals = cell
        .proposals(&pick_n_place(
            &cell.keys,
            MessageType::ProposalReq,
            "o-2",
            "o-2/1/1",
        ))
        .await
        .unwrap();
    assert!(
        proposals.is_empty(),
        "no offers while the journal cannot write: {proposals:?}"
    );

    // Space comes back: the outcome is recorded, then delivered, and offers resume.
    std::fs::remove_file(filler).unwrap();
    let done = inbox.next().await.unwrap();
    assert_eq!(done.message_type, MessageType::Done, "{done:?}");
    assert_eq!(done.conversation_id, "o-1/1/1");
    let state = cell
        .wait_state("robot1", "the fault cleared", |s| {
            s.get("journal_fault").is_none() && s["undelivered"] == 0
        })
        .await
        .unwrap();
    assert_eq!(state["state"], "free");
    cell.wait_proposals(
        &pick_n_place(&cell.keys, MessageType::ProposalReq, "o-2", "o-2/1/1"),
        1,
    )
    .await
    .unwrap();

    // A restart finds the step completed, not interrupted.
    node.kill();
    cell.wait_gone(&robot).await.unwrap();
    let _node = disk_robot.start().await;
    // (The acknowledgement is recorded with the next write, so the `done` may come once
    // more: the order ignores a duplicate. What must never come is `failed`.)
    while let Ok(message) = tokio::time::timeout(Duration::from_secs(2), inbox.next()).await {
        let message = message.unwrap();
        assert_eq!(
            message.message_type,
            MessageType::Done,
            "a completed step is never reported interrupted: {message:?}"
        );
    }
    assert_eq!(sim.executed("pick"), 1);
}

#[tokio::test(flavor = "multi_thread")]
async fn an_order_node_with_a_full_disk_keeps_the_result_unacknowledged_until_it_can_record_it() {
    let dir = tempfile::tempdir().unwrap();
    let disk = SmallDisk::mount(&dir.path().join("orders-data"), "1m");
    let cell = Cell::open("t-disk-orders").await.unwrap();
    let sim = Sim::start(dir.path(), "sim1", "127.0.0.1:0", &["--delay-ms", "1500"]).unwrap();
    let config = resource_config(dir.path(), "robot1", 10_000).unwrap();
    let _robot = start_node(
        dir.path(),
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &[
            "--data-dir",
            dir.path().join("robot-data").to_str().unwrap(),
        ],
    )
    .unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir.path(), &demo_config("orders1.toml"), &disk.path)
        .await
        .unwrap();
    cell.wait_alive(&HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    let orders = cell.submit("part", 1).await.unwrap();
    let order = &orders[0];
    // Started on robot1 (the step takes 3 s: pick and place): now the disk fills.
    cell.wait_state("robot1", "busy", |s| s["state"] == "busy")
        .await
        .unwrap();
    let filler = disk.fill();
    // The robot finishes; its `done` cannot be recorded by the order-node, so it is not
    // acknowledged: the resource keeps it and the order stays where it was.
    cell.wait_state("robot1", "a result waiting for its acknowledgement", |s| {
        s["state"] == "free" && s["undelivered"] == 1
    })
    .await
    .unwrap();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let state = cell.order_state(order).await.unwrap();
    assert_eq!(state["status"], "running", "{state}");
    assert_eq!(
        cell.status("robot1").await.unwrap()["undelivered"],
        1,
        "still unacknowledged"
    );

    // Space again: the order records the step, acknowledges it, and is done.
    std::fs::remove_file(filler).unwrap();
    cell.wait_order(order, "done", |s| s.is_some_and(|s| s["status"] == "done"))
        .await
        .unwrap();
    cell.wait_state("robot1", "the result acknowledged", |s| {
        s["undelivered"] == 0
    })
    .await
    .unwrap();
    assert_eq!(sim.executed("pick"), 1, "the step ran once");
}

#[tokio::test(flavor = "multi_thread")]
async fn stopping_while_the_disk_is_full_delivers_the_held_result_and_hands_the_booking_back() {
    let disk_robot = DiskRobot::new("t-disk-stop").await;
    let DiskRobot {
        cell, disk, sim, ..
    } = &disk_robot;
    let mut node = disk_robot.start().await;
    let mut running = book_and_start(cell, "o-1", "o-1/1/1").await;
    let mut waiting = cell.inbox("o-2", 0).await.unwrap();
    let booking = pick_n_place(&cell.keys, MessageType::BookingReq, "o-2", "o-2/1/1");
    let booked = cell.service("robot1", &booking).await.unwrap();
    assert_eq!(booked.result, Some(true), "{booked:?}");

    // The disk fills while the robot works: the job's end is held, not recorded.
    let _filler = disk.fill();
    cell.wait_state("robot1", "the job ended with a journal fault", |s| {
        s["journal_fault"].is_string() && s["state"] == "free"
    })
    .await
    .unwrap();
    assert!(
        running.silent_for(Duration::from_millis(1000)).await,
        "no result goes out before it is recorded"
    );

    // SIGTERM while the journal still cannot write: the held result goes out unrecorded
    // (the order records the outcome), the booking is handed back, and the holon stops
    // once both are acknowledged, well within its shutdown grace.
    let stopping = std::time::Instant::now();
    node.signal(nix::sys::signal::Signal::SIGTERM).unwrap();
    let done = running.next().await.unwrap();
    assert_eq!(done.message_type, MessageType::Done, "{done:?}");
    assert_eq!(done.conversation_id, "o-1/1/1");
    let handed_back = waiting.next().await.unwrap();
    assert_eq!(
        handed_back.message_type,
        MessageType::Failed,
        "{handed_back:?}"
    );
    assert_eq!(
        handed_back.reason.as_ref().map(|r| r.as_str()),
        Some("withdrawn")
    );
    assert_eq!(handed_back.conversation_id, "o-2/1/1");
    let status = node.wait_exit(Duration::from_secs(60)).unwrap();
    assert!(status.success(), "{}", node.stderr());
    println!("stopped {:?} after SIGTERM", stopping.elapsed());
    assert_eq!(sim.executed("pick"), 1);
}

/// A real order's booking waiting behind another job outlasts the grace: its
/// order-node says it holds the order (no token per order), so the resource keeps it.
#[tokio::test(flavor = "multi_thread")]
async fn a_waiting_booking_of_a_running_order_outlasts_the_grace() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-held").await.unwrap();
    // Every action takes 1.5 s: a job takes 3, three times the grace.
    let _robot = cell
        .resource(dir, "robot1")
        .sim_flags(&["--delay-ms", "1500"])
        .command_timeout_ms(10_000)
        .config("\n[agenda]\nrequester_grace_ms = 1000\n")
        .start()
        .await
        .unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &dir.join("orders-data"))
        .await
        .unwrap();
    let orders = cell.submit("part", 2).await.unwrap();
    cell.wait_state("robot1", "one order running, one waiting", |s| {
        s["current"].is_object() && s["agenda"].as_array().is_some_and(|a| a.len() == 1)
    })
    .await
    .unwrap();
    tokio::time::sleep(Duration::from_millis(2000)).await;
    let state = cell.status("robot1").await.unwrap();
    let agenda = state["agenda"].as_array().unwrap();
    assert_eq!(agenda.len(), 1, "the waiting booking is kept: {state}");
    assert!(
        agenda[0].get("requester_absent_since").is_none(),
        "its order is present: {state}"
    );
    for order in &orders {
        cell.wait_order(order, "done", |s| s.is_some_and(|s| s["status"] == "done"))
            .await
            .unwrap();
        let state = cell.order_state(order).await.unwrap();
        assert_eq!(
            state["rebooks"], 0,
            "{order} never lost its booking: {state}"
        );
    }
}

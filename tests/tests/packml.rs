//! PackML on real resource holons, commanded as an operator would: `cell packml` (the
//! real binary) and queries on `resource/<name>/packml`. Hold keeps the bookings and
//! lets the running step finish; Stop hands them back; a refused command changes
//! nothing; the mode changes only where PackML allows; Abort stops the controller
//! mid-step; orders go to the other robot while one is held; bookings a stop hands
//! back are booked again, not failed; a held robot comes back Held after kill -9.

use std::time::Duration;

use holarchy_tests::*;
use schemas::{MessageType, Service};

/// `cell packml ARGS` against `cell`: its exit success and stdout.
async fn cell_packml(cell: &Cell, args: &[&str]) -> (bool, String) {
    let output = tokio::process::Command::new(bin("cell"))
        .arg("packml")
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
    let stderr = String::from_utf8_lossy(&output.stderr);
    (output.status.success(), format!("{stdout}{stderr}"))
}

/// Asks `cell packml`, which must accept the command; returns what it printed.
async fn accepted(cell: &Cell, args: &[&str]) -> String {
    let (ok, out) = cell_packml(cell, args).await;
    assert!(ok, "cell packml {args:?}: {out}");
    out
}

fn request(cell: &Cell, kind: MessageType, conversation: &str) -> Service {
    pick_n_place(&cell.keys, kind, "o-1", conversation)
}

#[tokio::test(flavor = "multi_thread")]
async fn hold_stop_reset_start_and_modes_through_cell_packml() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-packml").await.unwrap();
    let robot = cell
        .resource(dir.path(), "robot1")
        .sim_flags(&["--delay-ms", "700"])
        .start()
        .await
        .unwrap();
    let state = cell.wait_packml("robot1", 6).await.unwrap();
    assert_eq!(state["packml"]["mode"], "production", "{state}");
    let mut inbox = cell.inbox("o-1", 0).await.unwrap();

    // c1 runs, c2 waits on the agenda.
    for kind in [MessageType::BookingReq, MessageType::Start] {
        let answer = cell
            .service("robot1", &request(&cell, kind, "c1"))
            .await
            .unwrap();
        assert_eq!(answer.result, Some(true), "{answer:?}");
    }
    let c2 = request(&cell, MessageType::BookingReq, "c2");
    assert_eq!(
        cell.service("robot1", &c2).await.unwrap().result,
        Some(true)
    );

    // Hold: Holding while c1 finishes, then Held; c2 is kept and does not start.
    let out = accepted(&cell, &["robot1", "hold"]).await;
    assert!(out.contains("robot1: Holding (10)"), "{out}");
    let done = inbox.next().await.unwrap();
    assert_eq!(
        done.message_type,
        MessageType::Done,
        "c1 finishes: {done:?}"
    );
    let held = cell.wait_packml("robot1", 11).await.unwrap();
    assert_eq!(held["agenda"].as_array().unwrap().len(), 1, "{held}");
    assert_eq!(held["packml"]["stop_reason"]["id"], 4, "{held}");
    let start = cell
        .service("robot1", &request(&cell, MessageType::Start, "c2"))
        .await
        .unwrap();
    assert_eq!(
        start.reason.as_ref().map(|r| r.as_str()),
        Some("unavailable"),
        "{start:?}"
    );
    assert_eq!(start.info["packml_state"], 11, "{start:?}");
    let ask = pick_n_place(&cell.keys, MessageType::ProposalReq, "o-9", "p");
    cell.wait_proposals(&ask, 0).await.unwrap();

    // A command out of place is refused, naming the state, and changes nothing.
    let (ok, out) = cell_packml(&cell, &["robot1", "start"]).await;
    assert!(!ok, "{out}");
    assert!(
        out.contains("refused: Start is not allowed in Held; it stays Held (11)"),
        "{out}"
    );
    let (ok, out) = cell_packml(&cell, &["robot1", "--mode", "maintenance"]).await;
    assert!(!ok && out.contains("cannot change in Held"), "{out}");

    // Unhold: c2 starts as booked.
    let out = accepted(&cell, &["robot1", "unhold"]).await;
    assert!(out.contains("Execute (6)"), "{out}");
    let start = cell
        .service("robot1", &request(&cell, MessageType::Start, "c2"))
        .await
        .unwrap();
    assert_eq!(start.result, Some(true), "{start:?}");
    assert_eq!(inbox.next().await.unwrap().message_type, MessageType::Done);
    cell.wait_free("robot1").await.unwrap();

    // Stop hands c3 back at once (failed withdrawn: its order books elsewhere).
    let c3 = request(&cell, MessageType::BookingReq, "c3");
    assert_eq!(
        cell.service("robot1", &c3).await.unwrap().result,
        Some(true)
    );
    accepted(&cell, &["robot1", "stop"]).await;
    let back = inbox.next().await.unwrap();
    assert_eq!(back.conversation_id, "c3");
    assert_eq!(
        back.reason.as_ref().map(|r| r.as_str()),
        Some("withdrawn"),
        "{back:?}"
    );
    cell.wait_packml("robot1", 2).await.unwrap();

    // Maintenance takes no orders' work, even in Execute.
    accepted(&cell, &["robot1", "--mode", "maintenance"]).await;
    accepted(&cell, &["robot1", "reset"]).await;
    cell.wait_packml("robot1", 4).await.unwrap();
    accepted(&cell, &["robot1", "3"]).await; // Stop by number
    accepted(&cell, &["robot1", "reset"]).await;
    accepted(&cell, &["robot1", "start"]).await;
    let state = cell.wait_packml("robot1", 6).await.unwrap();
    assert_eq!(state["packml"]["mode"], "maintenance");
    let refused = cell
        .service("robot1", &request(&cell, MessageType::BookingReq, "c4"))
        .await
        .unwrap();
    assert_eq!(
        refused.reason.as_ref().map(|r| r.as_str()),
        Some("unavailable")
    );
    assert!(
        refused.info["detail"]
            .as_str()
            .unwrap()
            .contains("Maintenance"),
        "{refused:?}"
    );

    // Back to production.
    for args in [
        &["robot1", "stop"][..],
        &["robot1", "--mode", "production"],
        &["robot1", "reset"],
        &["robot1", "start"],
    ] {
        accepted(&cell, args).await;
    }
    cell.wait_proposals(&ask, 1).await.unwrap();

    // The figures, as `cell packml NAME` and `cell status` show them.
    let out = accepted(&cell, &["robot1"]).await;
    assert!(
        out.contains("robot1: Execute (6), Production mode"),
        "{out}"
    );
    assert!(out.contains("processed: 2  defective: 0"), "{out}");
    // First-out: the Stop after the return to Execute replaced the Hold.
    assert!(out.contains("stop reason: Stop by cell"), "{out}");
    assert!(out.contains("commands now: Stop, Hold, Abort"), "{out}");
    let state = cell.status("robot1").await.unwrap();
    assert!(state["packml"]["cumulative_ms"]["held"].as_u64().unwrap() > 0);
    assert_eq!(robot.sim.executed("pick"), 2);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_malformed_packml_request_gets_an_error_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-packml-bad").await.unwrap();
    let _robot = cell.resource(dir.path(), "robot1").start().await.unwrap();
    for payload in [
        &br#"{"command":"halt"}"#[..],
        br#"{"command":"hold","mode":"manual"}"#,
        b"\xff\xfe",
    ] {
        let replies = cell
            .session
            .get(cell.keys.packml("robot1"))
            .payload(payload.to_vec())
            .timeout(Duration::from_secs(5))
            .await
            .unwrap();
        let reply = replies.recv_async().await.unwrap();
        let error = reply.result().expect_err("refused");
        let body = schemas::ErrorReply::from_json(&error.payload().to_bytes()).unwrap();
        assert_eq!(body.code.as_str(), "malformed", "{body:?}");
    }
    let state = cell.status("robot1").await.unwrap();
    assert_eq!(state["packml"]["state"], "execute");
}

#[tokio::test(flavor = "multi_thread")]
async fn abort_mid_step_tells_the_controller_and_fails_the_step_aborted() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-packml-abort").await.unwrap();
    let robot = cell
        .resource(dir.path(), "robot1")
        .sim_flags(&["--delay-ms", "4000"])
        .command_timeout_ms(10_000)
        .start()
        .await
        .unwrap();
    let mut inbox = cell.inbox("o-1", 0).await.unwrap();
    for kind in [MessageType::BookingReq, MessageType::Start] {
        let answer = cell
            .service("robot1", &request(&cell, kind, "c1"))
            .await
            .unwrap();
        assert_eq!(answer.result, Some(true), "{answer:?}");
    }
    robot.sim.wait_received(1).await.unwrap();
    accepted(&cell, &["robot1", "abort"]).await;
    let result = inbox.next().await.unwrap();
    assert_eq!(result.message_type, MessageType::Failed, "{result:?}");
    assert_eq!(
        result.reason.as_ref().map(|r| r.as_str()),
        Some("aborted"),
        "{result:?}"
    );
    let aborted = cell.wait_packml("robot1", 9).await.unwrap();
    assert_eq!(aborted["packml"]["defective"], 1, "{aborted}");
    // The simulator was told: the pick was aborted, never completed.
    assert_eq!(robot.sim.counts()["aborted"], 1, "{}", robot.sim.counts());
    assert_eq!(robot.sim.executed("pick"), 0);
    // Clear, Reset, Start: it works again.
    accepted(&cell, &["robot1", "clear"]).await;
    cell.wait_packml("robot1", 2).await.unwrap();
    accepted(&cell, &["robot1", "reset"]).await;
    accepted(&cell, &["robot1", "start"]).await;
    cell.wait_packml("robot1", 6).await.unwrap();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_held_robot_comes_back_held_after_kill_9() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let data = data.to_str().unwrap();
    let cell = Cell::open("t-packml-kill").await.unwrap();
    let mut robot = cell
        .resource(dir.path(), "robot1")
        .node_flags(&["--data-dir", data])
        .start()
        .await
        .unwrap();
    accepted(&cell, &["robot1", "hold"]).await;
    cell.wait_packml("robot1", 11).await.unwrap();
    robot.node.kill();
    cell.wait_gone(&schemas::HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    let _again = cell
        .start_free_resource(
            dir.path(),
            &robot.config,
            &robot.sim.address,
            &["--data-dir", data],
        )
        .await
        .unwrap();
    let state = cell.status("robot1").await.unwrap();
    assert_eq!(
        state["packml"]["state"], "held",
        "never silently Execute: {state}"
    );
    assert_eq!(state["packml"]["stop_reason"]["id"], 4, "{state}");
    let ask = pick_n_place(&cell.keys, MessageType::ProposalReq, "o-9", "p");
    cell.wait_proposals(&ask, 0).await.unwrap();
    accepted(&cell, &["robot1", "unhold"]).await;
    cell.wait_proposals(&ask, 1).await.unwrap();
}

/// Two robots and an order-node: while robot1 is held, the orders go to robot2, and
/// none is lost or fails.
#[tokio::test(flavor = "multi_thread")]
async fn while_robot1_is_held_the_orders_go_to_robot2() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-packml-orders").await.unwrap();
    let robot1 = cell
        .resource(dir.path(), "robot1")
        .sim_flags(&["--delay-ms", "100"])
        .start()
        .await
        .unwrap();
    let robot2 = cell
        .resource(dir.path(), "robot2")
        .sim_flags(&["--delay-ms", "100"])
        .start()
        .await
        .unwrap();
    let (_product, _orders) = cell
        .start_part_and_orders(
            dir.path(),
            &demo_config("orders1.toml"),
            &dir.path().join("orders-data"),
        )
        .await
        .unwrap();
    let first = cell.submit("part", 4).await.unwrap();
    wait_done(&cell, &first).await;
    accepted(&cell, &["robot1", "hold"]).await;
    cell.wait_packml("robot1", 11).await.unwrap();
    let picks_before = robot1.sim.executed("pick");
    let second = cell.submit("part", 6).await.unwrap();
    wait_done(&cell, &second).await;
    assert_eq!(
        robot1.sim.executed("pick"),
        picks_before,
        "a held robot starts no new job"
    );
    assert!(robot2.sim.executed("pick") >= 6);
    accepted(&cell, &["robot1", "unhold"]).await;
    cell.wait_packml("robot1", 6).await.unwrap();
}

/// An operator stops the only robot while orders wait on its agenda: their bookings are
/// handed back (`failed` `withdrawn`, nothing of them ran), and the orders book again
/// once it is started, each finishing with no failed attempt. The order-node allows one
/// failed attempt a step, so one handed-back booking counted as a failure would fail
/// its order.
#[tokio::test(flavor = "multi_thread")]
async fn bookings_a_stopped_robot_hands_back_are_booked_again_not_failed() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-packml-handed-back").await.unwrap();
    let robot = cell
        .resource(dir.path(), "robot1")
        .sim_flags(&["--delay-ms", "700"])
        .start()
        .await
        .unwrap();
    let (_product, _orders) = cell
        .start_part_and_demo_orders(dir.path(), 1)
        .await
        .unwrap();
    let orders = cell.submit("part", 3).await.unwrap();
    // One runs, the others wait their turn on the agenda.
    cell.wait_state("robot1", "one job running, two waiting", |s| {
        s["current"].is_object() && s["agenda"].as_array().is_some_and(|a| a.len() >= 2)
    })
    .await
    .unwrap();
    // Held, the running job finishes; stopped, the waiting bookings are handed back.
    accepted(&cell, &["robot1", "hold"]).await;
    cell.wait_packml("robot1", 11).await.unwrap();
    accepted(&cell, &["robot1", "stop"]).await;
    cell.wait_packml("robot1", 2).await.unwrap();
    let handed_back = robot.sim.executed("pick");
    accepted(&cell, &["robot1", "reset"]).await;
    accepted(&cell, &["robot1", "start"]).await;
    cell.wait_packml("robot1", 6).await.unwrap();
    wait_done(&cell, &orders).await;

    let mut rebooked = 0;
    for order in &orders {
        let state = cell.order_state(order).await.unwrap();
        assert_eq!(state["failed_attempts"], 0, "{state:#}");
        rebooked += state["rebooks"].as_u64().unwrap();
    }
    assert!(
        rebooked >= 1,
        "no booking was handed back (picks before the stop: {handed_back})"
    );
    assert_eq!(robot.sim.executed("pick"), 3, "each order's step once");
}

async fn wait_done(cell: &Cell, orders: &[String]) {
    for order in orders {
        cell.wait_order(order, "done", |s| s.is_some_and(|s| s["status"] == "done"))
            .await
            .unwrap();
    }
}

/// A planned hand-over (an upgrade) keeps the PackML state: a robot in Maintenance, Held
/// by an operator, is in Maintenance and Held in its successor, with its figures.
#[tokio::test(flavor = "multi_thread")]
async fn a_successor_takes_over_the_packml_state() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let data = data.to_str().unwrap();
    let cell = Cell::open("t-packml-upgrade").await.unwrap();
    let mut robot = cell
        .resource(dir.path(), "robot1")
        .node_flags(&["--data-dir", data])
        .start()
        .await
        .unwrap();
    let mut inbox = cell.inbox("o-1", 0).await.unwrap();
    let done = cell.job("robot1", &mut inbox, "o-1", "c1").await.unwrap();
    assert_eq!(done.message_type, MessageType::Done);
    for args in [
        &["robot1", "stop"][..],
        &["robot1", "--mode", "maintenance"],
        &["robot1", "reset"],
        &["robot1", "start"],
        &["robot1", "hold"],
    ] {
        accepted(&cell, args).await;
    }
    let before = cell.wait_packml("robot1", 11).await.unwrap();
    let next = dir.path().join("next");
    std::fs::create_dir_all(&next).unwrap();
    let mut successor = start_node(
        &next,
        &robot.config,
        cell.keys.cell(),
        &cell.endpoint,
        &robot.sim.address,
        &["--data-dir", data, "--take-over"],
    )
    .unwrap();
    let status = robot.node.wait_exit(Duration::from_secs(30)).unwrap();
    assert!(status.success(), "the predecessor hands over: {status:?}");
    cell.wait_alive(&schemas::HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    let after = cell.wait_packml("robot1", 11).await.unwrap();
    assert_eq!(after["packml"]["mode"], "maintenance", "{after}");
    assert_eq!(after["packml"]["processed"], 1, "{after}");
    assert_eq!(
        after["packml"]["stop_reason"], before["packml"]["stop_reason"],
        "{after}"
    );
    successor.kill();
}

/// Maintenance: not offered to orders, but an operator runs single jobs on it; the
/// result goes to no inbox and is in the PackML figures.
#[tokio::test(flavor = "multi_thread")]
async fn an_operator_runs_single_jobs_in_maintenance() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-packml-job").await.unwrap();
    let robot = cell.resource(dir.path(), "robot1").start().await.unwrap();
    let info = pick_n_place(&cell.keys, MessageType::Start, "o-1", "x").info;
    let job = schemas::PackmlRequest::job(
        schemas::packml::JobRequest {
            service_type: "pick_n_place".into(),
            info: info.clone(),
        },
        "a test",
    );
    let ask = |request: schemas::PackmlRequest| {
        let cell = &cell;
        async move {
            let replies = cell
                .session
                .get(cell.keys.packml("robot1"))
                .payload(serde_json::to_vec(&request).unwrap())
                .timeout(Duration::from_secs(5))
                .await
                .unwrap();
            let reply = replies.recv_async().await.unwrap();
            serde_json::from_slice::<schemas::PackmlReply>(
                &reply.result().unwrap().payload().to_bytes(),
            )
            .unwrap()
        }
    };
    // In Production: refused, nothing runs.
    let refused = ask(job.clone()).await;
    assert!(
        refused
            .detail
            .as_deref()
            .is_some_and(|d| d.contains("Maintenance mode")),
        "{refused:?}"
    );
    for args in [
        &["robot1", "stop"][..],
        &["robot1", "--mode", "maintenance"],
        &["robot1", "reset"],
        &["robot1", "start"],
    ] {
        accepted(&cell, args).await;
    }
    let began = ask(job).await;
    assert_eq!(began.job.as_deref(), Some("maintenance/1"), "{began:?}");
    let state = cell
        .wait_state("robot1", "the operator's job done", |s| {
            s["packml"]["operator_job"]["done"] == true
        })
        .await
        .unwrap();
    assert!(
        state["packml"]["operator_job"]["outcome"]
            .as_str()
            .unwrap()
            .starts_with("done pick=picking_done"),
        "{state}"
    );
    assert_eq!(state["undelivered"], 0, "delivered to nobody: {state}");
    assert_eq!(robot.sim.executed("pick"), 1);
    // The same from the command line: it waits for the job's end and says how.
    let info = serde_json::Value::Object(info).to_string();
    let out = accepted(&cell, &["robot1", "--job", "pick_n_place", "--info", &info]).await;
    assert!(
        out.contains("robot1: maintenance/2 pick_n_place: done pick=picking_done"),
        "{out}"
    );
    assert_eq!(robot.sim.executed("pick"), 2);
    // A job that does not fit is refused and exits 1.
    let (ok, out) = cell_packml(&cell, &["robot1", "--job", "pick_n_place"]).await;
    assert!(!ok && out.contains("does not fit"), "{out}");
    // Orders still get nothing from it.
    let book = pick_n_place(&cell.keys, MessageType::BookingReq, "o-1", "c1");
    assert_eq!(
        cell.service("robot1", &book).await.unwrap().reason,
        Some(schemas::Reason::Unavailable)
    );
}

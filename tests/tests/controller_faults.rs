//! Controller faults, each through a real resource holon: the step fails with a clear
//! reason delivered to the order, and the holon keeps serving (after a controller fault
//! or e-stop, once an operator has cleared, reset and started it: PackML Aborted).

use holarchy_tests::*;
use schemas::{MessageType, Service};

struct Robot {
    cell: Cell,
    sim: Sim,
    _node: Process,
    _dir: tempfile::TempDir,
}

async fn robot(cell: &str, sim_flags: &[&str]) -> Robot {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open(cell).await.unwrap();
    let Resource { sim, node, .. } = cell
        .resource(dir.path(), "robot1")
        .sim_flags(sim_flags)
        .command_timeout_ms(600)
        .start()
        .await
        .unwrap();
    Robot {
        cell,
        sim,
        _node: node,
        _dir: dir,
    }
}

impl Robot {
    /// Books and starts one job for `order`, and returns the result its inbox gets.
    async fn job(&self, inbox: &mut Inbox, order: &str, conversation: &str) -> Service {
        self.cell
            .job("robot1", inbox, order, conversation)
            .await
            .unwrap()
    }

    /// Waits until robot1 takes work again (see `Cell::wait_serving`).
    async fn free(&self) {
        self.cell.wait_serving("robot1").await.unwrap();
    }
}

fn assert_failed(result: &Service, reason: &str) {
    assert_eq!(result.message_type, MessageType::Failed, "{result:?}");
    assert_eq!(
        result.reason.as_ref().map(|r| r.as_str()),
        Some(reason),
        "{result:?}"
    );
    assert!(
        result.info["detail"]
            .as_str()
            .is_some_and(|d| !d.is_empty()),
        "{result:?}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn a_controller_that_stops_replying_times_the_step_out() {
    let r = robot("t-f-hang", &["--hang-after", "1"]).await;
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    let result = r.job(&mut inbox, "o-1", "c1").await;
    assert_failed(&result, "controller_timeout");
    // The holon serves on: its state answers, the connection was reset and re-made.
    r.cell
        .wait_state("robot1", "ready controller", |s| s["controller"] == "ready")
        .await
        .unwrap();
    assert!(r.sim.process.stderr().matches("bridge connected").count() >= 2);
}

#[tokio::test(flavor = "multi_thread")]
async fn an_error_result_fails_the_step_with_the_controllers_message() {
    // Every third command fails: job 1 (commands 1, 2) is done, job 2 fails at its pick
    // (command 3), job 3 (commands 4, 5) is done.
    let r = robot("t-f-error", &["--error-every", "3"]).await;
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    assert_eq!(
        r.job(&mut inbox, "o-1", "c1").await.message_type,
        MessageType::Done
    );
    r.free().await;
    let result = r.job(&mut inbox, "o-1", "c2").await;
    assert_failed(&result, "controller_error");
    assert!(
        result.info["detail"]
            .as_str()
            .unwrap()
            .contains("pick failed: simulated error"),
        "{result:?}"
    );
    r.free().await;
    assert_eq!(
        r.job(&mut inbox, "o-1", "c3").await.message_type,
        MessageType::Done
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn malformed_xml_resets_the_connection_and_the_next_job_succeeds() {
    let r = robot("t-f-garbage", &["--garbage-after", "1"]).await;
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    let result = r.job(&mut inbox, "o-1", "c1").await;
    assert_failed(&result, "controller_protocol_error");
    assert!(
        result.info["detail"]
            .as_str()
            .unwrap()
            .contains("malformed"),
        "{result:?}"
    );
    r.free().await;
    assert_eq!(
        r.job(&mut inbox, "o-1", "c2").await.message_type,
        MessageType::Done
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn a_dropped_connection_fails_the_step_and_reconnects() {
    let r = robot("t-f-close", &["--close-after", "1"]).await;
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    assert_failed(
        &r.job(&mut inbox, "o-1", "c1").await,
        "controller_disconnected",
    );
    r.free().await;
    // Each connection takes one command: the next job's pick works, its place fails again.
    let result = r.job(&mut inbox, "o-1", "c2").await;
    assert_failed(&result, "controller_disconnected");
    assert_eq!(r.sim.wait_executed("pick", 2).await.unwrap(), 2);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_fault_aborts_the_resource_until_an_operator_clears_resets_and_starts_it() {
    for state in ["fault", "estop"] {
        let r = robot(
            &format!("t-f-{state}"),
            &[
                "--fault-after",
                "1",
                "--fault-state",
                state,
                "--fault-for-ms",
                "1500",
            ],
        )
        .await;
        let ask = pick_n_place(&r.cell.keys, MessageType::ProposalReq, "o-9", "p");
        r.cell.wait_proposals(&ask, 1).await.unwrap();
        let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
        let result = r.job(&mut inbox, "o-1", "c1").await;
        assert_failed(&result, "controller_fault");
        assert!(
            result.info["detail"].as_str().unwrap().contains(state),
            "{result:?}"
        );
        // While in fault: no offers, no bookings.
        let state_now = r
            .cell
            .wait_state("robot1", state, |s| s["controller"] == state)
            .await
            .unwrap();
        assert_eq!(state_now["state"], "init");
        r.cell.wait_proposals(&ask, 0).await.unwrap();
        let book = pick_n_place(&r.cell.keys, MessageType::BookingReq, "o-2", "c2");
        assert_eq!(
            r.cell.service("robot1", &book).await.unwrap().reason,
            Some(schemas::Reason::Unavailable)
        );
        // PackML: the fault aborted the resource; ready again, it stays Aborted (no
        // offers) until an operator clears, resets and starts it.
        r.cell.wait_free("robot1").await.unwrap();
        let aborted = r
            .cell
            .wait_state("robot1", "Aborted", |s| s["packml"]["state"] == "aborted")
            .await
            .unwrap();
        assert_eq!(
            aborted["packml"]["stop_reason"]["id"],
            if state == "fault" { 100 } else { 101 }
        );
        r.cell.wait_proposals(&ask, 0).await.unwrap();
        for command in ["clear", "reset", "start"] {
            r.cell.packml("robot1", command).await.unwrap();
        }
        r.cell.wait_proposals(&ask, 1).await.unwrap();
        assert_eq!(
            r.job(&mut inbox, "o-1", "c3").await.message_type,
            MessageType::Done
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_controller_that_breaks_every_connection_is_reconnected_to_with_a_backoff() {
    // The simulator answers every status poll with a safety status the holon's dialect
    // does not know (`HOMING`, outside its `safety` table): each connection ends in a
    // protocol error at its first poll, and none ever serves.
    let dir = tempfile::tempdir().unwrap();
    let shipped = workspace_root().join("deploy/dialects/ur-dashboard.toml");
    let homing = std::fs::read_to_string(&shipped).unwrap().replacen(
        r#"ready = ["NORMAL", "REDUCED"]"#,
        r#"ready = ["HOMING"]"#,
        1,
    );
    assert!(homing.contains("HOMING"));
    let sim_dialect = dir.path().join("homing.toml");
    std::fs::write(&sim_dialect, homing).unwrap();
    let sim = Sim::start(
        dir.path(),
        "robot1-sim",
        "127.0.0.1:0",
        &["--dialect", sim_dialect.to_str().unwrap()],
    )
    .unwrap();
    let config = resource_config(dir.path(), "robot1", 5000).unwrap();
    let text = std::fs::read_to_string(&config).unwrap().replacen(
        "reconnect_interval_ms = 100\nreconnect_max_ms = 1000\n",
        "reconnect_interval_ms = 200\nreconnect_max_ms = 1600\ndialect = \"ur-dashboard\"\n",
        1,
    );
    assert!(text.contains("reconnect_max_ms = 1600"), "{text}");
    std::fs::write(&config, text).unwrap();
    let cell = Cell::open("t-f-backoff").await.unwrap();
    let _node = start_node(
        dir.path(),
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &[],
    )
    .unwrap();
    // From the first connection on, for a fixed window.
    let deadline = tokio::time::Instant::now() + std::time::Duration::from_secs(20);
    while sim.connections() == 0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the holon never connected"
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let first = sim.connections();
    tokio::time::sleep(std::time::Duration::from_secs(6)).await;
    let connections = sim.connections() - first + 1;
    // Pauses of 200, 400, 800, 1600, 1600, ... ms: connections at about 0, 0.2, 0.6,
    // 1.4, 3.0, 4.6 and 6.2 s, 6 within 6 s (each a few ms long). Without the backoff
    // (100 ms after each lost connection) there were 60.
    println!("{connections} connections within 6 s");
    assert!(
        (4..=8).contains(&connections),
        "{connections} connections within 6 s; a backoff from 200 ms doubling to 1600 ms allows 6"
    );
    // The holon reported its controller disconnected throughout.
    let state = cell
        .ask_state(&schemas::HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    assert_eq!(state["controller"], "disconnected", "{state}");
}

/// Orders wait on robot1's agenda when its connection breaks mid-job (`--reset-after
/// 2`: the second job's first command is cut): that job fails `controller_disconnected`
/// (it was sent: it may have run), and the next booking's turn comes while the
/// controller reconnects, so robot1 fails it `unavailable` without sending it. The
/// order-node allows one failed attempt a step: the job that was sent fails its order,
/// the one that never reached the controller is booked again and done, as is every
/// other. Before, the unsent one counted as a failure and failed its order too.
#[tokio::test(flavor = "multi_thread")]
async fn a_booking_whose_turn_comes_while_the_controller_reconnects_is_booked_again() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-f-turn-unready").await.unwrap();
    let robot = cell
        .resource(dir.path(), "robot1")
        .sim_flags(&["--delay-ms", "300", "--reset-after", "2"])
        // Away long enough that the next turn surely comes while it reconnects.
        .reconnect_interval_ms(1000)
        .start()
        .await
        .unwrap();
    let (_product, _orders) = cell
        .start_part_and_demo_orders(dir.path(), 1)
        .await
        .unwrap();
    let orders = cell.submit("part", 3).await.unwrap();
    let mut ended = Vec::new();
    for order in &orders {
        cell.wait_order(order, "ended", |s| {
            s.is_some_and(|s| s["status"] != "running")
        })
        .await
        .unwrap();
        ended.push(cell.order_state(order).await.unwrap());
    }
    let failed: Vec<&serde_json::Value> =
        ended.iter().filter(|s| s["status"] == "failed").collect();
    assert_eq!(
        failed.len(),
        1,
        "only the job that was sent fails: {ended:#?}"
    );
    assert!(
        failed[0]["reason"]
            .as_str()
            .is_some_and(|r| r.contains("controller_disconnected")),
        "{ended:#?}"
    );
    let rebooked: Vec<&serde_json::Value> = ended
        .iter()
        .filter(|s| s["status"] == "done")
        .filter(|s| {
            s["attempts"].as_array().unwrap().iter().any(|a| {
                a["detail"]
                    .as_str()
                    .is_some_and(|d| d.contains("unavailable (the controller is not ready)"))
            })
        })
        .collect();
    assert_eq!(
        rebooked.len(),
        1,
        "one turn came while robot1 reconnected: {ended:#?}"
    );
    assert_eq!(rebooked[0]["failed_attempts"], 0, "{:#}", rebooked[0]);
    assert_eq!(rebooked[0]["rebooks"], 1, "{:#}", rebooked[0]);
    assert_eq!(
        ended.iter().filter(|s| s["status"] == "done").count(),
        2,
        "{ended:#?}"
    );
    // Two jobs done; the cut one's place never ran.
    assert_eq!(robot.sim.executed("place"), 2);
}

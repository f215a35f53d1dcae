//! The resource holon end to end: `robot-sim` and `holon-node` as real processes, a
//! zenoh client that knows only the contract.

use std::time::Duration;

use holarchy_tests::*;
use nix::sys::signal::Signal;
use schemas::{HolonId, MessageType, Service};
use zenoh::sample::SampleKind;

struct Robot {
    cell: Cell,
    sim: Sim,
    node: Process,
    dir: tempfile::TempDir,
    holon: HolonId,
}

async fn robot(
    cell: &str,
    sim_flags: &[&str],
    node_flags: &[&str],
    command_timeout_ms: u64,
) -> Robot {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open(cell).await.unwrap();
    // Alive means serving; it waits for the controller too before booking.
    let Resource { sim, node, .. } = cell
        .resource(dir.path(), "robot1")
        .sim_flags(sim_flags)
        .command_timeout_ms(command_timeout_ms)
        .node_flags(node_flags)
        .start()
        .await
        .unwrap();
    let holon = HolonId::resource("robot1").unwrap();
    Robot {
        cell,
        sim,
        node,
        dir,
        holon,
    }
}

impl Robot {
    fn msg(&self, kind: MessageType, order: &str, conversation: &str) -> Service {
        pick_n_place(&self.cell.keys, kind, order, conversation)
    }

    async fn send(&self, kind: MessageType, order: &str, conversation: &str) -> Service {
        self.cell
            .service("robot1", &self.msg(kind, order, conversation))
            .await
            .unwrap()
    }
}

fn assert_refused(answer: &Service, why: &str) {
    assert_eq!(answer.result, Some(false), "{answer:?}");
    assert_eq!(
        answer.reason.as_ref().map(|r| r.as_str()),
        Some(why),
        "{answer:?}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn books_starts_and_delivers_done_until_acknowledged() {
    // Each command takes 100 ms on the controller, so the job lasts long enough to be
    // seen busy: the changes of one moment are published once, and a job of 0 ms
    // begins and ends within one moment.
    let r = robot("t-cycle", &["--delay-ms", "100"], &[], 5000).await;
    let states = r
        .cell
        .session
        .declare_subscriber(r.cell.keys.state(&r.holon))
        .await
        .unwrap();

    // Contract net: one proposal from the one live capable resource.
    let proposals = r
        .cell
        .wait_proposals(&r.msg(MessageType::ProposalReq, "o-1", "o-1/1/1"), 1)
        .await
        .unwrap();
    assert_eq!(proposals[0].message_type, MessageType::Proposal);
    assert_eq!(proposals[0].result, Some(true));
    assert_eq!(proposals[0].provider, Some(r.holon.clone()));
    assert_eq!(proposals[0].info["expected_wait_ms"], 0);

    // The inbox refuses the first two deliveries: `done` must come again.
    let mut inbox = r.cell.inbox("o-1", 2).await.unwrap();
    let booked = r.send(MessageType::BookingReq, "o-1", "o-1/1/1").await;
    assert_eq!(booked.result, Some(true), "{booked:?}");
    assert_eq!(booked.info["queue_position"], 1);
    let started = r.send(MessageType::Start, "o-1", "o-1/1/1").await;
    assert_eq!(started.result, Some(true), "{started:?}");

    for attempt in 1..=3 {
        let done = inbox.next().await.unwrap();
        assert_eq!(done.message_type, MessageType::Done, "attempt {attempt}");
        assert_eq!(done.conversation_id, "o-1/1/1");
        assert_eq!(done.result, Some(true));
        assert_eq!(done.provider, Some(r.holon.clone()));
        assert_eq!(done.info["results"]["pick"], "picking_done");
        assert_eq!(done.info["results"]["place"], "placing_done");
    }
    // Acknowledged on the third attempt: no more deliveries.
    assert!(inbox.silent_for(Duration::from_millis(1500)).await);
    let state = r
        .cell
        .wait_state("robot1", "free with nothing undelivered", |s| {
            s["state"] == "free" && s["undelivered"] == 0
        })
        .await
        .unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 0);
    assert_eq!(r.sim.executed("pick"), 1);
    assert_eq!(r.sim.executed("place"), 1);
    // The two attempts after the first are counted (the dashboard's metrics read them),
    // and the snapshot names the machine.
    assert_eq!(state["delivery_retries"], 2, "{state}");
    assert_eq!(state["host"], holon::presence::host_name(), "{state}");

    // Snapshots were published on every change that lasted: booked, busy, steps, free.
    let mut seen = Vec::new();
    while let Ok(Some(sample)) = states.try_recv() {
        let snapshot: serde_json::Value =
            serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
        seen.push(snapshot["state"].as_str().unwrap_or("").to_string());
    }
    assert!(seen.contains(&"busy".to_string()), "{seen:?}");
    assert!(seen.contains(&"free".to_string()), "{seen:?}");
    let log = std::fs::read_to_string(r.dir.path().join("robot1.log.json")).unwrap();
    let first: serde_json::Value = serde_json::from_str(log.lines().next().unwrap()).unwrap();
    assert!(first["timestamp"].is_string(), "{first}");
    assert!(
        log.lines()
            .any(|l| l.contains("\"conversation_id\":\"o-1/1/1\"")
                && l.contains("\"message_type\":\"start\"")),
        "the JSON log lacks the start message"
    );
}

/// The holon's own tasks and zenoh's work run on one pool of one thread (zenoh's `app`,
/// `holon/src/zenoh_runtime.rs`), the link's writer on a thread of its own (`tx-0`): no
/// runtime of its own, none of zenoh's other three. Its journal's fsyncs (`power_loss`)
/// hand the thread over while they wait, to one of the pool's blocking threads (named
/// `app-N` too).
#[tokio::test(flavor = "multi_thread")]
async fn the_holon_and_its_zenoh_share_one_pool() {
    let r = robot("t-pool", &[], &[], 5000).await;
    // A job done: requests read, answers and a result written.
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    let done = r.cell.job("robot1", &mut inbox, "o-1", "c1").await.unwrap();
    assert_eq!(done.message_type, MessageType::Done, "{done:?}");
    let mut threads: Vec<String> = std::fs::read_dir(format!("/proc/{}/task", r.node.pid()))
        .unwrap()
        .flatten()
        .filter_map(|task| std::fs::read_to_string(task.path().join("comm")).ok())
        .map(|name| name.trim().to_string())
        .collect();
    threads.sort();
    let workers: Vec<&String> = threads
        .iter()
        .filter(|t| {
            ["app-", "rx-", "tx-", "acc-", "net-", "tokio-"]
                .iter()
                .any(|p| t.starts_with(p))
        })
        .collect();
    assert!(
        workers
            .iter()
            .all(|t| t.starts_with("app-") || *t == "tx-0"),
        "only zenoh's app pool and the link's writer: {threads:?}"
    );
    assert!(threads.iter().any(|n| n == "app-0"), "{threads:?}");
    assert!(threads.iter().any(|n| n == "tx-0"), "{threads:?}");
}

#[tokio::test(flavor = "multi_thread")]
async fn bookings_on_turn_start_by_themselves_one_after_another() {
    let r = robot("t-on-turn", &["--delay-ms", "150"], &[], 5000).await;
    let mut first_inbox = r.cell.inbox("o-1", 0).await.unwrap();
    let mut second_inbox = r.cell.inbox("o-2", 0).await.unwrap();
    let on_turn = |order: &str, conversation: &str| {
        r.msg(MessageType::BookingReq, order, conversation)
            .with_start_on_turn()
    };
    // Free with nothing ahead: one request books and starts.
    let first = r
        .cell
        .service("robot1", &on_turn("o-1", "c1"))
        .await
        .unwrap();
    assert!(first.started(), "{first:?}");
    assert_eq!(first.info["queue_position"], 0, "{first:?}");
    // Behind the running job: booked, to start when that ends.
    let second = r
        .cell
        .service("robot1", &on_turn("o-2", "c2"))
        .await
        .unwrap();
    assert_eq!(second.result, Some(true), "{second:?}");
    assert!(!second.started(), "{second:?}");
    assert_eq!(second.info["queue_position"], 2, "{second:?}");
    // Asked again (a lost reply): begun, and not begun twice.
    let again = r
        .cell
        .service("robot1", &on_turn("o-1", "c1"))
        .await
        .unwrap();
    assert!(again.started(), "{again:?}");
    // Without it asking for anything else, each order gets its result.
    let done = first_inbox.next().await.unwrap();
    assert_eq!(
        (done.message_type, done.conversation_id.as_str()),
        (MessageType::Done, "c1")
    );
    let done = second_inbox.next().await.unwrap();
    assert_eq!(
        (done.message_type, done.conversation_id.as_str()),
        (MessageType::Done, "c2")
    );
    r.cell
        .wait_state("robot1", "free with nothing undelivered", |s| {
            s["state"] == "free" && s["undelivered"] == 0
        })
        .await
        .unwrap();
    assert_eq!(r.sim.executed("pick"), 2, "each job once");
    // A booking on turn without the poses its steps need is refused, nothing booked.
    let mut no_poses = on_turn("o-3", "c3");
    no_poses
        .info
        .retain(|key, _| key == schemas::info_key::START_ON_TURN);
    assert_refused(
        &r.cell.service("robot1", &no_poses).await.unwrap(),
        "invalid_info",
    );
    let state = r.cell.status("robot1").await.unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 0, "{state}");
}

#[tokio::test(flavor = "multi_thread")]
async fn cancel_removes_the_booking() {
    let r = robot("t-cancel", &[], &[], 5000).await;
    assert_eq!(
        r.send(MessageType::BookingReq, "o-1", "c1").await.result,
        Some(true)
    );
    assert_eq!(
        r.send(MessageType::BookingReq, "o-2", "c2").await.result,
        Some(true)
    );
    let cancelled = r.send(MessageType::BookingCancel, "o-1", "c1").await;
    assert_eq!(cancelled.result, Some(true));
    let state = r.cell.status("robot1").await.unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 1);
    assert_eq!(state["agenda"][0]["conversation_id"], "c2");
    assert_refused(&r.send(MessageType::Start, "o-1", "c1").await, "not_booked");
    assert_refused(
        &r.send(MessageType::BookingCancel, "o-1", "c1").await,
        "not_booked",
    );
    assert_eq!(r.sim.executed("pick"), 0);
}

#[tokio::test(flavor = "multi_thread")]
async fn starts_that_are_not_allowed_are_refused() {
    let r = robot("t-reject", &["--delay-ms", "400"], &[], 5000).await;
    let _inbox = r.cell.inbox("o-1", 0).await.unwrap();
    // Start by a requester that holds no booking.
    assert_refused(&r.send(MessageType::Start, "o-9", "c9").await, "not_booked");
    // Start while busy.
    r.send(MessageType::BookingReq, "o-1", "c1").await;
    r.send(MessageType::BookingReq, "o-2", "c2").await;
    assert_eq!(
        r.send(MessageType::Start, "o-1", "c1").await.result,
        Some(true)
    );
    assert_refused(&r.send(MessageType::Start, "o-2", "c2").await, "busy");
    // An unknown service type.
    let mut weld = r.msg(MessageType::BookingReq, "o-3", "c3");
    weld.service_type = "weld".into();
    assert_refused(
        &r.cell.service("robot1", &weld).await.unwrap(),
        "unknown_service",
    );
    // A start without the poses its steps need.
    r.cell
        .wait_state("robot1", "free", |s| s["state"] == "free")
        .await
        .unwrap();
    let mut no_poses = r.msg(MessageType::BookingReq, "o-5", "c5");
    no_poses.info.clear();
    assert_eq!(
        r.cell.service("robot1", &no_poses).await.unwrap().result,
        Some(true)
    );
    no_poses.message_type = MessageType::Start;
    let answer = r.cell.service("robot1", &no_poses).await.unwrap();
    assert_refused(&answer, "invalid_info");
    assert!(answer.info["detail"]
        .as_str()
        .unwrap()
        .contains("info.pick"));
    // Booked by an order-node at epoch 3: its deposed holder (epoch 2) can neither
    // start nor cancel the booking.
    let booked = r
        .msg(MessageType::BookingReq, "o-6", "c6")
        .with_epoch(Some(3));
    assert_eq!(
        r.cell.service("robot1", &booked).await.unwrap().result,
        Some(true)
    );
    for kind in [MessageType::Start, MessageType::BookingCancel] {
        let stale = r.msg(kind, "o-6", "c6").with_epoch(Some(2));
        let answer = r.cell.service("robot1", &stale).await.unwrap();
        assert_refused(&answer, "stale_epoch");
        assert!(
            answer.info["detail"]
                .as_str()
                .unwrap()
                .contains("booked at epoch 3"),
            "{answer:?}"
        );
    }
    // The refused bookings are still there.
    let state = r.cell.status("robot1").await.unwrap();
    assert_eq!(state["agenda"][0]["conversation_id"], "c2");
    assert_eq!(state["agenda"][1]["conversation_id"], "c5");
    assert_eq!(state["agenda"][2]["conversation_id"], "c6");
    assert_eq!(r.sim.executed("pick"), 1, "only the accepted start ran");
}

#[tokio::test(flavor = "multi_thread")]
async fn malformed_requests_get_an_error_and_change_nothing() {
    let r = robot("t-malformed", &[], &[], 5000).await;
    r.send(MessageType::BookingReq, "o-1", "c1").await;
    let service_key = r.cell.keys.service("robot1");
    let done = r.msg(MessageType::Done, "o-1", "c1").to_json();
    let mut bad_version =
        serde_json::to_value(r.msg(MessageType::BookingReq, "o-2", "c2")).unwrap();
    bad_version["v"] = serde_json::json!(9);
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (&service_key, b"this is not json".to_vec(), "malformed"),
        (&service_key, b"{\"v\":1}".to_vec(), "malformed"),
        (&service_key, vec![], "malformed"),
        (
            &service_key,
            serde_json::to_vec(&bad_version).unwrap(),
            "unsupported_version",
        ),
        (&service_key, done, "wrong_key"),
    ];
    for (key, payload, code) in cases {
        let answer = r.cell.request(key, payload).await.unwrap();
        let error = answer.expect_err("an error reply");
        assert_eq!(error.code.as_str(), code, "{error:?}");
        assert!(!error.message.is_empty());
    }
    // A booking sent to the offer key is not a proposal request.
    let offer_key = r.cell.keys.offer("pick_n_place", "robot1");
    let booking = r.msg(MessageType::BookingReq, "o-3", "c3").to_json();
    let error = r
        .cell
        .request(&offer_key, booking)
        .await
        .unwrap()
        .unwrap_err();
    assert_eq!(error.code.as_str(), "wrong_key");
    // Nothing changed, and the holon still serves.
    let state = r.cell.status("robot1").await.unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 1);
    assert_eq!(
        r.send(MessageType::BookingReq, "o-4", "c4").await.result,
        Some(true)
    );
    assert!(r.node.stderr().contains("request rejected"));
}

#[tokio::test(flavor = "multi_thread")]
async fn a_controller_killed_mid_step_fails_the_step_and_the_next_job_succeeds() {
    let mut r = robot("t-kill-ctl", &["--delay-ms", "1500"], &[], 10_000).await;
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    r.send(MessageType::BookingReq, "o-1", "c1").await;
    assert_eq!(
        r.send(MessageType::Start, "o-1", "c1").await.result,
        Some(true)
    );
    r.cell
        .wait_state("robot1", "picking", |s| s["current"]["step"] == "pick")
        .await
        .unwrap();
    r.sim.wait_received(1).await.unwrap();
    let address = r.sim.address.clone();
    r.sim.process.kill();

    let failed = inbox.next().await.unwrap();
    assert_eq!(failed.message_type, MessageType::Failed);
    assert_eq!(failed.conversation_id, "c1");
    assert_eq!(failed.result, Some(false));
    assert_eq!(
        failed.reason.as_ref().map(|r| r.as_str()),
        Some("controller_disconnected")
    );
    r.cell
        .wait_state("robot1", "init without a controller", |s| {
            s["state"] == "init" && s["controller"] == "disconnected"
        })
        .await
        .unwrap();
    // While the controller is away, no new commitments are made.
    assert_refused(
        &r.send(MessageType::BookingReq, "o-1", "c2").await,
        "unavailable",
    );

    // The controller comes back on the same address: the bridge reconnects.
    let sim = Sim::start(r.dir.path(), "sim1-again", &address, &[]).unwrap();
    r.cell
        .wait_state("robot1", "free again", |s| s["state"] == "free")
        .await
        .unwrap();
    assert_eq!(
        r.send(MessageType::BookingReq, "o-1", "c3").await.result,
        Some(true)
    );
    assert_eq!(
        r.send(MessageType::Start, "o-1", "c3").await.result,
        Some(true)
    );
    let done = inbox.next().await.unwrap();
    assert_eq!(done.message_type, MessageType::Done);
    assert_eq!(done.conversation_id, "c3");
    assert_eq!(sim.executed("pick"), 1);
    assert_eq!(sim.executed("place"), 1);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_crashed_component_is_restarted_with_the_bookings_intact() {
    let r = robot("t-crash", &[], &["--allow-fault-injection"], 5000).await;
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    r.send(MessageType::BookingReq, "o-1", "c1").await;
    r.send(MessageType::BookingReq, "o-2", "c2").await;
    let crash_key = r.cell.keys.debug_crash("robot1");
    for (restarts, component) in ["agenda", "execution", "communication", "interfacing"]
        .into_iter()
        .enumerate()
    {
        let replies = r
            .cell
            .session
            .get(&crash_key)
            .payload(component)
            .timeout(Duration::from_secs(5))
            .await
            .unwrap();
        let reply = replies.recv_async().await.unwrap();
        assert!(reply.result().is_ok(), "crash {component}");
        let deadline = std::time::Instant::now() + WAIT;
        while r.node.stderr().matches("restarting component").count() < restarts + 1 {
            assert!(
                std::time::Instant::now() < deadline,
                "{component} was not restarted"
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        // The supervisor restarts it; the holon serves again with both bookings (a new
        // interfacing component connects again first: until then the resource is
        // Suspended, and refuses a start `unavailable`).
        let state = r
            .cell
            .wait_state("robot1", "free and in Execute after the restart", |s| {
                s["state"] == "free"
                    && s["controller"] == "ready"
                    && s["packml"]["state_number"] == 6
            })
            .await
            .unwrap();
        assert_eq!(
            state["agenda"].as_array().unwrap().len(),
            2,
            "after {component}: {state}"
        );
    }
    let log = r.node.stderr();
    for component in ["agenda", "execution", "communication", "interfacing"] {
        assert!(
            log.contains(&format!("fault injection: {component}")),
            "no crash of {component} in the log"
        );
    }
    assert_eq!(log.matches("restarting component").count(), 4, "{log}");
    // The bookings still work.
    let started = r.send(MessageType::Start, "o-1", "c1").await;
    assert_eq!(started.result, Some(true), "{started:?}");
    assert_eq!(inbox.next().await.unwrap().message_type, MessageType::Done);
    assert_eq!(r.sim.executed("pick"), 1);
}

#[tokio::test(flavor = "multi_thread")]
async fn sigterm_withdraws_the_token_and_exits_zero() {
    let mut r = robot("t-sigterm", &[], &[], 5000).await;
    let presence = r
        .cell
        .session
        .liveliness()
        .declare_subscriber(r.cell.keys.alive(&r.holon))
        .await
        .unwrap();
    r.node.signal(Signal::SIGTERM).unwrap();
    let status = r.node.wait_exit(WAIT).unwrap();
    assert!(status.success(), "{status}");
    let sample = tokio::time::timeout(WAIT, presence.recv_async())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(sample.kind(), SampleKind::Delete);
    assert!(r.node.stderr().contains("holon stopped"));
    // The controller saw its connection closed: a new one is accepted by the sim later.
    assert!(r.cell.wait_gone(&r.holon).await.is_ok());
}

#[tokio::test(flavor = "multi_thread")]
async fn a_killed_resource_comes_back_with_its_bookings_and_reports_the_interrupted_step() {
    let data = tempfile::tempdir().unwrap();
    let data_dir = data.path().to_str().unwrap().to_string();
    let mut r = robot(
        "t-recover",
        &["--delay-ms", "800"],
        &["--data-dir", &data_dir],
        10_000,
    )
    .await;
    // o-3's result cannot be delivered yet: its inbox refuses everything for now.
    let mut refusing = r.cell.inbox("o-3", usize::MAX).await.unwrap();
    r.send(MessageType::BookingReq, "o-3", "c3").await;
    r.send(MessageType::Start, "o-3", "c3").await;
    let first = refusing.next().await.unwrap();
    assert_eq!(first.message_type, MessageType::Done);
    // Now a job in progress, and a booking waiting.
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    r.send(MessageType::BookingReq, "o-1", "c1").await;
    r.send(MessageType::BookingReq, "o-2", "c2").await;
    assert_eq!(
        r.send(MessageType::Start, "o-1", "c1").await.result,
        Some(true)
    );
    r.cell
        .wait_state("robot1", "picking", |s| s["current"]["step"] == "pick")
        .await
        .unwrap();
    // c3's pick and place, then c1's pick: on the controller before the holon dies.
    r.sim.wait_received(3).await.unwrap();

    r.node.kill(); // SIGKILL: no chance to clean up
    r.cell.wait_gone(&r.holon).await.unwrap();
    drop(refusing); // o-3's inbox goes away; a new one will acknowledge
    let mut accepting = r.cell.inbox("o-3", 0).await.unwrap();
    let config = r.dir.path().join("robot1.toml");
    r.node = start_node(
        r.dir.path(),
        &config,
        r.cell.keys.cell(),
        &r.cell.endpoint,
        &r.sim.address,
        &["--data-dir", &data_dir],
    )
    .unwrap();
    r.cell.wait_alive(&r.holon).await.unwrap();

    // The interrupted step is reported, never re-executed.
    let failed = inbox.next().await.unwrap();
    assert_eq!(failed.message_type, MessageType::Failed);
    assert_eq!(failed.conversation_id, "c1");
    assert_eq!(
        failed.reason.as_ref().map(|r| r.as_str()),
        Some("interrupted")
    );
    // The undelivered done is delivered again.
    let done = accepting.next().await.unwrap();
    assert_eq!(
        (done.message_type, done.conversation_id.as_str()),
        (MessageType::Done, "c3")
    );
    // The waiting booking is back.
    let state = r
        .cell
        .wait_state("robot1", "free with nothing undelivered", |s| {
            s["state"] == "free" && s["undelivered"] == 0
        })
        .await
        .unwrap();
    assert_eq!(state["agenda"].as_array().unwrap().len(), 1, "{state}");
    assert_eq!(state["agenda"][0]["conversation_id"], "c2");
    // c1's pick reached the controller once, its place never; c3 ran once.
    tokio::time::sleep(Duration::from_millis(1000)).await;
    assert_eq!(r.sim.executed("pick"), 2, "{}", r.sim.counts());
    assert_eq!(r.sim.executed("place"), 1, "{}", r.sim.counts());
    // And the holon serves the waiting booking.
    assert_eq!(
        r.send(MessageType::Start, "o-2", "c2").await.result,
        Some(true)
    );
}

/// SIGTERM with a result whose requester is gone (its order-node was stopped first, as
/// `cell up` and the demo stop a cell): the resource finishes its step, keeps the result
/// in its journal and stops at once instead of waiting its whole shutdown grace (30 s
/// here) for an acknowledgement nobody can send; back, it delivers the result.
#[tokio::test(flavor = "multi_thread")]
async fn a_result_for_a_requester_gone_does_not_hold_up_the_shutdown() {
    let data = tempfile::tempdir().unwrap();
    let data_dir = data.path().to_str().unwrap().to_string();
    let mut r = robot(
        "t-stop-promptly",
        &["--delay-ms", "300"],
        &["--data-dir", &data_dir],
        10_000,
    )
    .await;
    // o-1 refuses its results and holds no liveliness token: gone, as far as the
    // resource can tell.
    let mut refusing = r.cell.inbox("o-1", usize::MAX).await.unwrap();
    r.send(MessageType::BookingReq, "o-1", "c1").await;
    assert_eq!(
        r.send(MessageType::Start, "o-1", "c1").await.result,
        Some(true)
    );
    r.sim.wait_received(1).await.unwrap();
    r.node.signal(Signal::SIGTERM).unwrap();
    let status = r.node.wait_exit(Duration::from_secs(20)).unwrap();
    assert!(status.success(), "{status}");
    let log = r.node.stderr();
    assert!(
        log.contains("delivered when this resource is back"),
        "{log}"
    );
    // The step was finished, not cut short. Its result may have been tried before the
    // resource saw its requester gone, or not (the resource need not wait for that);
    // whatever was tried was refused, so only the journal holds it now.
    assert_eq!(r.sim.executed("place"), 1, "{}", r.sim.counts());
    while let Ok(tried) = refusing.received.try_recv() {
        assert_eq!(tried.conversation_id, "c1", "only c1 was running");
    }
    drop(refusing);
    let mut accepting = r.cell.inbox("o-1", 0).await.unwrap();
    let config = r.dir.path().join("robot1.toml");
    r.node = start_node(
        r.dir.path(),
        &config,
        r.cell.keys.cell(),
        &r.cell.endpoint,
        &r.sim.address,
        &["--data-dir", &data_dir],
    )
    .unwrap();
    let done = accepting.next().await.unwrap();
    assert_eq!(
        (done.message_type, done.conversation_id.as_str()),
        (MessageType::Done, "c1")
    );
}

/// What robot1 says became of `conversation` of `order` (`resource/robot1/outcome`).
async fn outcome(cell: &Cell, order: &str, conversation: &str) -> schemas::OutcomeReply {
    let request =
        schemas::OutcomeRequest::new(conversation, "pick_n_place", HolonId::order(order).unwrap());
    let replies = cell
        .session
        .get(cell.keys.outcome("robot1"))
        .payload(request.to_json())
        .timeout(WAIT)
        .await
        .unwrap();
    let reply = replies.recv_async().await.expect("robot1 answers");
    let sample = reply.result().expect("an outcome, not an error");
    schemas::OutcomeReply::from_json(&sample.payload().to_bytes()).unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn an_unfenced_resource_tells_what_became_of_a_conversation_from_its_agenda() {
    use schemas::{Outcome, OutcomeSource};
    let r = robot("t-outcome", &["--action-ms", "place=1000"], &[], 5000).await;
    // Never booked here: it cannot tell (and has no fenced controller to ask).
    let never = outcome(&r.cell, "o1", "o1/1/1").await;
    assert_eq!(
        (never.outcome, never.source),
        (Outcome::Unknown, OutcomeSource::Nowhere),
        "{never:?}"
    );
    assert_eq!(never.epoch, None, "unfenced: {never:?}");
    // Booked: waiting, then running (place takes a second); its result is refused, so
    // it stays in the agenda until acknowledged.
    let mut inbox = r.cell.inbox("o1", usize::MAX).await.unwrap();
    let booked = r.send(MessageType::BookingReq, "o1", "o1/1/1").await;
    assert_eq!(booked.result, Some(true), "{booked:?}");
    assert_eq!(
        outcome(&r.cell, "o1", "o1/1/1").await.outcome,
        Outcome::Running
    );
    let started = r.send(MessageType::Start, "o1", "o1/1/1").await;
    assert_eq!(started.result, Some(true), "{started:?}");
    let running = outcome(&r.cell, "o1", "o1/1/1").await;
    assert_eq!(
        (running.outcome, running.source),
        (Outcome::Running, OutcomeSource::Journal),
        "{running:?}"
    );
    let delivered = inbox.next().await.unwrap();
    assert_eq!(delivered.message_type, MessageType::Done, "{delivered:?}");
    let done = outcome(&r.cell, "o1", "o1/1/1").await;
    assert_eq!(
        (done.outcome, done.source),
        (Outcome::Done, OutcomeSource::Journal),
        "{done:?}"
    );
    assert_eq!(done.results["place"], "placing_done", "{done:?}");
    // Another requester's question about it is not answered from it.
    assert_eq!(
        outcome(&r.cell, "o2", "o1/1/1").await.outcome,
        Outcome::Unknown
    );
    assert_eq!(r.sim.executed("place"), 1);
}

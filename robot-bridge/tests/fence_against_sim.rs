//! The fence (issue 31) against a real robot-sim over TCP: one live holder, a silent
//! holder deposed, stale epochs refused and counted, step ids run at most once, step
//! status, and the unfenced paths unchanged. No timing is asserted.

mod common;

use std::time::Duration;

use common::{reply, start_sim, wait_received, WAIT};
use robot_bridge::client::{
    self, fence, ClaimError, ClientConfig, CommandFailure, ControllerEvent, ControllerRequest,
    Epoch, FenceEvent, FenceHandle, StepId, StepStatus,
};
use robot_bridge::sim::SimConfig;
use schemas::RobotCommand;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

const LEASE: Duration = Duration::from_millis(300);

/// A fenced client task: its fence handle, command mailbox and events.
struct Fenced {
    handle: FenceHandle,
    commands: mpsc::Sender<ControllerRequest>,
    events: mpsc::Receiver<ControllerEvent>,
    fence_events: mpsc::Receiver<FenceEvent>,
    shutdown: CancellationToken,
}

fn start(address: &str) -> Fenced {
    let config = ClientConfig {
        reconnect_interval: Duration::from_millis(50),
        command_timeout: Duration::from_secs(5),
        connect_timeout: Duration::from_secs(1),
        ..ClientConfig::new(address)
    };
    let (handle, mut port, fence_events) = fence::channel(&config);
    let (commands, mut command_rx) = mpsc::channel(16);
    let (event_tx, events) = mpsc::channel(64);
    let shutdown = CancellationToken::new();
    tokio::spawn({
        let shutdown = shutdown.clone();
        async move { client::run_fenced(config, &mut command_rx, &mut port, event_tx, shutdown).await }
    });
    Fenced {
        handle,
        commands,
        events,
        fence_events,
        shutdown,
    }
}

fn pick(id: u64) -> RobotCommand {
    RobotCommand {
        id,
        action: "pick".into(),
        pos: None,
        program: None,
        info: Default::default(),
    }
}

impl Fenced {
    /// Claims until connected: the answer once the controller gave one.
    async fn claim(&self, name: &str) -> Result<Epoch, ClaimError> {
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            match self.handle.claim(name).await {
                Err(ClaimError::NotConnected) if tokio::time::Instant::now() < deadline => {
                    tokio::time::sleep(Duration::from_millis(20)).await
                }
                other => return other,
            }
        }
    }

    /// Sends `command` as step `step` (answered as ordinary controller events).
    async fn step(&self, command: RobotCommand, step: StepId) {
        self.commands
            .send(ControllerRequest::Step { command, step })
            .await
            .expect("the client runs");
    }

    async fn answer(&mut self) -> ControllerEvent {
        loop {
            let event = tokio::time::timeout(WAIT, self.events.recv())
                .await
                .expect("an event in time")
                .expect("client gone");
            if !matches!(event, ControllerEvent::Status(..)) {
                return event;
            }
        }
    }

    async fn fence_event(&mut self) -> FenceEvent {
        tokio::time::timeout(WAIT, self.fence_events.recv())
            .await
            .expect("a fence event in time")
            .expect("client gone")
    }
}

fn fenced_sim(delay: Duration) -> SimConfig {
    SimConfig {
        delay,
        fence_lease: Some(LEASE),
        ..SimConfig::default()
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn one_holder_a_silent_one_is_deposed_and_a_step_runs_once() {
    let (address, stats, sim) = start_sim("127.0.0.1:0", fenced_sim(Duration::ZERO)).await;
    let mut first = start(&address);
    let mut second = start(&address);
    assert!(first.handle.fencing_supported());
    let e1 = first.claim("robot1").await.expect("granted");
    assert_eq!(e1, Epoch(1));
    // While the first holds it (heartbeats), the second is refused with its epoch.
    for _ in 0..3 {
        assert_eq!(second.claim("robot1").await, Err(ClaimError::Held(e1)));
        tokio::time::sleep(LEASE / 2).await;
    }
    // A step, run by the first.
    let step = StepId::of("orders1-3/2/1", 0).unwrap();
    first.step(pick(1), step.clone()).await;
    assert_eq!(first.answer().await, reply(1, "picking_done"));
    // The first goes silent: the controller closes it, the claim is lost.
    first.handle.pause_heartbeats(true).await.unwrap();
    assert_eq!(first.fence_event().await, FenceEvent::Lost { epoch: e1 });
    let e2 = loop {
        match second.claim("robot1").await {
            Ok(epoch) => break epoch,
            Err(ClaimError::Held(_)) => tokio::time::sleep(Duration::from_millis(20)).await,
            Err(other) => panic!("claim: {other}"),
        }
    };
    assert_eq!(e2, Epoch(2));
    // The old holder's next command: refused stale_epoch, counted, not executed.
    let executed = stats.executed();
    let mut id = 2;
    let answer = loop {
        first
            .step(pick(id), StepId::of("orders1-4/1/1", 0).unwrap())
            .await;
        match first.answer().await {
            // Still reconnecting after the controller closed it.
            ControllerEvent::CommandFailed { failure, .. }
                if !matches!(failure, CommandFailure::StaleEpoch { .. }) =>
            {
                tokio::time::sleep(Duration::from_millis(20)).await;
                id += 1;
            }
            other => break other,
        }
    };
    match answer {
        ControllerEvent::CommandFailed {
            failure: CommandFailure::StaleEpoch { current },
            ..
        } => assert_eq!(current, Some(Epoch(2))),
        other => panic!("expected stale_epoch, got {other:?}"),
    }
    assert!(matches!(
        first.fence_event().await,
        FenceEvent::Deposed {
            current: Some(Epoch(2)),
            ..
        }
    ));
    assert!(stats.stale_epoch_refused() >= 1);
    assert_eq!(stats.executed(), executed);
    // The new holder learns the step's outcome and repeats it: the stored outcome.
    assert_eq!(
        second.handle.step_status(&step).await,
        Ok(StepStatus::Done {
            result: "picking_done".into()
        })
    );
    second.step(pick(7), step.clone()).await;
    assert_eq!(second.answer().await, reply(7, "picking_done"));
    assert_eq!(stats.by_step().get(step.as_str()), Some(&1));
    assert_eq!(stats.executed(), executed);
    assert_eq!(
        second
            .handle
            .step_status(&StepId::new("never/ran#0").unwrap())
            .await,
        Ok(StepStatus::Unknown)
    );
    first.shutdown.cancel();
    second.shutdown.cancel();
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn step_status_of_a_running_step() {
    let (address, stats, sim) =
        start_sim("127.0.0.1:0", fenced_sim(Duration::from_millis(500))).await;
    let mut holder = start(&address);
    holder.claim("robot1").await.expect("granted");
    let step = StepId::of("o/1", 0).unwrap();
    holder.step(pick(1), step.clone()).await;
    wait_received(&stats, 1).await;
    assert_eq!(
        holder.handle.step_status(&step).await,
        Ok(StepStatus::Running)
    );
    assert_eq!(holder.answer().await, reply(1, "picking_done"));
    assert_eq!(
        holder.handle.step_status(&step).await,
        Ok(StepStatus::Done {
            result: "picking_done".into()
        })
    );
    holder.shutdown.cancel();
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn unfenced_sim_and_client_work_as_before() {
    let (address, stats, sim) = start_sim("127.0.0.1:0", SimConfig::default()).await;
    let mut fenced = start(&address);
    // An unfenced controller refuses the claim: standby is not possible.
    assert!(matches!(
        fenced.claim("robot1").await,
        Err(ClaimError::NotSupported(_))
    ));
    fenced.commands.send(pick(1).into()).await.unwrap();
    assert_eq!(fenced.answer().await, reply(1, "picking_done"));
    let mut plain = common::Harness::start(address.clone(), Duration::from_secs(5));
    plain.wait_ready().await;
    plain.send(2, "pick").await;
    assert_eq!(plain.answer().await, reply(2, "picking_done"));
    assert_eq!(stats.executed(), 2);
    assert!(!stats.to_json().contains("by_step"));
    plain.stop().await;
    fenced.shutdown.cancel();
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn an_unfenced_client_is_refused_by_a_fenced_sim() {
    let (address, stats, sim) = start_sim("127.0.0.1:0", fenced_sim(Duration::ZERO)).await;
    let mut plain = common::Harness::start(address, Duration::from_secs(5));
    plain.wait_ready().await;
    plain.send(1, "pick").await;
    match plain.answer().await {
        ControllerEvent::CommandFailed {
            id: 1,
            failure: CommandFailure::StaleEpoch { .. },
        } => {}
        other => panic!("expected stale_epoch, got {other:?}"),
    }
    assert_eq!(stats.executed(), 0);
    assert_eq!(stats.stale_epoch_refused(), 1);
    plain.stop().await;
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn garbage_fence_messages_are_refused_and_change_nothing() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let (address, stats, sim) = start_sim("127.0.0.1:0", fenced_sim(Duration::ZERO)).await;
    let holder = start(&address);
    let epoch = holder.claim("robot1").await.expect("granted");
    let mut raw = tokio::net::TcpStream::connect(&address).await.unwrap();
    let long = "x".repeat(200);
    let messages = [
        format!("<CLAIM><NAME>{long}</NAME></CLAIM>"),
        "<CLAIM><NAME>a b</NAME></CLAIM>".to_string(),
        "<HEARTBEAT><EPOCH>banana</EPOCH></HEARTBEAT>".to_string(),
        format!("<STEP_STATUS><STEP>{long}</STEP></STEP_STATUS>"),
    ];
    for m in &messages {
        raw.write_all(m.as_bytes()).await.unwrap();
    }
    let mut seen = String::new();
    let mut buf = [0u8; 4096];
    while seen.matches("<FENCE_REFUSED>").count() < messages.len() {
        let n = tokio::time::timeout(WAIT, raw.read(&mut buf))
            .await
            .unwrap()
            .unwrap();
        assert!(n > 0, "closed early: {seen}");
        seen.push_str(&String::from_utf8_lossy(&buf[..n]));
    }
    assert!(seen.contains("<REASON>invalid</REASON>"), "{seen}");
    assert!(seen.contains("<REASON>stale_epoch</REASON>"), "{seen}");
    // Oversized: the connection is closed, as for any over-size document.
    let mut big = b"<CLAIM><NAME>".to_vec();
    big.resize(70_000, b'x');
    let _ = raw.write_all(&big).await;
    assert_eq!(stats.epoch(), epoch.0);
    assert_eq!(holder.claim("robot1").await, Ok(epoch));
    holder.shutdown.cancel();
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn epochs_go_on_after_a_sim_restart_and_the_count_file_shows_the_fence() {
    let dir = tempfile::tempdir().unwrap();
    let counts = dir.path().join("counts.json");
    let config = || SimConfig {
        count_file: Some(counts.clone()),
        ..fenced_sim(Duration::ZERO)
    };
    let (address, _, sim) = start_sim("127.0.0.1:0", config()).await;
    let mut holder = start(&address);
    assert_eq!(holder.claim("robot1").await, Ok(Epoch(1)));
    let step = StepId::of("o/9", 1).unwrap();
    holder.step(pick(1), step.clone()).await;
    assert_eq!(holder.answer().await, reply(1, "picking_done"));
    holder.shutdown.cancel();
    sim.cancel();
    // The count file is written (off the command path): wait for the step in it.
    let deadline = tokio::time::Instant::now() + WAIT;
    let json = loop {
        let json: serde_json::Value = std::fs::read_to_string(&counts)
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default();
        if json["by_step"][step.as_str()] == 1 {
            break json;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the count file: {json}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    };
    assert_eq!(json["epoch"], 1);
    assert_eq!(json["stale_epoch_refused"], 0);
    // A new simulator on the same count file never grants epoch 1 again.
    let (address, _, sim) = start_sim("127.0.0.1:0", config()).await;
    let holder = start(&address);
    assert_eq!(holder.claim("robot1").await, Ok(Epoch(2)));
    holder.shutdown.cancel();
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_step_in_flight_when_its_holder_froze_runs_once() {
    let (address, stats, sim) =
        start_sim("127.0.0.1:0", fenced_sim(Duration::from_millis(600))).await;
    let old = start(&address);
    let mut new = start(&address);
    assert_eq!(old.claim("robot1").await, Ok(Epoch(1)));
    let step = StepId::of("orders1-5/1/1", 0).unwrap();
    old.step(pick(1), step.clone()).await;
    wait_received(&stats, 1).await;
    // It freezes with the step under way; the controller completes the motion.
    old.handle.pause_heartbeats(true).await.unwrap();
    let epoch = loop {
        match new.claim("robot1").await {
            Ok(epoch) => break epoch,
            Err(ClaimError::Held(_)) => tokio::time::sleep(Duration::from_millis(20)).await,
            Err(other) => panic!("claim: {other}"),
        }
    };
    assert_eq!(epoch, Epoch(2));
    // The new holder repeats the step: it is not run again (still running, or done).
    new.step(pick(5), step.clone()).await;
    match new.answer().await {
        ControllerEvent::Reply {
            id: 5,
            result,
            message,
        } if result == "error" => {
            assert!(message.unwrap_or_default().starts_with("step_running"));
        }
        other => assert_eq!(other, reply(5, "picking_done")),
    }
    // It learns the outcome from the controller.
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        match new.handle.step_status(&step).await {
            Ok(StepStatus::Done { result }) => {
                assert_eq!(result, "picking_done");
                break;
            }
            Ok(StepStatus::Running) => tokio::time::sleep(Duration::from_millis(20)).await,
            other => panic!("step status: {other:?}"),
        }
        assert!(tokio::time::Instant::now() < deadline);
    }
    assert_eq!(stats.by_step().get(step.as_str()), Some(&1));
    assert_eq!(stats.executed(), 1);
    old.shutdown.cancel();
    new.shutdown.cancel();
    sim.cancel();
}

/// Any claim name, valid or not, from a second session while a holder is live: refused
/// (held, or invalid), and the epoch stays the holder's.
#[tokio::test(flavor = "multi_thread")]
async fn arbitrary_claim_names_change_nothing() {
    use proptest::strategy::{Strategy, ValueTree};
    use proptest::test_runner::TestRunner;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let (address, stats, sim) = start_sim("127.0.0.1:0", fenced_sim(Duration::ZERO)).await;
    let holder = start(&address);
    let epoch = holder.claim("robot1").await.expect("granted");
    let mut raw = tokio::net::TcpStream::connect(&address).await.unwrap();
    let mut runner = TestRunner::deterministic();
    let names = proptest::string::string_regex(".{0,300}").unwrap();
    let mut buf = vec![0u8; 8192];
    let mut seen = String::new();
    for _ in 0..64 {
        let name = names.new_tree(&mut runner).unwrap().current();
        let claim = format!(
            "<CLAIM><NAME>{}</NAME></CLAIM>",
            quick_xml::escape::escape(name.as_str())
        );
        raw.write_all(claim.as_bytes()).await.unwrap();
        while !seen.contains("</FENCE_REFUSED>") {
            let n = tokio::time::timeout(WAIT, raw.read(&mut buf))
                .await
                .unwrap()
                .unwrap();
            assert!(n > 0, "the controller closed on {name:?}: {seen}");
            seen.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
        let (answer, rest) = seen.split_once("</FENCE_REFUSED>").unwrap();
        assert!(
            answer.ends_with("<REASON>held</REASON>")
                || answer.ends_with("<REASON>invalid</REASON>"),
            "{name:?}: {answer}"
        );
        seen = rest.to_string();
        assert_eq!(stats.epoch(), epoch.0);
    }
    assert_eq!(holder.claim("robot1").await, Ok(epoch));
    holder.shutdown.cancel();
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_grant_is_known_for_half_a_lease_and_not_once_the_connection_is_gone() {
    let lease = Duration::from_secs(2);
    let config = SimConfig {
        fence_lease: Some(lease),
        ..SimConfig::default()
    };
    let (address, _stats, sim) = start_sim("127.0.0.1:0", config).await;
    let mut holder = start(&address);
    assert!(!holder.handle.confirmed(), "nothing granted yet");
    holder.claim("robot1").await.expect("granted");
    assert!(holder.handle.confirmed(), "granted just now");
    // Half a lease after the claim was sent, it must be asked again.
    tokio::time::sleep(lease / 2).await;
    assert!(!holder.handle.confirmed(), "half a lease has passed");
    holder.claim("robot1").await.expect("granted again");
    assert!(holder.handle.confirmed());
    // The controller goes away: the claim is lost, and no longer known held.
    sim.cancel();
    loop {
        if let FenceEvent::Lost { .. } = holder.fence_event().await {
            break;
        }
    }
    assert!(
        !holder.handle.confirmed(),
        "the connection holding it ended"
    );
    holder.shutdown.cancel();
}

//! The worked case of docs/dialects.md section 7.7 (deploy/dialects/examples/
//! job-ack-end.toml), the controller client against robot-sim speaking the same file:
//! replies that echo the command's id (`ACK`, `END`) and one that does not (`NAK`), one
//! status reply per state with the controller's own words in the error, and an echoed id
//! that is not the command's.

use std::sync::Arc;
use std::time::Duration;

mod common;

use common::{reply, start_sim, Harness};
use robot_bridge::client::{CommandFailure, ControllerEvent, ControllerStatus};
use robot_bridge::dialect::Dialect;
use robot_bridge::sim::{SimConfig, SimStats};
use tokio_util::sync::CancellationToken;

fn example_text() -> String {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../deploy/dialects/examples/job-ack-end.toml"
    );
    std::fs::read_to_string(path).unwrap()
}

fn example() -> Arc<Dialect> {
    Arc::new(Dialect::from_toml(&example_text(), "job-ack-end.toml").unwrap())
}

async fn ready(
    dialect: Arc<Dialect>,
    faults: SimConfig,
    command_timeout: Duration,
) -> (Harness, Arc<SimStats>, CancellationToken) {
    let config = SimConfig {
        dialect: Some(dialect.clone()),
        delay: Duration::from_millis(5),
        ..faults
    };
    let (address, stats, sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start_in(dialect, address, command_timeout, None);
    h.wait_status(ControllerStatus::Ready).await;
    (h, stats, sim)
}

#[tokio::test(flavor = "multi_thread")]
async fn a_nak_without_an_id_answers_the_job_it_refused() {
    let (mut h, stats, _sim) = ready(example(), SimConfig::default(), Duration::from_secs(5)).await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    // robot-sim refuses an action it does not know with the NAK, which names no job: it
    // answers job 2 at once, not at the command timeout.
    h.send(2, "weld").await;
    assert_eq!(
        h.answer().await,
        ControllerEvent::Reply {
            id: 2,
            result: "error".into(),
            message: Some("refused the command: unknown action \"weld\"".into()),
        }
    );
    h.send(3, "place").await;
    assert_eq!(h.answer().await, reply(3, "placing_done"));
    assert_eq!(stats.connections(), 1, "no reset");
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_fault_rehearsed_says_the_controllers_words_and_nothing_is_sent_meanwhile() {
    let faults = SimConfig {
        fault_after: Some(1),
        fault_for: Duration::from_millis(1500),
        ..SimConfig::default()
    };
    let (mut h, stats, _sim) = ready(example(), faults, Duration::from_secs(5)).await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    // Job 2 faults the robot (it leaves the job unanswered); the polled state is the
    // error, in the controller's words (STATE ERROR simulated fault (--fault-after)).
    h.send(2, "place").await;
    let said = loop {
        match h.next().await {
            ControllerEvent::Status(ControllerStatus::Fault, words) => break words,
            ControllerEvent::Status(ControllerStatus::Ready, _) => {}
            other => panic!("unexpected {other:?}"),
        }
    };
    assert_eq!(said.as_deref(), Some("simulated fault (--fault-after)"));
    // Job 2 ends at once (not at its timeout, which would reset the connection later).
    assert_eq!(
        h.answer().await,
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Stopped(ControllerStatus::Fault),
        }
    );
    // Nothing goes to the faulted robot: the next job fails without a word to it.
    h.send(3, "pick").await;
    assert_eq!(
        h.answer().await,
        ControllerEvent::CommandFailed {
            id: 3,
            failure: CommandFailure::Stopped(ControllerStatus::Fault),
        }
    );
    h.wait_status(ControllerStatus::Ready).await;
    h.send(4, "pick").await;
    assert_eq!(h.answer().await, reply(4, "picking_done"));
    assert_eq!(stats.refused_while_stopped(), 0);
    assert_eq!(stats.connections(), 1, "no reset");
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn an_echoed_id_that_is_not_the_commands_is_never_its_answer() {
    let faults = || SimConfig {
        // Job 2 is answered ACK 29, END 29 OK.
        wrong_id_after: Some(1),
        ..SimConfig::default()
    };
    // One in flight: the answer on the wire names another command: the protocol broke.
    let one = example_text().replace("correlation = \"id\"", "correlation = \"one_in_flight\"");
    let one = Arc::new(Dialect::from_toml(&one, "one.toml").unwrap());
    let (mut h, _stats, _sim) = ready(one, faults(), Duration::from_secs(5)).await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    match h.answer().await {
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Protocol(why),
        } => assert!(
            why.contains("names command 29") && why.contains("on the wire is 2"),
            "{why}"
        ),
        other => panic!("unexpected {other:?}"),
    }
    h.stop().await;
    // With ids: ACK 29 answers no step; job 2 gets no answer of its own and times out.
    let (mut h, _stats, _sim) = ready(example(), faults(), Duration::from_millis(800)).await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    assert!(
        matches!(
            h.answer().await,
            ControllerEvent::CommandFailed {
                id: 2,
                failure: CommandFailure::Timeout(_),
            }
        ),
        "job 2 must not take another job's answer"
    );
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_polled_controller_says_its_state_only_when_asked_even_merged() {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let config = SimConfig {
        dialect: Some(example()),
        merge: true,
        ..SimConfig::default()
    };
    let (address, _stats, sim) = start_sim("127.0.0.1:0", config).await;
    let stream = tokio::net::TcpStream::connect(&address).await.unwrap();
    let (read, mut write) = stream.into_split();
    let mut lines = BufReader::new(read);
    let mut next = async || {
        let mut line = Vec::new();
        lines.read_until(b'\r', &mut line).await.unwrap();
        String::from_utf8(line).unwrap()
    };
    assert_eq!(next().await, "JOBSERVER READY\r");
    write.write_all(b"JOB 1 pick\r").await.unwrap();
    // The ACK and the END come in one write; no state comes with them.
    assert_eq!(next().await, "ACK 1\r");
    assert_eq!(next().await, "END 1 OK\r");
    write.write_all(b"STATE?\r").await.unwrap();
    assert_eq!(next().await, "STATE IDLE\r");
    sim.cancel();
}

#[tokio::test(flavor = "multi_thread")]
async fn fault_every_rehearses_the_fault_again_and_again() {
    let faults = SimConfig {
        fault_every: Some(2),
        // Longer than the state's poll interval (500 ms), or a poll might not see it.
        fault_for: Duration::from_millis(700),
        ..SimConfig::default()
    };
    let (mut h, stats, _sim) = ready(example(), faults, Duration::from_secs(5)).await;
    for round in 0..3u64 {
        let id = round * 2 + 1;
        h.send(id, "pick").await;
        assert_eq!(h.answer().await, reply(id, "picking_done"), "round {round}");
        h.send(id + 1, "place").await;
        h.wait_status(ControllerStatus::Fault).await;
        assert_eq!(
            h.answer().await,
            ControllerEvent::CommandFailed {
                id: id + 1,
                failure: CommandFailure::Stopped(ControllerStatus::Fault),
            },
            "round {round}"
        );
        h.wait_status(ControllerStatus::Ready).await;
    }
    assert_eq!(stats.executed(), 3);
    assert_eq!(stats.refused_while_stopped(), 0);
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_state_the_dialect_does_not_describe_breaks_the_protocol_and_nothing_is_sent_meanwhile() {
    // Every second command takes the controller into HOMING for 1.5 s (robot-sim
    // --unknown-state-every 2): job 2 is left unanswered, and the state poll is answered
    // `STATE HOMING`, a line the dialect does not describe.
    let faults = SimConfig {
        unknown_state_every: Some(2),
        fault_for: Duration::from_millis(1500),
        ..SimConfig::default()
    };
    let (mut h, stats, _sim) = ready(example(), faults, Duration::from_secs(5)).await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    match h.answer().await {
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Protocol(why),
        } => assert!(why.contains("STATE HOMING"), "{why}"),
        other => panic!("unexpected {other:?}"),
    }
    // The holon reconnects; while the controller is homing every poll breaks the
    // connection again; once it says STATE IDLE, jobs go on.
    h.wait_status(ControllerStatus::Ready).await;
    h.send(3, "pick").await;
    assert_eq!(h.answer().await, reply(3, "picking_done"));
    assert!(stats.connections() >= 2, "{}", stats.connections());
    assert_eq!(stats.refused_while_stopped(), 0);
    h.stop().await;
}

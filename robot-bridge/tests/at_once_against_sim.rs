//! A controller that runs several actions at once (`actions_at_once`, as a conveyor's PLC
//! moves several pallets at once), against a real robot-sim over TCP: each action ends
//! at its own time with its own reply, the one over the limit waits for one to end, the
//! abort stops each it names, and fenced, each step is recorded and settled on its own.
//! Order and overlap are told by the replies and the counts; time only as lower bounds.

mod common;

use std::time::{Duration, Instant};

use common::{start_sim, wait_received, WAIT};
use robot_bridge::dialect::Dialect;
use robot_bridge::sim::{SimConfig, SimConfigError, Simulator};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// How long each action takes.
const ACTION: Duration = Duration::from_secs(1);

/// A holarchy-xml connection played by hand, to see each document as it comes.
struct Wire {
    /// The connection.
    stream: tokio::net::TcpStream,
    /// What came and was not read yet.
    received: String,
}

impl Wire {
    async fn connect(address: &str) -> Wire {
        Wire {
            stream: tokio::net::TcpStream::connect(address).await.unwrap(),
            received: String::new(),
        }
    }

    async fn send(&mut self, xml: &str) {
        self.stream.write_all(xml.as_bytes()).await.unwrap();
    }

    /// The next whole document (its root element, whatever it is).
    async fn next(&mut self) -> String {
        loop {
            if let Some(doc) = self.take_doc() {
                return doc;
            }
            let mut buffer = [0u8; 4096];
            let n = tokio::time::timeout(WAIT, self.stream.read(&mut buffer))
                .await
                .expect("a document in time")
                .unwrap();
            assert!(n > 0, "the controller closed: {}", self.received);
            self.received
                .push_str(&String::from_utf8_lossy(&buffer[..n]));
        }
    }

    fn take_doc(&mut self) -> Option<String> {
        let start = self.received.find('<')?;
        let name_end = start + self.received[start..].find(['>', ' '])?;
        let close = format!("</{}>", &self.received[start + 1..name_end]);
        let end = self.received.find(&close)? + close.len();
        let doc = self.received[start..end].to_string();
        self.received.replace_range(..end, "");
        Some(doc)
    }

    /// The next document that is not the controller's state.
    async fn answer(&mut self) -> String {
        loop {
            let doc = self.next().await;
            if !doc.starts_with("<ROBOT_STATUS>") {
                return doc;
            }
        }
    }
}

fn pick(id: u64) -> String {
    format!("<ROBOT_CMD><ID>{id}</ID><ACTION>pick</ACTION></ROBOT_CMD>")
}

fn fenced_pick(id: u64, epoch: u64, step: &str) -> String {
    format!(
        "<ROBOT_CMD><ID>{id}</ID><EPOCH>{epoch}</EPOCH><STEP>{step}</STEP><ACTION>pick</ACTION></ROBOT_CMD>"
    )
}

fn done(id: u64) -> String {
    format!("<ROBOT_REPLY><ID>{id}</ID><RESULT>picking_done</RESULT></ROBOT_REPLY>")
}

fn aborted(id: u64) -> String {
    format!(
        "<ROBOT_REPLY><ID>{id}</ID><RESULT>error</RESULT><MESSAGE>aborted</MESSAGE></ROBOT_REPLY>"
    )
}

fn two_at_once(delay: Duration) -> SimConfig {
    SimConfig {
        delay,
        actions_at_once: 2,
        ..SimConfig::default()
    }
}

/// Three commands at once to a controller that runs two at once: the first two are
/// under way together (both begun before either is answered), the third waits for one
/// of them to end; each is answered with its own id, the third last.
#[tokio::test(flavor = "multi_thread")]
async fn two_run_at_once_and_the_third_waits_for_one_to_end() {
    let (address, stats, sim) = start_sim("127.0.0.1:0", two_at_once(ACTION)).await;
    let mut wire = Wire::connect(&address).await;
    assert_eq!(
        wire.next().await,
        "<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>"
    );
    let sent = Instant::now();
    wire.send(&format!("{}{}{}", pick(1), pick(2), pick(3)))
        .await;
    // Both first ones begun, and neither answered yet: they run together.
    wait_received(&stats, 2).await;
    assert_eq!(stats.received(), 2, "the third began before one ended");
    assert_eq!(stats.executed(), 0, "one ended before both began");
    let mut answers = Vec::new();
    for _ in 0..3 {
        answers.push((wire.answer().await, sent.elapsed()));
    }
    let order: Vec<&str> = answers.iter().map(|(a, _)| a.as_str()).collect();
    assert!(
        order[..2].contains(&done(1).as_str()) && order[..2].contains(&done(2).as_str()),
        "{order:?}"
    );
    assert_eq!(order[2], done(3), "{order:?}");
    // Each takes its action's time; the third began once one of the first had ended.
    assert!(answers[0].1 >= ACTION, "{answers:?}");
    assert!(answers[2].1 >= 2 * ACTION, "{answers:?}");
    assert_eq!(stats.executed(), 3);
    assert_eq!(stats.by_action()["pick"], 3);
    sim.cancel();
}

/// With several under way, the abort stops the one it names (holarchy-xml's abort names
/// its command's id), each answered as an aborted action is, and the rest run on.
#[tokio::test(flavor = "multi_thread")]
async fn the_abort_stops_each_action_it_names() {
    let (address, stats, sim) =
        start_sim("127.0.0.1:0", two_at_once(Duration::from_secs(30))).await;
    let mut wire = Wire::connect(&address).await;
    wire.send(&format!("{}{}", pick(1), pick(2))).await;
    wait_received(&stats, 2).await;
    wire.send("<ROBOT_ABORT><ID>2</ID></ROBOT_ABORT>").await;
    assert_eq!(wire.answer().await, aborted(2));
    wire.send("<ROBOT_ABORT><ID>1</ID></ROBOT_ABORT>").await;
    assert_eq!(wire.answer().await, aborted(1));
    // Room again: a new one begins at once.
    wire.send(&pick(3)).await;
    wait_received(&stats, 3).await;
    wire.send("<ROBOT_ABORT><ID>3</ID></ROBOT_ABORT>").await;
    assert_eq!(wire.answer().await, aborted(3));
    assert_eq!(stats.aborted(), 3);
    assert_eq!(stats.executed(), 0);
    sim.cancel();
}

/// Fenced, two steps under way at once: each recorded running (STEP_STATUS answered at
/// once while they run) and settled done with its own result; a connection cut while
/// two run completes each, unanswered, and settles each step.
#[tokio::test(flavor = "multi_thread")]
async fn fenced_each_step_under_way_is_recorded_and_settled_on_its_own() {
    let config = SimConfig {
        fence_lease: Some(Duration::from_secs(30)),
        ..two_at_once(ACTION)
    };
    let (address, stats, sim) = start_sim("127.0.0.1:0", config).await;
    let mut wire = Wire::connect(&address).await;
    wire.send("<CLAIM><NAME>conveyor1</NAME></CLAIM>").await;
    assert_eq!(
        wire.answer().await,
        "<CLAIM_GRANTED><EPOCH>1</EPOCH><LEASE_MS>30000</LEASE_MS></CLAIM_GRANTED>"
    );
    let state = |step: &str, state: &str, result: &str| {
        format!("<STEP_STATE><STEP>{step}</STEP><STATE>{state}</STATE>{result}</STEP_STATE>")
    };
    wire.send(&format!(
        "{}{}",
        fenced_pick(1, 1, "o-1/1/1"),
        fenced_pick(2, 1, "o-2/1/1")
    ))
    .await;
    wait_received(&stats, 2).await;
    for step in ["o-1/1/1", "o-2/1/1"] {
        wire.send(&format!("<STEP_STATUS><STEP>{step}</STEP></STEP_STATUS>"))
            .await;
        assert_eq!(wire.answer().await, state(step, "running", ""));
    }
    let mut answers = vec![wire.answer().await, wire.answer().await];
    answers.sort();
    assert_eq!(answers, [done(1), done(2)]);
    for step in ["o-1/1/1", "o-2/1/1"] {
        wire.send(&format!("<STEP_STATUS><STEP>{step}</STEP></STEP_STATUS>"))
            .await;
        let result = "<RESULT>picking_done</RESULT>";
        assert_eq!(wire.answer().await, state(step, "done", result));
    }

    // Two under way when the connection goes: each completes and settles its step.
    wire.send(&format!(
        "{}{}",
        fenced_pick(3, 1, "o-3/1/1"),
        fenced_pick(4, 1, "o-4/1/1")
    ))
    .await;
    wait_received(&stats, 4).await;
    drop(wire);
    let deadline = Instant::now() + WAIT;
    while stats.executed() < 4 {
        assert!(Instant::now() < deadline, "the cut actions never completed");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let mut again = Wire::connect(&address).await;
    again.send("<CLAIM><NAME>conveyor1</NAME></CLAIM>").await;
    assert!(again
        .answer()
        .await
        .starts_with("<CLAIM_GRANTED><EPOCH>2</EPOCH>"));
    for step in ["o-3/1/1", "o-4/1/1"] {
        again
            .send(&format!("<STEP_STATUS><STEP>{step}</STEP></STEP_STATUS>"))
            .await;
        let result = "<RESULT>picking_done</RESULT>";
        assert_eq!(again.answer().await, state(step, "done", result));
    }
    let by_step = stats.by_step();
    for step in ["o-1/1/1", "o-2/1/1", "o-3/1/1", "o-4/1/1"] {
        assert_eq!(by_step.get(step), Some(&1), "{by_step:?}");
    }
    sim.cancel();
}

/// With one at a time (the default), a second command waits for the first, as ever.
#[tokio::test(flavor = "multi_thread")]
async fn one_at_a_time_by_default() {
    let config = SimConfig {
        delay: Duration::from_millis(300),
        ..SimConfig::default()
    };
    assert_eq!(config.actions_at_once, 1);
    let (address, stats, sim) = start_sim("127.0.0.1:0", config).await;
    let mut wire = Wire::connect(&address).await;
    wire.send(&format!("{}{}", pick(1), pick(2))).await;
    wait_received(&stats, 1).await;
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert_eq!(stats.received(), 1, "the second began while the first ran");
    assert_eq!(wire.answer().await, done(1));
    assert_eq!(wire.answer().await, done(2));
    sim.cancel();
}

/// 0 actions at once, or more than 1 where a reply names no command, is refused at
/// start, naming the setting.
#[tokio::test]
async fn refused_at_start_zero_or_several_without_ids() {
    let zero = SimConfig {
        actions_at_once: 0,
        ..SimConfig::default()
    };
    assert_eq!(zero.check(), Err(SimConfigError::NoActionAtOnce));
    let refused = Simulator::bind("127.0.0.1:0", zero).await.err().unwrap();
    assert_eq!(refused.kind(), std::io::ErrorKind::InvalidInput);
    assert!(refused.to_string().contains("actions_at_once"), "{refused}");
    let kuka = Dialect::load("kuka-eki", None).unwrap();
    let several = SimConfig {
        actions_at_once: 3,
        dialect: Some(kuka),
        ..SimConfig::default()
    };
    let why = several.check().unwrap_err().to_string();
    assert!(
        why.contains("actions_at_once") && why.contains("one_in_flight"),
        "{why}"
    );
    assert!(Simulator::bind("127.0.0.1:0", several).await.is_err());
    let ids = SimConfig {
        actions_at_once: 3,
        ..SimConfig::default()
    };
    assert_eq!(ids.check(), Ok(()));
}

/// robot-sim refuses `--actions-at-once 0`, and more than 1 in a one-in-flight dialect,
/// with exit 2 and the flag named; `--help` tells of it.
#[test]
fn robot_sim_refuses_actions_at_once_it_cannot_serve() {
    for (args, says) in [
        (vec!["--actions-at-once", "0"], "at least 1"),
        (
            vec!["--actions-at-once", "2", "--dialect", "kuka-eki"],
            "one_in_flight",
        ),
    ] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_robot-sim"))
            .args(["--listen", "127.0.0.1:0"])
            .args(&args)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(
            stderr.contains("--actions-at-once") && stderr.contains(says),
            "{args:?}: {stderr}"
        );
    }
    let help = std::process::Command::new(env!("CARGO_BIN_EXE_robot-sim"))
        .arg("--help")
        .output()
        .unwrap();
    assert!(String::from_utf8_lossy(&help.stdout).contains("--actions-at-once <N>"));
}

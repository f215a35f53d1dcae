//! PackML Abort through every shipped dialect (and the worked example of
//! docs/dialects.md): the controller client against robot-sim speaking the same file,
//! over real TCP sockets on loopback. A long action aborted halfway ends at once, as the
//! dialect's controller reports it, and is not executed; a done that beats the abort
//! stays done; an abort with nothing in flight changes nothing; the connection serves
//! the next command in every case.

use std::sync::Arc;
use std::time::{Duration, Instant};

mod common;

use common::{reply, start_sim, wait_received, Harness, WAIT};
use robot_bridge::client::{CommandFailure, ControllerEvent, ControllerStatus};
use robot_bridge::dialect::{Dialect, SHIPPED};
use robot_bridge::sim::{SimConfig, SimStats};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

/// How long a pick takes in these tests: far longer than an abort may.
const LONG: Duration = Duration::from_secs(2);

/// The most an aborted step may take to end, from the abort.
const PROMPT: Duration = Duration::from_millis(500);

/// The shipped dialects and the worked example.
fn dialects() -> Vec<Arc<Dialect>> {
    let mut all: Vec<Arc<Dialect>> = SHIPPED
        .iter()
        .map(|(name, _)| Dialect::shipped(name).unwrap())
        .collect();
    let example = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../deploy/dialects/examples/staubli-val3-sio.toml"
    );
    all.push(Dialect::load(example, None).unwrap());
    all
}

/// A client and a simulator of `dialect` where a pick takes [`LONG`] and any other
/// action 5 ms; the client ready.
async fn ready(
    dialect: &Arc<Dialect>,
    abort_too_late: bool,
) -> (Harness, Arc<SimStats>, CancellationToken) {
    let config = SimConfig {
        dialect: Some(dialect.clone()),
        delay: Duration::from_millis(5),
        action_delays: [("pick".to_string(), LONG)].into(),
        abort_too_late,
        ..SimConfig::default()
    };
    let (address, stats, sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start_in(
        dialect.clone(),
        address,
        Duration::from_secs(10),
        Some("b2"),
    );
    h.wait_status(ControllerStatus::Ready).await;
    (h, stats, sim)
}

/// The step's end as the dialect's controller reports an abort.
fn aborted(dialect: &Dialect, id: u64) -> ControllerEvent {
    if dialect.name == "ur-dashboard" {
        // `stop` answers `Stopped`; the program itself says nothing more.
        ControllerEvent::CommandFailed {
            id,
            failure: CommandFailure::Aborted,
        }
    } else {
        // The aborted command's own failed reply.
        ControllerEvent::Reply {
            id,
            result: "error".into(),
            message: Some("aborted".into()),
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_long_action_aborted_halfway_ends_at_once_and_is_not_executed() {
    for dialect in dialects() {
        let name = &dialect.name;
        let (mut h, stats, _sim) = ready(&dialect, false).await;
        h.send(1, "pick").await;
        // The action is under way on the controller.
        wait_received(&stats, 1).await;
        tokio::time::sleep(Duration::from_millis(50)).await;
        let asked = Instant::now();
        h.abort().await;
        assert_eq!(h.answer().await, aborted(&dialect, 1), "{name}");
        let took = asked.elapsed();
        assert!(took < PROMPT, "{name}: the abort took {took:?}");
        assert_eq!(stats.aborted(), 1, "{name}");
        assert_eq!(stats.executed(), 0, "{name}");
        assert_eq!(stats.by_action().get("pick"), None, "{name}");
        // The same connection serves the next command.
        h.send(2, "place").await;
        assert_eq!(h.answer().await, reply(2, "placing_done"), "{name}");
        assert_eq!(stats.executed(), 1, "{name}");
        assert_eq!(stats.aborted(), 1, "{name}");
        assert_eq!(stats.connections(), 1, "{name}: the connection was reset");
        h.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_done_that_beats_the_abort_is_reported_done() {
    for dialect in dialects() {
        let name = &dialect.name;
        // The controller finishes the action as the abort arrives: its done crosses
        // the abort on the wire (ur-dashboard: `stop` finds no program running, and the
        // next poll finds it stopped).
        let (mut h, stats, _sim) = ready(&dialect, true).await;
        h.send(1, "pick").await;
        wait_received(&stats, 1).await;
        tokio::time::sleep(Duration::from_millis(50)).await;
        let asked = Instant::now();
        h.abort().await;
        assert_eq!(h.answer().await, reply(1, "picking_done"), "{name}");
        assert!(asked.elapsed() < PROMPT, "{name}");
        assert_eq!(stats.aborted(), 0, "{name}");
        assert_eq!(stats.executed(), 1, "{name}");
        h.send(2, "place").await;
        assert_eq!(h.answer().await, reply(2, "placing_done"), "{name}");
        assert_eq!(stats.connections(), 1, "{name}: the connection was reset");
        h.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn an_abort_with_nothing_in_flight_is_harmless() {
    for dialect in dialects() {
        let name = &dialect.name;
        let (mut h, stats, _sim) = ready(&dialect, false).await;
        // Nothing has run: nothing is sent.
        h.abort().await;
        h.send(1, "place").await;
        assert_eq!(h.answer().await, reply(1, "placing_done"), "{name}");
        // The last command has ended: the controller is told to stop, and has nothing
        // to stop (ur-dashboard answers `Failed to execute: stop`, which is consumed).
        h.abort().await;
        h.send(2, "place").await;
        assert_eq!(h.answer().await, reply(2, "placing_done"), "{name}");
        h.abort().await;
        h.abort().await;
        h.send(3, "move").await;
        assert_eq!(h.answer().await, reply(3, "arrived"), "{name}");
        assert_eq!(stats.aborted(), 0, "{name}");
        assert_eq!(stats.executed(), 3, "{name}");
        assert_eq!(stats.connections(), 1, "{name}: the connection was reset");
        h.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_dialect_without_an_abort_lets_the_step_run_to_its_end() {
    let text = SHIPPED[0].1.replace("abort = { send = \"abort\" }", "");
    let dialect = Arc::new(Dialect::from_toml(&text, "no-abort.toml").unwrap());
    assert!(!dialect.can_abort());
    let config = SimConfig {
        dialect: Some(dialect.clone()),
        delay: Duration::from_millis(300),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start_in(dialect, address, Duration::from_secs(5), None);
    h.wait_ready().await;
    let sent = Instant::now();
    h.send(1, "pick").await;
    wait_received(&stats, 1).await;
    h.abort().await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    assert!(sent.elapsed() >= Duration::from_millis(290));
    assert_eq!((stats.executed(), stats.aborted()), (1, 0));
    h.stop().await;
}

/// Reads from `socket` until `buf` holds `needle`, or fails after [`WAIT`].
async fn read_until(socket: &mut tokio::net::TcpStream, buf: &mut Vec<u8>, needle: &str) {
    let deadline = tokio::time::Instant::now() + WAIT;
    while !String::from_utf8_lossy(buf).contains(needle) {
        let mut chunk = [0u8; 1024];
        let n = tokio::time::timeout_at(deadline, socket.read(&mut chunk))
            .await
            .unwrap_or_else(|_| panic!("no {needle:?} in {:?}", String::from_utf8_lossy(buf)))
            .unwrap();
        assert!(n > 0, "the client closed the connection");
        buf.extend_from_slice(&chunk[..n]);
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn the_abort_on_the_wire_names_the_command_in_flight_or_the_last_one_run() {
    // A hand-played holarchy-xml controller, to see the bytes.
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let mut h = Harness::start(address, Duration::from_secs(5));
    let (mut socket, _) = listener.accept().await.unwrap();
    socket
        .write_all(b"<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>")
        .await
        .unwrap();
    h.wait_ready().await;
    // Nothing has run: nothing is written.
    h.abort().await;
    let mut byte = [0u8; 1];
    let quiet = tokio::time::timeout(Duration::from_millis(200), socket.read(&mut byte)).await;
    assert!(quiet.is_err(), "the client wrote {byte:?}");
    // In flight: the abort goes at once, with the command's id.
    h.send(7, "pick").await;
    let mut wire = Vec::new();
    read_until(&mut socket, &mut wire, "</ROBOT_CMD>").await;
    h.abort().await;
    let mut wire = Vec::new();
    read_until(&mut socket, &mut wire, "</ROBOT_ABORT>").await;
    assert_eq!(
        String::from_utf8(wire).unwrap(),
        "<ROBOT_ABORT><ID>7</ID></ROBOT_ABORT>"
    );
    socket
        .write_all(b"<ROBOT_REPLY><ID>7</ID><RESULT>error</RESULT><MESSAGE>aborted</MESSAGE></ROBOT_REPLY>")
        .await
        .unwrap();
    assert_eq!(
        h.answer().await,
        ControllerEvent::Reply {
            id: 7,
            result: "error".into(),
            message: Some("aborted".into())
        }
    );
    // Nothing in flight: the controller is still told, with the last command's id.
    h.abort().await;
    let mut wire = Vec::new();
    read_until(&mut socket, &mut wire, "</ROBOT_ABORT>").await;
    assert_eq!(
        String::from_utf8(wire).unwrap(),
        "<ROBOT_ABORT><ID>7</ID></ROBOT_ABORT>"
    );
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn an_abort_answered_in_a_dialect_with_ids() {
    // simple-message with an abort that is a service request, answered by its own
    // reply carrying the sequence number (after the task's failure reply).
    let text = SHIPPED[3]
        .1
        .replace(
            "abort = { send = \"abort\" }",
            "abort = { send = \"abort\", expect = [\"abort_done\", \"abort_none\"] }",
        )
        .replace(
            "  { type = \"i32\", value = \"2102\" },\n  { type = \"i32\", value = \"1\" },",
            "  { type = \"i32\", value = \"2102\" },\n  { type = \"i32\", value = \"2\" },",
        )
        + r#"
[[reply]]
name = "abort_done"
outcome = "accepted"
fields = [
  { type = "i32", value = "2102" },
  { type = "i32", value = "3" },
  { type = "i32", value = "1" },
  { type = "u64", value = "{id}" },
]

[[reply]]
name = "abort_none"
outcome = "rejected"
fields = [
  { type = "i32", value = "2102" },
  { type = "i32", value = "3" },
  { type = "i32", value = "2" },
  { type = "u64", value = "{id}" },
]
"#;
    let dialect = Arc::new(Dialect::from_toml(&text, "answered.toml").unwrap());
    assert_eq!(dialect.abort.as_ref().unwrap().expect.len(), 2);
    let (mut h, stats, _sim) = ready(&dialect, false).await;
    h.send(1, "pick").await;
    wait_received(&stats, 1).await;
    h.abort().await;
    assert_eq!(h.answer().await, aborted(&dialect, 1));
    // Its own reply is consumed; nothing in flight: answered "nothing to stop".
    h.abort().await;
    h.send(2, "place").await;
    assert_eq!(h.answer().await, reply(2, "placing_done"));
    assert_eq!((stats.aborted(), stats.executed()), (1, 1));
    assert_eq!(stats.connections(), 1);
    h.stop().await;
}

/// A hand-played ur-dashboard controller: answers `safetystatus` itself and hands every
/// other line to the test.
struct Dashboard {
    lines: tokio::io::Lines<tokio::io::BufReader<tokio::net::tcp::OwnedReadHalf>>,
    write: tokio::net::tcp::OwnedWriteHalf,
}

impl Dashboard {
    async fn accept(listener: &tokio::net::TcpListener) -> Dashboard {
        use tokio::io::AsyncBufReadExt;
        let (socket, _) = listener.accept().await.unwrap();
        let (read, mut write) = socket.into_split();
        write
            .write_all(b"Connected: Universal Robots Dashboard Server\n")
            .await
            .unwrap();
        let mut ur = Dashboard {
            lines: tokio::io::BufReader::new(read).lines(),
            write,
        };
        // The first status poll: the client is ready once it is answered.
        let first = ur.lines.next_line().await.unwrap();
        assert_eq!(first.as_deref(), Some("safetystatus"));
        ur.say("Safetystatus: NORMAL").await;
        ur
    }

    /// The next line that is not a status poll.
    async fn next(&mut self) -> String {
        loop {
            let line = tokio::time::timeout(WAIT, self.lines.next_line())
                .await
                .expect("a line in time")
                .unwrap()
                .expect("the client closed the connection");
            if line == "safetystatus" {
                self.say("Safetystatus: NORMAL").await;
                continue;
            }
            return line;
        }
    }

    async fn say(&mut self, line: &str) {
        self.write
            .write_all(format!("{line}\n").as_bytes())
            .await
            .unwrap();
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn an_abort_on_a_one_in_flight_wire_is_answered_by_its_own_reply() {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let dialect = Dialect::shipped("ur-dashboard").unwrap();
    let mut h = Harness::start_in(dialect, address, Duration::from_secs(5), None);
    let mut ur = Dashboard::accept(&listener).await;
    h.wait_ready().await;

    // Aborted while `load` awaits its answer: `stop` goes at once; `play` never does.
    h.send(1, "pick").await;
    assert_eq!(ur.next().await, "load pick.urp");
    h.abort().await;
    assert_eq!(ur.next().await, "stop");
    ur.say("Loading program: pick.urp").await;
    ur.say("Failed to execute: stop").await;
    assert_eq!(
        h.answer().await,
        ControllerEvent::CommandFailed {
            id: 1,
            failure: CommandFailure::Aborted
        }
    );

    // Aborted while polled: the poll's answer, then `Stopped`, which is the abort's.
    h.send(2, "place").await;
    assert_eq!(ur.next().await, "load place.urp");
    ur.say("Loading program: place.urp").await;
    assert_eq!(ur.next().await, "play");
    ur.say("Starting program").await;
    assert_eq!(ur.next().await, "programState");
    h.abort().await;
    assert_eq!(ur.next().await, "stop");
    ur.say("PLAYING place.urp").await;
    ur.say("Stopped").await;
    assert_eq!(
        h.answer().await,
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Aborted
        }
    );

    // The program had just ended: `stop` finds nothing, and the step is done.
    h.send(3, "move").await;
    assert_eq!(ur.next().await, "load move.urp");
    ur.say("Loading program: move.urp").await;
    assert_eq!(ur.next().await, "play");
    ur.say("Starting program").await;
    assert_eq!(ur.next().await, "programState");
    h.abort().await;
    assert_eq!(ur.next().await, "stop");
    ur.say("STOPPED move.urp").await;
    ur.say("Failed to execute: stop").await;
    assert_eq!(h.answer().await, reply(3, "arrived"));

    // The connection serves on; nothing was taken for a protocol error.
    h.send(4, "pick").await;
    assert_eq!(ur.next().await, "load pick.urp");
    h.stop().await;
}

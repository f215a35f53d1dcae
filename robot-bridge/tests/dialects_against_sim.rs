//! Every shipped dialect, the controller client against robot-sim speaking the same
//! file, over real TCP sockets on loopback: the work, and each of the simulator's hostile
//! modes (replies in 1-3 byte pieces and merged, garbage, an oversized message, silence,
//! a reset mid-step, an error, a fault), each ending the step with a clear reason while
//! the client goes on serving.

use std::sync::Arc;
use std::time::Duration;

mod common;

use common::{reply, start_sim, wait_received, Harness, WAIT};
use robot_bridge::client::{CommandFailure, ControllerEvent, ControllerStatus};
use robot_bridge::dialect::{Dialect, SHIPPED};
use robot_bridge::sim::{SimConfig, SimStats, Simulator};
use tokio_util::sync::CancellationToken;

fn dialects() -> Vec<Arc<Dialect>> {
    SHIPPED
        .iter()
        .map(|(name, _)| Dialect::shipped(name).unwrap())
        .collect()
}

/// A client and a simulator of `dialect` with `faults`, the client ready.
async fn ready(
    dialect: &Arc<Dialect>,
    faults: SimConfig,
    command_timeout: Duration,
) -> (Harness, Arc<SimStats>, CancellationToken) {
    let config = SimConfig {
        dialect: Some(dialect.clone()),
        delay: Duration::from_millis(5),
        ..faults
    };
    let (address, stats, sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start_in(dialect.clone(), address, command_timeout, Some("b2"));
    h.wait_status(ControllerStatus::Ready).await;
    (h, stats, sim)
}

#[tokio::test(flavor = "multi_thread")]
async fn every_dialect_does_the_work() {
    for dialect in dialects() {
        for (fragment, merge) in [(false, false), (true, false), (false, true), (true, true)] {
            let faults = SimConfig {
                fragment,
                merge,
                inspect_fail_every: Some(2),
                ..SimConfig::default()
            };
            let (mut h, stats, _sim) = ready(&dialect, faults, Duration::from_secs(5)).await;
            let what = format!("{} fragment={fragment} merge={merge}", dialect.name);
            h.send(1, "pick").await;
            assert_eq!(h.answer().await, reply(1, "picking_done"), "{what}");
            h.send(2, "place").await;
            assert_eq!(h.answer().await, reply(2, "placing_done"), "{what}");
            h.send(3, "inspect").await;
            assert_eq!(h.answer().await, reply(3, "inspect_pass"), "{what}");
            h.send(4, "inspect").await;
            // The dashboard server says only that the program stopped: the result is the
            // action's own, whatever the inspection found.
            let second = if dialect.name == "ur-dashboard" {
                "inspect_pass"
            } else {
                "inspect_fail"
            };
            assert_eq!(h.answer().await, reply(4, second), "{what}");
            h.send(5, "move").await;
            assert_eq!(h.answer().await, reply(5, "arrived"), "{what}");
            assert_eq!(stats.executed(), 5, "{what}");
            assert_eq!(stats.connections(), 1, "{what}");
            assert_eq!(stats.by_action()["inspect"], 2, "{what}");
            h.stop().await;
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn an_action_the_dialect_cannot_write_fails_without_a_word_to_the_controller() {
    for dialect in dialects() {
        if dialect.name == "holarchy-xml" {
            continue; // any action name can be written
        }
        let (mut h, stats, _sim) =
            ready(&dialect, SimConfig::default(), Duration::from_secs(5)).await;
        h.send(1, "weld").await;
        match h.answer().await {
            ControllerEvent::CommandFailed {
                id: 1,
                failure: CommandFailure::Unwritable(why),
            } => assert!(why.contains("weld"), "{}: {why}", dialect.name),
            other => panic!("{}: {other:?}", dialect.name),
        }
        assert_eq!(stats.received(), 0, "{}", dialect.name);
        h.send(2, "pick").await;
        assert_eq!(
            h.answer().await,
            reply(2, "picking_done"),
            "{}",
            dialect.name
        );
        h.stop().await;
    }
}

/// The second command meets `faults`; `check` says what its failure must be; the third
/// command is served again (on a new connection where the fault reset the old one).
async fn second_command_meets(
    faults: impl Fn() -> SimConfig,
    command_timeout: Duration,
    check: impl Fn(&str, ControllerEvent),
) {
    for dialect in dialects() {
        let (mut h, stats, _sim) = ready(&dialect, faults(), command_timeout).await;
        h.send(1, "pick").await;
        assert_eq!(
            h.answer().await,
            reply(1, "picking_done"),
            "{}",
            dialect.name
        );
        h.send(2, "place").await;
        check(&dialect.name, h.answer().await);
        h.serve_again(3, &dialect.name).await;
        assert_eq!(
            stats.by_action().get("place"),
            None,
            "{}: place ran",
            dialect.name
        );
        h.stop().await;
    }
}

fn protocol_error(name: &str, event: ControllerEvent, contains: &str) {
    match event {
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Protocol(why),
        } => assert!(why.contains(contains), "{name}: {why}"),
        other => panic!("{name}: {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn garbage_ends_the_step_as_a_protocol_error() {
    second_command_meets(
        || SimConfig {
            garbage_after: Some(1),
            ..SimConfig::default()
        },
        Duration::from_secs(5),
        |name, event| protocol_error(name, event, ""),
    )
    .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn an_oversized_message_ends_the_step_before_it_ends() {
    second_command_meets(
        || SimConfig {
            oversize_after: Some(1),
            ..SimConfig::default()
        },
        Duration::from_secs(5),
        |name, event| protocol_error(name, event, "exceeds"),
    )
    .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_silent_controller_times_the_step_out() {
    for dialect in dialects() {
        let faults = SimConfig {
            hang_after: Some(1),
            ..SimConfig::default()
        };
        let (mut h, _stats, _sim) = ready(&dialect, faults, Duration::from_millis(400)).await;
        h.send(1, "pick").await;
        assert_eq!(
            h.answer().await,
            reply(1, "picking_done"),
            "{}",
            dialect.name
        );
        h.send(2, "place").await;
        assert_eq!(
            h.answer().await,
            ControllerEvent::CommandFailed {
                id: 2,
                failure: CommandFailure::Timeout(Duration::from_millis(400))
            },
            "{}",
            dialect.name
        );
        // The connection is reset and made again.
        h.wait_status(ControllerStatus::Disconnected).await;
        h.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_reset_mid_step_is_a_disconnection() {
    second_command_meets(
        || SimConfig {
            reset_after: Some(1),
            delay: Duration::from_millis(40),
            ..SimConfig::default()
        },
        Duration::from_secs(5),
        |name, event| {
            assert_eq!(
                event,
                ControllerEvent::CommandFailed {
                    id: 2,
                    failure: CommandFailure::Disconnected
                },
                "{name}"
            )
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_controller_error_fails_the_step_with_its_message() {
    second_command_meets(
        || SimConfig {
            error_every: Some(2),
            ..SimConfig::default()
        },
        Duration::from_secs(5),
        |name, event| match event {
            ControllerEvent::Reply {
                id: 2,
                result,
                message,
            } => {
                assert_eq!(result, "error", "{name}");
                assert!(message.is_some(), "{name}: an error without a message");
            }
            other => panic!("{name}: {other:?}"),
        },
    )
    .await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_fault_is_reported_and_passes() {
    for dialect in dialects() {
        let faults = SimConfig {
            fault_after: Some(1),
            // Longer than a polled state's interval (ur-dashboard: 500 ms).
            fault_for: Duration::from_millis(1200),
            ..SimConfig::default()
        };
        let (mut h, stats, _sim) = ready(&dialect, faults, Duration::from_secs(5)).await;
        h.send(1, "pick").await;
        assert_eq!(
            h.answer().await,
            reply(1, "picking_done"),
            "{}",
            dialect.name
        );
        h.send(2, "place").await;
        h.wait_status(ControllerStatus::Fault).await;
        h.wait_status(ControllerStatus::Ready).await;
        h.send(3, "pick").await;
        // A one-in-flight dialect's command was answered with a failure too (before or
        // after the fault): only the pick's answer counts here.
        loop {
            match h.answer().await {
                ControllerEvent::Reply { id: 2, .. } => continue,
                other => {
                    assert_eq!(other, reply(3, "picking_done"), "{}", dialect.name);
                    break;
                }
            }
        }
        assert_eq!(stats.by_action().get("place"), None, "{}", dialect.name);
        h.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_controller_that_connects_to_the_holon() {
    // holarchy-xml, but the controller dials the holon.
    let text = SHIPPED[0].1.replace(
        "role = \"controller_listens\"",
        "role = \"controller_connects\"",
    );
    let dialect = Arc::new(Dialect::from_toml(&text, "dialing.toml").unwrap());
    let address = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .to_string();
    let mut h = Harness::start_in(
        dialect.clone(),
        address.clone(),
        Duration::from_secs(5),
        Some("b2"),
    );
    let sim = Simulator::dialing(
        &address,
        SimConfig {
            dialect: Some(dialect.clone()),
            ..SimConfig::default()
        },
    );
    let stats = sim.stats();
    let shutdown = CancellationToken::new();
    tokio::spawn(sim.run(shutdown.clone()));
    h.wait_status(ControllerStatus::Ready).await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    // A second controller is refused: the first one still serves.
    let mut intruder = tokio::net::TcpStream::connect(&address).await.unwrap();
    let mut buf = [0u8; 16];
    let read = tokio::time::timeout(WAIT, tokio::io::AsyncReadExt::read(&mut intruder, &mut buf))
        .await
        .expect("the second connection is closed at once");
    assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");
    h.send(2, "place").await;
    assert_eq!(h.answer().await, reply(2, "placing_done"));
    assert_eq!(stats.connections(), 1);
    // The controller goes and comes back: the holon takes its new connection.
    shutdown.cancel();
    h.wait_status(ControllerStatus::Disconnected).await;
    let sim = Simulator::dialing(
        &address,
        SimConfig {
            dialect: Some(dialect),
            ..SimConfig::default()
        },
    );
    let again = CancellationToken::new();
    tokio::spawn(sim.run(again.clone()));
    h.wait_status(ControllerStatus::Ready).await;
    h.send(3, "pick").await;
    assert_eq!(h.answer().await, reply(3, "picking_done"));
    again.cancel();
    h.stop().await;
}

/// Runs three commands through `dialect` (a variant of a shipped one) against robot-sim.
async fn three_commands(dialect: Dialect) {
    let dialect = Arc::new(dialect);
    let (mut h, stats, _sim) = ready(&dialect, SimConfig::default(), Duration::from_secs(2)).await;
    for id in 1..=3 {
        h.send(id, "pick").await;
        assert_eq!(
            h.answer().await,
            reply(id, "picking_done"),
            "{}",
            dialect.name
        );
        tokio::time::sleep(Duration::from_millis(60)).await;
    }
    assert_eq!(
        stats.connections(),
        1,
        "{}: the connection was reset",
        dialect.name
    );
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_keepalive_answered_by_the_controllers_state_frees_the_wire() {
    // ur-dashboard with a keep-alive every 20 ms, answered by a status line.
    let text = SHIPPED[2].1.replace(
        "banner = \"Connected: Universal Robots Dashboard Server\"",
        "banner = \"Connected: Universal Robots Dashboard Server\"\nkeepalive = { send = \"safety_status\", every_ms = 20, expect = [\"safety\"] }",
    );
    assert!(text.contains("keepalive"));
    three_commands(Dialect::from_toml(&text, "keepalive.toml").unwrap()).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_status_poll_without_an_id_in_a_dialect_with_ids() {
    // holarchy-xml with its state polled by a message that carries no id.
    let text = SHIPPED[0]
        .1
        .replace(
            "source = \"pushed\"",
            "source = \"polled\"\npoll = \"status_request\"\nevery_ms = 20",
        )
        .replace(
            "[[command]]\nname = \"command\"",
            "[[command]]\nname = \"status_request\"\nxml = '<ROBOT_STATUS_REQ/>'\n\n[[command]]\nname = \"command\"",
        );
    assert!(text.contains("ROBOT_STATUS_REQ"));
    three_commands(Dialect::from_toml(&text, "polled.toml").unwrap()).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn nothing_goes_to_a_stopped_controller() {
    for dialect in dialects() {
        let name = dialect.name.clone();
        let faults = SimConfig {
            fault_after: Some(0),
            fault_state: Some(schemas::ControllerState::Estop),
            fault_for: Duration::from_millis(1500),
            ..SimConfig::default()
        };
        let (mut h, stats, _sim) = ready(&dialect, faults, Duration::from_secs(5)).await;
        // The first command e-stops the robot. The next goes as soon as the client has
        // heard anything of it: the first command's failure (a polled dialect, whose
        // state the client has not read yet) or the e-stop itself (pushed).
        h.send(1, "pick").await;
        loop {
            match h.next().await {
                ControllerEvent::Status(ControllerStatus::Estop, _) => break,
                ControllerEvent::Reply { id: 1, .. }
                | ControllerEvent::CommandFailed { id: 1, .. } => break,
                _ => {}
            }
        }
        h.send(2, "place").await;
        loop {
            match h.next().await {
                ControllerEvent::CommandFailed { id: 2, failure } => {
                    assert_eq!(
                        failure,
                        CommandFailure::Stopped(ControllerStatus::Estop),
                        "{name}"
                    );
                    break;
                }
                ControllerEvent::Reply { id: 2, .. } => panic!("{name}: command 2 was answered"),
                _ => {}
            }
        }
        // The controller got nothing while stopped: no command of the sequence refused.
        assert_eq!(stats.refused_while_stopped(), 0, "{name}");
        assert_eq!(stats.received(), 1, "{name}");
        // Ready again, it is served.
        h.wait_status(ControllerStatus::Ready).await;
        h.send(3, "pick").await;
        loop {
            match h.answer().await {
                ControllerEvent::Reply { id: 1, .. }
                | ControllerEvent::CommandFailed { id: 1, .. } => {}
                other => {
                    assert_eq!(other, reply(3, "picking_done"), "{name}");
                    break;
                }
            }
        }
        assert_eq!(stats.refused_while_stopped(), 0, "{name}");
        h.stop().await;
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn robot_sim_refuses_a_command_while_stopped() {
    // A client that wrote to a stopped controller would have its command refused and
    // counted: the count a test of the holon checks can fail.
    for dialect in dialects() {
        let name = dialect.name.clone();
        let config = SimConfig {
            dialect: Some(dialect.clone()),
            fault_after: Some(0),
            fault_state: Some(schemas::ControllerState::Fault),
            fault_for: Duration::from_secs(30),
            ..SimConfig::default()
        };
        let (address, stats, sim) = start_sim("127.0.0.1:0", config).await;
        let mut link = RawLink::connect(&address).await;
        // The command that faults the robot, then one while it is stopped.
        link.send_step(&dialect, 1, "pick").await;
        link.send_step(&dialect, 2, "place").await;
        let deadline = tokio::time::Instant::now() + WAIT;
        while stats.refused_while_stopped() < 1 {
            assert!(
                tokio::time::Instant::now() < deadline,
                "{name}: nothing refused"
            );
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(stats.executed(), 0, "{name}");
        sim.cancel();
    }
}

/// A bare TCP link that writes a dialect's messages, answers unread: what a careless
/// client would do.
struct RawLink {
    stream: tokio::net::TcpStream,
}

impl RawLink {
    async fn connect(address: &str) -> RawLink {
        RawLink {
            stream: tokio::net::TcpStream::connect(address).await.unwrap(),
        }
    }

    /// Writes every `send` element of the sequence for command `id`.
    async fn send_step(&mut self, dialect: &Dialect, id: u64, action: &str) {
        use bytes::BytesMut;
        use tokio::io::AsyncWriteExt;
        use tokio_util::codec::Encoder;
        let command = schemas::RobotCommand {
            id,
            action: action.into(),
            pos: None,
            program: None,
            info: Default::default(),
        };
        let values = robot_bridge::dialect::command_values(&command, &dialect.format);
        for element in &dialect.sequence {
            if element.sending != robot_bridge::dialect::Sending::Send {
                continue;
            }
            let body = dialect.write_command(element.command, &values).unwrap();
            let mut framed = BytesMut::new();
            dialect
                .frame_codec()
                .encode(body.as_slice(), &mut framed)
                .unwrap();
            self.stream.write_all(&framed).await.unwrap();
        }
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_fault_outlasts_a_reconnect() {
    // A first connection faults the controller and goes; the client connecting next
    // finds it still stopped (holarchy-xml pushes its state on connect).
    let dialect = Dialect::holarchy_xml();
    let config = SimConfig {
        dialect: Some(dialect.clone()),
        fault_after: Some(0),
        fault_for: Duration::from_secs(2),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut first = RawLink::connect(&address).await;
    first.send_step(&dialect, 1, "pick").await;
    wait_received(&stats, 1).await;
    drop(first);
    let mut h = Harness::start_in(dialect, address, Duration::from_secs(5), None);
    loop {
        match h.next().await {
            ControllerEvent::Status(ControllerStatus::Fault, _) => break,
            ControllerEvent::Status(ControllerStatus::Disconnected, _) => {}
            other => panic!("{other:?} before the fault"),
        }
    }
    h.wait_status(ControllerStatus::Ready).await;
    h.stop().await;
}

//! The controller client against the simulator, over real TCP sockets on loopback.

use std::time::Duration;

mod common;

use common::{reply, start_sim, Harness};
use robot_bridge::client::{CommandFailure, ControllerEvent, ControllerStatus, LinkEnd, Reconnect};
use robot_bridge::sim::SimConfig;

#[tokio::test(flavor = "multi_thread")]
async fn executes_commands_and_tracks_status() {
    let (address, stats, _sim) = start_sim("127.0.0.1:0", SimConfig::default()).await;
    let mut h = Harness::start(address, Duration::from_secs(5));
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    h.wait_ready().await;
    h.send(1, "pick").await;
    assert_eq!(h.next().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    assert_eq!(h.next().await, reply(2, "placing_done"));
    h.send(3, "weld").await;
    match h.next().await {
        ControllerEvent::Reply {
            id: 3,
            result,
            message,
        } => {
            assert_eq!(result, "error");
            assert!(message.unwrap().contains("weld"));
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(stats.executed(), 2);
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn reconnects_when_the_controller_comes_back() {
    // Find a free port, then leave it closed: the controller is away.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let address = format!("127.0.0.1:{port}");
    let mut h = Harness::start(address.clone(), Duration::from_secs(5));
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    h.send(1, "pick").await;
    assert_eq!(
        h.next().await,
        ControllerEvent::CommandFailed {
            id: 1,
            failure: CommandFailure::NotConnected
        }
    );
    let (_, _, sim) = start_sim(&address, SimConfig::default()).await;
    h.wait_ready().await;
    h.send(2, "pick").await;
    assert_eq!(h.next().await, reply(2, "picking_done"));
    // The controller goes away mid-command: the command fails, the client reconnects.
    sim.cancel();
    tokio::time::sleep(Duration::from_millis(50)).await;
    let (_, _, _sim2) = start_sim(
        &address,
        SimConfig {
            delay: Duration::from_millis(10),
            ..SimConfig::default()
        },
    )
    .await;
    // The first server's connection is closed, so the client sees a disconnect...
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    // ...and comes back to the second one.
    h.wait_ready().await;
    h.send(3, "place").await;
    assert_eq!(h.next().await, reply(3, "placing_done"));
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_dropped_connection_fails_the_command_in_progress() {
    let config = SimConfig {
        close_after: Some(1),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start(address, Duration::from_secs(5));
    h.wait_ready().await;
    h.send(1, "pick").await;
    assert_eq!(h.next().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    assert_eq!(
        h.next().await,
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Disconnected
        }
    );
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    h.wait_ready().await;
    h.send(3, "place").await;
    assert_eq!(h.next().await, reply(3, "placing_done"));
    assert_eq!(stats.executed(), 2);
    assert_eq!(stats.connections(), 2);
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_silent_controller_times_out_and_is_reset() {
    let config = SimConfig {
        hang_after: Some(1),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start(address, Duration::from_millis(300));
    h.wait_ready().await;
    h.send(1, "pick").await;
    assert_eq!(h.next().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    assert_eq!(
        h.next().await,
        ControllerEvent::CommandFailed {
            id: 2,
            failure: CommandFailure::Timeout(Duration::from_millis(300))
        }
    );
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    h.wait_ready().await;
    assert_eq!(stats.executed(), 1);
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn garbage_from_the_controller_resets_the_connection() {
    let config = SimConfig {
        garbage_after: Some(0),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start(address, Duration::from_secs(5));
    h.wait_ready().await;
    h.send(1, "pick").await;
    match h.next().await {
        ControllerEvent::CommandFailed {
            id: 1,
            failure: CommandFailure::Protocol(why),
        } => {
            assert!(why.contains("malformed"), "{why}")
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    h.wait_ready().await;
    h.send(2, "pick").await;
    assert_eq!(h.next().await, reply(2, "picking_done"));
    assert_eq!(stats.executed(), 1);
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn error_results_are_reported_with_their_message() {
    let config = SimConfig {
        error_every: Some(2),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start(address, Duration::from_secs(5));
    h.wait_ready().await;
    h.send(1, "pick").await;
    assert_eq!(h.next().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    match h.next().await {
        ControllerEvent::Reply {
            id: 2,
            result,
            message: Some(_),
        } => assert_eq!(result, "error"),
        other => panic!("{other:?}"),
    }
    assert_eq!(stats.executed(), 1);
    h.stop().await;
}

/// A controller that says it is ready, takes one command and then ends the
/// connection the way `end` does: how a controller killed mid-message looks.
async fn controller_that_breaks(end: fn(tokio::net::TcpStream) -> std::io::Result<()>) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    tokio::spawn(async move {
        let (mut stream, _) = listener.accept().await.unwrap();
        stream
            .write_all(b"<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>")
            .await
            .unwrap();
        let mut command = [0u8; 64];
        let read = stream.read(&mut command).await.unwrap();
        assert!(read > 0, "the client sent its command");
        end(stream).unwrap();
        // Keep the port bound (and refusing nothing) until the test ends.
        std::future::pending::<()>().await;
    });
    address
}

async fn command_fails_as_disconnected(address: String) {
    let mut h = Harness::start(address, Duration::from_secs(5));
    h.wait_ready().await;
    h.send(1, "pick").await;
    assert_eq!(
        h.next().await,
        ControllerEvent::CommandFailed {
            id: 1,
            failure: CommandFailure::Disconnected
        },
        "a broken connection is a lost controller, not a protocol error"
    );
    assert_eq!(
        h.next().await,
        ControllerEvent::Status(ControllerStatus::Disconnected, None)
    );
    h.stop().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_connection_reset_mid_command_is_a_disconnection() {
    let address = controller_that_breaks(|stream| {
        // Linger 0: closing sends RST, as a killed process with unread input does.
        stream.set_zero_linger()?;
        drop(stream);
        Ok(())
    })
    .await;
    command_fails_as_disconnected(address).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn a_reply_cut_short_by_the_close_is_a_disconnection() {
    let address = controller_that_breaks(|stream| {
        let stream = stream.into_std()?;
        stream.set_nonblocking(false)?;
        use std::io::Write;
        (&stream).write_all(b"<ROBOT_REPLY><ID>1</ID><RES")?;
        drop(stream);
        Ok(())
    })
    .await;
    command_fails_as_disconnected(address).await;
}

#[tokio::test(flavor = "multi_thread")]
async fn actions_take_their_own_time_and_a_new_program_costs_a_changeover() {
    let config = SimConfig {
        action_delays: [("pick".to_string(), Duration::from_millis(150))].into(),
        changeover: Duration::from_millis(200),
        ..SimConfig::default()
    };
    let (address, stats, _sim) = start_sim("127.0.0.1:0", config).await;
    let mut h = Harness::start(address, Duration::from_secs(5));
    h.wait_ready().await;
    // (command, action, program, at least this long, changeovers after it)
    let script = [
        (1, "pick", Some("a"), 150, 0),
        (2, "place", Some("a"), 0, 0),
        (3, "place", Some("b"), 200, 1),
        (4, "place", None, 0, 1),
        (5, "pick", Some("b"), 150, 1),
        (6, "pick", Some("a"), 350, 2),
    ];
    for (id, action, program, at_least_ms, changeovers) in script {
        let sent = std::time::Instant::now();
        h.send_for(id, action, program).await;
        let result = if action == "pick" {
            "picking_done"
        } else {
            "placing_done"
        };
        assert_eq!(h.next().await, reply(id, result));
        assert!(
            sent.elapsed() >= Duration::from_millis(at_least_ms),
            "command {id} took {:?}, less than its {at_least_ms} ms",
            sent.elapsed()
        );
        assert_eq!(stats.changeovers(), changeovers, "after command {id}");
    }
    assert!(
        stats.to_json().contains("\"changeovers\":2"),
        "{}",
        stats.to_json()
    );
    h.stop().await;
}

/// The client's owner in a test: a mailbox and an event channel.
struct Mailboxes {
    commands: tokio::sync::mpsc::Receiver<robot_bridge::client::ControllerRequest>,
    events: tokio::sync::mpsc::Sender<ControllerEvent>,
}

impl robot_bridge::client::Owner for Mailboxes {
    async fn request(&mut self) -> Option<robot_bridge::client::ControllerRequest> {
        self.commands.recv().await
    }

    async fn report(&mut self, event: ControllerEvent) -> bool {
        self.events.send(event).await.is_ok()
    }
}

/// A reconnect policy that records how each attempt ended and pauses 50 ms.
struct Recorded(std::sync::Arc<std::sync::Mutex<Vec<LinkEnd>>>);

impl Reconnect for Recorded {
    fn pause(&mut self, last: LinkEnd) -> Duration {
        self.0.lock().unwrap().push(last);
        Duration::from_millis(50)
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn the_reconnect_policy_is_told_how_each_attempt_ended() {
    let config = SimConfig {
        close_after: Some(1),
        ..SimConfig::default()
    };
    let (address, _stats, sim) = start_sim("127.0.0.1:0", config).await;
    let (commands, command_rx) = tokio::sync::mpsc::channel(16);
    let (event_tx, events) = tokio::sync::mpsc::channel(64);
    let ends = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let shutdown = tokio_util::sync::CancellationToken::new();
    let client = tokio::spawn({
        let (shutdown, ends) = (shutdown.clone(), ends.clone());
        let config = robot_bridge::client::ClientConfig::new(address);
        async move {
            let mut owner = Mailboxes {
                commands: command_rx,
                events: event_tx,
            };
            let mut recorded = Recorded(ends);
            robot_bridge::client::drive(config, &mut owner, &mut recorded, None, shutdown).await
        }
    });
    let mut h = Harness {
        commands,
        events,
        shutdown: shutdown.clone(),
        client,
        dialect: "holarchy-xml".into(),
        program: None,
    };
    // The first connection answers a step, then closes at the second: it served.
    h.wait_ready().await;
    h.send(1, "pick").await;
    assert_eq!(h.answer().await, reply(1, "picking_done"));
    h.send(2, "place").await;
    assert!(matches!(
        h.answer().await,
        ControllerEvent::CommandFailed { id: 2, .. }
    ));
    // The second answers nothing and ends with the controller; then it is refused.
    h.wait_ready().await;
    sim.cancel();
    let deadline = tokio::time::Instant::now() + common::WAIT;
    while !ends.lock().unwrap().contains(&LinkEnd::NotConnected) {
        assert!(tokio::time::Instant::now() < deadline, "{:?}", ends.lock());
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // (A connect made while the stopped simulator's socket was still bound would be
    // one more connection that answered nothing, before the refusals.)
    let ends = ends.lock().unwrap().clone();
    assert!(
        matches!(ends[0], LinkEnd::Ended { answered: 1, .. }),
        "{ends:?}"
    );
    assert!(
        matches!(ends[1], LinkEnd::Ended { answered: 0, .. }),
        "{ends:?}"
    );
    h.stop().await;
}

//! What the client-against-simulator tests share: a controller client driven through its
//! mailboxes, and a simulator on a free port.

#![allow(dead_code)] // each test file uses its own part

pub mod plant;

use std::sync::Arc;
use std::time::Duration;

use robot_bridge::client::{
    self, ClientConfig, CommandFailure, ControllerEvent, ControllerRequest, ControllerStatus,
};
use robot_bridge::dialect::Dialect;
use robot_bridge::sim::{SimConfig, SimStats, Simulator};
use schemas::{Pose, RobotCommand};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

/// The longest wait for any one event.
pub const WAIT: Duration = Duration::from_secs(10);

/// A controller client task, its command mailbox and its events.
pub struct Harness {
    pub commands: mpsc::Sender<ControllerRequest>,
    pub events: mpsc::Receiver<ControllerEvent>,
    pub shutdown: CancellationToken,
    pub client: tokio::task::JoinHandle<()>,
    /// The dialect's name, in assertion messages.
    pub dialect: String,
    /// The program every [`Harness::send`] names.
    pub program: Option<String>,
}

impl Harness {
    /// A holarchy-xml client of `address`.
    pub fn start(address: String, command_timeout: Duration) -> Harness {
        Self::start_in(Dialect::holarchy_xml(), address, command_timeout, None)
    }

    /// A client of `address` in `dialect`, whose commands name `program`.
    pub fn start_in(
        dialect: Arc<Dialect>,
        address: String,
        command_timeout: Duration,
        program: Option<&str>,
    ) -> Harness {
        let (commands, mut command_rx) = mpsc::channel(16);
        let (event_tx, events) = mpsc::channel(64);
        let shutdown = CancellationToken::new();
        let name = dialect.name.clone();
        let config = ClientConfig {
            reconnect_interval: Duration::from_millis(100),
            command_timeout,
            connect_timeout: Duration::from_secs(1),
            dialect,
            ..ClientConfig::new(address)
        };
        let client = tokio::spawn({
            let shutdown = shutdown.clone();
            async move { client::run(config, &mut command_rx, event_tx, shutdown).await }
        });
        Harness {
            commands,
            events,
            shutdown,
            client,
            dialect: name,
            program: program.map(str::to_string),
        }
    }

    pub async fn next(&mut self) -> ControllerEvent {
        tokio::time::timeout(WAIT, self.events.recv())
            .await
            .unwrap_or_else(|_| panic!("{}: no event in time", self.dialect))
            .expect("client gone")
    }

    /// The next event that is not a status.
    pub async fn answer(&mut self) -> ControllerEvent {
        loop {
            match self.next().await {
                ControllerEvent::Status(..) => continue,
                other => return other,
            }
        }
    }

    pub async fn wait_status(&mut self, status: ControllerStatus) {
        loop {
            if matches!(self.next().await, ControllerEvent::Status(s, _) if s == status) {
                return;
            }
        }
    }

    pub async fn wait_ready(&mut self) {
        self.wait_status(ControllerStatus::Ready).await
    }

    /// A pick from `id` on, sent again while the client is (re)connecting, served.
    pub async fn serve_again(&mut self, mut id: u64, what: &str) {
        loop {
            self.send(id, "pick").await;
            match self.answer().await {
                ControllerEvent::CommandFailed {
                    failure: CommandFailure::NotConnected | CommandFailure::Disconnected,
                    ..
                } => {
                    self.wait_ready().await;
                    id += 1;
                }
                other => {
                    assert_eq!(other, reply(id, "picking_done"), "{what}");
                    return;
                }
            }
        }
    }

    /// A command of the harness's program.
    pub async fn send(&self, id: u64, action: &str) {
        let program = self.program.clone();
        self.send_for(id, action, program.as_deref()).await
    }

    /// A command of `program` (a product variant).
    pub async fn send_for(&self, id: u64, action: &str, program: Option<&str>) {
        let pos = Some(Pose {
            x: 1.0,
            y: 2.0,
            z: 3.0,
            ..Pose::default()
        });
        self.commands
            .send(
                RobotCommand {
                    id,
                    action: action.into(),
                    pos,
                    program: program.map(str::to_string),
                    info: Default::default(),
                }
                .into(),
            )
            .await
            .unwrap();
    }

    /// Asks the client to abort (PackML Abort).
    pub async fn abort(&self) {
        self.commands.send(ControllerRequest::Abort).await.unwrap();
    }

    pub async fn stop(self) {
        self.shutdown.cancel();
        tokio::time::timeout(WAIT, self.client)
            .await
            .unwrap()
            .unwrap();
    }
}

/// A simulator listening on `address` (port 0: a free one): its address, its counts and
/// what stops it.
pub async fn start_sim(
    address: &str,
    config: SimConfig,
) -> (String, Arc<SimStats>, CancellationToken) {
    let sim = Simulator::bind(address, config).await.unwrap();
    let address = sim.local_addr().unwrap().to_string();
    let stats = sim.stats();
    let shutdown = CancellationToken::new();
    tokio::spawn(sim.run(shutdown.clone()));
    (address, stats, shutdown)
}

/// The event of a command answered with `result`.
pub fn reply(id: u64, result: &str) -> ControllerEvent {
    ControllerEvent::Reply {
        id,
        result: result.into(),
        message: None,
    }
}

/// Waits until the simulator has received `n` commands (begun `n` actions).
pub async fn wait_received(stats: &SimStats, n: u64) {
    let deadline = tokio::time::Instant::now() + WAIT;
    while stats.received() < n {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the simulator never received {n} commands"
        );
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
}

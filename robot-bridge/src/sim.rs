//! `robot-sim`: a robot controller simulator that speaks the TCP/XML protocol.
//!
//! It is the TCP server, as a real controller is. On every connection it sends
//! `ROBOT_STATUS ready`, then answers each `ROBOT_CMD` when its action is done (to
//! within about 0.1 ms of the time it takes: `delay`, or the action's own time in
//! `action_delays`, plus `changeover` when the command's `PROGRAM` differs from the
//! last program the controller ran, as a robot's tooling or a fixture is changed
//! for another product variant): `pick` ->
//! `picking_done`, `place` -> `placing_done`, `inspect` -> `inspect_pass` (or
//! `inspect_fail`), `move` -> `arrived`; any other action -> `error`.
//!
//! Faults, for tests (command numbers count every command received, from 1):
//! - `error_every N`: every Nth command is answered `error` and not executed;
//! - `close_after N`: each connection is closed when its (N+1)th command arrives (that
//!   command is not executed);
//! - `hang_after N`: from the (N+1)th command of the process on, commands are read but
//!   never answered nor executed;
//! - `garbage_after N`: the (N+1)th command of the process gets malformed XML instead of
//!   a reply and is not executed; later commands are served normally;
//! - `fault_after N`: the (N+1)th command of the process is not answered nor executed:
//!   the controller reports `fault` (or `estop`) instead, and `ready` after `fault_for`.
//!
//! The simulator counts the commands it executed (answered with their success result);
//! [`SimStats`] can be written to a JSON file when each command arrives and after it is
//! answered, so tests can check that nothing ran twice. A thread of its own writes the
//! file, off the command's path (after the reply went out), with the latest counts (several commands in quick succession make one write): the count
//! file is the tests' window, and a controller command's round trip should cost what a
//! real controller's would (a write and a rename on the way cost the bridge about a
//! hundred microseconds per command).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use schemas::{ControllerState, RobotCommand, RobotMessage, RobotReply};
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpListener, TcpStream};
use tokio_util::codec::Framed;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::codec::RobotCodec;

/// How the simulator behaves.
#[derive(Debug, Clone, Default)]
pub struct SimConfig {
    /// How long each action takes, unless `action_delays` names it.
    pub delay: Duration,
    /// How long particular actions take (`pick` -> 300 ms): a robot that is fast at
    /// some work and slow at other.
    pub action_delays: BTreeMap<String, Duration>,
    /// What a change of program costs: added to the first command whose `PROGRAM`
    /// differs from the last program run (a command without one changes nothing).
    pub changeover: Duration,
    pub error_every: Option<u64>,
    pub close_after: Option<u64>,
    pub hang_after: Option<u64>,
    pub garbage_after: Option<u64>,
    /// Every Nth `inspect` is answered `inspect_fail`.
    pub inspect_fail_every: Option<u64>,
    /// When the (N+1)th command of the process arrives, report `fault_state` instead of
    /// answering it (it is not executed), then `ready` again after `fault_for`.
    pub fault_after: Option<u64>,
    pub fault_state: Option<ControllerState>,
    pub fault_for: Duration,
    /// Rewritten (atomically) with [`SimStats`] as JSON after every command, once its
    /// reply is sent.
    pub count_file: Option<PathBuf>,
}

/// What the simulator did.
#[derive(Debug, Default)]
pub struct SimStats {
    received: AtomicU64,
    executed: AtomicU64,
    inspections: AtomicU64,
    by_action: Mutex<BTreeMap<String, u64>>,
    connections: AtomicU64,
    /// The program of the last command run that named one.
    program: Mutex<Option<String>>,
    changeovers: AtomicU64,
}

impl SimStats {
    /// Commands executed (answered with their success result).
    pub fn executed(&self) -> u64 {
        self.executed.load(Ordering::SeqCst)
    }

    /// Commands received, executed or not.
    pub fn received(&self) -> u64 {
        self.received.load(Ordering::SeqCst)
    }

    /// Changes of program (each cost the config's `changeover`).
    pub fn changeovers(&self) -> u64 {
        self.changeovers.load(Ordering::SeqCst)
    }

    /// Whether running `program` changes the controller over, which it then is.
    fn change_to(&self, program: Option<&str>) -> bool {
        let Some(program) = program else {
            return false;
        };
        let mut last = self.program.lock().unwrap_or_else(|e| e.into_inner());
        let change = last.as_deref().is_some_and(|last| last != program);
        if last.as_deref() != Some(program) {
            *last = Some(program.to_string());
        }
        if change {
            self.changeovers.fetch_add(1, Ordering::SeqCst);
        }
        change
    }

    /// Connections accepted.
    pub fn connections(&self) -> u64 {
        self.connections.load(Ordering::SeqCst)
    }

    /// Executed commands per action.
    pub fn by_action(&self) -> BTreeMap<String, u64> {
        self.by_action
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// `{"executed": N, "received": N, "connections": N, "changeovers": N,
    /// "by_action": {"pick": N, ...}}`.
    pub fn to_json(&self) -> String {
        let by_action: Vec<String> = self
            .by_action()
            .iter()
            .map(|(k, v)| format!("\"{k}\":{v}"))
            .collect();
        format!(
            "{{\"executed\":{},\"received\":{},\"connections\":{},\"changeovers\":{},\"by_action\":{{{}}}}}",
            self.executed(),
            self.received(),
            self.connections(),
            self.changeovers(),
            by_action.join(",")
        )
    }
}

/// A bound simulator, ready to [`Simulator::run`].
pub struct Simulator {
    listener: TcpListener,
    config: Arc<SimConfig>,
    stats: Arc<SimStats>,
}

/// Asks the count file's writer thread to write the latest counts; never blocks (a
/// write already asked for and not yet started takes in this command's counts too).
#[derive(Clone)]
struct CountFile(Option<std::sync::mpsc::SyncSender<()>>);

impl CountFile {
    /// Starts the writer thread, when the config has a count file; join it after the
    /// last sender is dropped to have the last counts on disk.
    fn start(
        config: &Arc<SimConfig>,
        stats: &Arc<SimStats>,
    ) -> (CountFile, Option<std::thread::JoinHandle<()>>) {
        if config.count_file.is_none() {
            return (CountFile(None), None);
        }
        let (asks, asked) = std::sync::mpsc::sync_channel::<()>(1);
        let (config, stats) = (config.clone(), stats.clone());
        let writer = std::thread::spawn(move || {
            // Ends when every sender is gone, after the last write asked for.
            for () in asked {
                write_count_file(&config, &stats);
            }
        });
        let file = CountFile(Some(asks));
        file.update();
        (file, Some(writer))
    }

    fn update(&self) {
        let Some(asks) = &self.0 else { return };
        match asks.try_send(()) {
            // Full: a write is pending and will read the counts as they are then.
            Ok(()) | Err(std::sync::mpsc::TrySendError::Full(())) => {}
            Err(std::sync::mpsc::TrySendError::Disconnected(())) => {
                warn!("the count file's writer is gone: the file keeps older counts");
            }
        }
    }
}

impl Simulator {
    pub async fn bind(address: &str, config: SimConfig) -> std::io::Result<Simulator> {
        let listener = TcpListener::bind(address).await?;
        Ok(Simulator {
            listener,
            config: Arc::new(config),
            stats: Arc::default(),
        })
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    pub fn stats(&self) -> Arc<SimStats> {
        self.stats.clone()
    }

    /// Serves connections until `shutdown` is cancelled.
    pub async fn run(self, shutdown: CancellationToken) {
        let (count_file, writer) = CountFile::start(&self.config, &self.stats);
        let connections = tokio_util::task::TaskTracker::new();
        loop {
            tokio::select! {
                _ = shutdown.cancelled() => break,
                accepted = self.listener.accept() => match accepted {
                    Ok((stream, peer)) => {
                        let _ = stream.set_nodelay(true);
                        self.stats.connections.fetch_add(1, Ordering::SeqCst);
                        info!(%peer, "bridge connected");
                        let config = self.config.clone();
                        let stats = self.stats.clone();
                        let shutdown = shutdown.clone();
                        let count_file = count_file.clone();
                        connections.spawn(async move {
                            if let Err(e) = serve(stream, &config, &stats, &count_file, shutdown).await {
                                warn!(%peer, error = %e, "connection ended with an error");
                            } else {
                                info!(%peer, "bridge disconnected");
                            }
                        });
                    }
                    Err(e) => {
                        warn!(error = %e, "accept failed");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                    }
                }
            }
        }
        connections.close();
        connections.wait().await;
        drop(count_file);
        if let Some(writer) = writer {
            let joined = tokio::task::spawn_blocking(move || writer.join()).await;
            if !matches!(joined, Ok(Ok(()))) {
                warn!(
                    "the count file's writer ended abnormally: the file may miss the last counts"
                );
            }
        }
    }
}

fn success_result(action: &str, config: &SimConfig, stats: &SimStats) -> Option<&'static str> {
    match action {
        "pick" => Some("picking_done"),
        "place" => Some("placing_done"),
        "move" => Some("arrived"),
        "inspect" => {
            let n = stats.inspections.fetch_add(1, Ordering::SeqCst) + 1;
            match config.inspect_fail_every {
                Some(every) if every > 0 && n.is_multiple_of(every) => Some("inspect_fail"),
                _ => Some("inspect_pass"),
            }
        }
        _ => None,
    }
}

/// Waits until `done` (an action's end) to within about a tenth of a millisecond.
/// tokio's timer rounds a sleep up to its next millisecond tick (a 20 ms action took
/// 21.4 ms, which a benchmark of robots that take time would charge to the control),
/// so the last 2 ms are slept on a blocking thread.
async fn act_for(done: std::time::Instant) {
    if let Some(coarse) = done.checked_sub(Duration::from_millis(2)) {
        tokio::time::sleep_until(coarse.into()).await;
    }
    let rest = done.saturating_duration_since(std::time::Instant::now());
    if !rest.is_zero() {
        if let Err(e) = tokio::task::spawn_blocking(move || std::thread::sleep(rest)).await {
            warn!(error = %e, "the action's last moments were cut short");
        }
    }
}

/// Rewrites the count file, if any, in place (a write and a rename: readers see the
/// old counts or the new, never half). Blocking: on the writer thread only.
fn write_count_file(config: &SimConfig, stats: &SimStats) {
    let Some(path) = &config.count_file else {
        return;
    };
    let tmp = path.with_extension("tmp");
    let written = std::fs::write(&tmp, stats.to_json()).and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        warn!(path = %path.display(), error = %e, "cannot write the count file");
    }
}

async fn serve(
    stream: TcpStream,
    config: &SimConfig,
    stats: &SimStats,
    count_file: &CountFile,
    shutdown: CancellationToken,
) -> Result<(), crate::codec::CodecError> {
    let mut framed = Framed::new(stream, RobotCodec);
    framed
        .send(&RobotMessage::Status(ControllerState::Ready))
        .await?;
    let mut on_this_connection = 0u64;
    loop {
        let message = tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            message = framed.next() => message,
        };
        let command: RobotCommand = match message {
            None => return Ok(()),
            Some(Err(e)) => return Err(e),
            Some(Ok(RobotMessage::Command(command))) => command,
            Some(Ok(other)) => {
                warn!(?other, "ignored: not a ROBOT_CMD");
                continue;
            }
        };
        let received = std::time::Instant::now();
        let n = stats.received.fetch_add(1, Ordering::SeqCst) + 1;
        // The count file shows a command as received when it arrives (its writer runs
        // off this path), so a test can tell a command is on the controller.
        count_file.update();
        on_this_connection += 1;
        info!(id = command.id, action = %command.action, n, "command");
        if matches!(config.close_after, Some(limit) if on_this_connection > limit) {
            info!(id = command.id, "closing the connection (--close-after)");
            count_file.update();
            return Ok(());
        }
        if matches!(config.hang_after, Some(limit) if n > limit) {
            info!(id = command.id, "not answering (--hang-after)");
            count_file.update();
            continue;
        }
        if config.garbage_after.is_some_and(|limit| n == limit + 1) {
            info!(id = command.id, "answering garbage (--garbage-after)");
            let stream = framed.get_mut();
            stream
                .write_all(b"<ROBOT_REPLY><ID>oops</RESULT></ROBOT_REPLY>\n")
                .await?;
            count_file.update();
            continue;
        }
        if config.fault_after.is_some_and(|limit| n == limit + 1) {
            let state = config.fault_state.unwrap_or(ControllerState::Fault);
            info!(id = command.id, %state, "reporting a fault (--fault-after)");
            framed.send(&RobotMessage::Status(state)).await?;
            count_file.update();
            tokio::select! {
                _ = shutdown.cancelled() => return Ok(()),
                _ = tokio::time::sleep(config.fault_for) => {}
            }
            info!("ready again");
            framed
                .send(&RobotMessage::Status(ControllerState::Ready))
                .await?;
            continue;
        }
        let mut takes = config
            .action_delays
            .get(&command.action)
            .copied()
            .unwrap_or(config.delay);
        if stats.change_to(command.program.as_deref()) {
            info!(id = command.id, program = command.program.as_deref().unwrap_or(""), changeover = ?config.changeover, "changing over");
            takes += config.changeover;
        }
        if !takes.is_zero() {
            tokio::select! {
                _ = shutdown.cancelled() => return Ok(()),
                _ = act_for(received + takes) => {}
            }
        }
        let simulated_error =
            matches!(config.error_every, Some(every) if every > 0 && n.is_multiple_of(every));
        let reply = match success_result(&command.action, config, stats) {
            Some(result) if !simulated_error => {
                stats.executed.fetch_add(1, Ordering::SeqCst);
                *stats
                    .by_action
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .entry(command.action.clone())
                    .or_default() += 1;
                RobotReply {
                    id: command.id,
                    result: result.into(),
                    message: None,
                }
            }
            Some(_) => RobotReply {
                id: command.id,
                result: schemas::robot::RESULT_ERROR.into(),
                message: Some("simulated error (--error-every)".into()),
            },
            None => RobotReply {
                id: command.id,
                result: schemas::robot::RESULT_ERROR.into(),
                message: Some(format!("unknown action {:?}", command.action)),
            },
        };
        framed.send(&RobotMessage::Reply(reply)).await?;
        count_file.update();
    }
}

//! `robot-sim`: a robot controller simulator that speaks any controller dialect
//! ([`crate::dialect`]; holarchy's own TCP/XML protocol by default).
//!
//! It is the TCP server, as most controllers are (or, when the dialect's controller
//! connects, it dials the holon and dials again when the connection ends). On every
//! connection it sends the dialect's banner, if any, and its state (`ready`) when the
//! dialect pushes it; then it answers each message as the dialect's sequence says: the
//! message that begins an action ([`crate::dialect::Element::starts`]) is acted on for
//! the time the action takes (to within about 0.1 ms: `delay`, or the action's own time
//! in `action_delays`, plus `changeover` when the command's program differs from the last
//! program the controller ran, as a robot's tooling or a fixture is changed for another
//! product variant), and answered with the dialect's `done` reply: `pick` ->
//! `picking_done`, `place` -> `placing_done`, `inspect` -> `inspect_pass` (or
//! `inspect_fail`), `move` -> `arrived`; any other action -> the `failed` reply. Messages
//! before it are accepted; a poll is answered `running` until the action's time is up,
//! then `done`; a status poll is answered with the state.
//!
//! The dialect's abort stops the action under way at once (the connection keeps reading
//! while an action takes its time): the action is not executed, its command is answered
//! with the dialect's `failed` reply, message `aborted` (a polled program just stops, or,
//! where the abort has no reply of its own, its next poll finds it failed), and the
//! abort with its own `accepted` reply, if it has one. With nothing under way (or an
//! abort naming another command's id) nothing stops, and the abort gets its `rejected`
//! reply, if it has one.
//!
//! One action runs at a time on a connection unless `actions_at_once` (N) says more
//! (`robot-sim --actions-at-once N`, a plant file's `actions_at_once`), as a conveyor's
//! PLC moves several pallets at once: up to N are under way together, each ends at its
//! own time with its own `done` reply (its own id: a dialect with `correlation = "id"`
//! only), the abort stops each it names, and a message that comes while N are under way
//! (other than the abort and the fence's) waits until one ends. 0, or more than 1 in a
//! dialect with one request on the wire or whose actions end by a poll, is refused at
//! start ([`SimConfig::check`]).
//!
//! Faults, for tests (command numbers count every action begun, from 1):
//! - `error_every N`: every Nth command is answered with a `failed` (or `rejected`)
//!   reply and not executed;
//! - `close_after N`: each connection is closed when its (N+1)th command arrives (that
//!   command is not executed);
//! - `reset_after N`: the (N+1)th command of the process is begun and the connection is
//!   reset (RST) halfway through the action (not executed);
//! - `hang_after N`: from the (N+1)th command of the process on, the connection answers
//!   nothing (commands are read, never executed);
//! - `garbage_after N`: the (N+1)th command of the process gets bytes the dialect does not
//!   describe instead of a reply and is not executed; later commands are served normally;
//! - `oversize_after N`: the (N+1)th command gets a message larger than the dialect's
//!   `max_message_bytes` and is not executed;
//! - `fault_every N`: every Nth command faults the controller as `fault_after` does;
//! - `unknown_state_every N`: every Nth command takes the controller, for `fault_for`,
//!   into a state the dialect does not describe: as `fault_every`, but its status is
//!   the `ready` one with [`UNDESCRIBED_STATE`] for the state's word (`STATE HOMING`);
//! - `wrong_id_after N`: the (N+1)th command's answers echo another id (the command's
//!   with a `9` after it), where the dialect's replies echo one; it is executed;
//! - `fault_after N`: the (N+1)th command of the process is not executed: the controller
//!   reports `fault` (or `estop`) instead, and `ready` after `fault_for` (a dialect with
//!   one command in flight has the command answered with its `failed` reply too, so the
//!   wire is free for the state; with ids it is left unanswered); meanwhile it refuses
//!   every message of the sequence (counted: [`SimStats::refused_while_stopped`]);
//! - `fragment`: every message is written in pieces of 1 to 3 bytes;
//! - `merge`: messages are written together: an `accepted` reply with the `done` that
//!   follows it, and (where the dialect pushes its state) a `ready` with every reply;
//! - `abort_too_late`: an abort that comes while an action runs finds it just ended:
//!   the `done` goes out (crossing the abort on the wire) and nothing is stopped.
//!
//! Fenced (`fence_lease`, `robot-sim --fenced`), it is the fence of standby holons
//! ([`fence`]): one live session holds the claim with an epoch, a silent holder loses it
//! and its connection, a command with a stale epoch is refused and never begun, and a
//! step id runs at most once (a repeat gets the stored outcome).
//!
//! The simulator counts the commands it executed (answered with their success result)
//! and the actions an abort stopped;
//! [`SimStats`] can be written to a JSON file when each command arrives and after it is
//! answered (and when a connection is accepted), so tests can check that nothing ran
//! twice and how often a holon connected. A thread of its own writes the
//! file, off the command's path (after the reply went out), with the latest counts, at
//! most one write every 2 ms (the commands of one moment make one write): the count
//! file is the tests' window, and a controller command's round trip should cost what a real controller's
//! would (a write and a rename on the way cost the bridge about a hundred microseconds per
//! command).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::ControllerState;
use tokio::net::{TcpListener, TcpStream};
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

mod config;
pub mod fence;
pub mod physics;
pub mod process;
mod session;
mod writer;

pub use config::{SimConfig, SimConfigError};
use session::serve;

/// What the simulator did.
#[derive(Debug, Default)]
pub struct SimStats {
    received: AtomicU64,
    executed: AtomicU64,
    /// Commands of the sequence that came while the controller was in its simulated
    /// fault or e-stop: refused, not executed.
    refused: AtomicU64,
    /// Actions stopped by an abort (not executed).
    aborted: AtomicU64,
    inspections: AtomicU64,
    /// Inspections still to be answered `inspect_fail` whatever `inspect_fail_every`
    /// says (the plant's `fail` command: a fault played on a running cell).
    failing_inspections: AtomicU64,
    by_action: Mutex<BTreeMap<String, u64>>,
    connections: AtomicU64,
    /// The program of the last command run that named one.
    program: Mutex<Option<String>>,
    changeovers: AtomicU64,
    /// The fence, in fenced mode.
    fence: Mutex<Option<fence::FenceBook>>,
    /// Held while the count file is written.
    file_lock: Mutex<()>,
    /// The controller's simulated fault or e-stop (`--fault-after`) and until when: the
    /// controller's, not a connection's, so it outlasts a reconnect.
    stopped: Mutex<Option<(std::time::Instant, ControllerState)>>,
    /// Woken when the controller is stopped from outside a session (the plant's
    /// e-stop), so that every session says so at once.
    stop_changed: tokio::sync::Notify,
    /// Woken when the controller's links are cut from outside (the plant's `cut`):
    /// every session ends at once, as if the network between it and its holon failed.
    links_cut: tokio::sync::Notify,
    /// The stop under way is in a state the dialect does not describe
    /// (`unknown_state_every`): its status says `HOMING`.
    undescribed: std::sync::atomic::AtomicBool,
}

impl SimStats {
    /// The fence's state (None: unfenced).
    pub(crate) fn fence(&self) -> std::sync::MutexGuard<'_, Option<fence::FenceBook>> {
        self.fence.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Commands refused for a stale epoch (fenced mode).
    pub fn stale_epoch_refused(&self) -> u64 {
        self.fence().as_ref().map_or(0, |f| f.stale_refused)
    }

    /// The last epoch granted (fenced mode; 0: none).
    pub fn epoch(&self) -> u64 {
        self.fence().as_ref().map_or(0, |f| f.epoch())
    }

    /// Executions per step id, the last [`fence::STEPS_KEPT`] (fenced mode).
    pub fn by_step(&self) -> BTreeMap<String, u64> {
        self.fence()
            .as_ref()
            .map(|f| f.by_step())
            .unwrap_or_default()
    }

    /// Commands executed (answered with their success result).
    pub fn executed(&self) -> u64 {
        self.executed.load(Ordering::SeqCst)
    }

    /// An `action` executed (answered with its success result, or ended with nobody
    /// to tell: by a session, or by the plant simulator for a move it resumed).
    pub(crate) fn count_executed(&self, action: &str) {
        // Both under the lock the count file's snapshot takes ([`SimStats::to_json`]),
        // so that in it `executed` and `by_action` always agree (a write between the two
        // once showed one command executed and no pick).
        let mut by_action = self.by_action.lock().unwrap_or_else(|e| e.into_inner());
        *by_action.entry(action.to_string()).or_default() += 1;
        self.executed.fetch_add(1, Ordering::SeqCst);
    }

    /// Actions stopped by the dialect's abort while under way (not executed).
    pub fn aborted(&self) -> u64 {
        self.aborted.load(Ordering::SeqCst)
    }

    /// The simulated fault or e-stop under way, and when it ends (None: ready).
    pub(crate) fn stopped(&self) -> Option<(std::time::Instant, ControllerState)> {
        let stopped = *self.stopped.lock().unwrap_or_else(|e| e.into_inner());
        stopped.filter(|(until, _)| std::time::Instant::now() < *until)
    }

    /// The controller stops in `state` for `time`.
    pub(crate) fn stop(&self, state: ControllerState, time: Duration) {
        *self.stopped.lock().unwrap_or_else(|e| e.into_inner()) =
            Some((std::time::Instant::now() + time, state));
        self.undescribed.store(false, Ordering::SeqCst);
        self.stop_changed.notify_waiters();
    }

    /// Cuts every link to the controller: each session ends at once (the holon sees its
    /// connection drop and reconnects); what the controller was doing goes on.
    pub(crate) fn cut_links(&self) {
        self.links_cut.notify_waiters();
    }

    /// The controller's next `count` inspections fail (`inspect_fail`).
    pub(crate) fn fail_inspections(&self, count: u64) {
        self.failing_inspections.fetch_add(count, Ordering::SeqCst);
    }

    /// Whether this inspection is one of those told to fail: it is counted off.
    pub(crate) fn takes_failing_inspection(&self) -> bool {
        self.failing_inspections
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
            .is_ok()
    }

    /// The controller stops for `time` in a state the dialect does not describe (it
    /// refuses motion as in a fault; its status says [`UNDESCRIBED_STATE`]).
    pub(crate) fn stop_undescribed(&self, time: Duration) {
        *self.stopped.lock().unwrap_or_else(|e| e.into_inner()) =
            Some((std::time::Instant::now() + time, ControllerState::Fault));
        self.undescribed.store(true, Ordering::SeqCst);
        self.stop_changed.notify_waiters();
    }

    /// Whether the controller is stopped in a state the dialect does not describe.
    pub(crate) fn undescribed(&self) -> bool {
        self.stopped().is_some() && self.undescribed.load(Ordering::SeqCst)
    }

    /// Commands of the sequence that came while the controller was stopped (its
    /// simulated fault or e-stop): refused, not executed.
    pub fn refused_while_stopped(&self) -> u64 {
        self.refused.load(Ordering::SeqCst)
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

    /// `{"executed": N, "received": N, "aborted": N, "refused_while_stopped": N,
    /// "connections": N, "changeovers": N, "by_action": {"pick": N, ...}}`; fenced, with `"epoch": N,
    /// "stale_epoch_refused": N, "by_step": {"STEP ID": N, ...}` too.
    pub fn to_json(&self) -> String {
        let plain = self.plain_json();
        let fence = self.fence();
        let Some(fence) = fence.as_ref() else {
            return plain;
        };
        let by_step: Vec<String> = fence
            .by_step()
            .iter()
            .map(|(k, v)| format!("{}:{v}", serde_json::Value::String(k.clone())))
            .collect();
        format!(
            "{},\"epoch\":{},\"stale_epoch_refused\":{},\"by_step\":{{{}}}}}",
            plain.strip_suffix('}').unwrap_or(&plain),
            fence.epoch(),
            fence.stale_refused,
            by_step.join(",")
        )
    }

    fn plain_json(&self) -> String {
        // `executed` read with `by_action`, under its lock: they agree (see
        // `count_executed`).
        let (executed, by_action) = {
            let by_action = self.by_action.lock().unwrap_or_else(|e| e.into_inner());
            let listed: Vec<String> = by_action
                .iter()
                .map(|(k, v)| format!("\"{k}\":{v}"))
                .collect();
            (self.executed(), listed)
        };
        format!(
            "{{\"executed\":{},\"received\":{},\"aborted\":{},\"refused_while_stopped\":{},\"connections\":{},\"changeovers\":{},\"by_action\":{{{}}}}}",
            executed,
            self.received(),
            self.aborted(),
            self.refused_while_stopped(),
            self.connections(),
            self.changeovers(),
            by_action.join(",")
        )
    }
}

/// A simulator ready to [`Simulator::run`]: bound to its address, or set to dial the
/// holon.
pub struct Simulator {
    /// Where connections come from.
    link: SimLink,
    config: Arc<SimConfig>,
    stats: Arc<SimStats>,
}

enum SimLink {
    /// The controller listens (most dialects).
    Listen(TcpListener),
    /// The controller connects to the holon at this address.
    Dial(String),
}

/// The word `--unknown-state-every` says for the controller's state: in no table of a
/// dialect, as a controller that reports a state its integrator never described.
pub const UNDESCRIBED_STATE: &str = "HOMING";

/// How long the count file's writer waits after a write before the next: the file lags
/// the counts by at most this and one write (readers wait for it to settle).
const COUNT_FILE_GATHER: Duration = Duration::from_millis(2);

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
                // The commands of the next moment share one write: each is a new file
                // and a rename, and written for every command the writer took a third
                // of a core on two cores at 2,000 commands/s (docs/benchmarks.md).
                std::thread::sleep(COUNT_FILE_GATHER);
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
    /// Listens on `address`, for a dialect whose controller is the TCP server.
    /// Refused (`InvalidInput`) when [`SimConfig::check`] refuses the config.
    pub async fn bind(address: &str, config: SimConfig) -> std::io::Result<Simulator> {
        config
            .check()
            .map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidInput, e))?;
        let listener = TcpListener::bind(address).await?;
        let stats = fenced_stats(&config);
        Ok(Simulator {
            link: SimLink::Listen(listener),
            config: Arc::new(config),
            stats,
        })
    }

    /// Dials the holon at `address`, for a dialect whose controller connects (a config
    /// that [`SimConfig::check`] refuses is refused by [`Simulator::run`]).
    pub fn dialing(address: &str, config: SimConfig) -> Simulator {
        let stats = fenced_stats(&config);
        Simulator {
            link: SimLink::Dial(address.to_string()),
            config: Arc::new(config),
            stats,
        }
    }

    /// The address listened on (an error when dialing).
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        match &self.link {
            SimLink::Listen(listener) => listener.local_addr(),
            SimLink::Dial(_) => Err(std::io::Error::other(
                "the simulator dials; it listens on nothing",
            )),
        }
    }

    pub fn stats(&self) -> Arc<SimStats> {
        self.stats.clone()
    }

    /// Serves connections until `shutdown` is cancelled; at once returns, serving
    /// nothing, when [`SimConfig::check`] refuses the config (logged).
    pub async fn run(self, shutdown: CancellationToken) {
        if let Err(e) = self.config.check() {
            error!(error = %e, "the simulator's settings are refused: it serves nothing");
            return;
        }
        let (count_file, writer) = CountFile::start(&self.config, &self.stats);
        let connections = tokio_util::task::TaskTracker::new();
        let serve_one = |stream: TcpStream, peer: String| {
            if let Err(e) = stream.set_nodelay(true) {
                warn!(error = %e, "cannot set TCP_NODELAY");
            }
            let session = self.stats.connections.fetch_add(1, Ordering::SeqCst) + 1;
            info!(%peer, "bridge connected");
            // The count file counts connections too (a controller a holon reconnects
            // to, whatever the commands).
            count_file.update();
            let config = self.config.clone();
            let stats = self.stats.clone();
            let shutdown = shutdown.clone();
            let count_file = count_file.clone();
            connections.spawn(async move {
                let served = serve(stream, session, &config, &stats, &count_file, shutdown).await;
                if stats.fence().as_mut().is_some_and(|f| f.release(session)) {
                    info!(%peer, session, "the claim's holder is gone: the claim is free");
                }
                if let Err(e) = served {
                    warn!(%peer, error = %e, "connection ended with an error");
                } else {
                    info!(%peer, "bridge disconnected");
                }
            })
        };
        match &self.link {
            SimLink::Listen(listener) => loop {
                tokio::select! {
                    _ = shutdown.cancelled() => break,
                    accepted = listener.accept() => match accepted {
                        Ok((stream, peer)) => {
                            serve_one(stream, peer.to_string());
                        }
                        Err(e) => {
                            warn!(error = %e, "accept failed");
                            tokio::time::sleep(Duration::from_millis(50)).await;
                        }
                    }
                }
            },
            SimLink::Dial(address) => {
                let mut logged = false;
                loop {
                    let dialled = tokio::select! {
                        _ = shutdown.cancelled() => break,
                        dialled = TcpStream::connect(address) => dialled,
                    };
                    match dialled {
                        Ok(stream) => {
                            logged = false;
                            // One connection at a time: dial again when it ends.
                            let served = serve_one(stream, address.clone());
                            tokio::select! {
                                _ = shutdown.cancelled() => break,
                                _ = served => {}
                            }
                        }
                        Err(e) if !logged => {
                            warn!(%address, error = %e, "the holon is not listening; dialling again every 100 ms");
                            logged = true;
                        }
                        Err(_) => {}
                    }
                    tokio::select! {
                        _ = shutdown.cancelled() => break,
                        _ = tokio::time::sleep(Duration::from_millis(100)) => {}
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

/// The counts of a new simulator: in fenced mode with the fence, whose epochs go on
/// from the count file's `epoch` (a restart never grants an epoch again).
fn fenced_stats(config: &SimConfig) -> Arc<SimStats> {
    let stats = SimStats::default();
    if let Some(lease) = config.fence_lease {
        let epoch = config
            .count_file
            .as_ref()
            .and_then(|path| std::fs::read_to_string(path).ok())
            .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok())
            .and_then(|json| json.get("epoch").and_then(serde_json::Value::as_u64))
            .unwrap_or(0);
        if epoch > 0 {
            info!(epoch, "fenced: epochs go on from the count file's");
        }
        *stats.fence() = Some(fence::FenceBook::new(lease, epoch));
    }
    Arc::new(stats)
}

/// Rewrites the count file, if any, in place (a write and a rename: readers see the
/// old counts or the new, never half). Blocking: on the writer thread, and (fenced) once
/// per claim granted, before the grant is sent, so a restart never grants an epoch
/// again. Writes are one at a time, each with the counts as they are when it begins, so
/// the file never goes back to an older epoch.
pub(super) fn write_count_file(config: &SimConfig, stats: &SimStats) {
    let Some(path) = &config.count_file else {
        return;
    };
    let _one_at_a_time = stats.file_lock.lock().unwrap_or_else(|e| e.into_inner());
    let tmp = path.with_extension("tmp");
    let written = std::fs::write(&tmp, stats.to_json()).and_then(|()| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        warn!(path = %path.display(), error = %e, "cannot write the count file");
    }
}

/// Why a connection ended badly.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{0}")]
    Codec(#[from] crate::codec::CodecError),
    #[error("connection I/O: {0}")]
    Io(#[from] std::io::Error),
    #[error("the holon sent a message the dialect does not describe: {0}")]
    Unknown(String),
    #[error("cannot write a reply: {0}")]
    Write(String),
}

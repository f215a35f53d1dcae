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
//! - `fault_after N`: the (N+1)th command of the process is not executed: the controller
//!   reports `fault` (or `estop`) instead, and `ready` after `fault_for` (a dialect with
//!   one command in flight has the command answered with its `failed` reply too, so the
//!   wire is free for the state);
//! - `fragment`: every message is written in pieces of 1 to 3 bytes;
//! - `merge`: messages are written together: an `accepted` reply with the `done` that
//!   follows it, and (where the dialect pushes its state) a `ready` with every reply.
//!
//! The simulator counts the commands it executed (answered with their success result);
//! [`SimStats`] can be written to a JSON file when each command arrives and after it is
//! answered, so tests can check that nothing ran twice. A thread of its own writes the
//! file, off the command's path (after the reply went out), with the latest counts
//! (several commands in quick succession make one write): the count file is the tests'
//! window, and a controller command's round trip should cost what a real controller's
//! would (a write and a rename on the way cost the bridge about a hundred microseconds per
//! command).

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::BytesMut;
use futures_util::StreamExt;
use schemas::ControllerState;
use tokio::io::AsyncWriteExt;
use tokio::net::tcp::OwnedWriteHalf;
use tokio::net::{TcpListener, TcpStream};
use tokio_util::codec::{Encoder, FramedRead};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::dialect::framing::{FrameCodec, Framing};
use crate::dialect::{Correlation, Dialect, Element, Outcome, Sending, Status, Values};

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
    /// The protocol spoken (None: holarchy-xml).
    pub dialect: Option<Arc<Dialect>>,
    /// Begin the (N+1)th command, then reset the connection halfway through it.
    pub reset_after: Option<u64>,
    /// Answer the (N+1)th command with a message over the dialect's size limit.
    pub oversize_after: Option<u64>,
    /// Write every message in pieces of 1 to 3 bytes.
    pub fragment: bool,
    /// Write messages together (see the module docs).
    pub merge: bool,
}

impl SimConfig {
    /// The dialect spoken.
    pub fn dialect(&self) -> Arc<Dialect> {
        self.dialect.clone().unwrap_or_else(Dialect::holarchy_xml)
    }
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
    /// Listens on `address`, for a dialect whose controller is the TCP server.
    pub async fn bind(address: &str, config: SimConfig) -> std::io::Result<Simulator> {
        let listener = TcpListener::bind(address).await?;
        Ok(Simulator {
            link: SimLink::Listen(listener),
            config: Arc::new(config),
            stats: Arc::default(),
        })
    }

    /// Dials the holon at `address`, for a dialect whose controller connects.
    pub fn dialing(address: &str, config: SimConfig) -> Simulator {
        Simulator {
            link: SimLink::Dial(address.to_string()),
            config: Arc::new(config),
            stats: Arc::default(),
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

    /// Serves connections until `shutdown` is cancelled.
    pub async fn run(self, shutdown: CancellationToken) {
        let (count_file, writer) = CountFile::start(&self.config, &self.stats);
        let connections = tokio_util::task::TaskTracker::new();
        let serve_one = |stream: TcpStream, peer: String| {
            if let Err(e) = stream.set_nodelay(true) {
                warn!(error = %e, "cannot set TCP_NODELAY");
            }
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

/// The writing side of a connection: frames messages and writes them (in pieces, or held
/// to go together, as the faults say).
struct Writer<'a> {
    half: OwnedWriteHalf,
    codec: FrameCodec,
    dialect: &'a Dialect,
    config: &'a SimConfig,
    /// Messages held to be written with the next one (`merge`).
    held: BytesMut,
}

impl Writer<'_> {
    /// Frames the reply `index` with `values`.
    fn frame(&mut self, index: usize, values: &Values) -> Result<BytesMut, SimError> {
        let reply = &self.dialect.replies[index];
        let body = reply
            .body
            .as_ref()
            .ok_or_else(|| SimError::Write(format!("reply {} has no text to write", reply.name)))?;
        let bytes = self
            .dialect
            .write(body, values)
            .map_err(|e| SimError::Write(format!("reply {}: {e}", reply.name)))?;
        let mut framed = BytesMut::new();
        self.codec.encode(bytes.as_slice(), &mut framed)?;
        Ok(framed)
    }

    /// Writes reply `index` (with anything held before it).
    async fn reply(&mut self, index: usize, values: &Values) -> Result<(), SimError> {
        let mut framed = self.frame(index, values)?;
        if self.config.merge && self.dialect.status == Status::Pushed {
            // A state repeated in the same write as the reply.
            if let Some(status) = self.status_rule() {
                let mut state = Values::default();
                state.set("state", ControllerState::Ready.as_str().into());
                let before = self.frame(status, &state)?;
                self.held.extend_from_slice(&before);
            }
        }
        self.held.extend_from_slice(&framed);
        framed.clear();
        let all = std::mem::take(&mut self.held);
        self.raw(&all).await
    }

    /// Holds reply `index` to go with the next write (`merge`), or writes it now.
    async fn reply_or_hold(&mut self, index: usize, values: &Values) -> Result<(), SimError> {
        if self.config.merge {
            let framed = self.frame(index, values)?;
            self.held.extend_from_slice(&framed);
            return Ok(());
        }
        self.reply(index, values).await
    }

    fn status_rule(&self) -> Option<usize> {
        self.dialect
            .replies
            .iter()
            .position(|r| r.outcome == Outcome::Status)
    }

    async fn status(&mut self, state: ControllerState) -> Result<(), SimError> {
        let Some(index) = self.status_rule() else {
            return Ok(());
        };
        let mut values = Values::default();
        values.set("state", state.as_str().into());
        let framed = self.frame(index, &values)?;
        self.raw(&framed).await
    }

    /// Writes bytes as they are (in pieces with `fragment`).
    async fn raw(&mut self, bytes: &[u8]) -> Result<(), SimError> {
        if !self.config.fragment {
            self.half.write_all(bytes).await?;
            return Ok(());
        }
        let mut at = 0;
        let mut size = 1;
        while at < bytes.len() {
            let end = (at + size).min(bytes.len());
            self.half.write_all(&bytes[at..end]).await?;
            self.half.flush().await?;
            tokio::time::sleep(Duration::from_micros(200)).await;
            at = end;
            size = size % 3 + 1;
        }
        Ok(())
    }

    /// Bytes no rule of the dialect describes, framed so they arrive whole.
    async fn garbage(&mut self) -> Result<(), SimError> {
        let bytes: Vec<u8> = match &self.codec.framing {
            Framing::Xml => b"<ROBOT_REPLY><ID>oops</RESULT></ROBOT_REPLY>".to_vec(),
            Framing::Line { terminator } => {
                let mut line = b"\x01garbage \xff\xfe".to_vec();
                line.extend_from_slice(terminator);
                line
            }
            Framing::LengthPrefix { .. } => {
                let mut framed = BytesMut::new();
                self.codec
                    .encode(&b"\xde\xad\xbe\xef garbage"[..], &mut framed)?;
                framed.to_vec()
            }
        };
        self.raw(&bytes).await
    }

    /// A message one byte over the limit (its start: enough to be refused).
    async fn oversize(&mut self) -> Result<(), SimError> {
        let over = self.codec.max + 1;
        let bytes: Vec<u8> = match &self.codec.framing {
            Framing::Xml => {
                let mut doc = b"<X>".to_vec();
                doc.resize(over + 3, b'x');
                doc.extend_from_slice(b"</X>");
                doc
            }
            Framing::Line { terminator } => {
                let mut line = vec![b'x'; over];
                line.extend_from_slice(terminator);
                line
            }
            Framing::LengthPrefix { bytes, .. } => {
                let mut framed = BytesMut::new();
                let codec = FrameCodec {
                    framing: self.codec.framing.clone(),
                    max: usize::MAX,
                };
                let mut codec = codec;
                codec.encode(vec![0u8; over].as_slice(), &mut framed)?;
                framed.truncate(bytes + 16);
                framed.to_vec()
            }
        };
        self.raw(&bytes).await
    }
}

/// The action under way on a connection whose dialect polls for its end.
struct Running {
    until: std::time::Instant,
    /// The success result, or None for a simulated error.
    result: Option<&'static str>,
}

/// One connection's state.
struct Session<'a> {
    config: &'a SimConfig,
    stats: &'a SimStats,
    count_file: &'a CountFile,
    dialect: &'a Dialect,
    /// The values of the action under way, from every message that named them.
    context: Values,
    running: Option<Running>,
    /// Until when the controller reports a fault (polled state).
    fault_until: Option<(std::time::Instant, ControllerState)>,
    /// Commands begun on this connection.
    on_this_connection: u64,
    /// After `hang_after`: nothing more is answered.
    hung: bool,
}

async fn serve(
    stream: TcpStream,
    config: &SimConfig,
    stats: &SimStats,
    count_file: &CountFile,
    shutdown: CancellationToken,
) -> Result<(), SimError> {
    let dialect = config.dialect();
    let (read, half) = stream.into_split();
    let mut reader = FramedRead::new(read, dialect.frame_codec());
    let mut writer = Writer {
        half,
        codec: dialect.frame_codec(),
        dialect: &dialect,
        config,
        held: BytesMut::new(),
    };
    if let Some(banner) = &dialect.banner {
        let mut framed = BytesMut::new();
        writer
            .codec
            .clone()
            .encode(banner.as_bytes(), &mut framed)?;
        writer.raw(&framed).await?;
    }
    if dialect.status == Status::Pushed {
        writer.status(ControllerState::Ready).await?;
    }
    let mut session = Session {
        config,
        stats,
        count_file,
        dialect: &dialect,
        context: Values::default(),
        running: None,
        fault_until: None,
        on_this_connection: 0,
        hung: false,
    };
    loop {
        let frame = tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            frame = reader.next() => frame,
        };
        let frame = match frame {
            None => return Ok(()),
            Some(Err(e)) => return Err(e.into()),
            Some(Ok(frame)) => frame,
        };
        match session.message(&frame, &mut writer, &shutdown).await? {
            Flow::Continue => {}
            Flow::Close => return Ok(()),
            Flow::Reset => {
                let stream = reader
                    .into_inner()
                    .reunite(writer.half)
                    .map_err(|e| SimError::Write(e.to_string()))?;
                // A zero linger sends RST on close and never blocks the drop.
                #[allow(deprecated)]
                stream.set_linger(Some(Duration::ZERO))?;
                drop(stream);
                return Ok(());
            }
        }
    }
}

/// What a message does to the connection.
enum Flow {
    Continue,
    Close,
    /// Reset it (RST).
    Reset,
}

impl Session<'_> {
    fn state_now(&self) -> ControllerState {
        match self.fault_until {
            Some((until, state)) if std::time::Instant::now() < until => state,
            _ => ControllerState::Ready,
        }
    }

    /// The first of `element`'s expected replies with one of `outcomes`.
    fn rule(&self, element: &Element, outcomes: &[Outcome]) -> Option<usize> {
        outcomes.iter().find_map(|o| {
            element
                .expect
                .iter()
                .copied()
                .find(|&r| self.dialect.replies[r].outcome == *o)
        })
    }

    async fn message(
        &mut self,
        frame: &[u8],
        writer: &mut Writer<'_>,
        shutdown: &CancellationToken,
    ) -> Result<Flow, SimError> {
        if self.hung {
            return Ok(Flow::Continue);
        }
        let parsed = self.dialect.parse(frame)?;
        let mut found = None;
        for index in 0..self.dialect.commands.len() {
            match self.dialect.read_command(index, &parsed) {
                Ok(Some(values)) => {
                    found = Some((index, values));
                    break;
                }
                Ok(None) => {}
                Err(why) => return Err(SimError::Unknown(why)),
            }
        }
        let Some((index, values)) = found else {
            return Err(SimError::Unknown(
                String::from_utf8_lossy(frame).into_owned(),
            ));
        };
        if let Status::Polled { command, .. } = self.dialect.status {
            if command == index {
                let state = self.state_now();
                if let Some(rule) = writer.status_rule() {
                    let mut v = Values::default();
                    v.set("state", state.as_str().into());
                    writer.reply(rule, &v).await?;
                }
                return Ok(Flow::Continue);
            }
        }
        if let Some(keepalive) = &self.dialect.keepalive {
            if keepalive.command == index {
                if let Some(&rule) = keepalive.expect.first() {
                    writer.reply(rule, &Values::default()).await?;
                }
                return Ok(Flow::Continue);
            }
        }
        let Some(element) = self.dialect.sequence.iter().find(|e| e.command == index) else {
            // A command outside the sequence (e.g. a status poll of a pushing dialect).
            warn!(command = %self.dialect.commands[index].name, "a message the sequence does not use; not answered");
            return Ok(Flow::Continue);
        };
        let element = element.clone();
        if element.starts || values.contains("action") {
            // A message naming an action begins a new context.
            if values.contains("action") && !element.sending.eq(&Sending::Poll(Duration::ZERO)) {
                self.context = Values::default();
            }
        }
        self.context.fill_from(&values);
        for (name, value) in values.iter() {
            self.context.set(name, value.to_string());
        }
        if element.starts {
            return self.begin(&element, writer, shutdown).await;
        }
        match element.sending {
            Sending::Poll(_) => self.poll(&element, writer).await,
            Sending::Send => {
                if let Some(rule) = self.rule(&element, &[Outcome::Accepted]) {
                    let context = self.context.clone();
                    writer.reply(rule, &context).await?;
                }
                Ok(Flow::Continue)
            }
        }
    }

    /// The message that begins an action.
    async fn begin(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
        shutdown: &CancellationToken,
    ) -> Result<Flow, SimError> {
        let (config, stats) = (self.config, self.stats);
        let received = std::time::Instant::now();
        let n = stats.received.fetch_add(1, Ordering::SeqCst) + 1;
        // The count file shows a command as received when it arrives (its writer runs
        // off this path), so a test can tell a command is on the controller.
        self.count_file.update();
        self.on_this_connection += 1;
        let action = self.context.get("action").unwrap_or("").to_string();
        let id = self.context.get("id").unwrap_or("-").to_string();
        info!(%id, %action, n, "command");
        if matches!(config.close_after, Some(limit) if self.on_this_connection > limit) {
            info!(%id, "closing the connection (--close-after)");
            self.count_file.update();
            return Ok(Flow::Close);
        }
        if matches!(config.hang_after, Some(limit) if n > limit) {
            info!(%id, "not answering (--hang-after)");
            self.hung = true;
            self.count_file.update();
            return Ok(Flow::Continue);
        }
        if config.garbage_after.is_some_and(|limit| n == limit + 1) {
            info!(%id, "answering garbage (--garbage-after)");
            writer.garbage().await?;
            self.count_file.update();
            return Ok(Flow::Continue);
        }
        if config.oversize_after.is_some_and(|limit| n == limit + 1) {
            info!(%id, "answering an oversized message (--oversize-after)");
            writer.oversize().await?;
            self.count_file.update();
            return Ok(Flow::Continue);
        }
        if config.fault_after.is_some_and(|limit| n == limit + 1) {
            let state = config.fault_state.unwrap_or(ControllerState::Fault);
            info!(%id, %state, "reporting a fault (--fault-after)");
            self.count_file.update();
            let one = self.dialect.correlation == Correlation::OneInFlight;
            match self.dialect.status {
                Status::Pushed => {
                    writer.status(state).await?;
                    if one {
                        self.answer_failed(element, writer, &format!("{state}"))
                            .await?;
                    }
                    tokio::select! {
                        _ = shutdown.cancelled() => return Ok(Flow::Close),
                        _ = tokio::time::sleep(config.fault_for) => {}
                    }
                    info!("ready again");
                    writer.status(ControllerState::Ready).await?;
                }
                _ => {
                    self.fault_until = Some((std::time::Instant::now() + config.fault_for, state));
                    self.answer_failed(element, writer, &format!("{state}"))
                        .await?;
                }
            }
            return Ok(Flow::Continue);
        }
        let mut takes = config
            .action_delays
            .get(&action)
            .copied()
            .unwrap_or(config.delay);
        if stats.change_to(self.context.get("program")) {
            info!(%id, program = self.context.get("program").unwrap_or(""), changeover = ?config.changeover, "changing over");
            takes += config.changeover;
        }
        let simulated_error =
            matches!(config.error_every, Some(every) if every > 0 && n.is_multiple_of(every));
        let result = if simulated_error {
            None
        } else {
            success_result(&action, config, stats)
        };
        let done_here = self.rule(element, &[Outcome::Done]);
        let accepted = self.rule(element, &[Outcome::Accepted]);
        if config.reset_after.is_some_and(|limit| n == limit + 1) {
            info!(%id, "resetting the connection halfway through (--reset-after)");
            if let Some(rule) = accepted {
                let context = self.context.clone();
                writer.reply(rule, &context).await?;
            }
            tokio::select! {
                _ = shutdown.cancelled() => return Ok(Flow::Close),
                _ = act_for(received + takes / 2) => {}
            }
            self.count_file.update();
            return Ok(Flow::Reset);
        }
        if result.is_none() && (done_here.is_some() || simulated_error) {
            // Refused or failed without acting.
            let why = if simulated_error {
                "simulated error (--error-every)".to_string()
            } else {
                format!("unknown action {action:?}")
            };
            self.answer_failed(element, writer, &why).await?;
            self.count_file.update();
            return Ok(Flow::Continue);
        }
        if let Some(rule) = accepted {
            let context = self.context.clone();
            if done_here.is_some() {
                // Its done follows in this same turn: they may go together.
                writer.reply_or_hold(rule, &context).await?;
            } else {
                writer.reply(rule, &context).await?;
            }
        }
        if done_here.is_none() {
            // Its end is polled for.
            self.running = Some(Running {
                until: received + takes,
                result,
            });
            return Ok(Flow::Continue);
        }
        if !takes.is_zero() {
            tokio::select! {
                _ = shutdown.cancelled() => return Ok(Flow::Close),
                _ = act_for(received + takes) => {}
            }
        }
        self.finish(done_here, result, writer).await?;
        Ok(Flow::Continue)
    }

    /// Answers with `element`'s failed (or rejected) reply.
    async fn answer_failed(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
        why: &str,
    ) -> Result<(), SimError> {
        if let Some(rule) = self.rule(element, &[Outcome::Failed, Outcome::Rejected]) {
            let mut values = self.context.clone();
            values.set("message", why.to_string());
            writer.reply(rule, &values).await?;
        } else {
            warn!("the dialect has no failed reply here: the command is not answered");
        }
        Ok(())
    }

    /// Reports an action's end with the `done` reply `rule` (the action counted as
    /// executed), or its failure.
    async fn finish(
        &mut self,
        rule: Option<usize>,
        result: Option<&'static str>,
        writer: &mut Writer<'_>,
    ) -> Result<(), SimError> {
        let Some(rule) = rule else {
            return Ok(());
        };
        let mut values = self.context.clone();
        match result {
            Some(result) => {
                let stats = self.stats;
                stats.executed.fetch_add(1, Ordering::SeqCst);
                let action = self.context.get("action").unwrap_or("").to_string();
                *stats
                    .by_action
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .entry(action)
                    .or_default() += 1;
                values.set("result", result.into());
                writer.reply(rule, &values).await?;
            }
            None => {
                let element = self.dialect.sequence.last().expect("not empty").clone();
                self.answer_failed(&element, writer, "simulated error (--error-every)")
                    .await?;
            }
        }
        self.count_file.update();
        Ok(())
    }

    /// A poll for the end of the action under way.
    async fn poll(&mut self, element: &Element, writer: &mut Writer<'_>) -> Result<Flow, SimError> {
        let done = self.rule(element, &[Outcome::Done]);
        match &self.running {
            Some(running) if std::time::Instant::now() < running.until => {
                if let Some(rule) = self.rule(element, &[Outcome::Running, Outcome::Accepted]) {
                    let context = self.context.clone();
                    writer.reply(rule, &context).await?;
                }
            }
            Some(running) => {
                let result = running.result;
                self.running = None;
                if result.is_none() {
                    self.answer_failed(element, writer, "simulated error (--error-every)")
                        .await?;
                    self.count_file.update();
                } else {
                    self.finish(done, result, writer).await?;
                }
            }
            None => {
                // Nothing under way: the last action has ended.
                if let Some(rule) = done {
                    let mut values = self.context.clone();
                    values.set("result", "idle".into());
                    writer.reply(rule, &values).await?;
                }
            }
        }
        Ok(Flow::Continue)
    }
}

//! The controller client: one persistent TCP connection to the robot controller, in the
//! controller's dialect ([`crate::dialect`]).
//!
//! The client runs as a loop for an [`Owner`]: whoever owns it gives it its requests and
//! takes its events in order. [`run`] is that loop with a command mailbox and an event
//! channel for an owner that is a task of its own; a resource holon's execution
//! component is the owner itself ([`drive`]), so a command and its reply cross no
//! queue between tasks. It connects (or, when the dialect says the controller
//! connects, listens and accepts one connection at a time), pauses before each further
//! attempt as its [`Reconnect`] policy says (a holon's backoff, from
//! `reconnect_interval`, whatever ended the last connection or attempt), runs each
//! command's sequence of messages as the dialect says, and reports in order:
//!
//! - [`ControllerEvent::Status`] on every change of the controller's state (pushed,
//!   polled, or ready while connected, as the dialect says) or of the words it gave with
//!   it (a status reply's `{message}`, e.g. `overtravel axis 3`), and on disconnect;
//! - [`ControllerEvent::Reply`] when a command's step ends: its result, or `error` with
//!   the controller's message;
//! - [`ControllerEvent::CommandFailed`] when a command cannot have an answer: no
//!   connection, the connection broke, the controller sent what the dialect does not
//!   describe, the command cannot be written, no answer came within `command_timeout`
//!   (which covers a command's whole sequence), or a fenced controller refused the
//!   holder's epoch ([`CommandFailure::StaleEpoch`]).
//!
//! A controller that misses a deadline or sends something the dialect does not describe
//! has its connection reset; the client then reconnects as usual.
//!
//! A standby holon runs the client with the port of a fence ([`run_fenced`], or
//! [`drive`] with the port) and keeps its [`FenceHandle`] ([`fence`]): the same loop,
//! the one owner of the connection, also claims the controller, heartbeats while it
//! holds the claim, writes the epoch and step ids in commands
//! ([`ControllerRequest::Step`]) and asks step states.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use schemas::RobotCommand;
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

mod connection;
pub mod fence;

pub use fence::{
    ClaimError, Epoch, FenceError, FenceEvent, FenceHandle, FencePort, FenceRequest, StepId,
    StepStatus,
};

use crate::dialect::{Dialect, Role};
use connection::{Connection, ConnectionEnd};

/// How to reach the controller.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// `HOST:PORT` of the controller's TCP server, or the address the holon listens on
    /// when the dialect's controller connects.
    pub address: String,
    /// The shortest pause between connection attempts ([`FixedInterval`]'s pause, a
    /// holon's backoff's first), and between tries to listen.
    pub reconnect_interval: Duration,
    /// Longest wait for a command's answer (its whole sequence) before the step fails.
    pub command_timeout: Duration,
    /// Longest wait for one TCP connect (and for a dialect's banner).
    pub connect_timeout: Duration,
    /// The controller's protocol.
    pub dialect: Arc<Dialect>,
}

impl ClientConfig {
    pub fn new(address: impl Into<String>) -> Self {
        ClientConfig {
            address: address.into(),
            reconnect_interval: Duration::from_secs(1),
            command_timeout: Duration::from_secs(30),
            connect_timeout: Duration::from_secs(2),
            dialect: Dialect::holarchy_xml(),
        }
    }
}

/// The controller as the client sees it (one type with the snapshot's `controller`).
pub use schemas::ControllerStatus;

/// Why a command got no reply (no result of its step).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CommandFailure {
    #[error("not connected to the controller")]
    NotConnected,
    #[error("the connection to the controller broke")]
    Disconnected,
    #[error("no reply within {0:?}")]
    Timeout(Duration),
    #[error("the controller broke the protocol: {0}")]
    Protocol(String),
    /// The dialect cannot write this command (e.g. an action its enum tables lack).
    #[error("the command cannot be written in the controller's dialect: {0}")]
    Unwritable(String),
    /// An abort ([`ControllerRequest::Abort`]) ended it on the controller.
    #[error("aborted on the controller")]
    Aborted,
    /// The controller's last known state was fault or e-stop when the command's next
    /// message was due: nothing more of it was written.
    #[error("the controller is in {0}: the command was not sent")]
    Stopped(ControllerStatus),
    /// The controller's fence refused the command (the dialect's `fence.stale` reply):
    /// a newer holder's epoch is on it. Nothing of the command ran; this holder is
    /// deposed ([`FenceEvent::Deposed`]).
    #[error("the controller refused this holder's epoch (stale_epoch{}): the command was not run", current.map(|e| format!(": the controller's epoch is {e}")).unwrap_or_default())]
    StaleEpoch {
        /// The controller's epoch, when it said.
        current: Option<Epoch>,
    },
}

/// What the client's owner asks of it.
#[derive(Debug, Clone, PartialEq)]
pub enum ControllerRequest {
    /// Run this command; its `id` comes back in events.
    Command(RobotCommand),
    /// Run this command as step `step` of a fenced holon: the step id (and the epoch,
    /// while the claim is held) is written in it, and the controller runs a step id at
    /// most once. Without a fence it is an ordinary command.
    Step { command: RobotCommand, step: StepId },
    /// Ask the controller the state of step `step` (a fenced client's): the answer comes
    /// as [`ControllerEvent::StepStatus`] once the step has ended or is unknown (while
    /// it runs, the client asks again every `reconnect_interval`), or with why it
    /// cannot be told.
    StepStatus(StepId),
    /// Stop now: the dialect's abort message goes out at once, even while a command is
    /// in flight; the command in flight then ends as the controller reports it (its
    /// failure, or [`CommandFailure::Aborted`]). A dialect without an abort message
    /// cannot be told: the step runs to its end (logged).
    Abort,
}

impl From<RobotCommand> for ControllerRequest {
    fn from(command: RobotCommand) -> ControllerRequest {
        ControllerRequest::Command(command)
    }
}

/// What the client reports to its owner, in the order it happened.
#[derive(Debug, Clone, PartialEq)]
pub enum ControllerEvent {
    /// The controller's state, and what the controller said of it in its own words (a
    /// status reply's `{message}`), when it said anything.
    Status(ControllerStatus, Option<String>),
    Reply {
        id: u64,
        result: String,
        message: Option<String>,
    },
    CommandFailed {
        id: u64,
        failure: CommandFailure,
    },
    /// The controller says the move of command `id` has left its origin (a reply of
    /// outcome `departed`, docs/dialects.md): the command goes on, and ends with its
    /// own reply as any other.
    Departed {
        id: u64,
    },
    /// The answer to a [`ControllerRequest::StepStatus`].
    StepStatus {
        step: StepId,
        status: Result<StepStatus, FenceError>,
    },
}

/// Ready at `at`, at once when it has passed. Not `sleep_until`: tokio's timer fires on
/// its next millisecond tick even for a deadline already past, and the first connect
/// (due at once) waited for it, 1-2 ms of every holon's start (docs/benchmarks.md, "The
/// start path and footprint again").
async fn due(at: Instant) {
    if at > Instant::now() {
        tokio::time::sleep_until(at).await;
    }
}

/// How the last attempt at a connection ended: what a [`Reconnect`] policy decides the
/// next pause on. The client does not judge; the policy says what counts as served.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LinkEnd {
    /// No connection was made: refused, unreachable, or the connect timed out.
    NotConnected,
    /// A connection was made and ended, whatever ended it: the controller closed or
    /// reset it, or the client reset it (a protocol error, a timeout, a failed write).
    Ended {
        /// How long it was up.
        lasted: Duration,
        /// The steps the controller answered on it ([`ControllerEvent::Reply`]: the
        /// step's result, or its failure in the controller's words).
        answered: u64,
    },
}

/// What decides the pause before each connection attempt after the first (which is made
/// at once), told how the last attempt ended. Asked once per attempt, on the client's
/// task; requests that come while it waits are refused as usual (not connected).
///
/// A resource holon's is its backoff (holon-node's `component::interfacing`); with the
/// dialect's controller connecting, the client listens and is not asked.
pub trait Reconnect: Send {
    fn pause(&mut self, last: LinkEnd) -> Duration;
}

/// The same pause whatever ended the last attempt: robot-bridge's own [`run`] and
/// [`run_fenced`] (tests, benchmarks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct FixedInterval(pub Duration);

impl Reconnect for FixedInterval {
    fn pause(&mut self, _: LinkEnd) -> Duration {
        self.0
    }
}

/// Who owns the client: where its requests come from and where its events go.
///
/// The client awaits [`Owner::request`] beside the socket and its timers, so that
/// future must be cancel-safe: dropped before it is ready, it loses nothing.
/// [`Owner::report`] is awaited to its end, one event at a time, in the order things
/// happened.
pub trait Owner: Send {
    /// The next request; `None` when the owner is gone (the client stops).
    fn request(&mut self) -> impl Future<Output = Option<ControllerRequest>> + Send;
    /// One event; false when the owner is gone (the client stops).
    fn report(&mut self, event: ControllerEvent) -> impl Future<Output = bool> + Send;
}

/// The owner of [`run`]: a command mailbox and an event channel to a task of its own.
struct Channels<'a> {
    commands: &'a mut mpsc::Receiver<ControllerRequest>,
    events: mpsc::Sender<ControllerEvent>,
}

impl Owner for Channels<'_> {
    async fn request(&mut self) -> Option<ControllerRequest> {
        self.commands.recv().await
    }

    async fn report(&mut self, event: ControllerEvent) -> bool {
        self.events.send(event).await.is_ok()
    }
}

/// Runs the client until `shutdown` is cancelled or the event receiver is dropped.
/// Commands come from `commands`; their `id` comes back in events. It reconnects every
/// `reconnect_interval` ([`FixedInterval`]).
pub async fn run(
    config: ClientConfig,
    commands: &mut mpsc::Receiver<ControllerRequest>,
    events: mpsc::Sender<ControllerEvent>,
    shutdown: CancellationToken,
) {
    let mut reconnect = FixedInterval(config.reconnect_interval);
    let owner = &mut Channels { commands, events };
    drive(config, owner, &mut reconnect, None, shutdown).await
}

/// [`run`] with the fence of a standby holon: its requests come from `fence` (a
/// [`fence::channel`]'s port, whose [`FenceHandle`] the holon keeps).
pub async fn run_fenced(
    config: ClientConfig,
    commands: &mut mpsc::Receiver<ControllerRequest>,
    fence: &mut FencePort,
    events: mpsc::Sender<ControllerEvent>,
    shutdown: CancellationToken,
) {
    let mut reconnect = FixedInterval(config.reconnect_interval);
    let owner = &mut Channels { commands, events };
    drive(config, owner, &mut reconnect, Some(fence), shutdown).await
}

/// Runs the client for `owner` until `shutdown` is cancelled or the owner is gone; its
/// connection attempts paced by `reconnect`; with a fence's port when the holon is
/// fenced.
pub async fn drive<O: Owner>(
    config: ClientConfig,
    owner: &mut O,
    reconnect: &mut dyn Reconnect,
    fence: Option<&mut FencePort>,
    shutdown: CancellationToken,
) {
    run_with(config, owner, reconnect, fence, shutdown).await
}

async fn run_with<O: Owner>(
    config: ClientConfig,
    owner: &mut O,
    reconnect: &mut dyn Reconnect,
    mut fence: Option<&mut FencePort>,
    shutdown: CancellationToken,
) {
    let mut claimed = fence::Claimed::default();
    let mut reporter = Reporter {
        owner,
        status: None,
        said: None,
        answered: 0,
    };
    let mut listener = None;
    // How the last attempt ended (None: none yet, the first is made at once).
    let mut last_end = None;
    // The last command that reached the controller, across connections.
    let mut last_run = None;
    loop {
        if !reporter.status(ControllerStatus::Disconnected).await {
            return;
        }
        let link = Link {
            config: &config,
            fence: fence.as_deref_mut(),
            claimed: &mut claimed,
            reporter: &mut reporter,
            shutdown: &shutdown,
        };
        let stream = match config.dialect.role {
            Role::ControllerListens => link.connect(reconnect, last_end).await,
            Role::ControllerConnects => link.accept(&mut listener).await,
        };
        let Some(stream) = stream else { return };
        let connected = Instant::now();
        reporter.answered = 0;
        info!(controller = %config.address, dialect = %config.dialect.name, "connected to the controller");
        let mut connection = Connection::new(&config, &mut reporter, &mut last_run);
        connection.fence = fence.as_deref_mut();
        connection.claimed = Some(&mut claimed);
        match connection.serve(stream, listener.as_ref(), &shutdown).await {
            ConnectionEnd::Shutdown => {
                info!(controller = %config.address, "closed the controller connection");
                return;
            }
            ConnectionEnd::OwnerGone => return,
            ConnectionEnd::Lost(why) => {
                let lasted = connected.elapsed();
                let answered = reporter.answered;
                warn!(controller = %config.address, reason = %why, lasted_ms = lasted.as_millis() as u64, answered, "controller connection lost; reconnecting");
                last_end = Some(LinkEnd::Ended { lasted, answered });
            }
        }
    }
}

/// The owner, and the controller's status as last reported to it.
struct Reporter<'o, O> {
    owner: &'o mut O,
    status: Option<ControllerStatus>,
    /// The controller's words with that status, as last reported.
    said: Option<String>,
    /// The steps answered ([`ControllerEvent::Reply`]) on the current connection.
    answered: u64,
}

impl<O: Owner> Reporter<'_, O> {
    /// The owner's next request; `None` when the owner is gone.
    async fn request(&mut self) -> Option<ControllerRequest> {
        self.owner.request().await
    }

    /// Sends an event; false when the owner is gone.
    async fn send(&mut self, event: ControllerEvent) -> bool {
        // A stale epoch's refusal is the controller's answer too.
        if matches!(
            event,
            ControllerEvent::Reply { .. }
                | ControllerEvent::CommandFailed {
                    failure: CommandFailure::StaleEpoch { .. },
                    ..
                }
        ) {
            self.answered += 1;
        }
        self.owner.report(event).await
    }

    async fn status(&mut self, status: ControllerStatus) -> bool {
        self.status_said(status, None).await
    }

    /// A status with the controller's words: reported when either changed.
    async fn status_said(&mut self, status: ControllerStatus, said: Option<String>) -> bool {
        if self.status == Some(status) && self.said == said {
            return true;
        }
        self.status = Some(status);
        self.said = said.clone();
        self.send(ControllerEvent::Status(status, said)).await
    }
}

/// Establishing a connection, while commands that arrive meanwhile fail.
struct Link<'a, 'o, O> {
    config: &'a ClientConfig,
    /// The fence's requests, when fenced.
    fence: Option<&'a mut FencePort>,
    /// The fence's state.
    claimed: &'a mut fence::Claimed,
    reporter: &'a mut Reporter<'o, O>,
    shutdown: &'a CancellationToken,
}

impl<O: Owner> Link<'_, '_, O> {
    /// A request while no controller is connected: a command fails at once, an abort
    /// has nothing to stop.
    async fn refuse(&mut self, request: ControllerRequest) -> bool {
        match request {
            ControllerRequest::Command(command) | ControllerRequest::Step { command, .. } => {
                let event = ControllerEvent::CommandFailed {
                    id: command.id,
                    failure: CommandFailure::NotConnected,
                };
                self.reporter.send(event).await
            }
            ControllerRequest::Abort => {
                debug!("abort while not connected: nothing runs on the controller");
                true
            }
            ControllerRequest::StepStatus(step) => {
                let event = ControllerEvent::StepStatus {
                    step,
                    status: Err(FenceError::NotConnected),
                };
                self.reporter.send(event).await
            }
        }
    }

    /// A fence request while no controller is connected: it fails at once.
    async fn refuse_fence(&mut self, request: FenceRequest) -> bool {
        match request {
            FenceRequest::Claim { reply, .. } => {
                fence::answer_claim(reply, Err(ClaimError::NotConnected));
            }
            FenceRequest::StepStatus { step, reply } => {
                if reply.send(Err(FenceError::NotConnected)).is_err() {
                    debug!(
                        step = step.as_str(),
                        "a step state asked by a fence handle that is gone"
                    );
                }
            }
            FenceRequest::PauseHeartbeats(paused) => self.claimed.paused = paused,
        }
        true
    }

    /// Connects: at once the first time, else after the pause `reconnect` gives for
    /// how the last connection ended (`last`), and again after each failed attempt
    /// after the pause it gives for that.
    async fn connect(
        mut self,
        reconnect: &mut dyn Reconnect,
        last: Option<LinkEnd>,
    ) -> Option<TcpStream> {
        let config = self.config;
        let mut logged = false;
        let mut next_attempt = Instant::now();
        if let Some(last) = last {
            next_attempt += reconnect.pause(last);
        }
        loop {
            tokio::select! {
                _ = self.shutdown.cancelled() => return None,
                command = self.reporter.request() => {
                    if !self.refuse(command?).await {
                        return None;
                    }
                }
                request = next_fence(&mut self.fence) => {
                    if !self.refuse_fence(request).await {
                        return None;
                    }
                }
                _ = due(next_attempt) => {
                    let attempt = tokio::time::timeout(config.connect_timeout, TcpStream::connect(&config.address)).await;
                    match attempt {
                        Ok(Ok(stream)) => {
                            if let Err(e) = stream.set_nodelay(true) {
                                debug!(error = %e, "cannot set TCP_NODELAY; commands may wait for Nagle");
                            }
                            return Some(stream);
                        }
                        Ok(Err(e)) if !logged => {
                            warn!(controller = %config.address, error = %e, "controller unreachable; retrying");
                            logged = true;
                        }
                        Err(_) if !logged => {
                            warn!(controller = %config.address, timeout_ms = config.connect_timeout.as_millis() as u64, "controller connect timed out; retrying");
                            logged = true;
                        }
                        _ => debug!(controller = %config.address, "controller still unreachable"),
                    }
                    next_attempt = Instant::now() + reconnect.pause(LinkEnd::NotConnected);
                }
            }
        }
    }

    /// Listens on the address (once) and accepts the controller's connection.
    async fn accept(mut self, listener: &mut Option<TcpListener>) -> Option<TcpStream> {
        let config = self.config;
        let mut logged = false;
        loop {
            if listener.is_none() {
                match TcpListener::bind(&config.address).await {
                    Ok(bound) => {
                        info!(address = %config.address, "waiting for the controller to connect");
                        *listener = Some(bound);
                    }
                    Err(e) => {
                        if !logged {
                            warn!(address = %config.address, error = %e, "cannot listen for the controller; retrying every {:?}", config.reconnect_interval);
                            logged = true;
                        }
                    }
                }
            }
            let retry = tokio::time::sleep(config.reconnect_interval);
            tokio::select! {
                _ = self.shutdown.cancelled() => return None,
                command = self.reporter.request() => {
                    if !self.refuse(command?).await {
                        return None;
                    }
                }
                request = next_fence(&mut self.fence) => {
                    if !self.refuse_fence(request).await {
                        return None;
                    }
                }
                accepted = async { listener.as_ref().expect("bound").accept().await }, if listener.is_some() => match accepted {
                    Ok((stream, peer)) => {
                        info!(%peer, "the controller connected");
                        if let Err(e) = stream.set_nodelay(true) {
                            debug!(error = %e, "cannot set TCP_NODELAY");
                        }
                        return Some(stream);
                    }
                    Err(e) => warn!(error = %e, "accepting the controller's connection failed"),
                },
                _ = retry, if listener.is_none() => {}
            }
        }
    }
}

/// The next fence request; never, without a fence (or once its handles are gone).
async fn next_fence(fence: &mut Option<&mut FencePort>) -> FenceRequest {
    match fence {
        Some(port) => match port.requests.recv().await {
            Some(request) => request,
            None => std::future::pending().await,
        },
        None => std::future::pending().await,
    }
}

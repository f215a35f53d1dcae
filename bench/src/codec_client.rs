//! The controller client as it was before dialects: holarchy's TCP/XML protocol through
//! `robot_bridge::codec` directly, with the same task, mailbox and events as the client
//! of today. Kept here, and only here, as the baseline of the controller command rows:
//! the cost of running a dialect file is the difference, in the same sitting.

use std::collections::HashMap;
use std::time::Duration;

use futures_util::{SinkExt, StreamExt};
use schemas::RobotMessage;
use tokio::net::TcpStream;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::codec::Framed;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use robot_bridge::client::{
    ClientConfig, CommandFailure, ControllerEvent, ControllerRequest, ControllerStatus,
};
use robot_bridge::codec::RobotCodec;

/// Runs the client until `shutdown` is cancelled or the event receiver is dropped.
/// Commands come from `commands`; their `id` is the wire `ID` and comes back in events.
pub async fn run(
    config: ClientConfig,
    commands: &mut mpsc::Receiver<ControllerRequest>,
    events: mpsc::Sender<ControllerEvent>,
    shutdown: CancellationToken,
) {
    let mut reporter = Reporter {
        events,
        status: None,
    };
    let mut first_attempt = true;
    loop {
        if !reporter.status(ControllerStatus::Disconnected).await {
            return;
        }
        let stream = match connect(&config, commands, &mut reporter, &shutdown, first_attempt).await
        {
            Some(stream) => stream,
            None => return,
        };
        first_attempt = false;
        info!(controller = %config.address, "connected to the controller");
        let end = serve(&config, stream, commands, &mut reporter, &shutdown).await;
        match end {
            ConnectionEnd::Shutdown => {
                info!(controller = %config.address, "closed the controller connection");
                return;
            }
            ConnectionEnd::OwnerGone => return,
            ConnectionEnd::Lost(why) => {
                warn!(controller = %config.address, reason = %why, "controller connection lost; reconnecting");
            }
        }
    }
}

struct Reporter {
    events: mpsc::Sender<ControllerEvent>,
    status: Option<ControllerStatus>,
}

impl Reporter {
    /// Sends an event; false when the owner is gone.
    async fn send(&mut self, event: ControllerEvent) -> bool {
        self.events.send(event).await.is_ok()
    }

    async fn status(&mut self, status: ControllerStatus) -> bool {
        if self.status == Some(status) {
            return true;
        }
        self.status = Some(status);
        self.send(ControllerEvent::Status(status, None)).await
    }
}

/// Connects, retrying every `reconnect_interval`; fails commands that arrive meanwhile.
async fn connect(
    config: &ClientConfig,
    commands: &mut mpsc::Receiver<ControllerRequest>,
    reporter: &mut Reporter,
    shutdown: &CancellationToken,
    first_attempt: bool,
) -> Option<TcpStream> {
    let mut logged = false;
    let mut next_attempt = Instant::now();
    if !first_attempt {
        // A controller that just dropped us is given a moment before we knock again.
        next_attempt += config.reconnect_interval.min(Duration::from_millis(100));
    }
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return None,
            command = commands.recv() => {
                let ControllerRequest::Command(command) = command? else { continue };
                if !reporter.send(ControllerEvent::CommandFailed { id: command.id, failure: CommandFailure::NotConnected }).await {
                    return None;
                }
            }
            _ = tokio::time::sleep_until(next_attempt) => {
                let attempt = tokio::time::timeout(config.connect_timeout, TcpStream::connect(&config.address)).await;
                match attempt {
                    Ok(Ok(stream)) => {
                        if let Err(e) = stream.set_nodelay(true) {
                            debug!(error = %e, "cannot set TCP_NODELAY");
                        }
                        return Some(stream);
                    }
                    Ok(Err(e)) if !logged => {
                        warn!(controller = %config.address, error = %e, "controller unreachable; retrying every {:?}", config.reconnect_interval);
                        logged = true;
                    }
                    Err(_) if !logged => {
                        warn!(controller = %config.address, "controller connect timed out; retrying every {:?}", config.reconnect_interval);
                        logged = true;
                    }
                    _ => debug!(controller = %config.address, "controller still unreachable"),
                }
                next_attempt = Instant::now() + config.reconnect_interval;
            }
        }
    }
}

enum ConnectionEnd {
    Shutdown,
    OwnerGone,
    Lost(String),
}

async fn serve(
    config: &ClientConfig,
    stream: TcpStream,
    commands: &mut mpsc::Receiver<ControllerRequest>,
    reporter: &mut Reporter,
    shutdown: &CancellationToken,
) -> ConnectionEnd {
    let mut framed = Framed::new(stream, RobotCodec);
    // Wire id -> deadline of every command sent and not answered.
    let mut pending: HashMap<u64, Instant> = HashMap::new();
    // Status messages repeating the last one, since the last change.
    let mut repeats: u64 = 0;
    let end = loop {
        let next_deadline = pending.values().min().copied();
        tokio::select! {
            _ = shutdown.cancelled() => break ConnectionEnd::Shutdown,
            command = commands.recv() => {
                let command = match command {
                    None => break ConnectionEnd::OwnerGone,
                    Some(ControllerRequest::Command(command)) => command,
                    // The baseline has no abort and no fence.
                    Some(ControllerRequest::Abort | ControllerRequest::Step { .. } | ControllerRequest::StepStatus(_)) => continue,
                };
                debug!(id = command.id, action = %command.action, "command to controller");
                let id = command.id;
                if let Err(e) = framed.send(&RobotMessage::Command(command)).await {
                    if !reporter.send(ControllerEvent::CommandFailed { id, failure: CommandFailure::Disconnected }).await {
                        break ConnectionEnd::OwnerGone;
                    }
                    break ConnectionEnd::Lost(format!("send failed: {e}"));
                }
                pending.insert(id, Instant::now() + config.command_timeout);
            }
            message = framed.next() => match message {
                Some(Ok(RobotMessage::Reply(reply))) => {
                    if pending.remove(&reply.id).is_none() {
                        warn!(id = reply.id, result = %reply.result, "reply to no pending command; ignored");
                        continue;
                    }
                    debug!(id = reply.id, result = %reply.result, "reply from controller");
                    let event = ControllerEvent::Reply { id: reply.id, result: reply.result, message: reply.message };
                    if !reporter.send(event).await {
                        break ConnectionEnd::OwnerGone;
                    }
                }
                Some(Ok(RobotMessage::Status(state))) => {
                    // Changes are logged and reported; repeats (a chatty controller
                    // sends the same status over and over) are only counted.
                    let status = ControllerStatus::from(state);
                    if reporter.status == Some(status) {
                        repeats += 1;
                        continue;
                    }
                    info!(controller_state = %state, repeats_before = repeats, "controller status");
                    repeats = 0;
                    if !reporter.status(status).await {
                        break ConnectionEnd::OwnerGone;
                    }
                }
                Some(Ok(RobotMessage::Command(_))) => {
                    let why = "the controller sent a ROBOT_CMD".to_string();
                    if !fail_pending(&mut pending, reporter, CommandFailure::Protocol(why.clone())).await {
                        break ConnectionEnd::OwnerGone;
                    }
                    break ConnectionEnd::Lost(why);
                }
                Some(Err(e)) if e.is_broken_connection() => {
                    // A reset or a document cut short: the controller is gone
                    // (killed, or its host down), not talking nonsense. Pending
                    // commands fail as disconnected below.
                    break ConnectionEnd::Lost(e.to_string());
                }
                Some(Err(e)) => {
                    let why = e.to_string();
                    warn!(error = %why, "controller sent invalid data; resetting the connection");
                    if !fail_pending(&mut pending, reporter, CommandFailure::Protocol(why.clone())).await {
                        break ConnectionEnd::OwnerGone;
                    }
                    break ConnectionEnd::Lost(why);
                }
                None => break ConnectionEnd::Lost("the controller closed the connection".into()),
            },
            _ = async { tokio::time::sleep_until(next_deadline.unwrap_or_else(Instant::now)).await }, if next_deadline.is_some() => {
                let now = Instant::now();
                let expired: Vec<u64> = pending.iter().filter(|(_, d)| **d <= now).map(|(id, _)| *id).collect();
                for id in &expired {
                    pending.remove(id);
                    warn!(id, timeout = ?config.command_timeout, "controller did not reply in time");
                    if !reporter.send(ControllerEvent::CommandFailed { id: *id, failure: CommandFailure::Timeout(config.command_timeout) }).await {
                        return ConnectionEnd::OwnerGone;
                    }
                }
                break ConnectionEnd::Lost("a command timed out".into());
            }
        }
    };
    if !fail_pending(&mut pending, reporter, CommandFailure::Disconnected).await {
        return ConnectionEnd::OwnerGone;
    }
    end
}

async fn fail_pending(
    pending: &mut HashMap<u64, Instant>,
    reporter: &mut Reporter,
    failure: CommandFailure,
) -> bool {
    let mut ids: Vec<u64> = pending.drain().map(|(id, _)| id).collect();
    ids.sort_unstable();
    for id in ids {
        let event = ControllerEvent::CommandFailed {
            id,
            failure: failure.clone(),
        };
        if !reporter.send(event).await {
            return false;
        }
    }
    true
}

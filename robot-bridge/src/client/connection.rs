//! One connection to the controller: the commands in flight, each on its way through
//! the dialect's sequence, the request on a one-in-flight wire, the status poll and the
//! keep-alive; each message from the controller matched to what awaits it.
//!
//! An abort ([`ControllerRequest::Abort`]) is written at once, whatever is on the wire.
//! Every command in flight is then aborted: one that has not reached the controller ends
//! at once ([`CommandFailure::Aborted`]); the others send no further `send` element (an
//! exchange that would ends as aborted), and end as the controller reports: their own
//! answer (a `failed` reply, or `done` when the action ended before the abort took
//! effect), or, where the dialect's abort has a reply of its own, aborted when that
//! reply says the controller stopped (`accepted`); when it says there was nothing to
//! stop (`rejected`) they go on to their end. While the abort's own reply is awaited,
//! nothing else goes on a one-in-flight wire, and an aborted command is not polled.

use std::collections::VecDeque;

use futures_util::{SinkExt, StreamExt};
use schemas::RobotCommand;
use tokio::net::{TcpListener, TcpStream};
use tokio::time::Instant;
use tokio_util::codec::Framed;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::{
    ClientConfig, CommandFailure, ControllerEvent, ControllerRequest, ControllerStatus, Owner,
    Reporter,
};
use crate::dialect::{
    command_values, framing::FrameCodec, Correlation, Dialect, Sending, Status, Values,
};

mod abort;
mod fence;
mod incoming;

pub(super) enum ConnectionEnd {
    Shutdown,
    OwnerGone,
    Lost(String),
}

/// One command's way through the dialect's sequence.
struct Exchange {
    command: RobotCommand,
    values: Values,
    /// Each element's message, written once when the command came.
    messages: Vec<Vec<u8>>,
    /// The element of the sequence it is at.
    element: usize,
    /// Whether that element's message has been sent (and not yet answered).
    sent: bool,
    /// When a poll is due again.
    poll_at: Option<Instant>,
    /// Whether the controller has answered another command on this connection since
    /// this one came (any answer matched to a command in flight, a departure
    /// included): with ids, a command that times out while the controller answers
    /// others is that command's trouble (a pallet that stopped reporting), not the
    /// link's.
    others_answered: bool,
    /// When the step must have ended.
    deadline: Instant,
    /// Whether an abort has been asked while it was in flight.
    aborted: bool,
    /// Whether an answer naming its id has come since its message was last sent (an
    /// answer without an id goes to the oldest exchange without one).
    echoed: bool,
    /// Whether the controller has said its move left its origin (reported once).
    departed: bool,
}

impl Exchange {
    /// Whether a message of it has gone to the controller.
    fn reached(&self) -> bool {
        self.sent || self.element > 0 || self.poll_at.is_some()
    }
}

/// What the request on the wire is waiting for (one-in-flight dialects).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Awaiting {
    /// An exchange's element (by command id).
    Command(u64),
    StatusPoll {
        deadline: Instant,
    },
    Keepalive {
        deadline: Instant,
    },
}

/// What happened on the connection that ends it or must be told.
type Step = Result<(), ConnectionEnd>;

/// The state of one connection: exchanges in flight and the wire.
pub(super) struct Connection<'a, 'o, O> {
    config: &'a ClientConfig,
    dialect: &'a Dialect,
    /// The owner: requests in, events out.
    reporter: &'a mut Reporter<'o, O>,
    /// Commands in flight, oldest first.
    exchanges: VecDeque<Exchange>,
    /// One-in-flight: what the request on the wire awaits.
    awaiting: Option<Awaiting>,
    /// Until the banner is read: its deadline.
    banner_until: Option<Instant>,
    next_status_poll: Option<Instant>,
    /// When the link was last used (for the keep-alive).
    last_traffic: Instant,
    /// Status messages repeating the last one, since the last change.
    repeats: u64,
    /// Polled state: whether a status answer has been read since the connection began
    /// and since the last step that reached the controller ended. A step's first
    /// message waits for one (the step before may have left the controller stopped).
    state_fresh: bool,
    /// Polled state with ids: a status poll is on the wire, its answer not yet read.
    poll_outstanding: bool,
    /// Messages to write.
    outbox: Vec<Vec<u8>>,
    /// Abort messages whose own replies are awaited, oldest first.
    abort_waits: VecDeque<abort::AbortWait>,
    /// The values of the last command that reached the controller (on this connection
    /// or an earlier one): what an abort with nothing in flight is written with.
    last_run: &'a mut Option<Values>,
    /// The fence's requests, when fenced.
    pub(super) fence: Option<&'a mut super::FencePort>,
    /// The fence's state across connections, when fenced.
    pub(super) claimed: Option<&'a mut super::fence::Claimed>,
    /// What the fence awaits on this connection.
    fence_waits: fence::FenceWaits,
}

impl<'a, 'o, O: Owner> Connection<'a, 'o, O> {
    pub(super) fn new(
        config: &'a ClientConfig,
        reporter: &'a mut Reporter<'o, O>,
        last_run: &'a mut Option<Values>,
    ) -> Self {
        let now = Instant::now();
        let dialect = &*config.dialect;
        Connection {
            config,
            dialect,
            reporter,
            exchanges: VecDeque::new(),
            awaiting: None,
            banner_until: dialect
                .banner
                .as_ref()
                .map(|_| now + config.connect_timeout),
            next_status_poll: matches!(dialect.status, Status::Polled { .. }).then_some(now),
            last_traffic: now,
            repeats: 0,
            state_fresh: false,
            poll_outstanding: false,
            outbox: Vec::new(),
            abort_waits: VecDeque::new(),
            last_run,
            fence: None,
            claimed: None,
            fence_waits: fence::FenceWaits::default(),
        }
    }

    fn one_in_flight(&self) -> bool {
        self.dialect.correlation == Correlation::OneInFlight
    }

    /// Whether a new request may go on the wire now (with ids, always).
    fn wire_free(&self) -> bool {
        !self.one_in_flight() || (self.awaiting.is_none() && self.abort_waits.is_empty())
    }

    pub(super) async fn serve(
        mut self,
        stream: TcpStream,
        listener: Option<&TcpListener>,
        shutdown: &CancellationToken,
    ) -> ConnectionEnd {
        let mut framed = Framed::new(stream, self.dialect.frame_codec());
        if self.dialect.status == Status::Connection
            && self.banner_until.is_none()
            && !self.reporter.status(ControllerStatus::Ready).await
        {
            return ConnectionEnd::OwnerGone;
        }
        let end = loop {
            let step = self.pump(Instant::now()).await;
            if let Err(end) = step {
                break end;
            }
            if let Err(end) = flush(&mut framed, &mut self.outbox).await {
                break end;
            }
            let wake = self.next_wake();
            tokio::select! {
                _ = shutdown.cancelled() => break ConnectionEnd::Shutdown,
                request = self.reporter.request() => {
                    let step = match request {
                        None => break ConnectionEnd::OwnerGone,
                        Some(ControllerRequest::Command(command)) => self.take(command).await,
                        Some(ControllerRequest::Step { command, step }) => {
                            self.take_step(command, Some(step)).await
                        }
                        Some(ControllerRequest::StepStatus(step)) => {
                            self.ask_status(step, fence::StatusReply::Owner).await
                        }
                        Some(ControllerRequest::Abort) => self.abort().await,
                    };
                    if let Err(end) = step {
                        break end;
                    }
                }
                request = super::next_fence(&mut self.fence) => {
                    if let Err(end) = self.fence_request(request).await {
                        break end;
                    }
                }
                frame = framed.next() => {
                    let step = match frame {
                        Some(Ok(frame)) => self.incoming(&frame).await,
                        Some(Err(e)) if e.is_broken_connection() => {
                            // A reset or a message cut short: the controller is gone
                            // (killed, or its host down), not talking nonsense.
                            Err(ConnectionEnd::Lost(e.to_string()))
                        }
                        Some(Err(e)) => self.protocol_error(e.to_string()).await,
                        None => Err(ConnectionEnd::Lost("the controller closed the connection".into())),
                    };
                    if let Err(end) = step {
                        break end;
                    }
                }
                accepted = async { listener.expect("guarded").accept().await }, if listener.is_some() => {
                    if let Ok((_, peer)) = accepted {
                        warn!(%peer, "refused a second controller connection: one controller per holon");
                    }
                }
                _ = async { tokio::time::sleep_until(wake.unwrap_or_else(Instant::now)).await }, if wake.is_some() => {
                    if let Err(end) = self.timers(Instant::now()).await {
                        break end;
                    }
                }
            }
        };
        self.fence_ends().await;
        let failure = CommandFailure::Disconnected;
        if !self.fail_all(failure).await {
            return ConnectionEnd::OwnerGone;
        }
        end
    }

    /// The earliest deadline or due time, if any.
    fn next_wake(&self) -> Option<Instant> {
        let exchanges = self
            .exchanges
            .iter()
            .flat_map(|e| std::iter::once(e.deadline).chain(e.poll_at));
        let connection = if self.banner_until.is_some() {
            [self.banner_until, None]
        } else {
            let keepalive = self
                .dialect
                .keepalive
                .as_ref()
                .map(|k| self.last_traffic + k.every);
            [self.next_status_poll, keepalive]
        };
        let awaiting = match self.awaiting {
            Some(Awaiting::StatusPoll { deadline } | Awaiting::Keepalive { deadline }) => {
                Some(deadline)
            }
            _ => None,
        };
        exchanges
            .chain(connection.into_iter().flatten())
            .chain(awaiting)
            .chain(self.abort_waits.iter().map(|w| w.deadline))
            .chain(self.fence_waits.next_wake())
            .min()
    }

    /// A new command: its exchange begins (or waits its turn on a one-in-flight wire).
    async fn take(&mut self, command: RobotCommand) -> Step {
        self.take_step(command, None).await
    }

    /// A new command, with its step id when the fence is used.
    async fn take_step(&mut self, command: RobotCommand, step: Option<super::StepId>) -> Step {
        debug!(id = command.id, action = %command.action, "command to controller");
        let mut values = command_values(&command, &self.dialect.format);
        self.epoch_values(&mut values, step.as_ref());
        // Every message of the sequence is written before the first is sent.
        let mut messages = Vec::with_capacity(self.dialect.sequence.len());
        for element in &self.dialect.sequence {
            match self.dialect.write_command(element.command, &values) {
                Ok(message) => messages.push(message),
                Err(why) => {
                    let event = ControllerEvent::CommandFailed {
                        id: command.id,
                        failure: CommandFailure::Unwritable(why),
                    };
                    return self.report(event).await;
                }
            }
        }
        self.exchanges.push_back(Exchange {
            command,
            values,
            messages,
            element: 0,
            sent: false,
            poll_at: None,
            others_answered: false,
            deadline: Instant::now() + self.config.command_timeout,
            aborted: false,
            echoed: false,
            departed: false,
        });
        Ok(())
    }

    /// Keeps the values of an exchange that ends, if it reached the controller: an abort
    /// with nothing in flight is written with them.
    fn remember(&mut self, exchange: &mut Exchange) {
        if exchange.reached() {
            *self.last_run = Some(std::mem::take(&mut exchange.values));
            // What the step did to the controller's state is known from the next status.
            self.state_fresh = false;
        }
    }

    /// The controller's state as last reported, when it is stopped (fault or e-stop).
    fn stopped(&self) -> Option<ControllerStatus> {
        self.reporter
            .status
            .filter(|s| matches!(s, ControllerStatus::Fault | ControllerStatus::Estop))
    }

    /// Whether a step's message may be written now: the controller's last known state is
    /// `ready`, and (polled) no status answer that could say otherwise is awaited, and,
    /// for a step's first message, the state was read after the last step ended.
    fn may_write_step(&self, first: bool) -> bool {
        if self.reporter.status != Some(ControllerStatus::Ready) {
            return false;
        }
        match self.dialect.status {
            Status::Polled { .. } => {
                !self.poll_outstanding
                    && !matches!(self.awaiting, Some(Awaiting::StatusPoll { .. }))
                    && (self.state_fresh || !first)
            }
            Status::Pushed | Status::Connection => true,
        }
    }

    /// Every step not awaiting an answer on a one-in-flight wire fails without a word to
    /// a stopped controller: nothing more of it is written. With ids, one whose message is
    /// on the wire fails too (its late answer, if any, answers no step): it would
    /// otherwise wait for an answer a faulted controller may never give, and its timeout
    /// reset the connection under the steps that follow.
    async fn fail_unsent(&mut self, status: ControllerStatus) -> Step {
        let one = self.one_in_flight();
        while let Some(i) = self.exchanges.iter().position(|e| !e.sent || !one) {
            let Some(mut exchange) = self.exchanges.remove(i) else {
                break;
            };
            self.remember(&mut exchange);
            let id = exchange.command.id;
            warn!(id, controller_state = %status, "the controller is stopped: the step ends, nothing more of it is sent");
            self.report(ControllerEvent::CommandFailed {
                id,
                failure: CommandFailure::Stopped(status),
            })
            .await?;
        }
        Ok(())
    }

    async fn report(&mut self, event: ControllerEvent) -> Step {
        if self.reporter.send(event).await {
            Ok(())
        } else {
            Err(ConnectionEnd::OwnerGone)
        }
    }

    /// Sends whatever may go now: exchanges' next messages, the status poll, the
    /// keep-alive.
    async fn pump(&mut self, now: Instant) -> Step {
        if self.banner_until.is_some() {
            return Ok(());
        }
        // An aborted exchange whose next message would begin (or go on with) the action
        // ends here: that message is not sent.
        while let Some(i) = self.exchanges.iter().position(|e| {
            e.aborted
                && !e.sent
                && e.poll_at.is_none()
                && (e.element == 0 || self.dialect.sequence[e.element].sending == Sending::Send)
        }) {
            self.end_aborted(i).await?;
        }
        // Nothing of a step goes to a controller in fault or e-stop.
        if let Some(status) = self.stopped() {
            self.fail_unsent(status).await?;
        }
        let one = self.one_in_flight();
        for i in 0..self.exchanges.len() {
            if !self.wire_free() {
                break;
            }
            let exchange = &self.exchanges[i];
            if exchange.sent || exchange.poll_at.is_some_and(|at| at > now) {
                continue;
            }
            if !self.may_write_step(!exchange.reached()) {
                if !exchange.reached() && !self.state_fresh {
                    // Polled: ask the state now rather than at the next interval.
                    if let Some(at) = self.next_status_poll.as_mut() {
                        *at = (*at).min(now);
                    }
                }
                continue;
            }
            if exchange.aborted
                && self
                    .abort_waits
                    .iter()
                    .any(|w| w.ids.contains(&exchange.command.id))
            {
                // Not polled until the controller says whether it stopped.
                continue;
            }
            self.outbox
                .push(exchange.messages[exchange.element].clone());
            self.last_traffic = now;
            let exchange = &mut self.exchanges[i];
            exchange.sent = true;
            exchange.echoed = false;
            exchange.poll_at = None;
            if one {
                self.awaiting = Some(Awaiting::Command(exchange.command.id));
            }
        }
        if let (Status::Polled { command, every }, Some(at)) =
            (self.dialect.status, self.next_status_poll)
        {
            if at <= now && self.wire_free() {
                let bytes = self
                    .dialect
                    .write_command(command, &Values::default())
                    .map_err(ConnectionEnd::Lost)?;
                self.outbox.push(bytes);
                self.last_traffic = now;
                self.next_status_poll = if one { None } else { Some(now + every) };
                self.poll_outstanding = !one;
                if one {
                    self.awaiting = Some(Awaiting::StatusPoll {
                        deadline: now + self.config.command_timeout,
                    });
                }
            }
        }
        if let Some(keepalive) = &self.dialect.keepalive {
            if self.wire_free() && self.last_traffic + keepalive.every <= now {
                let bytes = self
                    .dialect
                    .write_command(keepalive.command, &Values::default())
                    .map_err(ConnectionEnd::Lost)?;
                self.outbox.push(bytes);
                self.last_traffic = now;
                if one && !keepalive.expect.is_empty() {
                    self.awaiting = Some(Awaiting::Keepalive {
                        deadline: now + self.config.command_timeout,
                    });
                }
            }
        }
        Ok(())
    }

    async fn timers(&mut self, now: Instant) -> Step {
        self.fence_timers(now).await?;
        if self.banner_until.is_some_and(|until| until <= now) {
            return Err(ConnectionEnd::Lost(format!(
                "no banner within {:?}",
                self.config.connect_timeout
            )));
        }
        if let Some(Awaiting::StatusPoll { deadline } | Awaiting::Keepalive { deadline }) =
            self.awaiting
        {
            if deadline <= now {
                return Err(ConnectionEnd::Lost(
                    "the controller did not answer a status poll or keep-alive in time".into(),
                ));
            }
        }
        if self.abort_waits.iter().any(|w| w.deadline <= now) {
            return Err(ConnectionEnd::Lost(
                "the controller did not answer the abort in time".into(),
            ));
        }
        let expired: Vec<u64> = self
            .exchanges
            .iter()
            .filter(|e| e.deadline <= now)
            .map(|e| e.command.id)
            .collect();
        if expired.is_empty() {
            return Ok(());
        }
        let timeout = self.config.command_timeout;
        // With ids, the controller's answers to other commands since this one came show
        // the link and the controller serve: only this command failed, the rest go on
        // (its late answer, if any, names an id in flight no more and is ignored). On a
        // one-in-flight wire, or with no other command answered since, the link is suspect.
        let mut link_serves = !self.one_in_flight();
        for id in expired {
            if let Some(i) = self.exchanges.iter().position(|e| e.command.id == id) {
                if let Some(mut exchange) = self.exchanges.remove(i) {
                    link_serves &= exchange.others_answered;
                    self.remember(&mut exchange);
                }
            }
            warn!(id, ?timeout, "controller did not reply in time");
            self.report(ControllerEvent::CommandFailed {
                id,
                failure: CommandFailure::Timeout(timeout),
            })
            .await?;
        }
        if link_serves {
            info!("the controller answers other commands: the connection is kept");
            return Ok(());
        }
        Err(ConnectionEnd::Lost("a command timed out".into()))
    }

    /// A status from the controller, with its words (a status reply's `{message}`).
    async fn status(&mut self, state: schemas::ControllerState, said: Option<&str>) -> Step {
        // Changes are logged and reported; repeats (a chatty controller sends the same
        // status over and over) are only counted.
        let status = ControllerStatus::from(state);
        let said = said.filter(|s| !s.is_empty()).map(str::to_string);
        if self.reporter.status == Some(status) && self.reporter.said == said {
            self.repeats += 1;
            return Ok(());
        }
        match (&said, state) {
            (Some(said), schemas::ControllerState::Ready) => {
                info!(controller_state = %state, controller_said = %said, repeats_before = self.repeats, "controller status");
            }
            (Some(said), _) => {
                warn!(controller_state = %state, controller_said = %said, repeats_before = self.repeats, "controller status");
            }
            (None, _) => {
                info!(controller_state = %state, repeats_before = self.repeats, "controller status")
            }
        }
        self.repeats = 0;
        if self.reporter.status_said(status, said).await {
            Ok(())
        } else {
            Err(ConnectionEnd::OwnerGone)
        }
    }

    async fn protocol_error(&mut self, why: String) -> Step {
        warn!(error = %why, "controller sent invalid data; resetting the connection");
        if !self.fail_all(CommandFailure::Protocol(why.clone())).await {
            return Err(ConnectionEnd::OwnerGone);
        }
        Err(ConnectionEnd::Lost(why))
    }

    /// Fails every command in flight, oldest first; false when the owner is gone.
    async fn fail_all(&mut self, failure: CommandFailure) -> bool {
        let mut exchanges = std::mem::take(&mut self.exchanges);
        let mut ids: Vec<u64> = exchanges.iter().map(|e| e.command.id).collect();
        for exchange in exchanges.iter_mut() {
            self.remember(exchange);
        }
        ids.sort_unstable();
        for id in ids {
            let event = ControllerEvent::CommandFailed {
                id,
                failure: failure.clone(),
            };
            if !self.reporter.send(event).await {
                return false;
            }
        }
        true
    }
}

/// Writes the messages waiting in `outbox`.
async fn flush(
    framed: &mut Framed<TcpStream, FrameCodec>,
    outbox: &mut Vec<Vec<u8>>,
) -> Result<(), ConnectionEnd> {
    if outbox.is_empty() {
        return Ok(());
    }
    for message in outbox.drain(..) {
        framed
            .feed(message.as_slice())
            .await
            .map_err(|e| ConnectionEnd::Lost(format!("send failed: {e}")))?;
    }
    framed
        .flush()
        .await
        .map_err(|e| ConnectionEnd::Lost(format!("send failed: {e}")))
}

//! One simulated controller connection: each message the holon sends matched to the
//! dialect's commands and answered as its sequence says, with the faults of the config.
//!
//! An action whose `done` reply goes in the same exchange is under way ([`Acting`])
//! while the connection goes on reading: the loop waits for the first end of the
//! actions under way and for the next message together. Up to N
//! ([`SimConfig::actions_at_once`], default 1) are under way at once, each with the
//! values (its id) and step id of the command that began it:
//!
//! | under way | what comes | what the session does |
//! |---|---|---|
//! | fewer than N | any message | answers it now (one that begins an action adds it) |
//! | N | the dialect's abort, or a fence message | answers it now |
//! | N | any other message | keeps it (deferred); kept ones are answered in order as soon as fewer than N are under way, as on a controller that runs N commands at a time |
//! | any | an action's time is up | its own `done` reply (its id), or, held up in the plant, looks again in 50 ms |
//! | any | 10 ms have passed, a move under way (its command names `info.from`) whose departure the dialect can say | asks the plant whether it left its origin: if so, its own `departed` reply (its id), once |
//! | any | the abort | each action it names (all, where it names none) stops: its own `failed` reply, `aborted` |
//! | any | the connection ends, is cut, or its lease is lost | each action goes on unanswered to its own end and settles its own step |

use std::collections::VecDeque;
use std::time::Duration;

use bytes::BytesMut;
use futures_util::StreamExt;
use schemas::ControllerState;
use tokio::net::TcpStream;
use tokio_util::codec::FramedRead;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

mod abort;
mod acting;
mod faults;
mod fenced;
mod poll;

use acting::{act_for, Acting};

use super::fence::StepRecord;
use super::writer::Writer;
use super::{CountFile, SimConfig, SimError, SimStats};
use crate::dialect::{Dialect, Element, Outcome, Sending, Status, Values};
use std::sync::atomic::Ordering;

fn success_result(action: &str, config: &SimConfig, stats: &SimStats) -> Option<&'static str> {
    match action {
        "pick" => Some("picking_done"),
        "place" => Some("placing_done"),
        "move" => Some("arrived"),
        "inspect" => {
            let n = stats.inspections.fetch_add(1, Ordering::SeqCst) + 1;
            if stats.takes_failing_inspection() {
                return Some("inspect_fail");
            }
            match config.inspect_fail_every {
                Some(every) if every > 0 && n.is_multiple_of(every) => Some("inspect_fail"),
                _ => Some("inspect_pass"),
            }
        }
        _ => None,
    }
}

/// The action under way on a connection whose dialect polls for its end (one at a
/// time: a poll names no action).
struct Running {
    /// When it ends.
    until: std::time::Instant,
    /// The success result, or why the action fails.
    result: Result<&'static str, String>,
}

/// One connection's state.
struct Session<'a> {
    /// The simulator's settings.
    config: &'a SimConfig,
    /// The controller's counts, shared by its connections.
    stats: &'a SimStats,
    /// Asks for the count file to be written.
    count_file: &'a CountFile,
    /// The dialect spoken.
    dialect: &'a Dialect,
    /// The values of the last command, from every message that named them (an action
    /// under way keeps its own: [`Acting::values`]).
    context: Values,
    /// The polled action under way, if any.
    running: Option<Running>,
    /// Commands begun on this connection.
    on_this_connection: u64,
    /// After `hang_after`: nothing more is answered.
    hung: bool,
    /// The actions under way (at most `config.actions_at_once`), each answered when it
    /// ends (or is aborted).
    acting: Vec<Acting>,
    /// Messages that came while `config.actions_at_once` actions were under way,
    /// answered once fewer are.
    deferred: VecDeque<bytes::Bytes>,
    /// This connection's number (the fence's session).
    session: u64,
    /// (Fenced) the step id of the command being begun (or of the polled action under
    /// way), recorded as running; an action under way keeps its own ([`Acting::step`]).
    step: Option<String>,
}

pub(super) async fn serve(
    stream: TcpStream,
    session_number: u64,
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
        // A fault outlasts the connection it began on.
        state: stats
            .stopped()
            .map_or(ControllerState::Ready, |(_, state)| state),
        stats,
    };
    writer.greet().await?;
    let mut session = Session {
        config,
        stats,
        count_file,
        dialect: &dialect,
        context: Values::default(),
        running: None,
        on_this_connection: 0,
        hung: false,
        acting: Vec::new(),
        deferred: VecDeque::new(),
        session: session_number,
        step: None,
    };
    loop {
        let ends = session.next_end();
        let lease_end = session.lease_end();
        let fault_end = stats.stopped().map(|(until, _)| until);
        let stop_changed = stats.stop_changed.notified();
        let links_cut = stats.links_cut.notified();
        let mut flow = tokio::select! {
            _ = shutdown.cancelled() => return Ok(()),
            _ = links_cut => {
                // As when the holon's socket closes: the claim is free at once, and the
                // action under way goes on and settles its step, after the connection
                // is gone.
                info!("the link is cut (the plant's control port): the connection ends, what runs goes on");
                session.release();
                drop(reader);
                drop(writer);
                session.complete_unanswered(&shutdown).await;
                return Ok(());
            }
            _ = stop_changed => {
                // Stopped from outside this session (the plant's e-stop): said at once.
                stopped(&mut writer, session.state_now()).await?;
                Flow::Continue
            }
            _ = tokio::time::sleep_until(fault_end.unwrap_or_else(std::time::Instant::now).into()), if fault_end.is_some() => {
                ready_again(&mut writer).await?;
                Flow::Continue
            }
            _ = tokio::time::sleep_until(lease_end.unwrap_or_else(std::time::Instant::now).into()), if lease_end.is_some() => {
                if session.lease_expired() {
                    drop(reader);
                    drop(writer);
                    session.complete_unanswered(&shutdown).await;
                    return Ok(());
                }
                Flow::Continue
            }
            frame = reader.next() => match frame {
                None => {
                    session.release();
                    session.complete_unanswered(&shutdown).await;
                    return Ok(());
                }
                Some(Err(e)) => {
                    session.release();
                    session.complete_unanswered(&shutdown).await;
                    return Err(e.into());
                }
                Some(Ok(frame)) => session.receive(frame, &mut writer, &shutdown).await?,
            },
            _ = act_for(ends.unwrap_or_else(std::time::Instant::now)), if ends.is_some() => {
                session.end_action(&mut writer).await?;
                Flow::Continue
            }
        };
        // What waited for an action to end, now that fewer are under way.
        while matches!(flow, Flow::Continue) && session.has_room() {
            let Some(frame) = session.deferred.pop_front() else {
                break;
            };
            flow = session.message(&frame, &mut writer, &shutdown).await?;
        }
        match flow {
            Flow::Continue => {}
            Flow::Close => {
                // What runs goes on, as when the holon's socket closes.
                drop(reader);
                drop(writer);
                session.complete_unanswered(&shutdown).await;
                return Ok(());
            }
            Flow::Reset => {
                let reset = reset(reader.into_inner(), writer.half);
                session.complete_unanswered(&shutdown).await;
                return reset;
            }
        }
    }
}

/// Stopped from outside the session (the plant's e-stop): said at once if the state
/// changed.
async fn stopped(writer: &mut Writer<'_>, state: ControllerState) -> Result<(), SimError> {
    if writer.state != state {
        writer.state = state;
        info!(%state, "stopped");
        if writer.dialect.status == Status::Pushed {
            writer.status().await?;
        }
    }
    Ok(())
}

/// The simulated fault is over: ready, and said so if the state is pushed.
async fn ready_again(writer: &mut Writer<'_>) -> Result<(), SimError> {
    writer.state = ControllerState::Ready;
    info!("ready again");
    if writer.dialect.status == Status::Pushed {
        writer.status().await?;
    }
    Ok(())
}

/// Resets the connection (RST) and drops it.
fn reset(
    read: tokio::net::tcp::OwnedReadHalf,
    write: tokio::net::tcp::OwnedWriteHalf,
) -> Result<(), SimError> {
    let stream = read
        .reunite(write)
        .map_err(|e| SimError::Write(e.to_string()))?;
    // A zero linger sends RST on close and never blocks the drop.
    #[allow(deprecated)]
    stream.set_linger(Some(Duration::ZERO))?;
    drop(stream);
    Ok(())
}

/// What a message does to the connection.
enum Flow {
    Continue,
    Close,
    /// Reset it (RST).
    Reset,
}

impl Session<'_> {
    /// The connection ends: a claim it held is free at once.
    fn release(&self) {
        if self
            .stats
            .fence()
            .as_mut()
            .is_some_and(|f| f.release(self.session))
        {
            info!(
                session = self.session,
                "the holder's connection closed: the claim is free"
            );
        }
    }

    fn state_now(&self) -> ControllerState {
        self.stats
            .stopped()
            .map_or(ControllerState::Ready, |(_, state)| state)
    }

    /// A message from the holon: answered now, or, while `actions_at_once` actions are
    /// under way, kept until one ends (an abort or a fence message is answered now).
    async fn receive(
        &mut self,
        frame: bytes::Bytes,
        writer: &mut Writer<'_>,
        shutdown: &CancellationToken,
    ) -> Result<Flow, SimError> {
        self.seen();
        if !self.has_room() && !self.hung {
            let (index, _) = self.identify(&frame)?;
            if self.dialect.abort.as_ref().map(|a| a.command) != Some(index)
                && self.fence_command(index).is_none()
            {
                self.deferred.push_back(frame);
                return Ok(Flow::Continue);
            }
        }
        self.message(&frame, writer, shutdown).await
    }

    /// The command `frame` is, and its values.
    fn identify(&self, frame: &[u8]) -> Result<(usize, Values), SimError> {
        let parsed = self.dialect.parse(frame)?;
        for index in 0..self.dialect.commands.len() {
            match self.dialect.read_command(index, &parsed) {
                Ok(Some(values)) => return Ok((index, values)),
                Ok(None) => {}
                Err(why) => return Err(SimError::Unknown(why)),
            }
        }
        Err(SimError::Unknown(
            String::from_utf8_lossy(frame).into_owned(),
        ))
    }

    /// The first of `element`'s expected replies with one of `outcomes`.
    fn rule(&self, element: &Element, outcomes: &[Outcome]) -> Option<usize> {
        outcomes.iter().find_map(|o| {
            element
                .expect
                .iter()
                .copied()
                // The fence's stale-epoch refusal is written by the fence alone.
                .filter(|&r| self.dialect.fence.is_none_or(|f| f.stale != r))
                .find(|&r| self.dialect.replies[r].outcome == *o)
        })
    }

    /// Answers one message (not deferred) as the dialect says.
    async fn message(
        &mut self,
        frame: &[u8],
        writer: &mut Writer<'_>,
        shutdown: &CancellationToken,
    ) -> Result<Flow, SimError> {
        if self.hung {
            return Ok(Flow::Continue);
        }
        let (index, values) = self.identify(frame)?;
        if let Some(fence) = self.fence_command(index) {
            return self.fence_message(fence, index, &values, writer).await;
        }
        if self
            .dialect
            .abort
            .as_ref()
            .is_some_and(|a| a.command == index)
        {
            return self.abort(&values, writer).await;
        }
        if let Status::Polled { command, .. } = self.dialect.status {
            if command == index {
                // Answered with the status reply that says the state now.
                writer.state = self.state_now();
                writer.status().await?;
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
        if values.contains("action") && !matches!(element.sending, Sending::Poll(_)) {
            // A message naming an action (not a poll echoing it) begins a new context.
            self.context = Values::default();
        }
        self.context.fill_from(&values);
        for (name, value) in values.iter() {
            self.context.set(name, value.to_string());
        }
        let state = self.state_now();
        if state != ControllerState::Ready && element.sending == Sending::Send {
            // A stopped controller refuses motion, as a real one does: counted, so a
            // test sees a command that reached it while stopped.
            let refused = self.stats.refused.fetch_add(1, Ordering::SeqCst) + 1;
            let command = &self.dialect.commands[index].name;
            warn!(%command, %state, refused, "a command while stopped: refused, not executed");
            let why = if self.stats.undescribed() {
                format!(
                    "refused: the robot is {}",
                    super::UNDESCRIBED_STATE.to_lowercase()
                )
            } else {
                format!("refused: the robot is in {state}")
            };
            self.answer_with(
                &element,
                writer,
                &why,
                &[Outcome::Rejected, Outcome::Failed],
            )
            .await?;
            self.count_file.update();
            return Ok(Flow::Continue);
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
        if let Some(flow) = self.fence_check(element, writer).await? {
            return Ok(flow);
        }
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
        if let Some(flow) = self.injected(writer, &id, n).await? {
            return Ok(flow);
        }
        let faults = config.fault_after.is_some_and(|limit| n == limit + 1)
            || config
                .fault_every
                .is_some_and(|every| every > 0 && n.is_multiple_of(every));
        let undescribed = !faults
            && config
                .unknown_state_every
                .is_some_and(|every| every > 0 && n.is_multiple_of(every));
        if faults || undescribed {
            return self
                .stop_controller(element, writer, &id, undescribed)
                .await;
        }
        let Some(takes) = self.takes(element, writer, &id, &action).await? else {
            return Ok(Flow::Continue);
        };
        if self.step.is_some() && self.config.reset_after.is_some_and(|limit| n == limit + 1) {
            // Reset halfway through: not executed, so not kept as run.
            self.forget_step();
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
            if simulated_error {
                let why = "simulated error (--error-every)";
                self.answer_failed(element, writer, why).await?;
            } else {
                // Not understood: refused, as a controller answers a command it cannot
                // run (its `rejected` reply where the element has one, e.g. a NAK).
                let why = format!("unknown action {action:?}");
                self.answer_with(element, writer, &why, &[Outcome::Rejected, Outcome::Failed])
                    .await?;
            }
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
                result: result.ok_or_else(|| format!("unknown action {action:?}")),
            });
            return Ok(Flow::Continue);
        }
        if let (Some(done), Some(result)) = (done_here, result) {
            let (values, step) = (self.context.clone(), self.step.take());
            if takes.is_zero() {
                self.finish(Some(done), result, &values, step, writer)
                    .await?;
            } else {
                // It ends (or is aborted) while the connection goes on reading.
                let departure = self.first_departure_look(element, &values);
                self.acting.push(Acting {
                    until: received + takes,
                    element: element.clone(),
                    done,
                    result,
                    values,
                    step,
                    departure,
                });
            }
        }
        Ok(Flow::Continue)
    }

    /// Answers with `element`'s failed (or rejected) reply.
    async fn answer_failed(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
        why: &str,
    ) -> Result<(), SimError> {
        self.answer_with(element, writer, why, &[Outcome::Failed, Outcome::Rejected])
            .await
    }

    /// Answers with `element`'s first reply of `outcomes` (failed or rejected), message
    /// `why`.
    async fn answer_with(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
        why: &str,
        outcomes: &[Outcome],
    ) -> Result<(), SimError> {
        if let Some(rule) = self.rule(element, outcomes) {
            let mut values = self.context.clone();
            values.set("message", why.to_string());
            self.settle(StepRecord::Failed(why.to_string()));
            writer.reply(rule, &values).await?;
        } else {
            warn!("the dialect has no failed reply here: the command is not answered");
        }
        Ok(())
    }
}

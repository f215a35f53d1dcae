//! Each message from the controller matched to what awaits it: the fence's answers, a
//! step's answer, the abort's, the keep-alive's, a status; anything else is a protocol
//! error (`docs/dialects.md`, section 4.4).

use tokio::time::Instant;
use tracing::{debug, warn};

use super::super::{CommandFailure, ControllerEvent, ControllerStatus};
use super::{Awaiting, Connection, ConnectionEnd, Step};
use crate::dialect::framing::Framing;
use crate::dialect::{Correlation, Outcome, Parsed, Sending, Status, Values};
use crate::shown::shown;

impl<O: super::Owner> Connection<'_, '_, O> {
    /// One message from the controller.
    pub(super) async fn incoming(&mut self, frame: &[u8]) -> Step {
        self.last_traffic = Instant::now();
        if self.banner_until.take().is_some() {
            debug!(banner = %String::from_utf8_lossy(frame), "controller banner");
            if self.dialect.status == Status::Connection
                && !self.reporter.status(ControllerStatus::Ready).await
            {
                return Err(ConnectionEnd::OwnerGone);
            }
            return Ok(());
        }
        let parsed = match self.dialect.parse(frame) {
            Ok(parsed) => parsed,
            Err(e) => return self.protocol_error(e.to_string()).await,
        };
        if let Some(step) = self.fence_incoming(&parsed).await {
            return step;
        }
        match self.answer(&parsed).await {
            Ok(true) => return Ok(()),
            Ok(false) => {}
            Err(Ok(why)) => return self.protocol_error(why).await,
            Err(Err(end)) => return Err(end),
        }
        // The abort's own answer, while one is awaited.
        if let (Some(abort), false) = (&self.dialect.abort, self.abort_waits.is_empty()) {
            for &reply in &abort.expect {
                match self.dialect.read_reply(reply, &parsed) {
                    Ok(None) => continue,
                    Ok(Some(values)) => return self.abort_answered(reply, &values).await,
                    Err(why) => return self.protocol_error(why).await,
                }
            }
        }
        // An answer to a keep-alive, whatever its outcome, frees the wire; a status or
        // ignore answer is acted on below as well.
        let mut keepalive_answered = false;
        if let Some(keepalive) = &self.dialect.keepalive {
            for &reply in &keepalive.expect {
                if let Ok(Some(_)) = self.dialect.read_reply(reply, &parsed) {
                    if matches!(self.awaiting, Some(Awaiting::Keepalive { .. })) {
                        self.awaiting = None;
                    }
                    keepalive_answered = true;
                    break;
                }
            }
        }
        match self.dialect.read_unsolicited(&parsed) {
            Ok(None) => {}
            Err(why) => return self.protocol_error(why).await,
            Ok(Some((_, _, None))) => return Ok(()),
            Ok(Some((_, values, Some(state)))) => {
                if self.dialect.status != Status::Pushed {
                    // A status read: the state is known as of now.
                    self.state_fresh = true;
                    self.poll_outstanding = false;
                }
                if matches!(self.awaiting, Some(Awaiting::StatusPoll { .. })) {
                    self.awaiting = None;
                    if let Status::Polled { every, .. } = self.dialect.status {
                        self.next_status_poll = Some(Instant::now() + every);
                    }
                }
                return self.status(state, values.get("message")).await;
            }
        }
        if keepalive_answered {
            return Ok(());
        }
        // A late answer to a command already failed (or a departure of one no longer in
        // flight) is shaped like an answer: ignored.
        for (i, reply) in self.dialect.replies.iter().enumerate() {
            if matches!(
                reply.outcome,
                Outcome::Status | Outcome::Ignore | Outcome::Fence
            ) {
                continue;
            }
            if let Ok(Some(values)) = self.dialect.read_reply(i, &parsed) {
                warn!(reply = %reply.name, id = values.get("id").unwrap_or("-"), "reply to no pending command; ignored");
                return Ok(());
            }
        }
        self.protocol_error(format!(
            "a message the dialect {} does not describe: {}",
            self.dialect.name,
            shown(
                frame,
                matches!(self.dialect.framing, Framing::LengthPrefix { .. })
            )
        ))
        .await
    }

    /// Tries `parsed` as the answer an exchange waits for. `Ok(true)`: it was;
    /// `Err(Ok(why))`: it was shaped like one but is wrong.
    ///
    /// With ids, an answer carrying an id answers the step of that id; one without an id
    /// (a `NAK` that names no command) answers the oldest step whose message on the wire
    /// has had no answer with its id yet, else the oldest on the wire. With one in
    /// flight, the answer is the request's on the wire; an id it echoes must be the
    /// command's (when the command writes its id), or the protocol is broken.
    async fn answer(&mut self, parsed: &Parsed) -> Result<bool, Result<String, ConnectionEnd>> {
        let one = self.one_in_flight();
        let unechoed = self
            .exchanges
            .iter()
            .position(|e| e.sent && !e.echoed)
            .or_else(|| self.exchanges.iter().position(|e| e.sent));
        for i in 0..self.exchanges.len() {
            let exchange = &self.exchanges[i];
            if one && self.awaiting != Some(Awaiting::Command(exchange.command.id)) {
                continue;
            }
            if !exchange.sent {
                continue;
            }
            let element = &self.dialect.sequence[exchange.element];
            for &reply in &element.expect {
                let values = match self.dialect.read_reply(reply, parsed) {
                    Ok(None) => continue,
                    Ok(Some(values)) => values,
                    Err(why) => return Err(Ok(why)),
                };
                let echoed = values.get("id");
                match (one, echoed) {
                    (false, Some(echoed))
                        if echoed.parse::<u64>().ok() != Some(exchange.command.id) =>
                    {
                        continue
                    }
                    (false, None) if unechoed != Some(i) => continue,
                    (true, Some(echoed))
                        if self.dialect.command_writes(element.command, "id")
                            && echoed.parse::<u64>().ok() != Some(exchange.command.id) =>
                    {
                        return Err(Ok(format!(
                            "the answer {} names command {echoed}, but the command on the wire is {}",
                            self.dialect.replies[reply].name, exchange.command.id
                        )));
                    }
                    _ => {}
                }
                if echoed.is_some() {
                    self.exchanges[i].echoed = true;
                }
                self.advance(i, reply, &values).await.map_err(Err)?;
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// Exchange `i`'s element was answered by `reply`.
    async fn advance(&mut self, i: usize, reply: usize, values: &Values) -> Step {
        // A stale epoch's refusal (outcome failed or rejected, as the dialect is
        // checked): reported as such, not as the step's result.
        let stale = match self.dialect.fence.is_some_and(|f| f.stale == reply) {
            true => {
                let current = values
                    .get("epoch")
                    .and_then(|e| e.parse().ok())
                    .map(super::super::Epoch);
                self.deposed(current).await;
                Some(CommandFailure::StaleEpoch { current })
            }
            false => None,
        };
        let rule = &self.dialect.replies[reply];
        let now = Instant::now();
        for (j, other) in self.exchanges.iter_mut().enumerate() {
            other.others_answered |= j != i;
        }
        let exchange = &mut self.exchanges[i];
        let id = exchange.command.id;
        if rule.outcome == Outcome::Departed {
            // Not an answer: the command stays in flight as it was (on a one-in-flight
            // wire its request still awaits its answer), its deadline unchanged.
            if std::mem::replace(&mut exchange.departed, true) {
                debug!(id, reply = %rule.name, "the controller says again the move left its origin; told once");
                return Ok(());
            }
            debug!(id, reply = %rule.name, "the move left its origin");
            return self.report(ControllerEvent::Departed { id }).await;
        }
        if self.awaiting == Some(Awaiting::Command(id)) {
            self.awaiting = None;
        }
        debug!(id, reply = %rule.name, outcome = ?rule.outcome, "answer from controller");
        let element = &self.dialect.sequence[exchange.element];
        match rule.outcome {
            Outcome::Accepted | Outcome::Running => {
                let last = exchange.element + 1 == self.dialect.sequence.len();
                match (element.sending, rule.outcome) {
                    (Sending::Poll(every), _) => {
                        // The action goes on: poll again later; the wire is free meanwhile.
                        exchange.sent = false;
                        exchange.poll_at = Some(now + every);
                    }
                    (Sending::Send, Outcome::Accepted) if !last => {
                        exchange.element += 1;
                        exchange.sent = false;
                    }
                    _ => {
                        // The end of this element comes in a later message.
                        if self.dialect.correlation == Correlation::OneInFlight {
                            self.awaiting = Some(Awaiting::Command(id));
                        }
                    }
                }
                Ok(())
            }
            Outcome::Done => {
                let result = self
                    .dialect
                    .evaluate(&rule.result, values, &exchange.values);
                if let Some(mut exchange) = self.exchanges.remove(i) {
                    self.remember(&mut exchange);
                }
                self.report(ControllerEvent::Reply {
                    id,
                    result,
                    message: None,
                })
                .await
            }
            Outcome::Failed | Outcome::Rejected => {
                let message = self
                    .dialect
                    .evaluate(&rule.message, values, &exchange.values);
                let message = match (rule.outcome, message.is_empty()) {
                    (Outcome::Rejected, _) => Some(format!("refused the command: {message}")),
                    (_, true) => None,
                    (_, false) => Some(message),
                };
                if let Some(mut exchange) = self.exchanges.remove(i) {
                    self.remember(&mut exchange);
                }
                if let Some(failure) = stale {
                    return self
                        .report(ControllerEvent::CommandFailed { id, failure })
                        .await;
                }
                self.report(ControllerEvent::Reply {
                    id,
                    result: schemas::robot::RESULT_ERROR.into(),
                    message,
                })
                .await
            }
            Outcome::Departed | Outcome::Status | Outcome::Ignore | Outcome::Fence => Ok(()),
        }
    }
}

//! An abort on the connection (PackML Abort): the dialect's abort message written at
//! once, its own reply awaited where the dialect has one, and the commands it stops
//! ended as the controller reports them.

use tokio::time::Instant;
use tracing::{debug, info, warn};

use super::super::{CommandFailure, ControllerEvent};
use super::{Awaiting, Connection, Step};
use crate::dialect::{Outcome, Values};

/// An abort message whose own reply is awaited.
pub(super) struct AbortWait {
    /// The commands it stops (those in flight when it was sent; none when nothing was).
    pub(super) ids: Vec<u64>,
    /// When the controller must have answered it.
    pub(super) deadline: Instant,
}

impl<O: super::Owner> Connection<'_, '_, O> {
    /// An abort: the dialect's abort message goes out at once, once for each distinct
    /// message the commands in flight make of it (or with the last command's values when
    /// none is in flight); the commands in flight are marked aborted.
    pub(super) async fn abort(&mut self) -> Step {
        let Some(abort) = &self.dialect.abort else {
            warn!(dialect = %self.dialect.name, "abort asked: the dialect has no abort message; the command in flight runs to its end");
            return Ok(());
        };
        let now = Instant::now();
        // What the abort is written with: each command on the controller.
        let mut targets: Vec<(Option<u64>, &Values)> = Vec::new();
        for exchange in self.exchanges.iter_mut() {
            exchange.aborted = true;
        }
        for exchange in self.exchanges.iter().filter(|e| e.reached()) {
            targets.push((Some(exchange.command.id), &exchange.values));
        }
        if targets.is_empty() {
            match self.last_run.as_ref() {
                Some(values) => targets.push((None, values)),
                None if self.exchanges.is_empty() => {
                    debug!(dialect = %self.dialect.name, "abort asked: nothing has run on the controller; nothing is sent");
                    return Ok(());
                }
                // Commands waiting for the wire: they end without a word to the controller.
                None => {}
            }
        }
        let mut messages: Vec<(Vec<u8>, Vec<u64>)> = Vec::new();
        let mut unwritable = Vec::new();
        for (id, values) in targets {
            match self.dialect.write_command(abort.command, values) {
                Ok(bytes) => match messages.iter_mut().find(|(written, _)| *written == bytes) {
                    Some((_, ids)) => ids.extend(id),
                    None => messages.push((bytes, id.into_iter().collect())),
                },
                Err(why) => {
                    warn!(id, error = %why, "the abort cannot be written for this command; it runs to its end");
                    unwritable.extend(id);
                }
            }
        }
        for exchange in self.exchanges.iter_mut() {
            if unwritable.contains(&exchange.command.id) {
                exchange.aborted = false;
            }
        }
        for (bytes, ids) in messages {
            info!(dialect = %self.dialect.name, commands = ?ids, "abort sent to the controller");
            self.outbox.push(bytes);
            self.last_traffic = now;
            if !abort.expect.is_empty() {
                self.abort_waits.push_back(AbortWait {
                    ids,
                    deadline: now + self.config.command_timeout,
                });
            }
        }
        Ok(())
    }

    /// The abort's own reply `reply` came: the controller stopped (`accepted`), and the
    /// commands that abort stops end as aborted; or it had nothing to stop, and they go on.
    pub(super) async fn abort_answered(&mut self, reply: usize, values: &Values) -> Step {
        let id = values.get("id").and_then(|id| id.parse::<u64>().ok());
        let at = id
            .and_then(|id| self.abort_waits.iter().position(|w| w.ids.contains(&id)))
            .unwrap_or(0);
        let Some(wait) = self.abort_waits.remove(at) else {
            return Ok(());
        };
        let rule = &self.dialect.replies[reply];
        if rule.outcome != Outcome::Accepted {
            let message = self
                .dialect
                .evaluate(&rule.message, values, &Values::default());
            info!(reply = %rule.name, %message, commands = ?wait.ids, "the controller had nothing to stop; the commands in flight go on");
            return Ok(());
        }
        info!(reply = %rule.name, commands = ?wait.ids, "the controller stopped");
        for id in wait.ids {
            if let Some(i) = self.exchanges.iter().position(|e| e.command.id == id) {
                self.end_aborted(i).await?;
            }
        }
        Ok(())
    }

    /// Ends exchange `i` as aborted.
    pub(super) async fn end_aborted(&mut self, i: usize) -> Step {
        let Some(mut exchange) = self.exchanges.remove(i) else {
            return Ok(());
        };
        let id = exchange.command.id;
        if self.awaiting == Some(Awaiting::Command(id)) {
            self.awaiting = None;
        }
        self.remember(&mut exchange);
        info!(id, "command aborted");
        self.report(ControllerEvent::CommandFailed {
            id,
            failure: CommandFailure::Aborted,
        })
        .await
    }
}

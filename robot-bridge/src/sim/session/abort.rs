//! The dialect's abort on a simulated controller's connection (PackML Abort): the
//! action under way stops at once and is not executed.

use std::sync::atomic::Ordering;

use tracing::info;

use super::super::writer::Writer;
use super::super::SimError;
use super::{Flow, Session};
use crate::dialect::{Outcome, Values};

impl Session<'_> {
    /// The dialect's abort, with the values it carries: the action under way (the one it
    /// names, where it names one) stops at once and is not executed; its command is
    /// answered with its `failed` reply (`aborted`), or, polled, its program just stops;
    /// the abort is answered with its `accepted` reply when something stopped, its
    /// `rejected` reply when nothing ran.
    pub(super) async fn abort(
        &mut self,
        values: &Values,
        writer: &mut Writer<'_>,
    ) -> Result<Flow, SimError> {
        let Some(abort) = &self.dialect.abort else {
            return Ok(Flow::Continue);
        };
        let rule = |outcome: Outcome| {
            abort
                .expect
                .iter()
                .copied()
                .find(|&r| self.dialect.replies[r].outcome == outcome)
        };
        let (stopped, nothing) = (rule(Outcome::Accepted), rule(Outcome::Rejected));
        let mut answer = values.clone();
        answer.fill_from(&self.context);
        // Where the dialect has ids, the abort names the command it stops.
        let this_one = values
            .get("id")
            .is_none_or(|id| Some(id) == self.context.get("id"));
        let now = std::time::Instant::now();
        let under_way = this_one
            && (self.acting.is_some()
                || self
                    .running
                    .as_ref()
                    .is_some_and(|r| now < r.until && r.result.is_ok()));
        let id = self.context.get("id").unwrap_or("-").to_string();
        let action = self.context.get("action").unwrap_or("").to_string();
        if under_way && self.config.abort_too_late {
            // The action ends as the abort comes: its done crosses the abort on the wire.
            info!(%id, %action, "the action ended before the abort (abort_too_late)");
            self.end_action(writer).await?;
            if let Some(running) = &mut self.running {
                running.until = now;
            }
        } else if under_way {
            self.stats.aborted.fetch_add(1, Ordering::SeqCst);
            info!(%id, %action, "action aborted");
            if let Some(physics) = &self.config.physics {
                // An aborted move is left where it stopped; the abort itself is said.
                physics.0.end(false);
            }
            if let Some(acting) = self.acting.take() {
                self.answer_failed(&acting.element, writer, "aborted")
                    .await?;
            } else if stopped.is_some() {
                // The program stops; the abort's answer says so.
                self.running = None;
            } else if let Some(running) = &mut self.running {
                // The next poll finds it failed.
                running.until = now;
                running.result = Err("aborted".into());
            }
            if let Some(rule) = stopped {
                writer.reply(rule, &answer).await?;
            }
            self.count_file.update();
            return Ok(Flow::Continue);
        } else {
            info!(%id, "abort with nothing under way");
        }
        if let Some(rule) = nothing {
            answer.set("message", "nothing to stop".into());
            writer.reply(rule, &answer).await?;
        }
        Ok(Flow::Continue)
    }
}

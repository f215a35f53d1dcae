//! The dialect's abort on a simulated controller's connection (PackML Abort): the
//! actions under way that it names stop at once and are not executed.

use std::sync::atomic::Ordering;

use tracing::info;

use super::super::writer::Writer;
use super::super::SimError;
use super::{Flow, Session};
use crate::dialect::{Outcome, Values};

impl Session<'_> {
    /// The dialect's abort, with the values it carries. It names the actions it stops:
    /// where it carries an id, the one with that id; where it carries none, every one
    /// under way.
    ///
    /// | under way | what it does |
    /// |---|---|
    /// | actions it names | each stops at once, not executed (counted aborted, each), its command answered with its own `failed` reply (`aborted`); the abort gets its `accepted` reply |
    /// | a polled program | it just stops (or, where the abort has no reply, its next poll finds it failed) |
    /// | (`abort_too_late`) actions it names | each ends just before: its `done` crosses the abort on the wire |
    /// | nothing it names | nothing stops; the abort gets its `rejected` reply |
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
        let names = |of: &Values| values.get("id").is_none_or(|id| Some(id) == of.get("id"));
        let now = std::time::Instant::now();
        let (named, others) = std::mem::take(&mut self.acting)
            .into_iter()
            .partition::<Vec<_>, _>(|a| names(&a.values));
        self.acting = others;
        let polled = names(&self.context)
            && self
                .running
                .as_ref()
                .is_some_and(|r| now < r.until && r.result.is_ok());
        if (polled || !named.is_empty()) && self.config.abort_too_late {
            // Each ends as the abort comes: its done crosses the abort on the wire.
            for acting in named {
                let id = acting.values.get("id").unwrap_or("-").to_string();
                info!(%id, "the action ended before the abort (abort_too_late)");
                self.end_or_keep(acting, writer).await?;
            }
            if let Some(running) = &mut self.running {
                running.until = now;
            }
        } else if polled || !named.is_empty() {
            for acting in named {
                let id = acting.values.get("id").unwrap_or("-");
                let action = acting.values.get("action").unwrap_or("");
                info!(%id, %action, "action aborted");
                self.stats.aborted.fetch_add(1, Ordering::SeqCst);
                if let Some(physics) = &self.config.physics {
                    // An aborted move is left where it stopped; the abort itself is said.
                    physics.0.end(&acting.values, false);
                }
                self.answer_aborted(acting, writer).await?;
            }
            if polled {
                self.abort_polled(stopped.is_some());
            }
            if let Some(rule) = stopped {
                writer.reply(rule, &answer).await?;
            }
            self.count_file.update();
            return Ok(Flow::Continue);
        } else {
            let id = self.context.get("id").unwrap_or("-");
            info!(%id, "abort with nothing under way");
        }
        if let Some(rule) = nothing {
            answer.set("message", "nothing to stop".into());
            writer.reply(rule, &answer).await?;
        }
        Ok(Flow::Continue)
    }

    /// The polled program under way is aborted: it stops (`said`: the abort's own reply
    /// says so), or its next poll finds it failed.
    fn abort_polled(&mut self, said: bool) {
        self.stats.aborted.fetch_add(1, Ordering::SeqCst);
        let id = self.context.get("id").unwrap_or("-");
        let action = self.context.get("action").unwrap_or("");
        info!(%id, %action, "action aborted");
        if let Some(physics) = &self.config.physics {
            physics.0.end(&self.context, false);
        }
        if said {
            // The program stops; the abort's answer says so.
            self.running = None;
        } else if let Some(running) = &mut self.running {
            // The next poll finds it failed.
            running.until = std::time::Instant::now();
            running.result = Err("aborted".into());
        }
    }
}

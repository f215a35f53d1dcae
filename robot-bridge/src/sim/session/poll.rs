//! A poll for the end of the action under way, in a dialect whose actions end by a poll
//! ([`super::Running`]: one at a time, as a poll names no action).

use super::super::writer::Writer;
use super::super::SimError;
use super::{Flow, Session};
use crate::dialect::{Element, Outcome};

impl Session<'_> {
    /// A poll for the end of the action under way.
    pub(super) async fn poll(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
    ) -> Result<Flow, SimError> {
        let done = self.rule(element, &[Outcome::Done]);
        // Held up in the plant (a pallet waiting on its way): not ended yet.
        let held = self.running.is_some()
            && self
                .config
                .physics
                .as_ref()
                .is_some_and(|p| p.0.held(&self.context));
        match &self.running {
            Some(running) if std::time::Instant::now() < running.until || held => {
                if let Some(rule) = self.rule(element, &[Outcome::Running, Outcome::Accepted]) {
                    let context = self.context.clone();
                    writer.reply(rule, &context).await?;
                }
            }
            Some(_) => {
                let result = self.running.take().expect("matched").result;
                match result {
                    Ok(result) => {
                        let values = self.context.clone();
                        // Unanswered (no done reply), the step stays as it is.
                        let step = done.and_then(|_| self.step.take());
                        self.finish(done, result, &values, step, writer).await?
                    }
                    Err(why) => {
                        self.answer_failed(element, writer, &why).await?;
                        self.count_file.update();
                    }
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

//! The fence on a simulated controller's connection (`--fenced`): claims, heartbeats and
//! step status answered at once (even while actions are under way), every command's
//! epoch checked and its step id run at most once ([`crate::sim::fence`]). Each action
//! under way keeps its own step id, recorded as running until that action ends.

use tracing::{info, warn};

use super::super::fence::{ClaimAnswer, CommandCheck, StepRecord};
use super::super::writer::Writer;
use super::super::SimError;
use super::{Flow, Session};
use crate::dialect::{Element, Fence, Outcome, Values};
use crate::fence_wire::{
    valid_token, MAX_NAME_BYTES, MAX_STEP_BYTES, REASON_HELD, REASON_INVALID, REASON_NOT_FENCED,
    REASON_STALE_EPOCH, STEP_DONE, STEP_FAILED, STEP_RUNNING, STEP_UNKNOWN,
};

impl Session<'_> {
    /// The dialect's fence, if the message `index` is one of its commands.
    pub(super) fn fence_command(&self, index: usize) -> Option<Fence> {
        self.dialect
            .fence
            .filter(|f| [f.claim, f.heartbeat, f.step_status].contains(&index))
    }

    /// Any message from the holon is life: the holder's lease starts again.
    pub(super) fn seen(&self) {
        if let Some(book) = self.stats.fence().as_mut() {
            book.seen(self.session, std::time::Instant::now());
        }
    }

    /// A fence message: claim, heartbeat or step status.
    pub(super) async fn fence_message(
        &mut self,
        fence: Fence,
        index: usize,
        values: &Values,
        writer: &mut Writer<'_>,
    ) -> Result<Flow, SimError> {
        if let Some((rule, answer)) = self.fence_answer(fence, index, values) {
            if rule == fence.granted {
                // The epoch is on disk before anyone holds it.
                super::super::write_count_file(self.config, self.stats);
                if let Some(physics) = &self.config.physics {
                    physics.0.epoch_granted();
                }
            }
            writer.reply(rule, &answer).await?;
        }
        Ok(Flow::Continue)
    }

    /// What a fence message is answered (None: nothing, a heartbeat of the holder).
    fn fence_answer(&self, fence: Fence, index: usize, values: &Values) -> Option<(usize, Values)> {
        let now = std::time::Instant::now();
        let refuse = |epoch: u64, reason: &str| {
            let mut v = Values::default();
            v.set("epoch", epoch.to_string());
            v.set("reason", reason.to_string());
            v
        };
        let answer = {
            let mut guard = self.stats.fence();
            let Some(book) = guard.as_mut() else {
                info!("a fence message to an unfenced controller: refused not_fenced");
                return Some((fence.refused, refuse(0, REASON_NOT_FENCED)));
            };
            if index == fence.claim {
                let name = values.get("name").unwrap_or("");
                if !valid_token(name, MAX_NAME_BYTES) {
                    warn!(name = %name.chars().take(80).collect::<String>(), "a claim with an invalid name: refused");
                    (fence.refused, refuse(book.epoch(), REASON_INVALID))
                } else {
                    match book.claim(self.session, name, now) {
                        ClaimAnswer::Granted { epoch } => {
                            info!(session = self.session, %name, epoch, "claim granted");
                            let mut v = Values::default();
                            v.set("epoch", epoch.to_string());
                            v.set("lease_ms", book.lease.as_millis().to_string());
                            (fence.granted, v)
                        }
                        ClaimAnswer::Held { epoch, holder } => {
                            info!(session = self.session, %name, %holder, epoch, "claim refused: held by a live session");
                            (fence.refused, refuse(epoch, REASON_HELD))
                        }
                    }
                }
            } else if index == fence.heartbeat {
                let epoch = values.get("epoch").and_then(|e| e.parse().ok());
                if book.heartbeat(self.session, epoch, now) {
                    return None;
                }
                info!(
                    session = self.session,
                    ?epoch,
                    "a heartbeat with no claim: refused stale_epoch"
                );
                (fence.refused, refuse(book.epoch(), REASON_STALE_EPOCH))
            } else {
                let step = values.get("step").unwrap_or("");
                if !valid_token(step, MAX_STEP_BYTES) {
                    (fence.refused, refuse(book.epoch(), REASON_INVALID))
                } else {
                    let mut v = Values::default();
                    v.set("step", step.to_string());
                    let state = match book.step(step) {
                        None => STEP_UNKNOWN,
                        Some(StepRecord::Running) => STEP_RUNNING,
                        Some(StepRecord::Done(result)) => {
                            v.set("result", result.clone());
                            STEP_DONE
                        }
                        Some(StepRecord::Failed(message)) => {
                            v.set("message", message.clone());
                            STEP_FAILED
                        }
                    };
                    v.set("step_state", state.to_string());
                    (fence.step_state, v)
                }
            }
        };
        Some(answer)
    }

    /// Before a command begins (fenced mode): a stale epoch is refused, a step id already
    /// known gets its stored outcome, a new one is recorded as running. `Some`: the
    /// command was answered here and does not run.
    pub(super) async fn fence_check(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
    ) -> Result<Option<Flow>, SimError> {
        let Some(fence) = self.dialect.fence else {
            return Ok(None);
        };
        let id = self.context.get("id").unwrap_or("-").to_string();
        let stored = match self.check_in_book() {
            Checked::Unfenced | Checked::Runs => return Ok(None),
            Checked::Stale(current) => {
                let epoch = self.context.get("epoch").unwrap_or("none");
                info!(%id, session = self.session, %epoch, current, "command refused: stale_epoch (not executed)");
                let mut v = self.context.clone();
                v.set("epoch", current.to_string());
                writer.reply(fence.stale, &v).await?;
                self.count_file.update();
                return Ok(Some(Flow::Continue));
            }
            Checked::Invalid(why) => Err(why),
            Checked::Known(record) => Ok(record),
        };
        match stored {
            Err(why) => {
                self.answer_failed(element, writer, &why).await?;
                Ok(Some(Flow::Continue))
            }
            Ok(record) => {
                let step = self.context.get("step").unwrap_or("").to_string();
                info!(%id, %step, ?record, "a step id already known: its stored outcome, not executed again");
                match record {
                    Some(StepRecord::Done(result)) => {
                        if let Some(rule) = self.rule(element, &[Outcome::Done]) {
                            let mut v = self.context.clone();
                            v.set("result", result);
                            writer.reply(rule, &v).await?;
                        }
                    }
                    Some(StepRecord::Failed(message)) => {
                        self.answer_failed(element, writer, &message).await?;
                    }
                    Some(StepRecord::Running) | None => {
                        self.answer_failed(
                            element,
                            writer,
                            "step_running: the step is still running; ask step_status",
                        )
                        .await?;
                    }
                }
                Ok(Some(Flow::Continue))
            }
        }
    }

    /// The command's epoch and step id against the book (no await while it is locked).
    fn check_in_book(&mut self) -> Checked {
        let epoch = self
            .context
            .get("epoch")
            .and_then(|e| e.parse::<u64>().ok());
        let step = self.context.get("step").map(str::to_string);
        let mut guard = self.stats.fence();
        let Some(book) = guard.as_mut() else {
            return Checked::Unfenced;
        };
        let now = std::time::Instant::now();
        if let CommandCheck::Stale { epoch: current } = book.check_command(self.session, epoch, now)
        {
            return Checked::Stale(current);
        }
        let Some(step) = step else {
            return Checked::Runs;
        };
        if !valid_token(&step, MAX_STEP_BYTES) {
            Checked::Invalid(format!(
                "invalid step id {:?}",
                step.chars().take(80).collect::<String>()
            ))
        } else if book.begin_step(&step) {
            drop(guard);
            self.step = Some(step);
            Checked::Runs
        } else {
            Checked::Known(book.step(&step).cloned())
        }
    }

    /// The step of the command being begun ended (`Done` counts as its execution).
    pub(super) fn settle(&mut self, record: StepRecord) {
        let step = self.step.take();
        self.settle_step(step, record);
    }

    /// The step `step` (an action's, if it has one) ended (`Done` counts as its
    /// execution).
    pub(super) fn settle_step(&self, step: Option<String>, record: StepRecord) {
        let Some(step) = step else { return };
        if let Some(book) = self.stats.fence().as_mut() {
            book.settle(&step, record);
        }
    }

    /// The step under way did not begin after all (a fault before the action).
    pub(super) fn forget_step(&mut self) {
        let Some(step) = self.step.take() else { return };
        if let Some(book) = self.stats.fence().as_mut() {
            book.forget(&step);
        }
    }

    /// When this session's lease ends, if it holds the claim.
    pub(super) fn lease_end(&self) -> Option<std::time::Instant> {
        self.stats
            .fence()
            .as_ref()
            .and_then(|f| f.lease_end(self.session))
    }

    /// The lease timer fired: true if the holder stayed silent and lost the claim (the
    /// connection is then closed, so late packets die with it).
    pub(super) fn lease_expired(&self) -> bool {
        let mut guard = self.stats.fence();
        let Some(book) = guard.as_mut() else {
            return false;
        };
        let now = std::time::Instant::now();
        if book.lease_end(self.session).is_some_and(|end| end <= now) {
            book.release(self.session);
            warn!(
                session = self.session,
                "the holder was silent past its lease: the claim is lost, the connection closed"
            );
            return true;
        }
        false
    }
}

/// A command checked against the fence.
enum Checked {
    /// No fence: it runs as ever.
    Unfenced,
    /// The holder's epoch, and a new step id (or none): it runs.
    Runs,
    /// Refused: the controller's epoch.
    Stale(u64),
    /// A step id that is not one.
    Invalid(String),
    /// A step id already known: its record.
    Known(Option<StepRecord>),
}

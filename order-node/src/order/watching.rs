//! Watching a step (or a move) for its result: the inbox, its provider's presence, its
//! turn on the provider's agenda and a new holder of a fenced provider, for a pause. A
//! move's `departed` on the way releases the place at its origin and the watch goes on
//! (docs/material-flow.md, "Departure"); it never ends an attempt.

use std::time::Duration;

use schemas::HolonId;
use tokio::sync::broadcast;
use tokio::time::Instant;
use tracing::info;

use super::{Leg, OrderTask};
use crate::context::OrderError;
use crate::inbox::{Judged, ResultReport};
use crate::progress::{Phase, StepOutcome};

/// How a watch for a result ended.
pub(super) enum Watched {
    /// The pause is over (or, before the start, it is this order's turn).
    Elapsed,
    /// Before the start: the resource published that the step runs (it began on its
    /// turn).
    Began,
    /// Started: the provider came back (its token returned, or a holder of a higher
    /// epoch serves it): it is asked what became of the step.
    CameBack,
    /// Something ended the attempt; a result to acknowledge once recorded.
    Ended(StepOutcome, Option<Box<ResultReport>>),
}

impl OrderTask<'_> {
    /// Whether the part's move is booked on `provider`, its start not recorded.
    fn move_booked_on(&self, provider: &HolonId) -> bool {
        let progress = self.progress.get();
        let moving = progress.part.as_ref().and_then(|p| p.moving.as_ref());
        moving.is_some_and(|m| matches!(&m.phase, Phase::Booked(p) if p == provider))
    }

    /// Pauses `pause`, watching the inbox (results of this conversation) and the
    /// provider's presence. A provider that vanishes while the step `may_run` (started,
    /// or booked to start on its turn) gets `vanished_grace` to come back and report
    /// before the attempt counts as lost.
    /// Before `started`, the pause also ends when the provider publishes that it is
    /// free with this conversation first; once `started`, when the provider comes back
    /// after it was gone, or a holder of a higher epoch than when the watch began
    /// publishes its state (it may not know the step: the order asks).
    /// A move's `departed` from its transporter releases the place at the move's origin
    /// (journalled first) and the watch goes on; a step's is acknowledged and ignored:
    /// a departure never ends an attempt. Errs only when the journal cannot record.
    pub(super) async fn await_outcome(
        &mut self,
        provider: &HolonId,
        conversation_id: &str,
        pause: Duration,
        started: bool,
        may_run: bool,
    ) -> Result<Watched, OrderError> {
        if started {
            if let Some(report) = self.early_departure.take() {
                // The departure that said the move began: its start is recorded now.
                self.move_departed(provider, report).await?;
            }
        }
        let ctx = self.ctx.clone();
        let worked_with = self.progress.get().worked_with.clone();
        let until = Instant::now() + pause;
        // Booked, not started: the pause ends early when the resource says it is our
        // turn, or that our step runs.
        let turn = async {
            if started {
                std::future::pending().await
            } else {
                ctx.presence.turn(provider, conversation_id).await
            }
        };
        tokio::pin!(turn);
        let new_holder = async {
            if started {
                ctx.presence
                    .new_holder(provider, ctx.presence.epoch(provider))
                    .await
            } else {
                std::future::pending().await
            }
        };
        tokio::pin!(new_holder);
        let lost = |why: &str| {
            Watched::Ended(
                StepOutcome::Lost {
                    provider: provider.clone(),
                    why: why.into(),
                },
                None,
            )
        };
        // How long a provider that is gone may take to come back: one that runs the
        // step may report it; one handed over to its successor (an upgrade) keeps the
        // booking, for the handover grace.
        let grace = || {
            let running = if may_run {
                ctx.settings.vanished_grace
            } else {
                Duration::ZERO
            };
            if ctx.presence.handing_over(provider) {
                running.max(ctx.settings.handover_grace)
            } else {
                running
            }
        };
        // A fenced provider that vanished may still run the step (its holder cut from
        // the cell, not from the controller, or frozen with the step on the
        // controller): the step is not given up, it waits for a holder's word (its
        // result, or a holder that never ran it) as if the provider were there. Known
        // from this node's presence, or from the order's journal (a node that took the
        // order over may not have heard the provider before it vanished).
        let fenced = may_run
            && (ctx.presence.fenced(provider) || self.progress.get().fenced.contains(provider));
        let gone = |alive: bool| (!alive && !fenced).then(|| Instant::now() + grace());
        // Whether the provider was last seen gone, and when its grace ends.
        let mut away = !ctx.presence.is_alive(provider);
        let mut gone_until = gone(!away);
        loop {
            // While the provider is gone, asking it is pointless: a booked step waits
            // out the grace whatever its pause (a pause that ended it would start the
            // grace over with the next watch), a started one at most its step timeout.
            let deadline = match gone_until {
                None => until,
                Some(gone) if started => gone.min(until),
                Some(gone) => gone,
            };
            tokio::select! {
                news = &mut turn => return Ok(match news {
                    crate::presence::TurnNews::Turn => Watched::Elapsed,
                    crate::presence::TurnNews::Began => Watched::Began,
                }),
                () = &mut new_holder => return Ok(Watched::CameBack),
                _ = tokio::time::sleep_until(deadline) => {
                    if gone_until.is_some_and(|g| Instant::now() >= g) {
                        return Ok(lost("the resource vanished"));
                    }
                    return Ok(Watched::Elapsed);
                }
                report = self.inbox.reports.recv() => {
                    let Some(report) = report else { return Ok(lost("inbox closed")) };
                    match crate::inbox::judge(report, provider, &worked_with, conversation_id).await {
                        Some(Judged::Ended(outcome, report)) => {
                            return Ok(Watched::Ended(outcome, Some(Box::new(report))));
                        }
                        Some(Judged::Departed(report)) if self.leg == Leg::Move => {
                            if !started && self.move_booked_on(provider) {
                                // Booked to start on its turn, and its start not seen
                                // yet: the departure says it began. Applied once the
                                // start is recorded (the part in transit).
                                info!(holon = %self.holon, %conversation_id, message_type = %report.message.message_type, "the move departed before its start was seen: it began");
                                if let Some(earlier) = self.early_departure.replace(report) {
                                    earlier.acknowledge().await;
                                }
                                return Ok(Watched::Began);
                            }
                            self.move_departed(provider, report).await?;
                        }
                        Some(Judged::Departed(report)) => {
                            info!(holon = %self.holon, %conversation_id, message_type = %report.message.message_type, "a departure for a step that moves nothing: acknowledged and ignored");
                            report.acknowledge().await;
                        }
                        None => {}
                    }
                }
                change = self.changes.recv() => match change {
                    Ok((holon, alive)) if &holon == provider => {
                        // A started step's provider back after being away: ask it.
                        if alive && started && away {
                            return Ok(Watched::CameBack);
                        }
                        away = !alive;
                        gone_until = gone(alive);
                    }
                    Ok(_) => {}
                    Err(broadcast::error::RecvError::Lagged(_)) => {
                        if gone_until.is_none() {
                            gone_until = gone(ctx.presence.is_alive(provider));
                        }
                    }
                    Err(broadcast::error::RecvError::Closed) => return Ok(Watched::Elapsed),
                },
            }
        }
    }
}

//! How long an action takes and how it ends: its delay, the plant's say in it (a move's
//! travel, a physical refusal, a move held up), the actions under way at once
//! ([`Acting`]), each ended on its own, and actions that complete after their connection
//! is gone.

use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::super::fence::StepRecord;
use super::super::physics::Report;
use super::super::writer::Writer;
use super::super::SimError;
use super::Session;
use crate::dialect::{Element, Outcome, Values};

/// An action under way whose `done` reply answers the message that began it.
pub(super) struct Acting {
    /// When its time is up (it ends then, unless held up in the plant).
    pub(super) until: std::time::Instant,
    /// The element that began it: its `done` and `failed` replies answer it.
    pub(super) element: Element,
    /// The `done` reply.
    pub(super) done: usize,
    /// Its result.
    pub(super) result: &'static str,
    /// The values of the command that began it (its id, action, part): its replies
    /// say them, and the plant knows it by them.
    pub(super) values: Values,
    /// (Fenced) its step id, recorded as running until it ends.
    pub(super) step: Option<String>,
    /// When to look again whether its move has left its origin, to say so with the
    /// element's `departed` reply; None: not looked for (said already, or the dialect
    /// has no such reply here, or there is no plant to ask).
    pub(super) departure: Option<std::time::Instant>,
}

/// How soon an action held up in the plant is looked at again.
pub(super) const HELD_RECHECK: Duration = Duration::from_millis(50);

/// How soon a move not yet off its origin is looked at again for its departure: the
/// order frees the origin's place when told, so a late word keeps a station's port
/// held (at 20x, 10 ms of wall time is 0.2 s of the plant's).
pub(super) const DEPARTURE_RECHECK: Duration = Duration::from_millis(10);

/// Waits until `done` (an action's end) to within about a tenth of a millisecond.
/// tokio's timer rounds a sleep up to its next millisecond tick (a 20 ms action took
/// 21.4 ms, which a benchmark of robots that take time would charge to the control),
/// so the last 2 ms are slept on a blocking thread.
pub(super) async fn act_for(done: std::time::Instant) {
    if let Some(coarse) = done.checked_sub(Duration::from_millis(2)) {
        tokio::time::sleep_until(coarse.into()).await;
    }
    let rest = done.saturating_duration_since(std::time::Instant::now());
    if !rest.is_zero() {
        if let Err(e) = tokio::task::spawn_blocking(move || std::thread::sleep(rest)).await {
            warn!(error = %e, "the action's last moments were cut short");
        }
    }
}

impl Session<'_> {
    /// How long the action takes (its delay, the plant's travel time, a changeover), or
    /// None when the plant does not allow it: then it is answered failed, in the plant's
    /// words (nothing to pick, a full place), and not executed, as a controller reports a
    /// physical error.
    pub(super) async fn takes(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
        id: &str,
        action: &str,
    ) -> Result<Option<Duration>, SimError> {
        let config = self.config;
        let mut takes = config
            .action_delays
            .get(action)
            .copied()
            .unwrap_or(config.delay);
        if let Some(physics) = &config.physics {
            match physics.0.begin(action, &self.context) {
                Ok(Some(travel)) => takes = travel,
                Ok(None) => {}
                Err(why) => {
                    info!(%id, %action, %why, "physically impossible");
                    self.answer_failed(element, writer, &why).await?;
                    self.count_file.update();
                    return Ok(None);
                }
            }
        }
        if self.stats.change_to(self.context.get("program")) {
            info!(%id, program = self.context.get("program").unwrap_or(""), changeover = ?config.changeover, "changing over");
            takes += config.changeover;
        }
        Ok(Some(takes))
    }

    /// When the first action under way is due to end, or to be looked at for its
    /// departure (None: none is under way).
    pub(super) fn next_end(&self) -> Option<std::time::Instant> {
        self.acting
            .iter()
            .map(|a| a.departure.map_or(a.until, |at| at.min(a.until)))
            .min()
    }

    /// When an action begun now by `element` with `values` is first looked at for its
    /// departure: None where nothing would say it (no plant, no `departed` reply in
    /// `element`, or not a move: its command names no origin, `info.from`).
    pub(super) fn first_departure_look(
        &self,
        element: &Element,
        values: &Values,
    ) -> Option<std::time::Instant> {
        let said = self.config.physics.is_some()
            && values.get("info.from").is_some()
            && self.rule(element, &[Outcome::Departed]).is_some();
        said.then(|| std::time::Instant::now() + DEPARTURE_RECHECK)
    }

    /// Looks whether `acting`'s move has left its origin: if the plant says so, its
    /// `departed` reply (its id), once; if not, looked at again shortly.
    async fn look_departed(
        &self,
        acting: &mut Acting,
        writer: &mut Writer<'_>,
    ) -> Result<(), SimError> {
        let (Some(physics), Some(rule)) = (
            &self.config.physics,
            self.rule(&acting.element, &[Outcome::Departed]),
        ) else {
            acting.departure = None;
            return Ok(());
        };
        if !physics.0.departed(&acting.values) {
            acting.departure = Some(std::time::Instant::now() + DEPARTURE_RECHECK);
            return Ok(());
        }
        acting.departure = None;
        info!(
            id = acting.values.get("id").unwrap_or("-"),
            part = acting.values.get("info.part").unwrap_or("-"),
            "the move left its origin"
        );
        writer.reply(rule, &acting.values).await
    }

    /// Whether another action may begin: fewer than `actions_at_once` are under way.
    pub(super) fn has_room(&self) -> bool {
        self.acting.len() < self.config.actions_at_once
    }

    /// Whether the plant holds `acting` up (a jammed track under its move).
    fn held(&self, acting: &Acting) -> bool {
        self.config
            .physics
            .as_ref()
            .is_some_and(|p| p.0.held(&acting.values))
    }

    /// The connection is gone while actions are under way: like a real robot, the
    /// controller completes each motion it began (counted as executed), each at its own
    /// end (a move held up in the plant ends once it is not), with nobody to tell.
    pub(super) async fn complete_unanswered(&mut self, shutdown: &CancellationToken) {
        loop {
            let now = std::time::Instant::now();
            let mut index = 0;
            while index < self.acting.len() {
                if self.acting[index].until <= now && !self.held(&self.acting[index]) {
                    let acting = self.acting.remove(index);
                    self.complete_one(acting);
                } else {
                    index += 1;
                }
            }
            // The next to look at: one not due yet at its end, one held up shortly.
            let Some(next) = self
                .acting
                .iter()
                .map(|a| a.until.max(now + HELD_RECHECK))
                .min()
            else {
                return;
            };
            tokio::select! {
                _ = shutdown.cancelled() => return,
                _ = act_for(next) => {}
            }
        }
    }

    /// `acting` ended with nobody to tell: counted as executed, its step settled.
    fn complete_one(&mut self, acting: Acting) {
        // Its step is settled before the plant is told: the plant keeps both in its
        // memory with the end (a plant started again knows the step is done).
        self.settle_step(acting.step, StepRecord::Done(acting.result.to_string()));
        if let Some(physics) = &self.config.physics {
            physics.0.end(&acting.values, true);
        }
        let action = acting.values.get("action").unwrap_or("").to_string();
        let id = acting.values.get("id").unwrap_or("-");
        info!(%id, %action, "the connection is gone: the action completes unanswered");
        self.stats.count_executed(&action);
        self.count_file.update();
    }

    /// An action under way is due: each one due to be looked at for its departure is
    /// ([`Session::look_departed`]); the first whose time is up ends
    /// ([`Session::end_or_keep`]).
    pub(super) async fn end_action(&mut self, writer: &mut Writer<'_>) -> Result<(), SimError> {
        let now = std::time::Instant::now();
        let mut acting = std::mem::take(&mut self.acting);
        let mut looked = Ok(());
        for a in acting.iter_mut() {
            if a.departure.is_some_and(|at| at <= now) {
                looked = self.look_departed(a, writer).await;
                if looked.is_err() {
                    break;
                }
            }
        }
        self.acting = acting;
        looked?;
        let first = (0..self.acting.len()).min_by_key(|&i| self.acting[i].until);
        if let Some(first) = first.filter(|&i| self.acting[i].until <= now) {
            let acting = self.acting.remove(first);
            self.end_or_keep(acting, writer).await?;
        }
        Ok(())
    }

    /// `acting`'s time is up: its `done` reply; held up in the plant (a jammed track),
    /// it stays under way and is looked at again shortly.
    pub(super) async fn end_or_keep(
        &mut self,
        mut acting: Acting,
        writer: &mut Writer<'_>,
    ) -> Result<(), SimError> {
        if acting.departure.is_some() {
            // A move that left before its end is said to have left first.
            self.look_departed(&mut acting, writer).await?;
        }
        if self.held(&acting) {
            acting.until = std::time::Instant::now() + HELD_RECHECK;
            self.acting.push(acting);
            return Ok(());
        }
        self.finish(
            Some(acting.done),
            acting.result,
            &acting.values,
            acting.step,
            writer,
        )
        .await
    }

    /// `acting` stopped by the abort: its own `failed` (or `rejected`) reply, message
    /// `aborted`, and its step settled failed.
    pub(super) async fn answer_aborted(
        &mut self,
        acting: Acting,
        writer: &mut Writer<'_>,
    ) -> Result<(), SimError> {
        let why = "aborted";
        let Some(rule) = self.rule(&acting.element, &[Outcome::Failed, Outcome::Rejected]) else {
            warn!("the dialect has no failed reply here: the command is not answered");
            return Ok(());
        };
        let mut values = acting.values;
        values.set("message", why.to_string());
        self.settle_step(acting.step, StepRecord::Failed(why.to_string()));
        writer.reply(rule, &values).await
    }

    /// Reports the end of the action the command `values` (step `step`) began with the
    /// `done` reply `rule`: the action counted as executed, its step settled done.
    pub(super) async fn finish(
        &mut self,
        rule: Option<usize>,
        result: &'static str,
        values: &Values,
        step: Option<String>,
        writer: &mut Writer<'_>,
    ) -> Result<(), SimError> {
        let Some(rule) = rule else {
            return Ok(());
        };
        let stats = self.stats;
        stats.count_executed(values.get("action").unwrap_or(""));
        let mut answer = values.clone();
        answer.set("result", result.into());
        // Settled before the plant is told, as in `complete_one`.
        self.settle_step(step, StepRecord::Done(result.to_string()));
        let report = match &self.config.physics {
            Some(physics) => physics.0.end(values, true),
            None => Report::Said,
        };
        if report == Report::Unsaid {
            // Done in the plant, never told (a pallet that stopped reporting).
            info!(
                id = values.get("id").unwrap_or("-"),
                "done, but not reported (a silent pallet)"
            );
            self.count_file.update();
            return Ok(());
        }
        writer.reply(rule, &answer).await?;
        self.count_file.update();
        Ok(())
    }
}

//! How long an action takes and how it ends: its delay, the plant's say in it (a move's
//! travel, a physical refusal, a move held up), and an action that completes after its
//! connection is gone.

use std::sync::atomic::Ordering;
use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::super::fence::StepRecord;
use super::super::writer::Writer;
use super::super::SimError;
use super::Session;
use crate::dialect::Element;

/// How soon an action held up in the plant is looked at again.
pub(super) const HELD_RECHECK: Duration = Duration::from_millis(50);

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
    /// words (nothing to pick, no free pallet), and not executed, as a controller reports a
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

    pub(super) async fn complete_unanswered(&mut self, shutdown: &CancellationToken) {
        let Some(acting) = self.acting.take() else {
            return;
        };
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = act_for(acting.until) => {}
        }
        if let Some(physics) = &self.config.physics {
            // The plant goes on without the holon: a move held up ends once it is not.
            while physics.0.held() {
                tokio::select! {
                    _ = shutdown.cancelled() => return,
                    _ = tokio::time::sleep(HELD_RECHECK) => {}
                }
            }
            physics.0.end(true);
        }
        let action = self.context.get("action").unwrap_or("").to_string();
        info!(%action, "the connection is gone: the action completes unanswered");
        self.settle(StepRecord::Done(acting.result.to_string()));
        self.stats.executed.fetch_add(1, Ordering::SeqCst);
        *self
            .stats
            .by_action
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(action)
            .or_default() += 1;
        self.count_file.update();
    }

    pub(super) async fn end_action(&mut self, writer: &mut Writer<'_>) -> Result<(), SimError> {
        if let (Some(physics), Some(acting)) = (&self.config.physics, &mut self.acting) {
            if physics.0.held() {
                // Held up in the plant (a jammed track): it ends once it is not.
                acting.until = std::time::Instant::now() + HELD_RECHECK;
                return Ok(());
            }
        }
        if let Some(acting) = self.acting.take() {
            self.finish(Some(acting.done), acting.result, writer)
                .await?;
        }
        Ok(())
    }
}

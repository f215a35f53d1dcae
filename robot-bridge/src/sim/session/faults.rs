//! The faults a simulated controller plays on a command (the config's `close_after`,
//! `hang_after`, `garbage_after`, `oversize_after`, `wrong_id_after`, and the stops:
//! `fault_after`, `fault_every`, `unknown_state_every`).

use schemas::ControllerState;
use tracing::info;

use super::super::writer::Writer;
use super::super::SimError;
use super::{Flow, Session};
use crate::dialect::{Correlation, Element, Status};

impl Session<'_> {
    /// The faults injected into the `n`th command (`close_after`, `hang_after`,
    /// `garbage_after`, `oversize_after`, `wrong_id_after`): what they do to the
    /// connection, or None for the command to go on.
    pub(super) async fn injected(
        &mut self,
        writer: &mut Writer<'_>,
        id: &str,
        n: u64,
    ) -> Result<Option<Flow>, SimError> {
        let config = self.config;
        if matches!(config.close_after, Some(limit) if self.on_this_connection > limit) {
            info!(%id, "closing the connection (--close-after)");
            self.count_file.update();
            return Ok(Some(Flow::Close));
        }
        if matches!(config.hang_after, Some(limit) if n > limit) {
            info!(%id, "not answering (--hang-after)");
            self.hung = true;
            self.count_file.update();
            return Ok(Some(Flow::Continue));
        }
        if config.garbage_after.is_some_and(|limit| n == limit + 1) {
            info!(%id, "answering garbage (--garbage-after)");
            writer.garbage().await?;
            self.count_file.update();
            return Ok(Some(Flow::Continue));
        }
        if config.oversize_after.is_some_and(|limit| n == limit + 1) {
            info!(%id, "answering an oversized message (--oversize-after)");
            writer.oversize().await?;
            self.count_file.update();
            return Ok(Some(Flow::Continue));
        }
        if config.wrong_id_after.is_some_and(|limit| n == limit + 1) {
            if let Some(id) = self.context.get("id").map(str::to_string) {
                info!(%id, "answering with another id (--wrong-id-after)");
                self.context.set("id", format!("{id}9"));
            }
        }
        Ok(None)
    }

    /// The command stops the controller (`fault_after`, `fault_every`, or, when
    /// `undescribed`, `unknown_state_every`) for `fault_for` instead of being executed.
    pub(super) async fn stop_controller(
        &mut self,
        element: &Element,
        writer: &mut Writer<'_>,
        id: &str,
        undescribed: bool,
    ) -> Result<Flow, SimError> {
        let config = self.config;
        let state = config.fault_state.unwrap_or(ControllerState::Fault);
        self.count_file.update();
        let one = self.dialect.correlation == Correlation::OneInFlight;
        // Stopped for `fault_for` (the session's timer reports `ready` again); what
        // comes meanwhile is refused.
        if undescribed {
            info!(%id, "in a state the dialect does not describe (--unknown-state-every)");
            self.stats.stop_undescribed(config.fault_for);
        } else {
            info!(%id, %state, "reporting a fault (--fault-after)");
            self.stats.stop(state, config.fault_for);
        }
        let state = self.state_now();
        writer.state = state;
        if self.dialect.status == Status::Pushed {
            // The state first, so the holon knows it before the command's answer.
            writer.status().await?;
        }
        // One in flight, the command is answered with its failed reply (which frees
        // the wire for the state); with ids it is left unanswered, as a faulted
        // controller leaves the job it was given (its state says why), unless its
        // state cannot be told (a dialect whose state is the connection's).
        if one || self.dialect.status == Status::Connection {
            let said = match undescribed {
                true => crate::sim::UNDESCRIBED_STATE.to_lowercase(),
                false => state.to_string(),
            };
            self.answer_failed(element, writer, &said).await?;
        }
        Ok(Flow::Continue)
    }
}

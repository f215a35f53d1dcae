//! A part outside the cell and its home (docs/material-flow.md, "Reservations"): it
//! enters only once a place at a buffer is reserved for it, and leaves a freed one to
//! a waiting part of a higher priority ([`crate::home_line`]).

use schemas::layout::{CellLayout, LocationId, LocationRole};
use tokio::time::Instant;
use tracing::info;

use super::super::OrderTask;
use super::PLACE_RETRY;
use crate::context::{jittered, OrderError, IDLE_POLL};
use crate::home_line::HomeTicket;

impl OrderTask<'_> {
    /// A part outside the cell takes a home if it may (none of a higher priority waits
    /// for one), else waits: whether it has a home now. `waiting` is its place among
    /// the parts waiting for one, kept across looks.
    pub(super) async fn enter(
        &mut self,
        layout: &CellLayout,
        waiting: &mut Option<HomeTicket>,
        backoff: &mut holon::Backoff,
    ) -> Result<bool, OrderError> {
        let priority = self.progress.get().priority;
        let ticket = waiting.get_or_insert_with(|| self.ctx.homes.wait(&self.holon, priority));
        let mut freed = self.ctx.presence.room_news().0;
        freed.mark_unchanged();
        if !ticket.outranked() && self.take_home(layout).await? {
            *waiting = None;
            return Ok(true);
        }
        if ticket.ahead_of_others() {
            // The others leave the next home to this part: it looks as soon as one
            // frees up.
            tokio::select! {
                _ = tokio::time::sleep(jittered(PLACE_RETRY)) => {}
                Ok(()) = freed.changed() => {}
            }
        } else {
            let pause = backoff.next_pause();
            self.wait_for_resource(pause, true, Instant::now() + IDLE_POLL)
                .await;
        }
        Ok(false)
    }

    /// Reserves the part's home: a place at a buffer of the cell (a location of role
    /// `buffer`, the first with a free place). False when every buffer is full (or the
    /// cell has none: then no part enters).
    async fn take_home(&mut self, layout: &CellLayout) -> Result<bool, OrderError> {
        let buffers: Vec<LocationId> = layout
            .locations()
            .map(|(_, l)| l)
            .filter(|l| l.role == LocationRole::Buffer)
            .map(|l| l.id.clone())
            .collect();
        for buffer in buffers {
            if self.reserve(&buffer).await? {
                self.ctx
                    .commit(self.progress, |p| {
                        if let Some(part) = &mut p.part {
                            part.home = Some(buffer.clone());
                        }
                    })
                    .await?;
                info!(holon = %self.holon, home = %buffer, "the part has a home in the cell");
                return Ok(true);
            }
        }
        Ok(false)
    }
}

//! A part at a station's port whose next station has no place yet waits there rather
//! than ride to its home and back, for as long as its move home would take, while no
//! other part of the node waits for the station it holds (`orders.wait_at_port`;
//! docs/material-flow.md, "Orders arrange their moves"). The wait is bounded, so two
//! parts each at the port the other needs cannot block each other for longer than a
//! move home: then both go home, as every part without a place did before.

use std::time::Duration;

use schemas::layout::{CellLayout, LocationId};
use tokio::time::Instant;
use tracing::info;

use super::super::OrderTask;
use crate::context::OrderError;
use crate::part::{MoveGoal, PartProgress};

/// How often a part waiting at its port for its next station checks that no other
/// part has come to wait for the station it holds, at the latest: a part joining a
/// line wakes it at once, as a freed place does. (A wall-clock poll alone let a
/// station stand idle up to a second, twenty seconds of plant time at 20x.)
pub(super) const PORT_RECHECK: Duration = Duration::from_secs(1);

impl OrderTask<'_> {
    /// Until when the part, at the port `here` of a station and without a place at its
    /// next one, may wait there rather than go home: for as long as its move home would
    /// take (the layout's travel estimate; the lap home and back is no faster after
    /// that), if no other part of the node waits for the station it is at
    /// ([`Self::station_wanted`]). None: it goes home now. The wait is bounded, so two
    /// parts each at the port the other needs cannot block each other for longer than
    /// a move home.
    pub(super) async fn port_wait_until(
        &self,
        layout: &CellLayout,
        here: &LocationId,
        part: &PartProgress,
    ) -> Option<Instant> {
        if !self.ctx.settings.wait_at_port {
            return None;
        }
        let home = part.home.as_ref()?;
        let lap = Duration::from_millis(layout.routes(here, home).first()?.travel_ms);
        (!self.station_wanted().await).then(|| Instant::now() + lap)
    }

    /// Whether a part waiting at its port until `until` waits on: its time is not up
    /// and no other part of the node waits for the station it is at.
    pub(super) async fn keeps_waiting_at_port(&self, until: Option<Instant>) -> bool {
        until.is_some_and(|until| Instant::now() < until) && !self.station_wanted().await
    }

    /// Whether another part of the node waits in line for the service the part was
    /// just worked for (so for the station whose port it holds).
    async fn station_wanted(&self) -> bool {
        let worked_for = self.progress.get().last_worked_for().map(str::to_string);
        match worked_for {
            Some(service) => self.ctx.line.waiting_for(&service, &self.holon).await > 0,
            None => false,
        }
    }

    /// The part, at the port `here`, goes back to its home.
    pub(super) async fn go_home(
        &mut self,
        here: LocationId,
        part: &PartProgress,
    ) -> Result<(), OrderError> {
        let home = part.home.clone().expect("a part at a port has a home");
        info!(holon = %self.holon, from = %here, %home, "no station has a place for the part, or other parts wait for one: it goes back to its home");
        self.begin_move(here, home, MoveGoal::Home).await
    }
}

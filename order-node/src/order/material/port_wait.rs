//! A part at a station's port whose next station has no place yet waits there rather
//! than ride to its home and back, while no other part of the node waits for the
//! station it holds (`orders.wait_at_port`; docs/material-flow.md, "Orders arrange
//! their moves"): until its move home's time has passed since it began to wait, or
//! since a station of its next service was last seen working (that station frees a
//! place when its job ends), and at most [`PORT_WAIT_LAPS`] moves home in all. The
//! wait is bounded, so two parts each at the port the other needs cannot block each
//! other for long, even when another node's part is one of them (a node sees only its
//! own parts in line): a station held by a waiting part works no job, so the wait of
//! the part waiting for it ends a move home's time after it began; then both go home,
//! as every part without a place did before.

use std::time::Duration;

use schemas::layout::{CellLayout, LocationId};
use schemas::HolonId;
use tokio::time::Instant;
use tracing::info;

use super::super::OrderTask;
use crate::context::OrderError;
use crate::part::{MoveGoal, PartProgress};

/// How often a part waiting at its port for its next station checks that no other
/// part has come to wait for the station it holds, at the latest: a part joining a
/// line wakes it at once, as a freed place does. (A wall-clock poll alone let a
/// station stand idle up to a second, twenty seconds of plant time at 20x.)
const PORT_RECHECK: Duration = Duration::from_secs(1);

/// The longest a part waits at its port, in moves home: while a station of its next
/// service works, it waits on after its move home's time, up to this many of them.
/// (Until 2026-11-28 it went home after one: a part whose next station was working a
/// block of steps made the lap home and back, about a minute of plant time on the
/// AIP-PRIMECA cell, while the station it held stood idle all the same.) A station
/// that works a block of steps longer than this many moves home still sends it home.
pub(super) const PORT_WAIT_LAPS: u32 = 4;

/// A part's wait at a station's port for its next station.
#[derive(Debug, Clone)]
pub(super) struct PortWait {
    /// The port it waits at.
    pub at: LocationId,
    /// Its move home's time (the layout's travel estimate).
    lap: Duration,
    /// Its move home's time after it began to wait, or after a station of its next
    /// service was last seen working: until then it waits.
    until: Instant,
    /// The longest it waits: [`PORT_WAIT_LAPS`] moves home after it began.
    most: Instant,
}

impl PortWait {
    /// When it checks again at the latest whether it waits on: when its time is up,
    /// or a [`PORT_RECHECK`] from now, whichever comes first.
    pub fn next_check(&self) -> Instant {
        let now = Instant::now();
        [self.until, self.most, now + PORT_RECHECK]
            .into_iter()
            .filter(|t| *t > now)
            .min()
            .unwrap_or(now)
    }
}

impl OrderTask<'_> {
    /// The wait at the port `here` of a part without a place at its next station, if
    /// no other part of the node waits for the station it is at
    /// ([`Self::station_wanted`]). None: it goes home now.
    pub(super) async fn port_wait(
        &self,
        layout: &CellLayout,
        here: &LocationId,
        part: &PartProgress,
    ) -> Option<PortWait> {
        if !self.ctx.settings.wait_at_port {
            return None;
        }
        let home = part.home.as_ref()?;
        let lap = Duration::from_millis(layout.routes(here, home).first()?.travel_ms);
        if self.station_wanted(here).await {
            return None;
        }
        info!(holon = %self.holon, at = %here, ?lap, laps_at_most = PORT_WAIT_LAPS, "no station has a place for the part yet, and no part waits for this one: it waits at its port");
        let now = Instant::now();
        Some(PortWait {
            at: here.clone(),
            lap,
            until: now + lap,
            most: now + lap * PORT_WAIT_LAPS,
        })
    }

    /// Whether a part waiting at its port (`wait`) for a station of `service` waits
    /// on: no other part of the node waits for the station it is at, and its time is
    /// not up, a move home's time after it began or after a station of `service` was
    /// last seen working (seen now: its time runs from now), within its longest wait.
    /// A station that has just ended its job is about to free its place: the part
    /// waits for it a move home's time more.
    pub(super) async fn keeps_waiting_at_port(&self, wait: &mut PortWait, service: &str) -> bool {
        let now = Instant::now();
        let working = HolonId::resource(wait.at.holon())
            .is_ok_and(|station| self.ctx.presence.working_for(service, &station));
        if working {
            wait.until = wait.until.max(now + wait.lap);
        }
        now < wait.until.min(wait.most) && !self.station_wanted(&wait.at).await
    }

    /// Whether another part of the node waits in line for a service the station at
    /// the port `here` offers (so for the place the part holds): each service it last
    /// published, and the one the part was just worked for.
    async fn station_wanted(&self, here: &LocationId) -> bool {
        let mut services = HolonId::resource(here.holon())
            .map(|station| self.ctx.presence.services_of(&station))
            .unwrap_or_default();
        if let Some(worked_for) = self.progress.get().last_worked_for() {
            services.push(worked_for.to_string());
        }
        services.sort();
        services.dedup();
        for service in &services {
            if self.ctx.line.waiting_for(service, &self.holon).await > 0 {
                return true;
            }
        }
        false
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

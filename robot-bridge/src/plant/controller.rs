//! One controller of the plant: its actions asked of and told to the shared plant
//! ([`Physics`] for the simulator serving it).
//!
//! A transporter's controller moves a part when its command names one and where it goes
//! (`info.part`, `info.from`, `info.to`: holarchy-xml's `PART`, `FROM` and `TO`): the
//! plant checks the move and begins it; the simulator waits the move's unobstructed
//! travel, then asks [`Physics::held`] until the part has arrived in the plant (its
//! pallet may wait on the way: a full port, a full or jammed track, an e-stop). A
//! station's controller works on the part at its port (`info.part` where the command
//! names it, else whichever is there). A command naming no part is not in the material
//! flow: the plant lets it run as robot-sim would.
//!
//! A transporter's controller may move several parts at once (`actions_at_once` in the
//! plant file): each move is known by its part, begun, looked at ([`Physics::held`]) and
//! ended on its own; the plant's pallets ride together, each waiting where the way ahead
//! of it is full.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::layout::LocationId;
use tracing::{debug, info, warn};

use super::model::{Happening, Plant};
use super::Clock;
use crate::dialect::Values;
use crate::sim::physics::{Physics, Report};

/// Told after every change of the plant (writes the state file, wakes the task that
/// drives the plant's time).
pub type OnChange = Arc<dyn Fn(&Plant) + Send + Sync>;

/// A move a controller has under way (known by the part it moves).
#[derive(Debug, Clone)]
struct Moving {
    /// Its pallet when the move began, if it rides one (a silent one's arrival is not
    /// said).
    carrier: Option<String>,
}

/// The physics of the controller of resource `resource`.
pub struct ControllerPhysics {
    /// The plant, shared by all its controllers. A lock is the right tool here: each
    /// controller's session asks it synchronously from its own task, holds it for a few
    /// map operations and never across an await.
    plant: Arc<Mutex<Plant>>,
    /// The plant's time.
    clock: Clock,
    /// The resource whose controller this is.
    resource: String,
    /// The moves under way, by the part each moves; each ended by `end`.
    moving: Mutex<BTreeMap<String, Moving>>,
    /// Told after every change this controller makes.
    on_change: OnChange,
}

impl ControllerPhysics {
    pub fn new(
        plant: Arc<Mutex<Plant>>,
        clock: Clock,
        resource: &str,
        on_change: OnChange,
    ) -> ControllerPhysics {
        ControllerPhysics {
            plant,
            clock,
            resource: resource.to_string(),
            moving: Mutex::new(BTreeMap::new()),
            on_change,
        }
    }

    fn plant(&self) -> std::sync::MutexGuard<'_, Plant> {
        self.plant.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn moving(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Moving>> {
        self.moving.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// Logs what happened in the plant as its time went on.
pub fn log_happenings(happened: &[Happening]) {
    for happening in happened {
        match happening {
            Happening::Arrived {
                part,
                at,
                transporter,
            } => info!(part, %at, transporter, "arrived"),
            Happening::Shipped { part, at } => info!(part, %at, "shipped: left the plant"),
            Happening::Waits { pallet, what } => info!(pallet, waits = %what, "a pallet waits"),
            Happening::Left { pallet, from } => debug!(pallet, %from, "left onto the loop"),
            Happening::Passed { pallet, stopper } => debug!(pallet, stopper, "passed a stopper"),
            Happening::Docking { pallet, at } => debug!(pallet, %at, "docking"),
        }
    }
}

fn location(values: &Values, field: &str) -> Result<Option<LocationId>, String> {
    values
        .get(field)
        .map(|id| LocationId::try_from(id.to_string()).map_err(|e| format!("{field}: {e}")))
        .transpose()
}

impl Physics for ControllerPhysics {
    fn begin(&self, action: &str, values: &Values) -> Result<Option<Duration>, String> {
        let part = values.get("info.part");
        let mut plant = self.plant();
        log_happenings(&plant.advance(self.clock.now_ms()));
        let transporter = plant
            .layout()
            .parts
            .get(&self.resource)
            .is_some_and(|p| p.transporter.is_some());
        if transporter {
            let (from, to) = (location(values, "info.from")?, location(values, "info.to")?);
            let (Some(part), Some(from), Some(to)) = (part, from, to) else {
                return Ok(None);
            };
            let took = plant
                .begin_move(&self.resource, part, &from, &to)
                .map_err(|e| e.to_string())?;
            let carrier = plant.carrier_of(part);
            info!(resource = %self.resource, %action, part, %from, %to, ?carrier, ?took, "moving");
            self.moving().insert(part.to_string(), Moving { carrier });
            (self.on_change)(&plant);
            // The plant's travel, in the wall time the simulator waits.
            return Ok(Some(self.clock.wall(took)));
        }
        plant
            .check_work(&self.resource, part)
            .map_err(|e| e.to_string())?;
        Ok(None)
    }

    fn held(&self, values: &Values) -> bool {
        let Some(part) = values.get("info.part") else {
            return false;
        };
        if !self.moving().contains_key(part) {
            return false;
        }
        let mut plant = self.plant();
        // A wall ms of slack: the simulator times the move from the command's receipt, a
        // moment before the plant began it (its ms may have ticked in between).
        let happened = plant.advance(self.clock.now_ms() + self.clock.one_wall_ms());
        log_happenings(&happened);
        if !happened.is_empty() {
            (self.on_change)(&plant);
        }
        match plant.on_its_way(part, &self.resource) {
            Some(why) => {
                debug!(resource = %self.resource, part, %why, "the move is held up");
                true
            }
            None => false,
        }
    }

    fn end(&self, values: &Values, done: bool) -> Report {
        let Some(part) = values.get("info.part") else {
            return Report::Said;
        };
        let Some(moving) = self.moving().remove(part) else {
            return Report::Said;
        };
        let mut plant = self.plant();
        log_happenings(&plant.advance(self.clock.now_ms() + self.clock.one_wall_ms()));
        if !done {
            plant.stop_move(part);
        } else if let Some(why) = plant.on_its_way(part, &self.resource) {
            // Said done before the plant has it there (a dialect polled for the end):
            // the plant's truth stands, the part arrives when its pallet does.
            warn!(resource = %self.resource, part, %why, "the controller says done, the part is not there yet in the plant");
        }
        let unreported = moving
            .carrier
            .as_deref()
            .is_some_and(|p| plant.is_silent(p));
        info!(resource = %self.resource, part, where_it_is = %plant.where_is(part), unreported, "moved");
        (self.on_change)(&plant);
        if done && unreported {
            Report::Unsaid
        } else {
            Report::Said
        }
    }
}

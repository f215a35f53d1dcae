//! One controller of the plant: its actions asked of and told to the shared plant
//! ([`Physics`] for the simulator serving it).
//!
//! A transporter's controller moves a part when its command names one and where it goes
//! (`info.part`, `info.from`, `info.to`: holarchy-xml's `PART`, `FROM` and `TO`): the
//! plant checks the move and times it. A station's controller works on the part at its
//! port (`info.part` where the command names it, else whichever is there). A command
//! naming no part is not in the material flow: the plant lets it run as robot-sim would.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::layout::LocationId;
use tracing::{debug, info};

use super::model::Plant;
use crate::dialect::Values;
use crate::sim::physics::{Physics, Report};

/// Told after every change of the plant (the state file's writer).
pub type OnChange = Arc<dyn Fn(&Plant) + Send + Sync>;

/// The physics of the controller of resource `resource`.
pub struct ControllerPhysics {
    /// The plant, shared by all its controllers. A lock is the right tool here: each
    /// controller's session asks it synchronously from its own task, holds it for a few
    /// map operations and never across an await.
    plant: Arc<Mutex<Plant>>,
    /// The resource whose controller this is.
    resource: String,
    /// The part this controller is moving (the move under way), ended by `end`.
    moving: Mutex<Option<String>>,
    on_change: OnChange,
}

impl ControllerPhysics {
    pub fn new(plant: Arc<Mutex<Plant>>, resource: &str, on_change: OnChange) -> ControllerPhysics {
        ControllerPhysics {
            plant,
            resource: resource.to_string(),
            moving: Mutex::new(None),
            on_change,
        }
    }

    fn plant(&self) -> std::sync::MutexGuard<'_, Plant> {
        self.plant.lock().unwrap_or_else(|e| e.into_inner())
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
            info!(resource = %self.resource, %action, part, %from, %to, ?took, "moving");
            *self.moving.lock().unwrap_or_else(|e| e.into_inner()) = Some(part.to_string());
            (self.on_change)(&plant);
            return Ok(Some(took));
        }
        plant
            .check_work(&self.resource, part)
            .map_err(|e| e.to_string())?;
        Ok(None)
    }

    fn held(&self) -> bool {
        let moving = self
            .moving
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        let Some(part) = moving else { return false };
        match self.plant().held_up(&part) {
            Some(why) => {
                debug!(resource = %self.resource, part, %why, "the move is held up");
                true
            }
            None => false,
        }
    }

    fn end(&self, done: bool) -> Report {
        let Some(part) = self.moving.lock().unwrap_or_else(|e| e.into_inner()).take() else {
            return Report::Said;
        };
        let mut plant = self.plant();
        let unreported = plant.unreported(&part);
        if done {
            plant.end_move(&part);
        } else {
            plant.stop_move(&part);
        }
        info!(resource = %self.resource, part, where_it_is = %plant.where_is(&part), unreported, "moved");
        (self.on_change)(&plant);
        if done && unreported {
            Report::Unsaid
        } else {
            Report::Said
        }
    }
}

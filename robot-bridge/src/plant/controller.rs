//! One controller of the plant: its actions asked of and told to the shared plant
//! ([`Physics`] for the simulator serving it).
//!
//! A transporter's controller moves a part when its command names one and where it goes
//! (`info.part`, `info.from`, `info.to`: holarchy-xml's `PART`, `FROM` and `TO`): the
//! plant checks the move and begins it; the simulator waits the move's unobstructed
//! travel, then asks [`Physics::held`] until the part has arrived in the plant (its
//! pallet may wait on the way: a full port, a full or jammed track, an e-stop); while it
//! waits, it asks [`Physics::departed`] until the part's pallet has left the move's
//! origin (a transfer's move never says so: no pallet leaves). A
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
use super::trace::{Trace, TraceRecord};
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
    /// Its action, and when it began (plant ms), for the trace.
    action: String,
    begin_ms: u64,
}

/// A station's action under way, for the trace (known by the part its command names,
/// or "" when it names none).
#[derive(Debug, Clone)]
struct Working {
    action: String,
    /// The part at its port when it began.
    part: Option<String>,
    begin_ms: u64,
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
    /// A station's actions under way, by the part each command names ("" for none).
    working: Mutex<BTreeMap<String, Working>>,
    /// Told after every change this controller makes.
    on_change: OnChange,
    /// Where every ended action is written.
    trace: Trace,
}

impl ControllerPhysics {
    pub fn new(
        plant: Arc<Mutex<Plant>>,
        clock: Clock,
        resource: &str,
        on_change: OnChange,
        trace: Trace,
    ) -> ControllerPhysics {
        ControllerPhysics {
            plant,
            clock,
            resource: resource.to_string(),
            moving: Mutex::new(BTreeMap::new()),
            working: Mutex::new(BTreeMap::new()),
            on_change,
            trace,
        }
    }

    fn plant(&self) -> std::sync::MutexGuard<'_, Plant> {
        self.plant.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The plant, advanced to now (what happened logged and told).
    fn advanced(&self) -> std::sync::MutexGuard<'_, Plant> {
        let mut plant = self.plant();
        // A wall ms of slack: the simulator times the move from the command's receipt, a
        // moment before the plant began it (its ms may have ticked in between).
        let happened = plant.advance(self.clock.now_ms() + self.clock.one_wall_ms());
        log_happenings(&happened);
        if !happened.is_empty() {
            (self.on_change)(&plant);
        }
        plant
    }

    fn moving(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Moving>> {
        self.moving.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn working(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, Working>> {
        self.working.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// A station's action ended: traced. A fenced one's step (settled already) is
    /// written to the plant's memory before its reply goes out, so that a plant started
    /// again knows it is done.
    fn end_work(&self, values: &Values, done: bool) {
        let key = values.get("info.part").unwrap_or_default().to_string();
        let Some(working) = self.working().remove(&key) else {
            return;
        };
        self.trace.record(&TraceRecord {
            resource: self.resource.clone(),
            action: working.action,
            part: working.part,
            carrier: None,
            begin_ms: working.begin_ms,
            end_ms: self.clock.now_ms(),
            done,
        });
        if values.get("step").is_some() {
            (self.on_change)(&self.plant());
        }
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
            Happening::AwaitsPallet { part, conveyor, at } => {
                info!(part, conveyor, %at, "no pallet is free: the part waits for one")
            }
            Happening::Retired { pallet, out: true } => info!(pallet, "taken out of service"),
            Happening::Retired { pallet, out: false } => info!(pallet, "back in service"),
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
    fn epoch_granted(&self) {
        // The plant's memory keeps the fence: written before the grant is sent.
        (self.on_change)(&self.plant());
    }

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
            plant.note_command(part, action, values.get("step"));
            let carrier = plant.carrier_of(part);
            info!(resource = %self.resource, %action, part, %from, %to, ?carrier, ?took, "moving");
            let moving = Moving {
                carrier,
                action: action.to_string(),
                begin_ms: self.clock.now_ms(),
            };
            self.moving().insert(part.to_string(), moving);
            (self.on_change)(&plant);
            // The plant's travel, in the wall time the simulator waits.
            return Ok(Some(self.clock.wall(took)));
        }
        plant
            .check_work(&self.resource, part)
            .map_err(|e| e.to_string())?;
        let working = Working {
            action: action.to_string(),
            part: part
                .map(str::to_string)
                .or_else(|| plant.part_at_station(&self.resource)),
            begin_ms: self.clock.now_ms(),
        };
        self.working()
            .insert(part.unwrap_or_default().to_string(), working);
        Ok(None)
    }

    fn held(&self, values: &Values) -> bool {
        let Some(part) = values.get("info.part") else {
            return false;
        };
        if !self.moving().contains_key(part) {
            return false;
        }
        let plant = self.advanced();
        match plant.on_its_way(part, &self.resource) {
            Some(why) => {
                debug!(resource = %self.resource, part, %why, "the move is held up");
                true
            }
            None => false,
        }
    }

    fn departed(&self, values: &Values) -> bool {
        let Some(part) = values.get("info.part") else {
            return false;
        };
        let Some(on_pallet) = self.moving().get(part).map(|m| m.carrier.is_some()) else {
            return false;
        };
        let plant = self.advanced();
        if plant.left_origin(part) {
            debug!(resource = %self.resource, part, "the move left its origin");
            return true;
        }
        // Ended in the plant already: a pallet that arrived has left its origin.
        on_pallet && plant.on_its_way(part, &self.resource).is_none()
    }

    fn end(&self, values: &Values, done: bool) -> Report {
        let moving = values
            .get("info.part")
            .and_then(|part| Some((part, self.moving().remove(part)?)));
        let Some((part, moving)) = moving else {
            self.end_work(values, done);
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
        if let Some(step) = values.get("step") {
            plant.end_told(&self.resource, step);
        }
        // Traced before the memory is written (resume.rs, `end_resumed_move`).
        self.trace.record(&TraceRecord {
            resource: self.resource.clone(),
            action: moving.action,
            part: Some(part.to_string()),
            carrier: moving.carrier,
            begin_ms: moving.begin_ms,
            end_ms: self.clock.now_ms(),
            done,
        });
        (self.on_change)(&plant);
        if done && unreported {
            Report::Unsaid
        } else {
            Report::Said
        }
    }
}

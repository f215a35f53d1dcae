//! The plant's physical state: where every part and pallet is. Pure: no I/O, no clock;
//! time comes in as an argument ([`Plant::advance`], in ms since the plant started) and
//! the controllers' physics ([`super::controller`]) and the control port ask it and tell
//! it, each after advancing it to their now.
//!
//! A conveyor's loop is cut by its stoppers into **tracks**: track `s2` is the one that
//! ends at stopper `s2` (from the stopper before it) and holds the stopper's `queue` of
//! pallets, one behind the other in the order they came. A pallet is **parked** (free,
//! off the loop), **docked** in a location (off the loop, in a station's port), **on a
//! track** (riding to its end, or there, queued) or **docking** into a location.
//!
//! | what happens | what the plant checks | what changes |
//! |---|---|---|
//! | a transporter begins a move of part P from A to B | the transporter reaches A to B; P is at A (a part unknown to the plant at an entry is new raw material), not moving already; a transfer: B has a place, counting the parts on their way | P is in transit; on a conveyor its pallet (docked at A, or a parked one brought there) is bound for B, docked at A until it can leave, and with no pallet free (all carry parts, or some are retired) P waits at A for the first freed, the longest waiting first; a transfer takes P off its pallet (parked again) |
//! | a pallet leaves A (docked at stopper Sa) | nothing waits at Sa (a pallet stopped there holds the spot where A's pallets come back onto the loop) and the track after Sa has room (not full, not jammed) | P leaves A; the pallet is at the back of that track, riding for `dock_ms` and the track's length at the conveyor's speed |
//! | a pallet reaches the stopper at the end of its track, first in the queue | the track is not jammed; at B's stopper: B has a place; elsewhere: the next track has room | it docks into B (`dock_ms`), or passes onto the next track; else it **waits** there, holding its place in the queue and the pallets behind it |
//! | a pallet has docked into B | | P is at B; at an exit P leaves the plant (shipped) and the pallet is parked |
//! | a transfer's `move_ms` has passed | | P is at B (at an exit: shipped) |
//! | the move is aborted | | P stays on the transporter, stopped where it is (its pallet holds its place) until someone puts it somewhere |
//! | a station works on a part (pick, place, inspect) | a part is at one of its ports (P, where the command names it) | |
//! | a track is jammed (`jam conveyor1.s2`: the track that ends at that stopper) | | no pallet enters it or leaves it (as if full) until it is cleared |
//! | a pallet stops reporting (`silence conveyor1/p2`) | | a move it carries ends in the plant, but its controller does not say so |
//! | a transporter's e-stop is pressed (`estop conveyor1 MS`) | | its pallets (or its transfer) stand still until it is released, then go on with the time they had left |
//! | a pallet is taken out of service (`retire conveyor1/p2`), or put back (`restore`) | | a free one is retired at once, one carrying a part once it is free; a retired pallet takes no part; one put back is free |
//!
//! Every pallet that cannot go on **waits**, since the moment it stopped: for a full
//! location, a full or jammed track, the stopper's spot, or the pallet ahead of it. The
//! plant is **deadlocked** when some waiting pallets wait only on one another (a cycle
//! in the wait-for graph, [`Plant::deadlock`]): nothing in the plant can free them.

mod boarding;
mod faults;
mod flow;
mod memory;
#[cfg(test)]
mod tests;
mod waits;

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::time::Duration;

use schemas::layout::{CellLayout, ConveyorSpec, Dock, LocationId, LocationRole, TransporterSpec};
use serde::{Deserialize, Serialize};

pub use memory::{PlantMemory, ResumedMove};
pub use waits::{PalletView, WaitView};

/// A part and the carrier it rides on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Load {
    /// The part (its order's id, `o-1`).
    pub part: String,
    /// Its pallet (`conveyor1/p2`), if it is on one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub carrier: Option<String>,
}

/// A part on a transporter.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Transit {
    /// The part and its pallet.
    pub load: Load,
    /// The conveyor or transfer moving it.
    pub transporter: String,
    /// Where it was moved from.
    pub from: LocationId,
    /// Where it goes.
    pub to: LocationId,
    /// Aborted on the way: it is nowhere the plant can tell until it is put somewhere.
    pub stopped: bool,
    /// A transfer's move: when (plant ms) the part is at `to`. None on a conveyor (its
    /// pallet says where it is).
    #[serde(skip_serializing_if = "Option::is_none", default)]
    arrives_ms: Option<u64>,
    /// On a conveyor: no pallet was free when the move began (some are taken out, or
    /// all carry parts), so the part waits at `from` for one; the first to free up
    /// takes the part that has waited longest.
    #[serde(skip_serializing_if = "std::ops::Not::not", default)]
    pub awaits_pallet: bool,
    /// When the move began (plant ms).
    pub began_ms: u64,
    /// The controller command that began it ([`Plant::note_command`]): what a plant
    /// started again after its death needs to end the move as its controller would.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub command: Option<MoveCommand>,
}

/// The controller command that began a move.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MoveCommand {
    /// Its action (`move`), for the trace.
    pub action: String,
    /// Its step id (fenced controllers: `STEP`), if it has one.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub step: Option<String>,
}

/// What the plant refuses, physically.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PhysicalError {
    #[error("{transporter} cannot move a part from {from} to {to}")]
    NoRoute {
        transporter: String,
        from: LocationId,
        to: LocationId,
    },
    #[error("part {part} is not at {at} ({where_it_is})")]
    NotThere {
        part: String,
        at: LocationId,
        where_it_is: String,
    },
    /// A transfer's destination is full (a conveyor's pallet goes and waits instead).
    #[error("{at} is full ({held} held, {coming} on their way, capacity {capacity})")]
    Full {
        at: LocationId,
        held: usize,
        coming: usize,
        capacity: u32,
    },
    #[error("nothing to work on at {ports}: the port is empty")]
    Empty { ports: String },
    #[error("part {part} is not at {ports} ({where_it_is})")]
    NotAtStation {
        part: String,
        ports: String,
        where_it_is: String,
    },
    #[error("part {part} is moving already ({where_it_is})")]
    Moving { part: String, where_it_is: String },
}

/// Where a pallet is.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Place {
    /// Free, off the loop in its conveyor's park: it holds no track place and no
    /// location's place; a move that needs a pallet takes one from here.
    Parked,
    /// In a location, off the loop.
    Docked(LocationId),
    /// On the track that ends at stopper `track` (an index into the conveyor's
    /// stoppers), in its queue; it reaches the stopper (or the queue's back) at `due`
    /// (plant ms; `u64::MAX`: stopped on the way, it never does).
    Track { track: usize, due: u64 },
    /// Leaving the loop into location `at`; inside at `due`.
    Docking { at: LocationId, due: u64 },
    /// Taken out of service by an operator (`retire`): off the loop, holding nothing;
    /// no move takes it until it is put back.
    Retired,
}

/// Where a pallet takes its part: the move under way.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Bound {
    /// The location it goes to.
    to: LocationId,
    /// The stopper where that location docks (an index into the conveyor's stoppers).
    stopper: usize,
    /// How far it has ridden since it left, in mm: each track's time is counted from
    /// it, so the tracks' times add up to the whole move's (no rounding per track).
    ridden_mm: u64,
}

/// A conveyor's pallet.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Pallet {
    /// The conveyor it rides.
    conveyor: String,
    /// Where it is.
    place: Place,
    /// The part it carries, if any.
    part: Option<String>,
    /// The move it carries, if one is under way.
    bound: Option<Bound>,
    /// Aborted on the way: it stays where it stopped.
    stopped: bool,
    /// Since when (plant ms) it waits, if it does.
    waiting_since: Option<u64>,
    /// To be taken out of service once it is free (`retire` while it carried a part).
    retiring: bool,
}

/// A conveyor's loop: its layout and what is on its tracks.
#[derive(Debug, Clone)]
struct Loop {
    /// Its stoppers, speed, queues and `dock_ms`.
    spec: ConveyorSpec,
    /// Each track's pallets, first the one nearest its stopper (index: the stopper the
    /// track ends at).
    tracks: Vec<VecDeque<String>>,
}

/// Something that happened in the plant as time went on ([`Plant::advance`]): for the
/// log, and to know the state file is to be written again.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Happening {
    /// `pallet` left `from` onto the loop.
    Left { pallet: String, from: LocationId },
    /// `pallet` passed `stopper` onto the next track.
    Passed { pallet: String, stopper: String },
    /// `pallet` began to dock into `at`.
    Docking { pallet: String, at: LocationId },
    /// `part` arrived at `at` (on `transporter`).
    Arrived {
        part: String,
        at: LocationId,
        transporter: String,
    },
    /// `part` left the plant at the exit `at`.
    Shipped { part: String, at: LocationId },
    /// `pallet` began to wait, for `what`.
    Waits { pallet: String, what: String },
    /// `part`, to be moved by `conveyor`, waits at `at` for a free pallet.
    AwaitsPallet {
        part: String,
        conveyor: String,
        at: LocationId,
    },
    /// `pallet` was taken out of service (true) or put back (false).
    Retired { pallet: String, out: bool },
}

/// The plant's physical state.
#[derive(Debug, Clone)]
pub struct Plant {
    /// The cell's layout: locations, conveyors, transfers.
    layout: CellLayout,
    /// What each location holds now, in the order it arrived (a part whose pallet waits
    /// to leave is still here: it is, physically).
    held: BTreeMap<LocationId, Vec<Load>>,
    /// Parts on a transporter, by part.
    transit: BTreeMap<String, Transit>,
    /// Every conveyor's pallets, by id (`conveyor1/p2`).
    pallets: BTreeMap<String, Pallet>,
    /// Every conveyor's loop, by conveyor.
    loops: BTreeMap<String, Loop>,
    /// Parts that left the plant at an exit.
    shipped: u64,
    /// Jammed tracks, each named by the stopper it ends at.
    jammed: BTreeSet<Dock>,
    /// Pallets that stopped reporting.
    silent: BTreeSet<String>,
    /// Resources whose e-stop is pressed, and since when (plant ms): a transporter's
    /// moves do not go on.
    estopped: BTreeMap<String, u64>,
    /// The plant's time: ms since it started, as far as it has been advanced.
    clock: u64,
    /// The longest any pallet waited, of the waits that are over, in ms.
    longest_wait_ms: u64,
    /// Moves that have ended in the plant and whose controller has not said so yet
    /// ([`Plant::end_told`]), by transporter: their step ids, so that a plant started
    /// again after its death knows those steps are done.
    arrived_steps: BTreeSet<(String, String)>,
    /// What happened since the last [`Plant::advance`] returned.
    happened: Vec<Happening>,
}

/// Where everything is, as the plant's state file and the control port's `where` say.
#[derive(Debug, Clone, Serialize)]
pub struct PlantView {
    /// The plant's time: ms since it started.
    pub now_ms: u64,
    /// What each location holds (every location of the layout, empty ones too).
    pub locations: BTreeMap<String, Vec<Load>>,
    /// Parts on a transporter.
    pub in_transit: Vec<Transit>,
    /// Every conveyor pallet and where it is.
    pub pallets: BTreeMap<String, PalletView>,
    /// Each conveyor's free (parked) pallets.
    pub free_pallets: BTreeMap<String, Vec<String>>,
    /// Parts that left the plant at an exit.
    pub shipped: u64,
    /// Whether some pallets wait only on one another ([`Plant::deadlock`]).
    pub deadlocked: bool,
    /// The pallets that do.
    pub deadlock: Vec<String>,
    /// The longest any pallet has waited (or waits now), in ms.
    pub longest_wait_ms: u64,
    /// Jammed tracks (`conveyor1.s2`: the track that ends at that stopper).
    pub jammed: Vec<String>,
    /// Pallets that stopped reporting.
    pub silent: Vec<String>,
    /// Transporters whose e-stop is pressed.
    pub estopped: Vec<String>,
}

impl Plant {
    /// The plant of `layout`, empty, at time 0: every conveyor's pallets parked
    /// (`<conveyor>/p1` to `p<N>`).
    pub fn new(layout: CellLayout) -> Plant {
        let mut pallets = BTreeMap::new();
        let mut loops = BTreeMap::new();
        for part in layout.parts.values() {
            if let Some(TransporterSpec::Conveyor(conveyor)) = &part.transporter {
                for n in 1..=conveyor.pallets {
                    let pallet = Pallet {
                        conveyor: part.holon.clone(),
                        place: Place::Parked,
                        part: None,
                        bound: None,
                        stopped: false,
                        waiting_since: None,
                        retiring: false,
                    };
                    pallets.insert(format!("{}/p{n}", part.holon), pallet);
                }
                let tracks = vec![VecDeque::new(); conveyor.stoppers.len()];
                let spec = conveyor.clone();
                loops.insert(part.holon.clone(), Loop { spec, tracks });
            }
        }
        let held = layout
            .locations()
            .map(|(_, l)| (l.id.clone(), Vec::new()))
            .collect();
        Plant {
            layout,
            held,
            transit: BTreeMap::new(),
            pallets,
            loops,
            shipped: 0,
            jammed: BTreeSet::new(),
            silent: BTreeSet::new(),
            estopped: BTreeMap::new(),
            clock: 0,
            longest_wait_ms: 0,
            arrived_steps: BTreeSet::new(),
            happened: Vec::new(),
        }
    }

    pub fn layout(&self) -> &CellLayout {
        &self.layout
    }

    /// The plant's time, ms since it started, as far as it has been advanced.
    pub fn now_ms(&self) -> u64 {
        self.clock
    }

    /// Where `part` is, in words (`at robot1.port`, `on conveyor1 from ... to ...`,
    /// `not in the plant`).
    pub fn where_is(&self, part: &str) -> String {
        if let Some(t) = self.transit.get(part) {
            let stopped = if t.stopped { ", stopped" } else { "" };
            return format!("on {} from {} to {}{stopped}", t.transporter, t.from, t.to);
        }
        match self.location_of(part) {
            Some(at) => format!("at {at}"),
            None => "not in the plant".into(),
        }
    }

    fn location_of(&self, part: &str) -> Option<&LocationId> {
        self.held
            .iter()
            .find(|(_, loads)| loads.iter().any(|l| l.part == part))
            .map(|(at, _)| at)
    }

    /// How many parts are on their way to `at`.
    fn coming(&self, at: &LocationId) -> usize {
        self.transit
            .values()
            .filter(|t| &t.to == at && !t.stopped)
            .count()
    }

    fn is_exit(&self, at: &LocationId) -> bool {
        matches!(
            self.layout.location(at).map(|l| l.role),
            Some(LocationRole::Exit | LocationRole::EntryExit)
        )
    }

    /// `transporter` begins to move `part` from `from` to `to`, at the plant's time
    /// (advance it first): checked, then the part is in transit. Returns how long the
    /// move takes unobstructed (the layout's travel: on a conveyor the distance at its
    /// speed and `dock_ms` twice; it takes longer when its pallet waits on the way).
    pub fn begin_move(
        &mut self,
        transporter: &str,
        part: &str,
        from: &LocationId,
        to: &LocationId,
    ) -> Result<Duration, PhysicalError> {
        let route = self
            .layout
            .routes(from, to)
            .into_iter()
            .find(|r| r.transporter == transporter)
            .ok_or_else(|| PhysicalError::NoRoute {
                transporter: transporter.into(),
                from: from.clone(),
                to: to.clone(),
            })?;
        if self.transit.contains_key(part) {
            return Err(PhysicalError::Moving {
                part: part.into(),
                where_it_is: self.where_is(part),
            });
        }
        let from_role = self.layout.location(from).map(|l| l.role);
        let new_material = matches!(
            from_role,
            Some(LocationRole::Entry | LocationRole::EntryExit)
        ) && self.location_of(part).is_none();
        if !new_material && self.location_of(part) != Some(from) {
            return Err(PhysicalError::NotThere {
                part: part.into(),
                at: from.clone(),
                where_it_is: self.where_is(part),
            });
        }
        let load = match self.held[from].iter().find(|l| l.part == part) {
            Some(load) => load.clone(),
            None => Load {
                part: part.into(),
                carrier: None,
            },
        };
        let load = if self.loops.contains_key(transporter) {
            self.board(transporter, load, from, to)
        } else {
            self.transfer(load, from, to)?
        };
        self.transit.insert(
            part.into(),
            Transit {
                load: load.clone(),
                transporter: transporter.into(),
                from: from.clone(),
                to: to.clone(),
                stopped: false,
                arrives_ms: (!self.loops.contains_key(transporter))
                    .then_some(self.clock + route.travel_ms),
                awaits_pallet: load.carrier.is_none() && self.loops.contains_key(transporter),
                began_ms: self.clock,
                command: None,
            },
        );
        if self.transit[part].awaits_pallet {
            self.happened.push(Happening::AwaitsPallet {
                part: part.into(),
                conveyor: transporter.into(),
                at: from.clone(),
            });
        }
        // A pallet that can leave at once does.
        self.settle();
        Ok(Duration::from_millis(route.travel_ms))
    }

    /// A transfer's move begins: `to` has a place (a transfer does not wait at a full
    /// one), the part leaves `from` and its pallet, which is parked.
    fn transfer(
        &mut self,
        mut load: Load,
        from: &LocationId,
        to: &LocationId,
    ) -> Result<Load, PhysicalError> {
        let capacity = self
            .layout
            .location(to)
            .expect("a routed location")
            .capacity;
        let (held, coming) = (self.held[to].len(), self.coming(to));
        if !self.is_exit(to) && held + coming >= capacity as usize {
            return Err(PhysicalError::Full {
                at: to.clone(),
                held,
                coming,
                capacity,
            });
        }
        if let Some(loads) = self.held.get_mut(from) {
            loads.retain(|l| l.part != load.part);
        }
        self.park(load.carrier.take());
        Ok(load)
    }

    /// The index of the stopper where `at` docks on `conveyor`.
    fn stopper_of(&self, conveyor: &str, at: &LocationId) -> Option<usize> {
        let dock = self.layout.location(at)?.dock.as_ref()?;
        if dock.conveyor != conveyor {
            return None;
        }
        self.loops[conveyor]
            .spec
            .stoppers
            .iter()
            .position(|s| s.name == dock.stopper)
    }

    /// `part`'s move stopped on the way (aborted), at the plant's time: it stays on its
    /// transporter, and its pallet where it is (on a track it holds its place, short of
    /// the stopper if it had not reached it).
    pub fn stop_move(&mut self, part: &str) {
        let Some(transit) = self.transit.get_mut(part) else {
            return;
        };
        transit.stopped = true;
        let Some(pallet) = transit.load.carrier.clone() else {
            return;
        };
        let clock = self.clock;
        if let Some(p) = self.pallets.get_mut(&pallet) {
            p.stopped = true;
            p.waiting_since = None;
            match &mut p.place {
                Place::Track { due, .. } | Place::Docking { due, .. } if *due > clock => {
                    *due = u64::MAX;
                }
                _ => {}
            }
        }
    }

    /// Whether `part` is still on its way with `transporter` (its move has not ended in
    /// the plant), and if so why, in words.
    pub fn on_its_way(&self, part: &str, transporter: &str) -> Option<String> {
        let transit = self
            .transit
            .get(part)
            .filter(|t| t.transporter == transporter)?;
        if self.estopped.contains_key(transporter) {
            return Some(format!("{transporter} is e-stopped"));
        }
        if transit.stopped {
            return Some("stopped".into());
        }
        if transit.awaits_pallet {
            return Some(format!("waits at {} for a free pallet", transit.from));
        }
        let pallet = transit.load.carrier.as_deref();
        let waits = pallet.and_then(|p| self.waits_for(p));
        Some(match (pallet, waits) {
            (Some(pallet), Some(what)) => format!("{pallet} waits: {what}"),
            _ => "on its way".into(),
        })
    }

    /// Whether `part`'s move has left its origin: its pallet is no longer docked at the
    /// move's `from` (it rides the loop, or docks at the destination). False while the
    /// pallet is docked there (waiting to leave, or stopped by an abort), while the part
    /// waits for a pallet, for a transfer's move (no pallet leaves), and for a part not
    /// in transit.
    pub fn left_origin(&self, part: &str) -> bool {
        let Some(transit) = self.transit.get(part).filter(|t| !t.awaits_pallet) else {
            return false;
        };
        transit
            .load
            .carrier
            .as_deref()
            .and_then(|p| self.pallets.get(p))
            .is_some_and(|p| p.place != Place::Docked(transit.from.clone()))
    }

    /// The pallet `part` rides, if it rides one.
    pub fn carrier_of(&self, part: &str) -> Option<String> {
        if let Some(t) = self.transit.get(part) {
            return t.load.carrier.clone();
        }
        self.held
            .values()
            .flatten()
            .find(|l| l.part == part)
            .and_then(|l| l.carrier.clone())
    }

    /// The part at one of `station`'s ports (the first, by location), if any: the one
    /// a command naming no part works on.
    pub fn part_at_station(&self, station: &str) -> Option<String> {
        let layout = self.layout.parts.get(station)?;
        layout
            .locations
            .iter()
            .filter(|l| matches!(l.role, LocationRole::Port | LocationRole::Input))
            .find_map(|l| self.held.get(&l.id).and_then(|loads| loads.first()))
            .map(|load| load.part.clone())
    }

    /// Whether `station` can work on a part now: one is at one of its ports (`part`,
    /// where the command names it). A station without ports in the layout is not in the
    /// material flow: anything goes.
    pub fn check_work(&self, station: &str, part: Option<&str>) -> Result<(), PhysicalError> {
        let Some(layout) = self.layout.parts.get(station) else {
            return Ok(());
        };
        let ports: Vec<&LocationId> = layout
            .locations
            .iter()
            .filter(|l| matches!(l.role, LocationRole::Port | LocationRole::Input))
            .map(|l| &l.id)
            .collect();
        if ports.is_empty() {
            return Ok(());
        }
        let names = ports
            .iter()
            .map(|p| p.as_str())
            .collect::<Vec<_>>()
            .join(", ");
        let here = |id: &&LocationId| self.held.get(*id).map_or(&[][..], Vec::as_slice);
        match part {
            Some(part) if !ports.iter().any(|p| here(p).iter().any(|l| l.part == part)) => {
                Err(PhysicalError::NotAtStation {
                    part: part.into(),
                    ports: names,
                    where_it_is: self.where_is(part),
                })
            }
            None if ports.iter().all(|p| here(p).is_empty()) => {
                Err(PhysicalError::Empty { ports: names })
            }
            _ => Ok(()),
        }
    }

    /// Where everything is.
    pub fn view(&self) -> PlantView {
        let mut free_pallets: BTreeMap<String, Vec<String>> =
            self.loops.keys().map(|c| (c.clone(), Vec::new())).collect();
        for (id, p) in &self.pallets {
            if p.place == Place::Parked {
                free_pallets
                    .entry(p.conveyor.clone())
                    .or_default()
                    .push(id.clone());
            }
        }
        let deadlock = self.deadlock();
        PlantView {
            now_ms: self.clock,
            locations: self
                .held
                .iter()
                .map(|(id, loads)| (id.to_string(), loads.clone()))
                .collect(),
            in_transit: self.transit.values().cloned().collect(),
            pallets: self.pallet_views(),
            free_pallets,
            shipped: self.shipped,
            deadlocked: !deadlock.is_empty(),
            deadlock,
            longest_wait_ms: self.longest_wait_ms(),
            jammed: self.jammed.iter().map(Dock::to_string).collect(),
            silent: self.silent.iter().cloned().collect(),
            estopped: self.estopped.keys().cloned().collect(),
        }
    }
}

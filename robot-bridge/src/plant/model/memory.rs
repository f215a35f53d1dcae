//! The plant's memory: all of its physical state but the layout, so that a plant
//! simulator killed and started again goes on from where it was (docs/material-flow.md,
//! "When the plant simulator dies"). The physical world does not die with its
//! controllers: a pallet on its way goes on to where it was bound (as a real palletised
//! conveyor's pallet carries its destination on its tag), a part stays where it is.
//!
//! The memory also keeps which ended moves their controller has not told of yet
//! ([`Plant::note_arrival`], [`Plant::end_told`]) and each move's command
//! ([`Plant::note_command`]), so that the plant started again ends each move as its
//! controller would have: its step done, in the trace once.

use std::collections::{BTreeMap, BTreeSet, VecDeque};

use schemas::layout::{CellLayout, Dock, LocationId};
use serde::{Deserialize, Serialize};

use super::{Load, MoveCommand, Pallet, Place, Plant, Transit};

/// Everything the plant knows but its layout, as written with the state file.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlantMemory {
    /// The plant's time: ms since it first started.
    clock: u64,
    /// What each location holds, in the order it arrived.
    held: BTreeMap<LocationId, Vec<Load>>,
    /// Parts on a transporter.
    transit: BTreeMap<String, Transit>,
    /// Every pallet.
    pallets: BTreeMap<String, Pallet>,
    /// Each conveyor's tracks, each a queue of pallets, first the one nearest its
    /// stopper.
    tracks: BTreeMap<String, Vec<VecDeque<String>>>,
    /// Parts that left the plant at an exit.
    shipped: u64,
    /// Jammed tracks.
    jammed: BTreeSet<Dock>,
    /// Pallets that stopped reporting.
    silent: BTreeSet<String>,
    /// Transporters whose e-stop is pressed, since when.
    estopped: BTreeMap<String, u64>,
    /// The longest wait that is over.
    longest_wait_ms: u64,
    /// Moves ended in the plant whose controller has not told of it: (transporter, step).
    arrived_steps: BTreeSet<(String, String)>,
}

/// A move the plant remembers as under way when it starts again.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ResumedMove {
    /// The part it moves.
    pub part: String,
    /// Its transporter.
    pub transporter: String,
    /// Its pallet, if it rides one.
    pub carrier: Option<String>,
    /// When it began (plant ms).
    pub began_ms: u64,
    /// Its command, if the plant was told it.
    pub command: Option<MoveCommand>,
    /// Aborted on the way before the plant died: it does not go on.
    pub stopped: bool,
}

impl Plant {
    /// What the plant knows, but its layout.
    pub fn memory(&self) -> PlantMemory {
        PlantMemory {
            clock: self.clock,
            held: self.held.clone(),
            transit: self.transit.clone(),
            pallets: self.pallets.clone(),
            tracks: self
                .loops
                .iter()
                .map(|(c, l)| (c.clone(), l.tracks.clone()))
                .collect(),
            shipped: self.shipped,
            jammed: self.jammed.clone(),
            silent: self.silent.clone(),
            estopped: self.estopped.clone(),
            longest_wait_ms: self.longest_wait_ms,
            arrived_steps: self.arrived_steps.clone(),
        }
    }

    /// The plant of `layout` as `memory` left it. Err: every way the memory does not fit
    /// the layout (a pallet, conveyor, track or location it does not have), each in
    /// words; nothing is resumed then.
    pub fn resume(layout: CellLayout, memory: PlantMemory) -> Result<Plant, Vec<String>> {
        let mut plant = Plant::new(layout);
        let mut problems = Vec::new();
        let known: BTreeSet<&String> = plant.pallets.keys().collect();
        let remembered: BTreeSet<&String> = memory.pallets.keys().collect();
        for missing in known.difference(&remembered) {
            problems.push(format!(
                "pallet {missing} of the layout is not in the memory"
            ));
        }
        for extra in remembered.difference(&known) {
            problems.push(format!("pallet {extra} is not in the layout"));
        }
        let location = |id: &LocationId, problems: &mut Vec<String>, what: &str| {
            if plant.layout.location(id).is_none() {
                problems.push(format!("{what}: location {id} is not in the layout"));
            }
        };
        for id in memory.held.keys() {
            location(id, &mut problems, "held");
        }
        for (part, t) in &memory.transit {
            location(&t.from, &mut problems, part);
            location(&t.to, &mut problems, part);
            if !plant.layout.parts.contains_key(&t.transporter) {
                problems.push(format!(
                    "{part}: transporter {} is not in the layout",
                    t.transporter
                ));
            }
        }
        for (id, pallet) in &memory.pallets {
            match &pallet.place {
                Place::Docked(at) | Place::Docking { at, .. } => location(at, &mut problems, id),
                Place::Track { track, .. } => {
                    let tracks = plant.loops.get(&pallet.conveyor).map(|l| l.tracks.len());
                    if tracks.is_none_or(|n| *track >= n) {
                        problems.push(format!("{id}: track {track} is not on its conveyor"));
                    }
                }
                Place::Parked | Place::Retired => {}
            }
        }
        for (conveyor, tracks) in &memory.tracks {
            match plant.loops.get(conveyor) {
                Some(l) if l.tracks.len() == tracks.len() => {}
                Some(l) => problems.push(format!(
                    "conveyor {conveyor} has {} tracks, the memory {}",
                    l.tracks.len(),
                    tracks.len()
                )),
                None => problems.push(format!("conveyor {conveyor} is not in the layout")),
            }
            for pallet in tracks.iter().flatten() {
                if !memory.pallets.contains_key(pallet) {
                    problems.push(format!("{conveyor}: pallet {pallet} on a track is unknown"));
                }
            }
        }
        if !problems.is_empty() {
            return Err(problems);
        }
        for (id, loads) in memory.held {
            plant.held.insert(id, loads);
        }
        for (conveyor, tracks) in memory.tracks {
            plant.loops.get_mut(&conveyor).expect("checked").tracks = tracks;
        }
        plant.transit = memory.transit;
        plant.pallets = memory.pallets;
        plant.clock = memory.clock;
        plant.shipped = memory.shipped;
        plant.jammed = memory.jammed;
        plant.silent = memory.silent;
        plant.estopped = memory.estopped;
        plant.longest_wait_ms = memory.longest_wait_ms;
        plant.arrived_steps = memory.arrived_steps;
        Ok(plant)
    }

    /// The command that began `part`'s move (its action and step id), remembered with
    /// it.
    pub fn note_command(&mut self, part: &str, action: &str, step: Option<&str>) {
        if let Some(transit) = self.transit.get_mut(part) {
            transit.command = Some(MoveCommand {
                action: action.to_string(),
                step: step.map(str::to_string),
            });
        }
    }

    /// `transit` has ended in the plant: its step, if it has one, is kept until its
    /// controller tells of the end.
    pub(super) fn note_arrival(&mut self, transit: &Transit) {
        let step = transit.command.as_ref().and_then(|c| c.step.clone());
        if let Some(step) = step {
            self.arrived_steps
                .insert((transit.transporter.clone(), step));
        }
    }

    /// `transporter`'s controller has told of the end of the move of step `step`.
    pub fn end_told(&mut self, transporter: &str, step: &str) {
        self.arrived_steps
            .remove(&(transporter.to_string(), step.to_string()));
    }

    /// Forgets every ended move still untold: a plant started again has settled their
    /// steps (or their controller is not fenced any more), and nobody will tell them.
    pub fn forget_untold(&mut self) {
        self.arrived_steps.clear();
    }

    /// Whether `transporter`'s move of step `step` has ended in the plant, untold.
    pub fn arrived_untold(&self, transporter: &str, step: &str) -> bool {
        self.arrived_steps
            .contains(&(transporter.to_string(), step.to_string()))
    }

    /// Every move under way (or stopped on the way), for a plant started again.
    pub fn moves_under_way(&self) -> Vec<ResumedMove> {
        self.transit
            .iter()
            .map(|(part, t)| ResumedMove {
                part: part.clone(),
                transporter: t.transporter.clone(),
                carrier: t.load.carrier.clone(),
                began_ms: t.began_ms,
                command: t.command.clone(),
                stopped: t.stopped,
            })
            .collect()
    }
}

//! The plant's physical state: where every part and pallet is. Pure: no I/O, no clock;
//! the controllers' physics ([`super::controller`]) ask it and tell it.
//!
//! | what a controller does | what the plant checks | what changes |
//! |---|---|---|
//! | a transporter begins a move of part P from A to B | the transporter reaches A to B; P is at A (a part unknown to the plant at an entry is new raw material); B has a place (counting the parts on their way there); on a conveyor, P has a pallet or a free one is there | P is in transit on the transporter (with its pallet); A has a place more |
//! | the move ends (arrived) | | P is at B; at an exit P leaves the plant and its pallet is free again |
//! | the move is aborted | | P stays on the transporter, stopped: in transit from A to B until someone puts it somewhere |
//! | a station works on a part (pick, place, inspect) | a part is at one of its ports (P, where the command names it) | |
//! | a transfer takes a part off its pallet | | the pallet is free again (back on its conveyor's loop) |
//! | a track is jammed (`jam conveyor1.s2`: the track that ends at that stopper) | | a move whose way runs along it does not end until it is cleared |
//! | a pallet stops reporting (`silence conveyor1/p2`) | | a move it carries ends in the plant, but its controller does not say so |
//! | a transporter's e-stop is pressed (`estop conveyor1 MS`) | | its moves do not go on until it is released |

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;

use schemas::layout::{CellLayout, Dock, LocationId, LocationRole, TransporterSpec};
use serde::Serialize;

/// A part and the carrier it rides on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Load {
    pub part: String,
    /// Its pallet (`conveyor1/p2`), if it is on one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub carrier: Option<String>,
}

/// A part on a transporter.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Transit {
    pub load: Load,
    pub transporter: String,
    pub from: LocationId,
    pub to: LocationId,
    /// Aborted on the way: it is nowhere the plant can tell until it is put somewhere.
    pub stopped: bool,
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
    #[error("{at} is full ({held} held, {coming} on their way, capacity {capacity})")]
    Full {
        at: LocationId,
        held: usize,
        coming: usize,
        capacity: u32,
    },
    #[error("no free pallet on {conveyor}")]
    NoPallet { conveyor: String },
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

/// The plant's physical state.
#[derive(Debug, Clone)]
pub struct Plant {
    layout: CellLayout,
    /// What each location holds now, in the order it arrived.
    held: BTreeMap<LocationId, Vec<Load>>,
    /// Parts on a transporter, by part.
    transit: BTreeMap<String, Transit>,
    /// Each conveyor's pallets that carry nothing (riding its loop).
    free_pallets: BTreeMap<String, Vec<String>>,
    /// Parts that left the plant at an exit.
    shipped: u64,
    /// Jammed tracks, each named by the stopper it ends at.
    jammed: BTreeSet<Dock>,
    /// Pallets that stopped reporting.
    silent: BTreeSet<String>,
    /// Transporters whose e-stop is pressed: their moves do not go on.
    estopped: BTreeSet<String>,
}

/// Where everything is, as the plant's state file and `--state-file` readers see it.
#[derive(Debug, Clone, Serialize)]
pub struct PlantView {
    /// What each location holds (every location of the layout, empty ones too).
    pub locations: BTreeMap<String, Vec<Load>>,
    /// Parts on a transporter.
    pub in_transit: Vec<Transit>,
    /// Each conveyor's pallets that carry nothing.
    pub free_pallets: BTreeMap<String, Vec<String>>,
    /// Parts that left the plant at an exit.
    pub shipped: u64,
    /// Jammed tracks (`conveyor1.s2`: the track that ends at that stopper).
    pub jammed: Vec<String>,
    /// Pallets that stopped reporting.
    pub silent: Vec<String>,
    /// Transporters whose e-stop is pressed.
    pub estopped: Vec<String>,
}

impl Plant {
    /// The plant of `layout`, empty: every conveyor's pallets free on its loop
    /// (`<conveyor>/p1` to `p<N>`).
    pub fn new(layout: CellLayout) -> Plant {
        let mut free_pallets = BTreeMap::new();
        for part in layout.parts.values() {
            if let Some(TransporterSpec::Conveyor(conveyor)) = &part.transporter {
                let pallets = (1..=conveyor.pallets)
                    .map(|n| format!("{}/p{n}", part.holon))
                    .collect();
                free_pallets.insert(part.holon.clone(), pallets);
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
            free_pallets,
            shipped: 0,
            jammed: BTreeSet::new(),
            silent: BTreeSet::new(),
            estopped: BTreeSet::new(),
        }
    }

    pub fn layout(&self) -> &CellLayout {
        &self.layout
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

    /// `transporter` begins to move `part` from `from` to `to`: checked, then the part
    /// is in transit. Returns how long the move takes.
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
        let destination = self.layout.location(to).expect("a routed location");
        let (held, coming) = (self.held[to].len(), self.coming(to));
        if held + coming >= destination.capacity as usize {
            return Err(PhysicalError::Full {
                at: to.clone(),
                held,
                coming,
                capacity: destination.capacity,
            });
        }
        let on_conveyor = self.free_pallets.contains_key(transporter);
        let mut load = if new_material {
            Load {
                part: part.into(),
                carrier: None,
            }
        } else {
            let loads = self.held.get_mut(from).expect("a location of the layout");
            let at = loads
                .iter()
                .position(|l| l.part == part)
                .expect("found above");
            loads[at].clone()
        };
        let carried_here = load
            .carrier
            .as_ref()
            .is_some_and(|c| c.starts_with(&format!("{transporter}/")));
        if on_conveyor && !carried_here && self.free_pallets[transporter].is_empty() {
            return Err(PhysicalError::NoPallet {
                conveyor: transporter.into(),
            });
        }
        // Checked: now it moves.
        if !new_material {
            let loads = self.held.get_mut(from).expect("a location of the layout");
            loads.retain(|l| l.part != part);
        }
        if !carried_here {
            // Off its old pallet (back on that conveyor's loop), onto one of this one's.
            self.free(load.carrier.take());
            if on_conveyor {
                load.carrier = self
                    .free_pallets
                    .get_mut(transporter)
                    .and_then(|pallets| pallets.pop());
            }
        }
        self.transit.insert(
            part.into(),
            Transit {
                load,
                transporter: transporter.into(),
                from: from.clone(),
                to: to.clone(),
                stopped: false,
            },
        );
        Ok(Duration::from_millis(route.travel_ms))
    }

    /// `part`'s move ends: it is at its destination (or, at an exit, leaves the plant
    /// and its pallet is free). False if it was not moving.
    pub fn end_move(&mut self, part: &str) -> bool {
        let Some(transit) = self.transit.remove(part) else {
            return false;
        };
        let exit = matches!(
            self.layout.location(&transit.to).map(|l| l.role),
            Some(LocationRole::Exit | LocationRole::EntryExit)
        );
        if exit {
            self.free(transit.load.carrier);
            self.shipped += 1;
        } else {
            self.held
                .get_mut(&transit.to)
                .expect("a location of the layout")
                .push(transit.load);
        }
        true
    }

    /// `part`'s move stopped on the way (aborted): it stays on its transporter.
    pub fn stop_move(&mut self, part: &str) {
        if let Some(transit) = self.transit.get_mut(part) {
            transit.stopped = true;
        }
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

    fn free(&mut self, carrier: Option<String>) {
        let Some(carrier) = carrier else { return };
        let conveyor = carrier.split('/').next().unwrap_or_default().to_string();
        self.free_pallets.entry(conveyor).or_default().push(carrier);
    }

    /// Where everything is.
    pub fn view(&self) -> PlantView {
        PlantView {
            locations: self
                .held
                .iter()
                .map(|(id, loads)| (id.to_string(), loads.clone()))
                .collect(),
            in_transit: self.transit.values().cloned().collect(),
            free_pallets: self.free_pallets.clone(),
            shipped: self.shipped,
            jammed: self.jammed.iter().map(Dock::to_string).collect(),
            silent: self.silent.iter().cloned().collect(),
            estopped: self.estopped.iter().cloned().collect(),
        }
    }

    /// Presses (true) or releases (false) `resource`'s e-stop: a transporter's moves do
    /// not go on while it is pressed.
    pub fn estop(&mut self, resource: &str, pressed: bool) {
        if pressed {
            self.estopped.insert(resource.to_string());
        } else {
            self.estopped.remove(resource);
        }
    }

    /// Jams the track that ends at `at` (true), or clears it (false). An error if the
    /// layout has no such conveyor stopper.
    pub fn jam(&mut self, at: Dock, jammed: bool) -> Result<(), String> {
        let known = self
            .layout
            .conveyor(&at.conveyor)
            .is_some_and(|c| c.stoppers.iter().any(|s| s.name == at.stopper));
        if !known {
            return Err(format!("{at}: no such conveyor stopper in the plant"));
        }
        if jammed {
            self.jammed.insert(at);
        } else {
            self.jammed.remove(&at);
        }
        Ok(())
    }

    /// `pallet` stops reporting (true) or reports again (false).
    pub fn silence(&mut self, pallet: &str, silent: bool) -> Result<(), String> {
        let known = self.free_pallets.values().flatten().any(|p| p == pallet)
            || self
                .held
                .values()
                .flatten()
                .chain(self.transit.values().map(|t| &t.load))
                .any(|l| l.carrier.as_deref() == Some(pallet));
        if !known {
            return Err(format!("{pallet}: no such pallet in the plant"));
        }
        if silent {
            self.silent.insert(pallet.to_string());
        } else {
            self.silent.remove(pallet);
        }
        Ok(())
    }

    /// Why `part`'s move cannot end now: a jammed track on its way (its conveyor's
    /// tracks from the stopper after where it left to the one it goes to).
    pub fn held_up(&self, part: &str) -> Option<String> {
        let transit = self.transit.get(part)?;
        if self.estopped.contains(&transit.transporter) {
            return Some(format!("{} is e-stopped", transit.transporter));
        }
        let conveyor = self.layout.conveyor(&transit.transporter)?;
        let dock_of = |id: &LocationId| self.layout.location(id)?.dock.clone();
        let (from, to) = (dock_of(&transit.from)?, dock_of(&transit.to)?);
        let at = |name: &str| conveyor.stoppers.iter().position(|s| s.name == name);
        let (start, end) = (at(&from.stopper)?, at(&to.stopper)?);
        let n = conveyor.stoppers.len();
        let mut i = start;
        while i != end {
            i = (i + 1) % n;
            let track = Dock {
                conveyor: transit.transporter.clone(),
                stopper: conveyor.stoppers[i].name.clone(),
            };
            if self.jammed.contains(&track) {
                return Some(format!("the track to {track} is jammed"));
            }
        }
        None
    }

    /// Whether `part` rides a pallet that stopped reporting.
    pub fn unreported(&self, part: &str) -> bool {
        self.transit
            .get(part)
            .and_then(|t| t.load.carrier.as_ref())
            .is_some_and(|pallet| self.silent.contains(pallet))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(holon: &str, toml_text: &str) -> schemas::layout::LayoutPart {
        schemas::layout::part_from_toml(holon, toml_text).unwrap_or_else(|e| panic!("{e}"))
    }

    fn id(s: &str) -> LocationId {
        LocationId::try_from(s.to_string()).unwrap()
    }

    /// Two stations of one port each on a conveyor of two pallets, an entry and exit,
    /// and a transfer robot between the stations.
    fn plant() -> Plant {
        let station = |dock: &str| {
            format!("[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n")
        };
        Plant::new(CellLayout::assemble([
            part(
                "conveyor1",
                r#"
[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"
[layout.conveyor]
length_mm = 3000
speed_mm_s = 1000
pallets = 2
stoppers = [{ name = "load", at_mm = 0 }, { name = "s1", at_mm = 1000 }, { name = "s2", at_mm = 2000 }]
"#,
            ),
            part("robot1", &station("conveyor1.s1")),
            part("robot2", &station("conveyor1.s2")),
            part(
                "mover1",
                "[layout.transfer]\nbetween = [\"robot1.port\", \"robot2.port\"]\nmove_ms = 500\n",
            ),
        ]))
    }

    #[test]
    fn a_part_rides_a_pallet_from_the_entry_through_the_stations_and_leaves() {
        let mut plant = plant();
        assert_eq!(
            plant.check_work("robot1", None),
            Err(PhysicalError::Empty {
                ports: "robot1.port".into()
            })
        );
        let took = plant
            .begin_move(
                "conveyor1",
                "o-1",
                &id("conveyor1.load"),
                &id("robot1.port"),
            )
            .unwrap();
        assert_eq!(took, Duration::from_millis(1000));
        assert_eq!(
            plant.where_is("o-1"),
            "on conveyor1 from conveyor1.load to robot1.port"
        );
        assert_eq!(plant.view().free_pallets["conveyor1"].len(), 1);
        // Not there yet: nothing to pick.
        assert!(plant.check_work("robot1", Some("o-1")).is_err());
        assert!(plant.end_move("o-1"));
        assert_eq!(plant.where_is("o-1"), "at robot1.port");
        plant.check_work("robot1", Some("o-1")).unwrap();
        plant.check_work("robot1", None).unwrap();
        assert!(matches!(
            plant.check_work("robot1", Some("o-2")),
            Err(PhysicalError::NotAtStation { .. })
        ));
        // The transfer takes it off its pallet, which goes back to the loop.
        plant
            .begin_move("mover1", "o-1", &id("robot1.port"), &id("robot2.port"))
            .unwrap();
        assert_eq!(plant.view().free_pallets["conveyor1"].len(), 2);
        plant.end_move("o-1");
        // Back on the conveyor (a pallet comes for it) to the exit: it leaves.
        let took = plant
            .begin_move(
                "conveyor1",
                "o-1",
                &id("robot2.port"),
                &id("conveyor1.load"),
            )
            .unwrap();
        assert_eq!(took, Duration::from_millis(1000));
        plant.end_move("o-1");
        let view = plant.view();
        assert_eq!(view.shipped, 1);
        assert_eq!(view.free_pallets["conveyor1"].len(), 2);
        assert!(view.locations.values().all(Vec::is_empty), "{view:?}");
        assert_eq!(plant.where_is("o-1"), "not in the plant");
    }

    #[test]
    fn a_jammed_track_holds_the_moves_along_it_and_a_silent_pallet_goes_unreported() {
        let mut plant = plant();
        let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
        let dock = |s: &str| Dock::try_from(s.to_string()).unwrap();
        assert!(plant.jam(dock("conveyor1.s9"), true).is_err());
        plant.jam(dock("conveyor1.s2"), true).unwrap();
        // load -> s1 does not pass the track to s2; load -> s2 does.
        plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
        assert_eq!(plant.held_up("o-1"), None);
        plant.begin_move("conveyor1", "o-2", &load, &r2).unwrap();
        assert_eq!(
            plant.held_up("o-2").as_deref(),
            Some("the track to conveyor1.s2 is jammed")
        );
        plant.jam(dock("conveyor1.s2"), false).unwrap();
        assert_eq!(plant.held_up("o-2"), None);
        // A transfer has no tracks.
        plant.end_move("o-1");
        plant.end_move("o-2");
        let pallet = plant.view().locations["robot2.port"][0]
            .carrier
            .clone()
            .unwrap();
        assert!(plant.silence("conveyor1/p9", true).is_err());
        plant.silence(&pallet, true).unwrap();
        plant.begin_move("conveyor1", "o-2", &r2, &load).unwrap();
        assert!(plant.unreported("o-2"));
        assert!(!plant.unreported("o-1"));
        assert_eq!(plant.view().silent, vec![pallet]);
    }

    #[test]
    fn the_plant_refuses_what_cannot_happen() {
        let mut plant = plant();
        let (load, r1, r2) = (id("conveyor1.load"), id("robot1.port"), id("robot2.port"));
        plant.begin_move("conveyor1", "o-1", &load, &r1).unwrap();
        // A full port refuses a pallet: the one on its way counts.
        assert!(matches!(
            plant.begin_move("conveyor1", "o-2", &load, &r1),
            Err(PhysicalError::Full {
                held: 0,
                coming: 1,
                ..
            })
        ));
        plant.end_move("o-1");
        assert!(matches!(
            plant.begin_move("conveyor1", "o-2", &load, &r1),
            Err(PhysicalError::Full {
                held: 1,
                coming: 0,
                ..
            })
        ));
        // A part is moved from where it is, by a transporter that reaches both ends.
        assert!(matches!(
            plant.begin_move("conveyor1", "o-1", &r2, &load),
            Err(PhysicalError::NotThere { .. })
        ));
        assert!(matches!(
            plant.begin_move("mover1", "o-1", &r1, &load),
            Err(PhysicalError::NoRoute { .. })
        ));
        // Two pallets: the third part waits for one.
        plant.begin_move("conveyor1", "o-2", &load, &r2).unwrap();
        assert!(matches!(
            plant.begin_move("conveyor1", "o-3", &load, &r2),
            Err(PhysicalError::Full { .. })
        ));
        plant.end_move("o-2");
        let refused = plant.begin_move("conveyor1", "o-3", &load, &load);
        assert!(refused.is_err(), "{refused:?}");
        // Aborted on the way, a part stays on its transporter, stopped, and its
        // destination's place is no longer promised to it.
        plant.begin_move("mover1", "o-1", &r1, &r2).unwrap_err();
        plant.begin_move("conveyor1", "o-2", &r2, &load).unwrap();
        plant.stop_move("o-2");
        assert_eq!(
            plant.where_is("o-2"),
            "on conveyor1 from robot2.port to conveyor1.load, stopped"
        );
        plant.begin_move("mover1", "o-1", &r1, &r2).unwrap();
        assert!(matches!(
            plant.begin_move("conveyor1", "o-1", &r2, &load),
            Err(PhysicalError::Moving { .. })
        ));
    }
}

//! The cell's layout: the parts of its holons put together, and what is wrong with them
//! together (a dock on a conveyor that is not there, a location nothing reaches, a port
//! a part cannot get to from an entry or leave for an exit).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::fmt;

use serde::Serialize;

use super::{ConveyorSpec, LayoutPart, LocationId, LocationSpec, TransporterSpec};

/// The parts put together.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct CellLayout {
    /// Every holon's part, by holon name.
    pub parts: BTreeMap<String, LayoutPart>,
    /// What is wrong, each naming the holon and field it is about.
    pub problems: Vec<Problem>,
}

/// Something wrong with the layout, named by the holon and the field of its config.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Problem {
    /// The holon whose config it is about (None: the cell as a whole).
    pub holon: Option<String>,
    /// The field of that config (`layout.locations[0].dock`).
    pub field: Option<String>,
    pub message: String,
}

impl fmt::Display for Problem {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if let Some(holon) = &self.holon {
            write!(f, "{holon}: ")?;
        }
        if let Some(field) = &self.field {
            write!(f, "{field}: ")?;
        }
        f.write_str(&self.message)
    }
}

/// One way to move a part from a location to another: a transporter and how long the
/// move takes (travel only, no queueing).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Route {
    pub transporter: String,
    pub travel_ms: u64,
}

impl CellLayout {
    /// Puts the parts together (a holon named twice: its first part) and finds what is
    /// wrong with them together.
    pub fn assemble(parts: impl IntoIterator<Item = LayoutPart>) -> CellLayout {
        let mut layout = CellLayout::default();
        for part in parts {
            if layout.parts.contains_key(&part.holon) {
                layout.problems.push(Problem {
                    holon: Some(part.holon.clone()),
                    field: None,
                    message: "declared twice; the first part is kept".into(),
                });
                continue;
            }
            layout.parts.insert(part.holon.clone(), part);
        }
        layout.check_docks();
        layout.check_transfers();
        layout.check_reach();
        layout
    }

    /// Every location, with the holon's index of it in `[[layout.locations]]`.
    pub fn locations(&self) -> impl Iterator<Item = (usize, &LocationSpec)> {
        self.parts
            .values()
            .flat_map(|p| p.locations.iter().enumerate())
    }

    pub fn location(&self, id: &LocationId) -> Option<&LocationSpec> {
        self.parts
            .get(id.holon())?
            .locations
            .iter()
            .find(|l| &l.id == id)
    }

    /// The conveyor of that name, if it is in the layout.
    pub fn conveyor(&self, name: &str) -> Option<&ConveyorSpec> {
        match &self.parts.get(name)?.transporter {
            Some(TransporterSpec::Conveyor(conveyor)) => Some(conveyor),
            _ => None,
        }
    }

    /// The direct moves from `from` to `to` (one transporter each), shortest first.
    pub fn routes(&self, from: &LocationId, to: &LocationId) -> Vec<Route> {
        let (Some(a), Some(b)) = (self.location(from), self.location(to)) else {
            return Vec::new();
        };
        if !a.role.gives_parts() || !b.role.takes_parts() || from == to {
            return Vec::new();
        }
        let mut routes = Vec::new();
        for part in self.parts.values() {
            match &part.transporter {
                Some(TransporterSpec::Conveyor(conveyor)) => {
                    let on_it = |l: &LocationSpec| {
                        l.dock
                            .as_ref()
                            .filter(|d| d.conveyor == part.holon)
                            .map(|d| d.stopper.clone())
                    };
                    if let (Some(s), Some(t)) = (on_it(a), on_it(b)) {
                        if let Some(ms) = conveyor.travel_ms(&s, &t) {
                            routes.push(Route {
                                transporter: part.holon.clone(),
                                travel_ms: ms + 2 * conveyor.dock_ms,
                            });
                        }
                    }
                }
                Some(TransporterSpec::Transfer(transfer))
                    if transfer.between.contains(from) && transfer.between.contains(to) =>
                {
                    routes.push(Route {
                        transporter: part.holon.clone(),
                        travel_ms: transfer.move_ms,
                    });
                }
                _ => {}
            }
        }
        routes.sort_by_key(|r| r.travel_ms);
        routes
    }

    fn problem(&mut self, holon: &str, field: String, message: String) {
        self.problems.push(Problem {
            holon: Some(holon.to_string()),
            field: Some(field),
            message,
        });
    }

    /// Every dock names a conveyor of the layout and one of its stoppers, and no two
    /// locations share a stopper.
    fn check_docks(&mut self) {
        let mut found = Vec::new();
        let mut taken: BTreeMap<String, LocationId> = BTreeMap::new();
        for (i, location) in self.locations() {
            let Some(dock) = &location.dock else { continue };
            let field = format!("layout.locations[{i}].dock");
            let holon = location.id.holon().to_string();
            let Some(conveyor) = self.conveyor(&dock.conveyor) else {
                found.push((
                    holon,
                    field,
                    format!("{}: no conveyor of that name in the layout", dock.conveyor),
                ));
                continue;
            };
            if !conveyor.stoppers.iter().any(|s| s.name == dock.stopper) {
                let known: Vec<&str> = conveyor.stoppers.iter().map(|s| s.name.as_str()).collect();
                found.push((
                    holon,
                    field,
                    format!(
                        "{dock}: {} has no stopper {:?} (it has {})",
                        dock.conveyor,
                        dock.stopper,
                        known.join(", ")
                    ),
                ));
                continue;
            }
            if let Some(other) = taken.insert(dock.to_string(), location.id.clone()) {
                found.push((
                    holon,
                    field,
                    format!("{dock} is already the dock of {other}: one location per stopper"),
                ));
            }
        }
        for (holon, field, message) in found {
            self.problem(&holon, field, message);
        }
    }

    /// Every location a transfer names is in the layout.
    fn check_transfers(&mut self) {
        let mut found = Vec::new();
        for part in self.parts.values() {
            let Some(TransporterSpec::Transfer(transfer)) = &part.transporter else {
                continue;
            };
            for (i, id) in transfer.between.iter().enumerate() {
                if self.location(id).is_none() {
                    found.push((
                        part.holon.clone(),
                        format!("layout.transfer.between[{i}]"),
                        format!("{id}: no location of that name in the layout"),
                    ));
                }
            }
        }
        for (holon, field, message) in found {
            self.problem(&holon, field, message);
        }
    }

    /// Every location is reached by a transporter; every station port can be reached
    /// from an entry and can reach an exit.
    fn check_reach(&mut self) {
        let ids: Vec<(usize, LocationSpec)> =
            self.locations().map(|(i, l)| (i, l.clone())).collect();
        if ids.is_empty() {
            return;
        }
        let moves: BTreeMap<&LocationId, Vec<&LocationId>> = ids
            .iter()
            .map(|(_, a)| {
                let to = ids
                    .iter()
                    .filter(|(_, b)| !self.routes(&a.id, &b.id).is_empty())
                    .map(|(_, b)| &b.id)
                    .collect();
                (&a.id, to)
            })
            .collect();
        let reached = |starts: Vec<&LocationId>, forward: bool| -> BTreeSet<LocationId> {
            let mut seen: BTreeSet<LocationId> = starts.iter().map(|id| (*id).clone()).collect();
            let mut queue: VecDeque<&LocationId> = starts.into_iter().collect();
            while let Some(at) = queue.pop_front() {
                for (from, tos) in &moves {
                    let next: Vec<&LocationId> = if forward {
                        if *from == at {
                            tos.clone()
                        } else {
                            Vec::new()
                        }
                    } else if tos.contains(&at) {
                        vec![*from]
                    } else {
                        Vec::new()
                    };
                    for id in next {
                        if seen.insert(id.clone()) {
                            queue.push_back(id);
                        }
                    }
                }
            }
            seen
        };
        let entries: Vec<&LocationId> = ids
            .iter()
            .filter(|(_, l)| {
                matches!(
                    l.role,
                    super::LocationRole::Entry | super::LocationRole::EntryExit
                )
            })
            .map(|(_, l)| &l.id)
            .collect();
        let exits: Vec<&LocationId> = ids
            .iter()
            .filter(|(_, l)| {
                matches!(
                    l.role,
                    super::LocationRole::Exit | super::LocationRole::EntryExit
                )
            })
            .map(|(_, l)| &l.id)
            .collect();
        let no_entry = entries.is_empty();
        let no_exit = exits.is_empty();
        let from_entry = reached(entries, true);
        let to_exit = reached(exits, false);
        let mut found = Vec::new();
        for (i, location) in &ids {
            let holon = location.id.holon().to_string();
            let field = format!("layout.locations[{i}]");
            let touched = moves[&location.id].len()
                + moves
                    .values()
                    .filter(|tos| tos.contains(&&location.id))
                    .count();
            if touched == 0 {
                found.push((holon, field, format!("{}: unreachable: no transporter reaches it (no dock on a conveyor, in no transfer)", location.id)));
                continue;
            }
            if !location.role.is_station_port() {
                continue;
            }
            if !no_entry && !from_entry.contains(&location.id) && location.role.takes_parts() {
                found.push((
                    holon.clone(),
                    field.clone(),
                    format!(
                        "{}: unreachable: no part from an entry can get here",
                        location.id
                    ),
                ));
            }
            if !no_exit && !to_exit.contains(&location.id) && location.role.gives_parts() {
                found.push((
                    holon,
                    field,
                    format!(
                        "{}: a dead end: no part here can get to an exit",
                        location.id
                    ),
                ));
            }
        }
        for (holon, field, message) in found {
            self.problem(&holon, field, message);
        }
        let ports = ids.iter().any(|(_, l)| l.role.is_station_port());
        for (missing, what) in [(no_entry, "entry"), (no_exit, "exit")] {
            if missing && ports {
                self.problems.push(Problem {
                    holon: None,
                    field: None,
                    message: format!("no {what}: the layout has station ports but no location whose role is {what} or entry_exit"),
                });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(holon: &str, toml_text: &str) -> LayoutPart {
        crate::layout::part_from_toml(holon, toml_text).unwrap_or_else(|e| panic!("{e}"))
    }

    fn conveyor() -> LayoutPart {
        part(
            "conveyor1",
            r#"
[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"

[layout.conveyor]
length_mm = 4000
speed_mm_s = 200
pallets = 3
stoppers = [{ name = "load", at_mm = 0 }, { name = "s1", at_mm = 1000 }, { name = "s2", at_mm = 3000 }]
"#,
        )
    }

    fn station(holon: &str, dock: &str) -> LayoutPart {
        part(
            holon,
            &format!("[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n"),
        )
    }

    fn messages(layout: &CellLayout) -> Vec<String> {
        layout.problems.iter().map(|p| p.to_string()).collect()
    }

    #[test]
    fn stations_on_a_conveyor_make_a_layout_without_problems() {
        let layout = CellLayout::assemble([
            conveyor(),
            station("robot1", "conveyor1.s1"),
            station("inspect1", "conveyor1.s2"),
        ]);
        assert!(layout.problems.is_empty(), "{:?}", messages(&layout));
        let id = |s: &str| LocationId::try_from(s.to_string()).unwrap();
        assert_eq!(
            layout.routes(&id("robot1.port"), &id("inspect1.port")),
            vec![Route {
                transporter: "conveyor1".into(),
                travel_ms: 10_000
            }]
        );
        assert_eq!(
            layout.routes(&id("inspect1.port"), &id("robot1.port"))[0].travel_ms,
            10_000
        );
    }

    #[test]
    fn a_transfer_robot_is_a_second_way() {
        let transfer = part(
            "mover1",
            "[layout.transfer]\nbetween = [\"robot1.port\", \"inspect1.port\"]\nmove_ms = 2500\n",
        );
        let layout = CellLayout::assemble([
            conveyor(),
            station("robot1", "conveyor1.s1"),
            station("inspect1", "conveyor1.s2"),
            transfer,
        ]);
        assert!(layout.problems.is_empty(), "{:?}", messages(&layout));
        let id = |s: &str| LocationId::try_from(s.to_string()).unwrap();
        let routes = layout.routes(&id("robot1.port"), &id("inspect1.port"));
        assert_eq!(routes.len(), 2);
        assert_eq!(routes[0].transporter, "mover1");
    }

    #[test]
    fn what_the_parts_name_of_each_other_is_checked_where_they_meet() {
        let layout = CellLayout::assemble([
            conveyor(),
            station("robot1", "conveyor1.s9"),
            station("robot2", "conveyor2.s1"),
            station("robot3", "conveyor1.s1"),
            station("robot4", "conveyor1.s1"),
            part(
                "mover1",
                "[layout.transfer]\nbetween = [\"robot3.port\", \"robot5.port\"]\nmove_ms = 10\n",
            ),
        ]);
        let found = messages(&layout);
        assert!(found.contains(&"robot1: layout.locations[0].dock: conveyor1.s9: conveyor1 has no stopper \"s9\" (it has load, s1, s2)".to_string()), "{found:?}");
        assert!(found.contains(&"robot2: layout.locations[0].dock: conveyor2: no conveyor of that name in the layout".to_string()), "{found:?}");
        assert!(found.contains(&"robot4: layout.locations[0].dock: conveyor1.s1 is already the dock of robot3.port: one location per stopper".to_string()), "{found:?}");
        assert!(found.contains(&"mover1: layout.transfer.between[1]: robot5.port: no location of that name in the layout".to_string()), "{found:?}");
        assert!(found.contains(&"robot1: layout.locations[0]: robot1.port: unreachable: no transporter reaches it (no dock on a conveyor, in no transfer)".to_string()), "{found:?}");
    }

    #[test]
    fn a_port_must_be_reached_from_an_entry_and_reach_an_exit() {
        // robot1 is on the conveyor with the entry; robot2 and the exit are reached only
        // by a transfer between them: nothing from the entry gets to robot2, nothing at
        // robot1 gets to the exit.
        let entry_only = part(
            "conveyor1",
            "[[layout.locations]]\nname = \"load\"\nrole = \"entry\"\ndock = \"conveyor1.load\"\n\n[layout.conveyor]\nlength_mm = 4000\nspeed_mm_s = 200\npallets = 1\nstoppers = [{ name = \"load\", at_mm = 0 }, { name = \"s1\", at_mm = 1000 }]\n",
        );
        let layout = CellLayout::assemble([
            entry_only,
            station("robot1", "conveyor1.s1"),
            part(
                "robot2",
                "[[layout.locations]]\nname = \"port\"\nrole = \"port\"\n",
            ),
            part(
                "unload1",
                "[[layout.locations]]\nname = \"out\"\nrole = \"exit\"\n",
            ),
            part(
                "mover1",
                "[layout.transfer]\nbetween = [\"robot2.port\", \"unload1.out\"]\nmove_ms = 10\n",
            ),
        ]);
        assert_eq!(
            messages(&layout),
            vec![
                "robot1: layout.locations[0]: robot1.port: a dead end: no part here can get to an exit".to_string(),
                "robot2: layout.locations[0]: robot2.port: unreachable: no part from an entry can get here".to_string(),
            ]
        );
        let no_entry = CellLayout::assemble([
            station("robot1", "conveyor1.s1"),
            part("conveyor1", "[layout.conveyor]\nlength_mm = 100\nspeed_mm_s = 10\npallets = 1\nstoppers = [{ name = \"s1\", at_mm = 0 }, { name = \"s2\", at_mm = 50 }]\n"),
        ]);
        let found = messages(&no_entry);
        assert!(found.iter().any(|m| m.starts_with("no entry")), "{found:?}");
        assert!(found.iter().any(|m| m.starts_with("no exit")), "{found:?}");
    }
}

//! A scenario on a shipped cell (`deploy/scenarios/aip-*.toml` documents the format):
//! which cell, how fast its plant runs, which orders are released when, and what
//! happens to the cell meanwhile.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::Deserialize;

/// The scenario file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellScenario {
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// The cell's directory (its `cell.toml`), relative to the scenario file.
    pub cell: PathBuf,
    /// Plant time runs this many times as fast as the wall clock (1 to 1000).
    #[serde(default = "twenty")]
    pub time_scale: u32,
    /// The orders, released in groups.
    pub releases: Vec<Release>,
    /// What happens to the cell while it runs.
    #[serde(default)]
    pub events: Vec<Event>,
}

fn twenty() -> u32 {
    20
}

/// A group of orders of one product released together.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Release {
    /// The product (a product holon of the cell: `<product>.toml` in its directory).
    pub product: String,
    /// How many orders.
    #[serde(default = "one")]
    pub count: u32,
    /// When, in plant seconds from the run's start.
    #[serde(default)]
    pub at_s: f64,
    /// Their priority (-1000 to 1000; a rush order has more than 0).
    #[serde(default)]
    pub priority: i32,
    /// When they are due, in plant seconds from the run's start (their tardiness is
    /// counted against it).
    #[serde(default)]
    pub due_s: Option<f64>,
}

fn one() -> u32 {
    1
}

/// Something that happens to the cell at a moment of plant time.
#[derive(Debug, Clone, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Event {
    /// A station breaks down: its controller is e-stopped for `repair_s` plant seconds
    /// (it refuses every command meanwhile, its holon says it is unavailable and its
    /// PackML unit goes to Aborted); then it is ready again and the maintenance
    /// operator clears, resets and starts its unit (`cell packml`), as after any
    /// e-stop.
    Breakdown {
        at_s: f64,
        station: String,
        repair_s: f64,
    },
    /// A station is added while the cell runs: its resource holon is started from
    /// `<station>.toml` in the cell's directory (its controller is in plant.toml
    /// already), and joins the layout by starting.
    HotAdd { at_s: f64, station: String },
    /// An inspection station finds faulty parts: its controller answers its next
    /// `count` inspections `inspect_fail` (the plant's `fail STATION N`), and each
    /// rejected part goes where its plan's `on_reject` says (on the AIP-PRIMECA cell:
    /// recovery on M6, then inspected again).
    InspectionFail {
        at_s: f64,
        station: String,
        count: u32,
    },
    /// A shuttle (a pallet of a conveyor, `monorail/p3`) is taken out of service (the
    /// plant's `retire`): at once if it is free, else once its part has left it; moves
    /// that find no free shuttle wait for one. Put back `back_s` plant seconds later
    /// (the plant's `restore`), if it says. The bench tells the conveyor's holon both
    /// (`cell carrier`), as the operator who took it off the track would.
    ShuttleOut {
        at_s: f64,
        shuttle: String,
        #[serde(default)]
        back_s: Option<f64>,
    },
}

impl Event {
    pub fn at_s(&self) -> f64 {
        match self {
            Event::Breakdown { at_s, .. }
            | Event::HotAdd { at_s, .. }
            | Event::InspectionFail { at_s, .. }
            | Event::ShuttleOut { at_s, .. } => *at_s,
        }
    }
}

/// What the bench does at a moment of a run.
#[derive(Debug, Clone)]
pub enum Happening {
    /// Releases `releases[i]`.
    Release(usize),
    /// Plays an event.
    Event(Event),
    /// The repaired station's unit cleared, reset and started by the operator.
    Repaired { station: String },
    /// The shuttle taken out is put back.
    ShuttleBack { shuttle: String },
}

impl CellScenario {
    /// Everything the bench does, with its plant seconds from the start, in order.
    pub fn timeline(&self) -> Vec<(f64, Happening)> {
        let mut timeline: Vec<(f64, Happening)> = self
            .releases
            .iter()
            .enumerate()
            .map(|(i, r)| (r.at_s, Happening::Release(i)))
            .collect();
        for event in &self.events {
            timeline.push((event.at_s(), Happening::Event(event.clone())));
            if let Event::Breakdown {
                at_s,
                station,
                repair_s,
            } = event
            {
                let station = station.clone();
                timeline.push((at_s + repair_s, Happening::Repaired { station }));
            }
            if let Event::ShuttleOut {
                at_s,
                shuttle,
                back_s: Some(back_s),
            } = event
            {
                let shuttle = shuttle.clone();
                timeline.push((at_s + back_s, Happening::ShuttleBack { shuttle }));
            }
        }
        timeline.sort_by(|a, b| a.0.total_cmp(&b.0));
        timeline
    }
}

impl CellScenario {
    /// Whether the scenario file at `path` is one on a cell (it names one).
    pub fn is_one(path: &Path) -> bool {
        std::fs::read_to_string(path)
            .ok()
            .and_then(|text| toml::from_str::<toml::Table>(&text).ok())
            .is_some_and(|t| t.contains_key("cell"))
    }

    /// Reads and checks the scenario at `path`; its cell's directory resolved.
    pub fn load(path: &Path) -> Result<CellScenario> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let mut scenario: CellScenario =
            toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
        let base = path.parent().unwrap_or(Path::new("."));
        scenario.cell = base.join(&scenario.cell);
        let at = |what: String| format!("{}: {what}", path.display());
        if !scenario.cell.join("cell.toml").is_file() {
            bail!(at(format!(
                "cell: no cell.toml in {}",
                scenario.cell.display()
            )));
        }
        if !(1..=1000).contains(&scenario.time_scale) {
            bail!(at("time_scale: from 1 to 1000".into()));
        }
        if scenario.releases.is_empty() {
            bail!(at("releases: at least one".into()));
        }
        for (i, release) in scenario.releases.iter().enumerate() {
            if !scenario
                .cell
                .join(format!("{}.toml", release.product))
                .is_file()
            {
                bail!(at(format!(
                    "releases[{i}].product: no {}.toml in the cell",
                    release.product
                )));
            }
            if release.count == 0 || release.at_s < 0.0 {
                bail!(at(format!(
                    "releases[{i}]: count at least 1, at_s at least 0"
                )));
            }
        }
        for (i, event) in scenario.events.iter().enumerate() {
            let (field, holon) = match event {
                Event::Breakdown { station, .. }
                | Event::HotAdd { station, .. }
                | Event::InspectionFail { station, .. } => ("station", station.as_str()),
                Event::ShuttleOut { shuttle, .. } => {
                    let conveyor = shuttle
                        .split_once("/p")
                        .filter(|(_, n)| n.parse::<u32>().is_ok_and(|n| n > 0))
                        .map(|(conveyor, _)| conveyor);
                    let Some(conveyor) = conveyor else {
                        bail!(at(format!(
                            "events[{i}].shuttle: {shuttle:?} is not CONVEYOR/pN"
                        )));
                    };
                    ("shuttle", conveyor)
                }
            };
            if matches!(event, Event::InspectionFail { count: 0, .. }) {
                bail!(at(format!("events[{i}].count: at least 1")));
            }
            if matches!(event, Event::ShuttleOut { back_s: Some(b), .. } if *b <= 0.0) {
                bail!(at(format!("events[{i}].back_s: above 0")));
            }
            if !scenario.cell.join(format!("{holon}.toml")).is_file() {
                bail!(at(format!(
                    "events[{i}].{field}: no {holon}.toml in the cell"
                )));
            }
            if event.at_s() < 0.0 {
                bail!(at(format!("events[{i}].at_s: at least 0")));
            }
        }
        Ok(scenario)
    }

    /// How many orders it releases.
    pub fn orders(&self) -> u32 {
        self.releases.iter().map(|r| r.count).sum()
    }

    /// The stations it hot-adds.
    pub fn added(&self) -> Vec<String> {
        self.events
            .iter()
            .filter_map(|e| match e {
                Event::HotAdd { station, .. } => Some(station.clone()),
                Event::Breakdown { .. }
                | Event::InspectionFail { .. }
                | Event::ShuttleOut { .. } => None,
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_cell_scenarios_load() {
        let dir = holarchy_tests::workspace_root().join("deploy/scenarios");
        let mut loaded = 0;
        for entry in std::fs::read_dir(&dir).unwrap().flatten() {
            let path = entry.path();
            if CellScenario::is_one(&path) {
                let scenario = CellScenario::load(&path).unwrap();
                assert!(scenario.orders() > 0, "{}", path.display());
                loaded += 1;
            }
        }
        assert!(loaded >= 6, "{loaded} cell scenarios");
    }

    #[test]
    fn a_scenario_naming_what_its_cell_lacks_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let cell = holarchy_tests::workspace_root().join("deploy/cells/aip-primeca");
        let write = |body: &str| {
            let path = dir.path().join("s.toml");
            std::fs::write(
                &path,
                format!(
                    "name = \"s\"\ncell = {:?}\n{body}",
                    cell.display().to_string()
                ),
            )
            .unwrap();
            format!("{:#}", CellScenario::load(&path).unwrap_err())
        };
        let no_product = write("[[releases]]\nproduct = \"z\"\n");
        assert!(no_product.contains("releases[0].product"), "{no_product}");
        let no_station = write(
            "[[releases]]\nproduct = \"b\"\n[[events]]\nkind = \"hot_add\"\nat_s = 1\nstation = \"m9\"\n",
        );
        assert!(no_station.contains("events[0].station"), "{no_station}");
        let shuttle = |name: &str| {
            write(&format!(
                "[[releases]]\nproduct = \"b\"\n[[events]]\nkind = \"shuttle_out\"\nat_s = 1\nshuttle = \"{name}\"\n"
            ))
        };
        for bad in ["monorail", "monorail/p0", "monorail/x", "tram/p1"] {
            let said = shuttle(bad);
            assert!(said.contains("events[0].shuttle"), "{bad}: {said}");
        }
        // Three out at once, more than the shuttles beyond the cell's 8 homes: taken,
        // since the monorail holon is told (`cell carrier`) and lets in only as many
        // parts as shuttles are in service.
        let out = |name: &str, at: u32, back: &str| {
            format!("[[events]]\nkind = \"shuttle_out\"\nat_s = {at}\nshuttle = \"{name}\"\n{back}")
        };
        let path = dir.path().join("s.toml");
        std::fs::write(
            &path,
            format!(
                "name = \"s\"\ncell = {:?}\n[[releases]]\nproduct = \"b\"\n{}{}{}",
                cell.display().to_string(),
                out("monorail/p1", 1, ""),
                out("monorail/p2", 2, "back_s = 100\n"),
                out("monorail/p3", 50, "")
            ),
        )
        .unwrap();
        CellScenario::load(&path).unwrap();
        let unknown = write("[[releases]]\nproduct = \"b\"\nwhen = 3\n");
        assert!(unknown.contains("when"), "{unknown}");
        let scale = write("time_scale = 0\n[[releases]]\nproduct = \"b\"\n");
        assert!(scale.contains("time_scale"), "{scale}");
    }
}

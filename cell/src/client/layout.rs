//! `cell layout`: the cell's layout (docs/material-flow.md), live from the holons that
//! serve (each answers its own part on `resource/<name>/layout`), or checked from a
//! cell's manifest and configs before they run (`--check DIR`).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use schemas::layout::{CellLayout, LayoutSection, Problem, TransporterSpec};
use schemas::CellKeys;

use crate::up::manifest::Manifest;

/// The parts every serving resource answers within `timeout`, put together.
pub async fn live(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<CellLayout> {
    let answered = holon::layout::ask(session, keys, timeout)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let unreadable = answered.unreadable.into_iter().map(|message| Problem {
        holon: None,
        field: None,
        message,
    });
    let parts = answered.parts;
    let mut layout = CellLayout::assemble(parts);
    layout.problems.extend(unreadable);
    Ok(layout)
}

/// The layout the resource holons of the manifest `dir`/cell.toml state in their
/// configs (`--config`, with `--name` where the manifest gives one), and which config
/// each holon's part comes from.
pub fn from_manifest(dir: &Path) -> Result<(CellLayout, BTreeMap<String, PathBuf>)> {
    let manifest = Manifest::load(dir)?;
    let mut parts = Vec::new();
    let mut problems = Vec::new();
    let mut sources = BTreeMap::new();
    for process in &manifest.processes {
        let program = Path::new(&process.program)
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        if program != "holon-node" {
            continue;
        }
        let flag = |name: &str| {
            process
                .args
                .iter()
                .position(|a| a == name)
                .and_then(|i| process.args.get(i + 1))
        };
        let Some(config) = flag("--config") else {
            continue;
        };
        let path = dir.join(config);
        let Some((name, section)) = layout_of(&path, flag("--name").map(String::as_str))? else {
            continue;
        };
        sources.insert(name.clone(), path);
        match section.part(&name) {
            Ok(part) => parts.push(part),
            Err(e) => problems.push(Problem {
                holon: Some(name),
                field: Some(e.field),
                message: e.message,
            }),
        }
    }
    let mut layout = CellLayout::assemble(parts);
    layout.problems.splice(0..0, problems);
    Ok((layout, sources))
}

/// A resource config's holon name and `[layout]` ([`schemas::layout::from_resource_config`]).
fn layout_of(path: &Path, name_override: Option<&str>) -> Result<Option<(String, LayoutSection)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    schemas::layout::from_resource_config(&text, name_override)
        .map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// The layout as `cell layout` prints it: its locations, its transporters, then what is
/// wrong (each problem named by the holon, with its config file where known).
pub fn render(cell: &str, layout: &CellLayout, sources: &BTreeMap<String, PathBuf>) -> String {
    let mut out = String::new();
    let locations: Vec<_> = layout.locations().map(|(_, l)| l).collect();
    let _ = writeln!(
        out,
        "layout of cell {cell}: {} holons, {} locations",
        layout.parts.len(),
        locations.len()
    );
    if !locations.is_empty() {
        let _ = writeln!(
            out,
            "{:<24} {:<11} {:>8}  reached at",
            "location", "role", "capacity"
        );
        for l in &locations {
            let at = l
                .dock
                .as_ref()
                .map(|d| d.to_string())
                .unwrap_or_else(|| "-".into());
            let _ = writeln!(
                out,
                "{:<24} {:<11} {:>8}  {at}",
                l.id.as_str(),
                l.role.as_str(),
                l.capacity
            );
        }
    }
    for part in layout.parts.values() {
        match &part.transporter {
            Some(TransporterSpec::Conveyor(conveyor)) => {
                let stoppers: Vec<String> = conveyor
                    .stoppers
                    .iter()
                    .map(|s| {
                        let docked = locations.iter().find(|l| {
                            l.dock
                                .as_ref()
                                .is_some_and(|d| d.conveyor == part.holon && d.stopper == s.name)
                        });
                        match docked {
                            Some(l) => format!("{} ({})", s.name, l.id),
                            None => format!("{} (free)", s.name),
                        }
                    })
                    .collect();
                let _ = writeln!(
                    out,
                    "conveyor {}: {} pallets, {} mm at {} mm/s (a loop in {:.1} s); stoppers {}",
                    part.holon,
                    conveyor.pallets,
                    conveyor.length_mm,
                    conveyor.speed_mm_s,
                    f64::from(conveyor.length_mm) / f64::from(conveyor.speed_mm_s),
                    stoppers.join(", ")
                );
            }
            Some(TransporterSpec::Transfer(transfer)) => {
                let _ = writeln!(
                    out,
                    "transfer {}: between {} and {}, {} ms a move",
                    part.holon, transfer.between[0], transfer.between[1], transfer.move_ms
                );
            }
            None => {}
        }
    }
    if layout.problems.is_empty() {
        let _ = writeln!(out, "no problems");
    } else {
        let _ = writeln!(out, "{} problems:", layout.problems.len());
        for problem in &layout.problems {
            let source = problem
                .holon
                .as_ref()
                .and_then(|h| sources.get(h))
                .map(|p| format!("{}: ", p.display()))
                .unwrap_or_default();
            let _ = writeln!(out, "  {source}{problem}");
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_demo_cells_layout_has_no_problems() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/cells/demo");
        let (layout, sources) = from_manifest(&dir).unwrap();
        let shown = render("demo", &layout, &sources);
        assert!(layout.problems.is_empty(), "{shown}");
        for location in [
            "conveyor1.load",
            "robot1.port",
            "robot2.port",
            "inspect1.port",
        ] {
            assert!(shown.contains(location), "{shown}");
        }
        assert!(shown.contains("s3 (free)"), "{shown}");
    }

    #[test]
    fn a_config_error_names_its_file_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let demo = Path::new(env!("CARGO_MANIFEST_DIR")).join("../deploy/cells/demo");
        for file in [
            "cell.toml",
            "robot1.toml",
            "robot2.toml",
            "inspect1.toml",
            "conveyor1.toml",
            "transfer1.toml",
            "breaker.toml",
            "planner.toml",
            "orders1.toml",
        ] {
            std::fs::copy(demo.join(file), dir.path().join(file)).unwrap();
        }
        let robot2 = dir.path().join("robot2.toml");
        let text = std::fs::read_to_string(&robot2).unwrap();
        std::fs::write(
            &robot2,
            text.replace("dock = \"conveyor1.s2\"", "dock = \"conveyor1.s1\""),
        )
        .unwrap();
        let inspect1 = dir.path().join("inspect1.toml");
        let text = std::fs::read_to_string(&inspect1).unwrap();
        std::fs::write(&inspect1, text.replace("capacity = 1", "capacity = 0")).unwrap();
        let (layout, sources) = from_manifest(dir.path()).unwrap();
        let shown = render("demo", &layout, &sources);
        assert!(
            shown.contains("inspect1.toml: inspect1: layout.locations[0].capacity: 0 is below one"),
            "{shown}"
        );
        assert!(
            shown.contains("robot2.toml: robot2: layout.locations[0].dock: conveyor1.s1 is already the dock of robot1.port"),
            "{shown}"
        );
    }
}

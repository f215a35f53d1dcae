//! A scenario's shuttles taken out, against the cell's homes (docs/scheduling.md, "A
//! shuttle taken out"): every part in the cell rides a shuttle of its own, and the
//! order-node admits as many parts as the buffers have homes. With fewer shuttles in
//! service than homes, a part admitted to a home reserves its first station's port and
//! waits at the entry for a shuttle, while the parts in the cell, each on its shuttle,
//! wait for that port: the cell deadlocks, and nothing in the control sees it (the
//! transporter holon does not know which shuttles are in service). Such a scenario is
//! refused before it runs, saying how many may be out at once.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use anyhow::{anyhow, bail, Result};
use schemas::layout::{LocationRole, TransporterSpec};

use super::scenario::Event;

/// Refuses `events` on the cell in `cell` (its `plant.toml`) if at some moment fewer of
/// a conveyor's shuttles are in service than the cell's buffers have homes.
pub fn check(cell: &Path, events: &[Event]) -> Result<()> {
    let outs: Vec<(&str, f64, Option<f64>)> = events
        .iter()
        .filter_map(|event| match event {
            Event::ShuttleOut {
                at_s,
                shuttle,
                back_s,
            } => Some((shuttle.as_str(), *at_s, back_s.map(|b| at_s + b))),
            _ => None,
        })
        .collect();
    if outs.is_empty() {
        return Ok(());
    }
    let plant_path = cell.join("plant.toml");
    let plant = robot_bridge::plant::read(&plant_path).map_err(|e| anyhow!("{e}"))?;
    let layout = robot_bridge::plant::layout_of(&plant_path, &plant).map_err(|e| anyhow!("{e}"))?;
    let homes: u32 = layout
        .locations()
        .map(|(_, l)| l)
        .filter(|l| l.role == LocationRole::Buffer)
        .map(|l| l.capacity)
        .sum();
    let pallets: BTreeMap<&str, u32> = layout
        .parts
        .values()
        .filter_map(|part| match &part.transporter {
            Some(TransporterSpec::Conveyor(c)) => Some((part.holon.as_str(), c.pallets)),
            _ => None,
        })
        .collect();
    // At each moment a shuttle goes out, the shuttles out then, by conveyor.
    for &(_, at, _) in &outs {
        let mut out: BTreeMap<&str, BTreeSet<&str>> = BTreeMap::new();
        for &(shuttle, from, back) in &outs {
            if from <= at && back.is_none_or(|back| at < back) {
                let conveyor = shuttle.split_once('/').map_or(shuttle, |(c, _)| c);
                out.entry(conveyor).or_default().insert(shuttle);
            }
        }
        for (conveyor, shuttles) in out {
            let Some(&total) = pallets.get(conveyor) else {
                bail!("events: {conveyor} is not a conveyor of the cell's plant");
            };
            let left = total.saturating_sub(shuttles.len() as u32);
            if left < homes {
                bail!(
                    "events: at {at} s {} of {conveyor}'s {total} shuttles are out, leaving {left} \
                     for the cell's {homes} homes: a part admitted to a home would wait for a \
                     shuttle while holding its first station's port, and the cell deadlocks \
                     (docs/scheduling.md, \"A shuttle taken out\"); take out at most {} at once",
                    shuttles.len(),
                    total.saturating_sub(homes)
                );
            }
        }
    }
    Ok(())
}

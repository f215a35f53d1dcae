//! A cell whose parts move, as the moves section starts it: the plant simulator
//! (`plant-sim`) with a conveyor, stations and transfers, each resource holon on its
//! own controller connection of the plant, products and the demo's order-node.
//!
//! The conveyor `conveyor1` holds the cell's entry and exit (`conveyor1.load`) and the
//! parts' homes (`conveyor1.buffer`); a station has one port, docked on the conveyor or
//! reached by a transfer of its own between the load and the port. A station without a
//! layout (a "still" station) works as on a robot-sim: it is the baseline of a step
//! whose part needs no move.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use holarchy_tests::{resource_config, start_holon, start_node, Cell, PlantProcess, Process};
use schemas::HolonId;

use crate::cells::router;

/// The conveyor's loop: its length, its speed and how long docking takes. A move
/// between two stoppers 1,000 mm apart takes 1000 / 20000 s (50 ms) plus docking out
/// and in (2 x 10 ms): 70 ms, unobstructed (docs/material-flow.md, section 5).
pub const LOOP_MM: u32 = 2000;
/// The pallets' speed.
pub const SPEED_MM_S: u32 = 20_000;
/// Leaving the loop into a location, or coming back onto it.
pub const DOCK_MS: u64 = 10;
/// Where the stopper of a station docked on the conveyor is (the load's is at 0).
pub const STATION_STOPPER_MM: u32 = 1000;

/// A station of the cell.
pub struct Station {
    /// Its holon's name.
    pub name: String,
    /// The service its step offers (a pick and a place).
    pub service: String,
    /// How its port is reached: `Some(stopper)` docked on the conveyor, `None` by a
    /// transfer of its own (`tr<n>` for station `st<n>`).
    pub dock: Option<String>,
    /// Whether it takes part in the material flow at all (a port); a station without
    /// one works whatever it is told, as on a robot-sim.
    pub has_port: bool,
}

/// What the cell holds.
pub struct Spec {
    /// The cell's name (its zenoh keys).
    pub cell: String,
    /// Its stations.
    pub stations: Vec<Station>,
    /// Each station controller's time per action, in ms.
    pub action_ms: u64,
    /// A transfer's `move_ms`.
    pub transfer_ms: u64,
    /// The buffer's places: how many parts may be in the cell at once.
    pub buffer: u32,
    /// Products: name, the service of their one step, whether their parts move.
    pub products: Vec<(String, String, bool)>,
}

/// The running cell: every process killed when it is dropped.
pub struct MoveCell {
    /// The cell's router (this process), as the other sections' cells.
    pub cell: Cell,
    /// The plant simulator.
    pub plant: PlantProcess,
    /// The resource holons by name: conveyor1, the stations, the transfers.
    pub resources: BTreeMap<String, Process>,
    /// The product holons by name.
    pub products: BTreeMap<String, Process>,
    /// The order-node `orders1`.
    pub orders: Process,
    /// The cell's directory (configs, journals, logs).
    pub dir: PathBuf,
}

impl MoveCell {
    /// Writes the configs and the plant file of `spec` in `dir`, starts the plant, the
    /// resources (each until it serves), the products and the order-node.
    pub async fn start(dir: &Path, spec: &Spec) -> Result<MoveCell> {
        let cell = router(&spec.cell, None).await?;
        let Written {
            plant_file,
            resources: names,
        } = write(dir, spec)?;
        let plant = PlantProcess::start(dir, &plant_file);
        let data = dir.join("data");
        let data = data.to_str().context("a data directory that is UTF-8")?;
        let mut resources = BTreeMap::new();
        for name in &names {
            let process = start_node(
                dir,
                &dir.join(format!("{name}.toml")),
                cell.keys.cell(),
                &cell.endpoint,
                &plant.controllers[name],
                &["--data-dir", data],
            )?;
            resources.insert(name.clone(), process);
        }
        for name in &names {
            cell.wait_alive(&HolonId::resource(name)?)
                .await
                .with_context(|| format!("{name}: {}", resources[name].stderr()))?;
            cell.wait_serving(name).await?;
        }
        let mut products = BTreeMap::new();
        for (name, service, moves) in &spec.products {
            let config = product_config(dir, name, service, *moves)?;
            products.insert(
                name.clone(),
                start_holon(dir, "holon-node", &config, name, &cell, &[])?,
            );
            cell.wait_alive(&HolonId::new(schemas::HolonKind::Product, name)?)
                .await?;
        }
        let orders = start_orders(&cell, dir, "power_loss").await?;
        Ok(MoveCell {
            cell,
            plant,
            resources,
            products,
            orders,
            dir: dir.to_path_buf(),
        })
    }

    /// Stops the order-node and starts it again with its journal's `durability`, on a
    /// journal of its own (nothing to recover).
    pub async fn restart_orders(&mut self, durability: &str) -> Result<()> {
        self.orders.kill();
        // Until the router has seen the killed node's link close, its token is there:
        // the new node's, waited for below, would be taken for it, and a work order
        // sent meanwhile would find no order-node.
        self.cell
            .wait_token_gone(&self.cell.keys.host("order-node", "orders1"))
            .await?;
        self.orders = start_orders(&self.cell, &self.dir, durability).await?;
        Ok(())
    }

    /// Every process of the cell, named: the order-node, the plant, the products, the
    /// resources.
    pub fn processes(&self) -> Vec<(String, i32)> {
        [
            ("orders1".to_string(), self.orders.pid()),
            ("plant-sim".to_string(), self.plant.process.pid()),
        ]
        .into_iter()
        .chain(self.products.iter().map(|(n, p)| (n.clone(), p.pid())))
        .chain(self.resources.iter().map(|(n, p)| (n.clone(), p.pid())))
        .collect()
    }
}

/// The configs and the plant file of a cell, written.
pub struct Written {
    /// The plant file's text (its layout names the configs beside it).
    pub plant_file: String,
    /// Every resource holon, in the order they start.
    pub resources: Vec<String>,
}

/// Writes every config of `spec` in `dir` (and its `data` directory): conveyor1, the
/// stations, a transfer for each station not docked on the conveyor; the plant file's
/// text is returned, not written (the plant starts on it).
pub fn write(dir: &Path, spec: &Spec) -> Result<Written> {
    std::fs::create_dir_all(dir.join("data"))?;
    let mut layout = vec!["conveyor1.toml".to_string()];
    std::fs::write(dir.join("conveyor1.toml"), conveyor(spec))?;
    let mut controllers = vec![controller("conveyor1", 0)];
    let mut transfers = Vec::new();
    for station in &spec.stations {
        station_config(dir, station)?;
        if station.has_port {
            layout.push(format!("{}.toml", station.name));
        }
        controllers.push(controller(&station.name, spec.action_ms));
        if station.has_port && station.dock.is_none() {
            let name = transfer_of(&station.name);
            transfer_config(dir, &name, &station.name, spec.transfer_ms)?;
            layout.push(format!("{name}.toml"));
            controllers.push(controller(&name, 0));
            transfers.push(name);
        }
    }
    let plant_file = format!("layout = {layout:?}\n\n{}", controllers.concat());
    let resources = ["conveyor1".to_string()]
        .into_iter()
        .chain(spec.stations.iter().map(|s| s.name.clone()))
        .chain(transfers)
        .collect();
    Ok(Written {
        plant_file,
        resources,
    })
}

/// The demo's order-node `orders1` with its journal's `durability` (the demo's is
/// `power_loss`), its journal in `DIR/data-orders-<durability>`, serving.
async fn start_orders(cell: &Cell, dir: &Path, durability: &str) -> Result<Process> {
    let demo = std::fs::read_to_string(holarchy_tests::demo_config("orders1.toml"))?;
    let config = dir.join(format!("orders1-{durability}.toml"));
    std::fs::write(
        &config,
        demo.replace(
            "durability = \"power_loss\"",
            &format!("durability = \"{durability}\""),
        ),
    )?;
    let data = dir.join(format!("data-orders-{durability}"));
    std::fs::create_dir_all(&data)?;
    let data = data.to_str().context("a data directory that is UTF-8")?;
    let process = start_holon(
        dir,
        "order-node",
        &config,
        "orders1",
        cell,
        &["--data-dir", data],
    )?;
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await?;
    Ok(process)
}

/// The transfer that serves station `station` (`st3` -> `tr3`).
pub fn transfer_of(station: &str) -> String {
    format!(
        "tr{}",
        station.trim_start_matches(|c: char| c.is_alphabetic())
    )
}

/// A `[[controller]]` of the plant file for `resource`, its actions `delay_ms` each.
fn controller(resource: &str, delay_ms: u64) -> String {
    format!("[[controller]]\nresource = \"{resource}\"\nlisten = \"127.0.0.1:0\"\ndelay_ms = {delay_ms}\n\n")
}

/// What every resource of the cell shares: its controller (the plant's address is
/// given by `--controller`), its agenda, and the journal of the booking figures
/// (`process_crash`, as the cycle's target).
fn resource_head(name: &str) -> String {
    format!(
        r#"cell = "unset"
name = "{name}"

[controller]
address = "127.0.0.1:1"
reconnect_interval_ms = 100
reconnect_max_ms = 1000
command_timeout_ms = 30000
connect_timeout_ms = 500

[agenda]
capacity = 256

[journal]
durability = "process_crash"

[services.transport]
nominal_duration_ms = 100
steps = [{{ action = "move", until = ["arrived"] }}]
"#
    )
}

/// conveyor1: the load (entry and exit) at 0, the buffer at 500, a stopper at 1000
/// and one at 1500 for stations.
fn conveyor(spec: &Spec) -> String {
    format!(
        r#"{}
[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 1
dock = "conveyor1.load"

[[layout.locations]]
name = "buffer"
role = "buffer"
capacity = {buffer}
dock = "conveyor1.b"

[layout.conveyor]
length_mm = {LOOP_MM}
speed_mm_s = {SPEED_MM_S}
pallets = 3
dock_ms = {DOCK_MS}
stoppers = [
  {{ name = "load", at_mm = 0 }},
  {{ name = "b", at_mm = 500 }},
  {{ name = "s1", at_mm = {STATION_STOPPER_MM} }},
  {{ name = "s2", at_mm = 1500 }},
]
"#,
        resource_head("conveyor1"),
        buffer = spec.buffer,
    )
}

/// A station's config: a pick and a place as `service`, with a port if it has one.
fn station_config(dir: &Path, station: &Station) -> Result<PathBuf> {
    let path = resource_config(dir, &station.name, 30_000)?;
    let mut text = std::fs::read_to_string(&path)?.replace(
        "[services.pick_n_place]",
        &format!(
            "[journal]\ndurability = \"process_crash\"\n\n[agenda]\ncapacity = 256\n\n[services.{}]",
            station.service
        ),
    );
    if station.has_port {
        text.push_str("\n[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ncapacity = 1\n");
        if let Some(stopper) = &station.dock {
            writeln!(text, "dock = \"conveyor1.{stopper}\"")?;
        }
    }
    std::fs::write(&path, text)?;
    Ok(path)
}

/// A transfer `name` between the load and `station`'s port, `move_ms` a move.
fn transfer_config(dir: &Path, name: &str, station: &str, move_ms: u64) -> Result<()> {
    let text = format!(
        "{}\n[layout.transfer]\nbetween = [\"conveyor1.load\", \"{station}.port\"]\nmove_ms = {move_ms}\n",
        resource_head(name)
    );
    std::fs::write(dir.join(format!("{name}.toml")), text)?;
    Ok(())
}

/// A product of one step, `service`, whose parts move or not.
fn product_config(dir: &Path, name: &str, service: &str, moves: bool) -> Result<PathBuf> {
    let path = dir.join(format!("{name}.toml"));
    std::fs::write(
        &path,
        format!(
            "cell = \"unset\"\nname = \"{name}\"\nkind = \"product\"\nmoves_parts = {moves}\n\n[[steps]]\nservice_type = \"{service}\"\ninfo = {{ pick = {{ x = 1.0, y = 2.0, z = 3.0 }}, place = {{ x = 4.0, y = 5.0, z = 6.0 }} }}\n"
        ),
    )?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The layout the plant and `cell up --check` would assemble from what `write`
    /// wrote: no problems, for both of the section's cells.
    #[test]
    fn the_written_layouts_have_no_problems() {
        let station = |name: &str, dock: Option<&str>, has_port: bool| Station {
            name: name.into(),
            service: "work".into(),
            dock: dock.map(String::from),
            has_port,
        };
        let cells = [
            vec![
                station("st0", Some("s1"), true),
                station("still0", None, false),
            ],
            (0..20)
                .map(|i| station(&format!("st{i}"), None, true))
                .collect(),
        ];
        for stations in cells {
            let dir = tempfile::tempdir().unwrap();
            let spec = Spec {
                cell: "t".into(),
                stations,
                action_ms: 10,
                transfer_ms: 40,
                buffer: 200,
                products: vec![],
            };
            let written = write(dir.path(), &spec).unwrap();
            let plant: toml::Value = toml::from_str(&written.plant_file).unwrap();
            let parts: Vec<_> = plant["layout"]
                .as_array()
                .unwrap()
                .iter()
                .map(|file| file.as_str().unwrap())
                .map(|file| {
                    let text = std::fs::read_to_string(dir.path().join(file)).unwrap();
                    let (name, section) = schemas::layout::from_resource_config(&text, None)
                        .unwrap()
                        .unwrap_or_else(|| panic!("{file} has no [layout]"));
                    section.part(&name).unwrap()
                })
                .collect();
            let layout = schemas::layout::CellLayout::assemble(parts);
            assert!(layout.problems.is_empty(), "{:?}", layout.problems);
            assert!(written.plant_file.contains("resource = \"conveyor1\""));
        }
    }
}

//! The material-flow cell of the tests (docs/material-flow.md): a conveyor with a
//! loading point, a buffer and stoppers for stations, stations of one port each and
//! products whose parts are moved, each holon a real process on the plant simulator
//! over its own controller connection.

use std::path::{Path, PathBuf};
use std::time::Duration;

use schemas::HolonId;

use crate::*;

/// The loop: the loading point (where parts enter and leave), the buffer (every
/// part's home while it is in the cell), and the two stations' stoppers.
pub const CONVEYOR: &str = r#"
cell = "unset"
name = "conveyor1"

[controller]
address = "127.0.0.1:1"
reconnect_interval_ms = 100
reconnect_max_ms = 1000
command_timeout_ms = 10000
connect_timeout_ms = 500

[agenda]
capacity = 32

[services.transport]
nominal_duration_ms = 500
steps = [{ action = "move", until = ["arrived"] }]

[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 1
dock = "conveyor1.load"

[[layout.locations]]
name = "buffer"
role = "buffer"
capacity = 2
dock = "conveyor1.b"

[layout.conveyor]
length_mm = 2000
speed_mm_s = 4000
pallets = 3
dock_ms = 50
stoppers = [
  { name = "load", at_mm = 0 },
  { name = "b", at_mm = 500 },
  { name = "sa", at_mm = 1000 },
  { name = "sb", at_mm = 1500 },
]
"#;

/// A slow loop: the buffer at 0.25 m, the first station's stopper (`sa`) 0.5 m further
/// on, the second's (`sb`) 1.5 m, at 0.5 m/s (CONVEYOR's loop otherwise).
pub fn slow_loop() -> String {
    let text = CONVEYOR
        .replace("speed_mm_s = 4000", "speed_mm_s = 500")
        .replace(
            "{ name = \"b\", at_mm = 500 }",
            "{ name = \"b\", at_mm = 250 }",
        )
        .replace(
            "{ name = \"sa\", at_mm = 1000 }",
            "{ name = \"sa\", at_mm = 750 }",
        )
        .replace(
            "{ name = \"sb\", at_mm = 1500 }",
            "{ name = \"sb\", at_mm = 1750 }",
        );
    assert!(text.contains("at_mm = 1750") && text.contains("speed_mm_s = 500"));
    text
}

/// `conveyor` (conveyor1's config text) and [`PLANT`], both running `n` moves at once:
/// the holon's `[controller] jobs_at_once`, its plant controller's `actions_at_once`.
pub fn moving_at_once(conveyor: &str, n: usize) -> (String, String) {
    let conveyor = conveyor.replace(
        "connect_timeout_ms = 500",
        &format!("connect_timeout_ms = 500\njobs_at_once = {n}"),
    );
    assert!(conveyor.contains(&format!("jobs_at_once = {n}")));
    // The plant's conveyor1 is its first controller.
    let plant = PLANT.replacen(
        "listen = \"127.0.0.1:0\"",
        &format!("listen = \"127.0.0.1:0\"\nactions_at_once = {n}"),
        1,
    );
    assert!(plant.contains(&format!(
        "conveyor1\"\nlisten = \"127.0.0.1:0\"\nactions_at_once = {n}"
    )));
    (conveyor, plant)
}

pub const PLANT: &str = r#"
layout = ["conveyor1.toml", "station_a.toml", "station_b.toml"]

[[controller]]
resource = "conveyor1"
listen = "127.0.0.1:0"

[[controller]]
resource = "station_a"
listen = "127.0.0.1:0"
delay_ms = 150

[[controller]]
resource = "station_b"
listen = "127.0.0.1:0"
delay_ms = 150
"#;

/// A station offering `service` (a pick and a place, or for `inspect` one inspection
/// that passes or fails the part; nominally 1000 ms unless `nominal_ms` says), its one
/// port on `stopper`.
pub fn station(dir: &Path, name: &str, service: &str, stopper: &str, nominal_ms: u64) -> PathBuf {
    let path = resource_config(dir, name, 10_000).unwrap();
    let mut text = std::fs::read_to_string(&path).unwrap().replace(
        "[services.pick_n_place]\nnominal_duration_ms = 1000",
        &format!("[services.{service}]\nnominal_duration_ms = {nominal_ms}"),
    );
    if service == "inspect" {
        let pick = text.find("  { action = \"pick\"").expect("a pick step");
        let end = pick + text[pick..].find("\n]").expect("the steps' end");
        text.replace_range(
            pick..end,
            "  { action = \"inspect\", until = [\"inspect_pass\", \"inspect_fail\"] },",
        );
    }
    let layout = format!(
        "\n[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ncapacity = 1\ndock = \"conveyor1.{stopper}\"\n"
    );
    std::fs::write(&path, format!("{text}{layout}")).unwrap();
    path
}

/// A product whose parts are moved, its steps the services `steps` names, separated by
/// spaces (`"drill mill"`).
/// A step written `S>R` is one of service S whose `inspect_fail` sends the part to be
/// recovered by service R, then to S again (once; a second failure scraps it).
pub fn product(dir: &Path, name: &str, steps: &str) -> PathBuf {
    let path = dir.join(format!("{name}.toml"));
    let step = |service: &str| {
        let (service, recover) = match service.split_once('>') {
            Some((service, by)) => (service, format!("reject_results = [\"inspect_fail\"]\non_reject = {{ recover = {{ service_type = \"{by}\", then_step = 2, max_recoveries = 1 }} }}\n")),
            None => (service, String::new()),
        };
        format!(
            "[[steps]]\nservice_type = \"{service}\"\ninfo = {{ pick = {{ x = 1.0, y = 2.0, z = 3.0 }}, place = {{ x = 4.0, y = 5.0, z = 6.0 }} }}\n{recover}"
        )
    };
    let steps: Vec<String> = steps.split_whitespace().map(step).collect();
    let text = format!(
        "cell = \"unset\"\nname = \"{name}\"\nkind = \"product\"\nmoves_parts = true\n\n{}",
        steps.join("\n")
    );
    std::fs::write(&path, text).unwrap();
    path
}

/// The cell on its plant: every holon started and serving.
pub struct FlowCell {
    pub dir: tempfile::TempDir,
    pub plant: PlantProcess,
    pub cell: Cell,
    /// The resource holons, by name (conveyor1 and the stations).
    pub resources: std::collections::BTreeMap<String, Process>,
    /// The product holons.
    pub _products: Vec<Process>,
    /// The order-node orders1.
    pub orders: Option<Process>,
}

impl FlowCell {
    /// Starts the cell; `conveyor` is conveyor1's config text.
    pub async fn start(tag: &str, conveyor: &str) -> FlowCell {
        FlowCell::start_on(tag, conveyor, PLANT).await
    }

    /// Starts the cell on the plant file `plant`.
    pub async fn start_on(tag: &str, conveyor: &str, plant: &str) -> FlowCell {
        let stations = [
            ("station_a", "drill", "sa", 1000),
            ("station_b", "mill", "sb", 1000),
        ];
        let products = [("ab", "drill mill"), ("ba", "mill drill")];
        FlowCell::start_with(tag, conveyor, plant, &stations, &products).await
    }

    /// Starts the cell on the plant file `plant` with `stations` (name, service,
    /// stopper, nominal duration) and `products` (name, and its steps' services separated by spaces).
    pub async fn start_with(
        tag: &str,
        conveyor: &str,
        plant: &str,
        stations: &[(&str, &str, &str, u64)],
        products: &[(&str, &str)],
    ) -> FlowCell {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("data")).unwrap();
        std::fs::write(dir.path().join("conveyor1.toml"), conveyor).unwrap();
        for &(name, service, stopper, nominal_ms) in stations {
            station(dir.path(), name, service, stopper, nominal_ms);
        }
        let plant = PlantProcess::start(dir.path(), plant);
        let cell = Cell::open(tag).await.unwrap();
        let mut flow = FlowCell {
            orders: None,
            dir,
            plant,
            cell,
            resources: Default::default(),
            _products: Vec::new(),
        };
        flow.start_resource("conveyor1").await;
        for (name, _, _, _) in stations {
            flow.start_resource(name).await;
        }
        for &(name, steps) in products {
            let config = product(flow.dir.path(), name, steps);
            flow._products.push(
                start_holon(
                    flow.dir.path(),
                    "holon-node",
                    &config,
                    name,
                    &flow.cell,
                    &[],
                )
                .unwrap(),
            );
            flow.cell
                .wait_alive(&HolonId::new(schemas::HolonKind::Product, name).unwrap())
                .await
                .unwrap();
        }
        flow.start_orders().await;
        flow
    }

    pub fn data(&self) -> String {
        self.dir.path().join("data").to_str().unwrap().to_string()
    }

    /// Starts (or starts again, on its journal) the resource holon `name`.
    pub async fn start_resource(&mut self, name: &str) {
        let config = self.dir.path().join(format!("{name}.toml"));
        let process = start_node(
            self.dir.path(),
            &config,
            self.cell.keys.cell(),
            &self.cell.endpoint,
            &self.plant.controllers[name],
            &["--data-dir", &self.data()],
        )
        .unwrap();
        let alive = self
            .cell
            .wait_alive(&HolonId::resource(name).unwrap())
            .await;
        if let Err(e) = alive {
            let log = std::fs::read_to_string(self.dir.path().join(format!("{name}.log.json")))
                .unwrap_or_default();
            let tail: Vec<&str> = log.lines().rev().take(15).collect();
            panic!("{e}: {}\n{}", process.stderr(), tail.join("\n"));
        }
        self.resources.insert(name.to_string(), process);
        self.cell.wait_serving(name).await.unwrap();
    }

    /// Starts (or starts again, on its journal) the order-node.
    pub async fn start_orders(&mut self) {
        let data = self.data();
        let orders = self
            .cell
            .start_order_node(self.dir.path(), &["--data-dir", &data])
            .await
            .unwrap();
        self.orders = Some(orders);
    }

    /// Waits until every order in `orders` has ended (at most `within`).
    pub async fn wait_ended(&self, orders: &[String], within: Duration) {
        let deadline = tokio::time::Instant::now() + within;
        for order in orders {
            loop {
                let state = self.cell.order_state(order).await;
                let status = state.as_ref().and_then(|s| s["status"].as_str());
                if status.is_some_and(|s| s != "running") {
                    break;
                }
                assert!(
                    tokio::time::Instant::now() < deadline,
                    "{order} did not finish: {state:?}\nplant: {:#}",
                    self.plant.state()
                );
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
        }
    }

    /// Every order done, each step once where its part was, every part shipped; the
    /// plant agrees (nothing anywhere, every pallet free) and no place is held.
    pub async fn assert_all_done_and_plant_empty(&self, orders: &[String]) {
        for order in orders {
            let state = self.cell.order_state(order).await.unwrap();
            assert_eq!(state["status"], "done", "{state:#}");
            assert_eq!(state["completed"].as_array().unwrap().len(), 2, "{state:#}");
            assert_eq!(state["part"]["state"], "shipped", "{state:#}");
            assert_eq!(state["part"]["exit"], "conveyor1.load", "{state:#}");
        }
        let truth = self.plant.state();
        assert_eq!(truth["shipped"], orders.len(), "{truth:#}");
        assert!(
            truth["in_transit"].as_array().unwrap().is_empty(),
            "{truth:#}"
        );
        for (location, parts) in truth["locations"].as_object().unwrap() {
            assert!(
                parts.as_array().unwrap().is_empty(),
                "{location} still holds parts: {truth:#}"
            );
        }
        assert_eq!(free_pallets(&truth, "conveyor1"), 3, "{truth:#}");
        for resource in self.resources.keys() {
            let status = self.cell.status(resource).await.unwrap();
            assert!(
                status.get("places").is_none(),
                "{resource} still holds places: {status:#}"
            );
        }
    }

    /// `cell part ORDER --at LOCATION` as an operator runs it: its output.
    pub fn say_part_at(&self, order: &str, at: &str) -> std::process::Output {
        std::process::Command::new(bin("cell"))
            .args(["part", order, "--at", at, "--cell", self.cell.keys.cell()])
            .args(["--connect", &self.cell.endpoint, "--timeout-ms", "5000"])
            .output()
            .unwrap()
    }

    /// Counts the order-node's log lines containing `what`.
    pub fn count_in_orders_log(&self, what: &str) -> usize {
        let log =
            std::fs::read_to_string(self.dir.path().join("orders1.log.json")).unwrap_or_default();
        log.lines().filter(|l| l.contains(what)).count()
    }
}

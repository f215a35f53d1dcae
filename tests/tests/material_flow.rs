//! Orders that move their parts (docs/material-flow.md, "Orders arrange their moves"):
//! real holons on the plant simulator, each over its own controller connection. Before
//! each step the order reserves a place at a station's port and books the conveyor to
//! take the part there; it works the step only where the part physically is (the plant
//! refuses a station's work at an empty port), and the part leaves by the exit.
//!
//! The cell is the one that deadlocks without reservations: two stations of one port
//! each, and parts crossing between them in opposite directions (one product drills
//! then mills, the other mills then drills). With its places reserved and a home for
//! every part in the buffer, every order finishes and the plant ends empty.

use std::path::{Path, PathBuf};
use std::time::Duration;

use holarchy_tests::*;
use schemas::HolonId;

/// The loop: the loading point (where parts enter and leave), the buffer (every
/// part's home while it is in the cell), and the two stations' stoppers.
const CONVEYOR: &str = r#"
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

const PLANT: &str = r#"
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

/// A station offering `service` (a pick and a place), its one port on `stopper`.
fn station(dir: &Path, name: &str, service: &str, stopper: &str) -> PathBuf {
    let path = resource_config(dir, name, 10_000).unwrap();
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("[services.pick_n_place]", &format!("[services.{service}]"));
    let layout = format!(
        "\n[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ncapacity = 1\ndock = \"conveyor1.{stopper}\"\n"
    );
    std::fs::write(&path, format!("{text}{layout}")).unwrap();
    path
}

/// A product whose parts are moved, its steps the services `first` then `second`.
fn product(dir: &Path, name: &str, first: &str, second: &str) -> PathBuf {
    let path = dir.join(format!("{name}.toml"));
    let step = |service: &str| {
        format!(
            "[[steps]]\nservice_type = \"{service}\"\ninfo = {{ pick = {{ x = 1.0, y = 2.0, z = 3.0 }}, place = {{ x = 4.0, y = 5.0, z = 6.0 }} }}\n"
        )
    };
    let text = format!(
        "cell = \"unset\"\nname = \"{name}\"\nkind = \"product\"\nmoves_parts = true\n\n{}\n{}",
        step(first),
        step(second)
    );
    std::fs::write(&path, text).unwrap();
    path
}

#[tokio::test(flavor = "multi_thread")]
async fn crossing_parts_reserve_their_places_and_every_order_finishes() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), CONVEYOR).unwrap();
    let a = station(dir.path(), "station_a", "drill", "sa");
    let b = station(dir.path(), "station_b", "mill", "sb");
    let plant = PlantProcess::start(dir.path(), PLANT);
    let cell = Cell::open("t-flow").await.unwrap();
    let mut holons = Vec::new();
    for (name, config) in [
        ("conveyor1", dir.path().join("conveyor1.toml")),
        ("station_a", a),
        ("station_b", b),
    ] {
        let data = data.to_str().unwrap();
        holons.push(
            start_node(
                dir.path(),
                &config,
                "t-flow",
                &cell.endpoint,
                &plant.controllers[name],
                &["--data-dir", data],
            )
            .unwrap(),
        );
        cell.wait_alive(&HolonId::resource(name).unwrap())
            .await
            .unwrap();
        cell.wait_serving(name).await.unwrap();
    }
    for (name, first, second) in [("ab", "drill", "mill"), ("ba", "mill", "drill")] {
        let config = product(dir.path(), name, first, second);
        holons.push(start_holon(dir.path(), "holon-node", &config, name, &cell, &[]).unwrap());
        cell.wait_alive(&HolonId::new(schemas::HolonKind::Product, name).unwrap())
            .await
            .unwrap();
    }
    let data_dir = data.to_str().unwrap();
    let _orders = cell
        .start_order_node(dir.path(), &["--data-dir", data_dir])
        .await
        .unwrap();

    // Three of each, crossing: more parts than the buffer holds, so some wait outside.
    let mut orders = Vec::new();
    for product in ["ab", "ba", "ab", "ba", "ab", "ba"] {
        orders.extend(cell.submit(product, 1).await.unwrap());
    }
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    for order in &orders {
        loop {
            let state = cell.order_state(order).await;
            let status = state.as_ref().and_then(|s| s["status"].as_str());
            if status.is_some_and(|s| s != "running") {
                break;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{order} did not finish: {state:?}\nplant: {:#}",
                plant.state()
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    // Every order done, each step once, where its part was; every part shipped.
    for order in &orders {
        let state = cell.order_state(order).await.unwrap();
        assert_eq!(state["status"], "done", "{state:#}");
        assert_eq!(state["failed_attempts"], 0, "{state:#}");
        assert_eq!(state["completed"].as_array().unwrap().len(), 2, "{state:#}");
        assert_eq!(state["part"]["state"], "shipped", "{state:#}");
        assert_eq!(state["part"]["exit"], "conveyor1.load", "{state:#}");
    }
    // The plant agrees: every part left, nothing anywhere, every pallet free.
    let truth = plant.state();
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
    assert_eq!(
        truth["free_pallets"]["conveyor1"].as_array().unwrap().len(),
        3,
        "{truth:#}"
    );
    // And no place is left held at any resource.
    for resource in ["conveyor1", "station_a", "station_b"] {
        let status = cell.status(resource).await.unwrap();
        assert!(
            status.get("places").is_none(),
            "{resource} still holds places: {status:#}"
        );
    }
    // What the orders did on the way, for whoever reads the test's output.
    let log = std::fs::read_to_string(dir.path().join("orders1.log.json")).unwrap_or_default();
    let count = |what: &str| log.lines().filter(|l| l.contains(what)).count();
    eprintln!(
        "moves ended: {}; places reserved at stations: {}; parts sent home: {}; errors logged: {}",
        count("move ended"),
        count("a place at the station is reserved"),
        count("it goes back to its home"),
        count("\"ERROR\"")
    );
    assert_eq!(count("\"ERROR\""), 0, "the order-node logged errors");
    drop(holons);
}

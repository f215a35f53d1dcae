//! The AIP-PRIMECA benchmark cell (deploy/cells/aip-primeca, its README.md): its configs
//! check together and each on its own, with M7 hot-added too; the monorail's hops are
//! the emulator's machine-to-machine times divided by 10; every step of every product is
//! offered by some station. Quick: nothing runs.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::Command;

use holarchy_tests::*;
use schemas::layout::LocationRole;

fn cell_dir() -> PathBuf {
    workspace_root().join("deploy/cells/aip-primeca")
}

const STATIONS: [&str; 7] = ["m1", "m2", "m3", "m4", "m5", "m6", "m7"];
const PRODUCTS: [&str; 7] = ["b", "e", "l", "t", "a", "i", "p"];

/// `cell up --check DIR`: its exit status and what it printed.
fn cell_up_check(dir: &Path) -> (bool, String) {
    let output = Command::new(bin("cell"))
        .args(["up", "--check"])
        .arg(dir)
        .output()
        .unwrap();
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stdout).into_owned()
            + &String::from_utf8_lossy(&output.stderr),
    )
}

fn read_toml(file: &str) -> toml::Table {
    let path = cell_dir().join(file);
    let text = std::fs::read_to_string(&path).unwrap();
    text.parse()
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn the_aip_primeca_cell_checks_with_m7_away_and_hot_added() {
    // As shipped: M7 is not started, its stopper waits free.
    let (ok, said) = cell_up_check(&cell_dir());
    assert!(ok, "{said}");
    assert!(said.contains("no problems"), "{said}");
    assert!(said.contains("m7 (free)"), "{said}");

    // With M7's process uncommented, as cell.toml says: seven machine ports, each on its
    // own stopper of the monorail.
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(cell_dir()).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            std::fs::copy(&path, dir.path().join(path.file_name().unwrap())).unwrap();
        }
    }
    let manifest = dir.path().join("cell.toml");
    let text = std::fs::read_to_string(&manifest).unwrap();
    let commented = "# [[process]]\n# name = \"m7\"\n# program = \"holon-node\"\n# args = [";
    assert!(text.contains(commented), "cell.toml has no commented M7");
    std::fs::write(
        &manifest,
        text.replace(
            commented,
            "[[process]]\nname = \"m7\"\nprogram = \"holon-node\"\nargs = [",
        ),
    )
    .unwrap();
    let (ok, said) = cell_up_check(dir.path());
    assert!(ok, "{said}");
    assert!(said.contains("no problems"), "{said}");

    let (layout, _) = cell::client::layout::from_manifest(dir.path()).unwrap();
    assert!(layout.problems.is_empty(), "{:?}", layout.problems);
    let ports: BTreeSet<String> = layout
        .locations()
        .map(|(_, l)| l)
        .filter(|l| l.role == LocationRole::Port)
        .map(|l| {
            let dock = l.dock.as_ref().expect("every port is on the monorail");
            assert_eq!(
                format!("{}.{}", dock.conveyor, dock.stopper),
                format!("monorail.{}", l.id.holon()),
                "{}",
                l.id.as_str()
            );
            l.id.as_str().to_string()
        })
        .collect();
    let expected: BTreeSet<String> = STATIONS.iter().map(|m| format!("{m}.port")).collect();
    assert_eq!(ports, expected);
    for role in [
        LocationRole::Entry,
        LocationRole::Exit,
        LocationRole::Buffer,
    ] {
        assert_eq!(
            layout.locations().filter(|(_, l)| l.role == role).count(),
            1,
            "{role:?}"
        );
    }

    // Each hop between neighbours on the loop, unobstructed (the loop's distance and the
    // spur out and in), is the emulator's time divided by 10 (README.md).
    let monorail = layout.conveyor("monorail").expect("the monorail");
    for (from, to, emulator_s) in [
        ("m1", "m2", 68.3),
        ("m2", "m3", 77.0),
        ("m3", "m4", 43.2),
        ("m4", "m5", 68.3),
        ("m5", "m6", 70.8),
        ("m6", "m7", 75.6),
        ("m7", "m1", 74.1),
    ] {
        let hop = monorail.travel_ms(from, to).unwrap() + 2 * monorail.dock_ms;
        let expected = (emulator_s * 100.0_f64).round() as u64;
        assert_eq!(hop, expected, "{from} -> {to}");
    }
    assert_eq!(monorail.pallets, 10);
    // Every shuttle moves on its own: the holon runs as many moves at once as there are
    // shuttles, and so does its controller in the plant (else the plant would run the
    // holon's moves one after the other).
    let holon = read_toml("monorail.toml");
    assert_eq!(holon["controller"]["jobs_at_once"].as_integer(), Some(10));
    let plant = read_toml("plant.toml");
    let controller = plant["controller"]
        .as_array()
        .unwrap()
        .iter()
        .find(|c| c["resource"].as_str() == Some("monorail"))
        .unwrap();
    assert_eq!(controller["actions_at_once"].as_integer(), Some(10));
    let buffer = layout
        .locations()
        .map(|(_, l)| l)
        .find(|l| l.role == LocationRole::Buffer)
        .unwrap();
    assert!(buffer.capacity < monorail.pallets);
}

#[test]
fn every_step_of_every_aip_primeca_product_is_offered_by_a_station() {
    let mut offered = BTreeSet::new();
    for station in STATIONS {
        let config = read_toml(&format!("{station}.toml"));
        let services = config["services"].as_table().unwrap();
        for (service, spec) in services {
            assert!(
                spec["nominal_duration_ms"].as_integer().unwrap() > 0,
                "{station}: {service}"
            );
            offered.insert((service.clone(), station));
        }
    }
    let manifest = read_toml("cell.toml");
    let started: BTreeSet<String> = manifest["process"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect();
    for product in PRODUCTS {
        assert!(
            started.contains(product),
            "cell.toml does not start {product}"
        );
        let config = read_toml(&format!("{product}.toml"));
        assert_eq!(config["moves_parts"].as_bool(), Some(true), "{product}");
        let steps: Vec<&str> = config["steps"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["service_type"].as_str().unwrap())
            .collect();
        assert_eq!(steps.first(), Some(&"load"), "{product}");
        assert_eq!(steps.last(), Some(&"unload"), "{product}");
        assert_eq!(steps[steps.len() - 2], "inspection", "{product}");
        for step in steps {
            // Offered by a station the cell starts (M7 is optional: never the only one).
            assert!(
                offered
                    .iter()
                    .any(|(s, station)| s == step && started.contains(*station)),
                "{product}: no station cell.toml starts offers {step}"
            );
        }
    }
}

#[test]
fn each_aip_primeca_config_passes_its_own_check() {
    let mut holons: Vec<String> = STATIONS.iter().map(|s| format!("{s}.toml")).collect();
    holons.extend(PRODUCTS.iter().map(|p| format!("{p}.toml")));
    holons.push("monorail.toml".into());
    holons.push("planner.toml".into());
    let mut checks: Vec<(&str, Vec<String>)> = holons
        .into_iter()
        .map(|file| ("holon-node", vec!["--config".into(), file]))
        .collect();
    checks.push(("order-node", vec!["--config".into(), "orders1.toml".into()]));
    checks.push(("plant-sim", vec!["--plant".into(), "plant.toml".into()]));
    for (program, args) in checks {
        let output = Command::new(bin(program))
            .current_dir(cell_dir())
            .args(&args)
            .arg("--check")
            .output()
            .unwrap();
        assert!(
            output.status.success(),
            "{program} {args:?}: {}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
    }
}

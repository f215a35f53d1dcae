//! The cell's layout (docs/material-flow.md): each resource states its own part in its
//! config; the running cell's layout is what the serving holons state together, so a
//! station joins it by starting and leaves it by stopping; `cell up --check` checks a
//! cell's configs together before anything runs.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use holarchy_tests::*;
use schemas::HolonId;

const CONVEYOR: &str = r#"
[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"

[layout.conveyor]
length_mm = 4000
speed_mm_s = 1000
pallets = 3
stoppers = [
  { name = "load", at_mm = 0 },
  { name = "s1", at_mm = 1000 },
  { name = "s2", at_mm = 2000 },
  { name = "s3", at_mm = 3000 },
]
"#;

fn station(dock: &str) -> String {
    format!("\n[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n")
}

/// A test resource's config with `layout` appended.
fn config_with(dir: &Path, name: &str, layout: &str) -> std::path::PathBuf {
    let path = resource_config(dir, name, 5000).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    std::fs::write(&path, format!("{text}{layout}")).unwrap();
    path
}

/// `cell layout` of the cell, as JSON, until `done` says it is the one awaited.
async fn layout_until(
    cell: &Cell,
    what: &str,
    done: impl Fn(&serde_json::Value) -> bool,
) -> (serde_json::Value, String) {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    loop {
        let run = |json: bool| {
            let mut command = tokio::process::Command::new(bin("cell"));
            command.args([
                "layout",
                "--cell",
                cell.keys.cell(),
                "--connect",
                &cell.endpoint,
                "--timeout-ms",
                "1000",
            ]);
            if json {
                command.arg("--json");
            }
            command.output()
        };
        let output = run(true).await.unwrap();
        assert!(
            output.status.success(),
            "{}",
            String::from_utf8_lossy(&output.stderr)
        );
        let layout: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
        if done(&layout) {
            let text = run(false).await.unwrap();
            return (layout, String::from_utf8_lossy(&text.stdout).into_owned());
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the layout never became {what}: {layout:#}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

fn holons(layout: &serde_json::Value) -> Vec<String> {
    layout["parts"]
        .as_object()
        .unwrap()
        .keys()
        .cloned()
        .collect()
}

fn problems(layout: &serde_json::Value) -> Vec<String> {
    layout["problems"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["message"].as_str().unwrap().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn a_station_joins_the_layout_by_starting_and_leaves_it_by_stopping() {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-layout").await.unwrap();
    let mut running = Vec::new();
    let mut start = |name: &str, layout: &str| {
        let sim = Sim::start(dir.path(), &format!("{name}-sim"), "127.0.0.1:0", &[]).unwrap();
        let config = config_with(dir.path(), name, layout);
        let node = start_node(
            dir.path(),
            &config,
            cell.keys.cell(),
            &cell.endpoint,
            &sim.address,
            &[],
        )
        .unwrap();
        running.push((name.to_string(), sim, node));
    };
    start("conveyor1", CONVEYOR);
    start("robot1", &station("conveyor1.s1"));
    start("robot2", &station("conveyor1.s2"));
    let (layout, shown) = layout_until(&cell, "three holons", |l| holons(l).len() == 3).await;
    assert!(problems(&layout).is_empty(), "{shown}");
    assert!(
        shown.contains("s1 (robot1.port), s2 (robot2.port), s3 (free)"),
        "{shown}"
    );
    assert!(
        shown.contains("robot2.port              port               1  conveyor1.s2"),
        "{shown}"
    );

    // Hot-added on the free stopper: in the layout by starting, nothing else edited.
    start("robot3", &station("conveyor1.s3"));
    let (layout, shown) = layout_until(&cell, "with robot3", |l| {
        holons(l).contains(&"robot3".to_string())
    })
    .await;
    assert!(problems(&layout).is_empty(), "{shown}");
    assert!(shown.contains("s3 (robot3.port)"), "{shown}");

    // A station docked where another is: the running cell says so, naming both.
    start("robot4", &station("conveyor1.s3"));
    let (_, shown) = layout_until(&cell, "with robot4", |l| {
        holons(l).contains(&"robot4".to_string())
    })
    .await;
    assert!(
        shown.contains("robot4: layout.locations[0].dock: conveyor1.s3 is already the dock of robot3.port: one location per stopper"),
        "{shown}"
    );

    // Stopped (robot1 as an operator stops it, robot4 killed), a station leaves the
    // layout; the conveyor killed, its docks name a conveyor that is not there.
    for (name, kill) in [("robot1", false), ("robot4", true)] {
        let at = running.iter().position(|(n, _, _)| n == name).unwrap();
        let (_, _sim, mut node) = running.remove(at);
        if kill {
            node.kill();
        } else {
            node.signal(nix::sys::signal::Signal::SIGTERM).unwrap();
            node.wait_exit(Duration::from_secs(40)).unwrap();
        }
        cell.wait_gone(&HolonId::resource(name).unwrap())
            .await
            .unwrap();
    }
    let (layout, shown) =
        layout_until(&cell, "without robot1 and robot4", |l| holons(l).len() == 3).await;
    assert!(problems(&layout).is_empty(), "{shown}");
    assert!(shown.contains("s1 (free)"), "{shown}");
    assert!(!shown.contains("robot1.port"), "{shown}");
    let at = running
        .iter()
        .position(|(n, _, _)| n == "conveyor1")
        .unwrap();
    running.remove(at).2.kill();
    let (layout, shown) =
        layout_until(&cell, "without the conveyor", |l| holons(l).len() == 2).await;
    assert!(
        problems(&layout)
            .contains(&"conveyor1: no conveyor of that name in the layout".to_string()),
        "{shown}"
    );
}

#[test]
fn cell_up_check_checks_the_cells_configs_together() {
    let output = Command::new(bin("cell"))
        .args(["up", "--check"])
        .arg(workspace_root().join("deploy/cells/demo"))
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(output.status.success(), "{stdout}");
    assert!(stdout.contains("no problems"), "{stdout}");

    // A station moved onto a stopper that is taken, and a conveyor without an entry.
    let dir = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(workspace_root().join("deploy/cells/demo")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "toml") {
            std::fs::copy(&path, dir.path().join(path.file_name().unwrap())).unwrap();
        }
    }
    let edit = |file: &str, from: &str, to: &str| {
        let path = dir.path().join(file);
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains(from), "{file} has no {from}");
        std::fs::write(&path, text.replace(from, to)).unwrap();
    };
    edit(
        "inspect1.toml",
        "dock = \"conveyor1.s4\"",
        "dock = \"conveyor1.s2\"",
    );
    edit(
        "conveyor1.toml",
        "role = \"entry_exit\"",
        "role = \"buffer\"",
    );
    let output = Command::new(bin("cell"))
        .args(["up", "--check"])
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert_eq!(output.status.code(), Some(1), "{stdout}");
    assert!(
        stdout.contains("robot2.toml: robot2: layout.locations[0].dock: conveyor1.s2 is already the dock of inspect1.port"),
        "{stdout}"
    );
    assert!(
        stdout.contains("no entry: the layout has station ports"),
        "{stdout}"
    );
}

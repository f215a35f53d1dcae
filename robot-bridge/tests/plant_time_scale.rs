//! A plant run faster than real time (`plant-sim --time-scale`): a move and a station's
//! action take 1/N of their plant time on the wall clock, and the plant reports its own
//! time, which ran N times as fast. The check on the wall clock is one-sided and loose
//! (at 50x, a 10 s move must end within 5 s): it fails only if the factor is not applied.

use std::path::Path;
use std::time::{Duration, Instant};

use robot_bridge::plant::trace::TraceRecord;
use schemas::TimeScale;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

mod common;
use common::plant::{control, start_plant};

/// A 2000 mm loop at 100 mm/s: from the loading point to the station's port at 1000 mm
/// is 10 s of plant time.
const CONVEYOR: &str = r#"
name = "conveyor1"

[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"

[layout.conveyor]
length_mm = 2000
speed_mm_s = 100
pallets = 2
stoppers = [{ name = "load", at_mm = 0 }, { name = "st", at_mm = 1000 }]
"#;

const STATION: &str = r#"
name = "station1"

[[layout.locations]]
name = "port"
role = "port"
capacity = 1
dock = "conveyor1.st"
"#;

fn plant_file(dir: &Path) -> std::path::PathBuf {
    std::fs::write(dir.join("conveyor1.toml"), CONVEYOR).unwrap();
    std::fs::write(dir.join("station1.toml"), STATION).unwrap();
    let path = dir.join("plant.toml");
    std::fs::write(
        &path,
        format!("layout = [\"conveyor1.toml\", \"station1.toml\"]\ntrace_file = {:?}\n\n\
         [[controller]]\nresource = \"conveyor1\"\nlisten = \"127.0.0.1:0\"\n\n\
         [[controller]]\nresource = \"station1\"\nlisten = \"127.0.0.1:0\"\naction_ms = {{ pick = 10000 }}\n",
            dir.join("trace.jsonl")
        ),
    )
    .unwrap();
    path
}

/// Sends `command` on a new link to `address` and reads until `reply` (at most 20 s).
async fn exchange(address: &str, command: &str, reply: &str) -> Duration {
    let began = Instant::now();
    let mut link = tokio::net::TcpStream::connect(address).await.unwrap();
    link.write_all(command.as_bytes()).await.unwrap();
    let mut received = String::new();
    while !received.contains(reply) {
        let mut buffer = [0u8; 4096];
        let n = tokio::time::timeout(Duration::from_secs(20), link.read(&mut buffer))
            .await
            .unwrap_or_else(|_| panic!("no {reply} in 20 s: {received}"))
            .unwrap();
        assert!(n > 0, "the controller closed: {received}");
        received.push_str(&String::from_utf8_lossy(&buffer[..n]));
    }
    assert!(!received.contains("error"), "{received}");
    began.elapsed()
}

#[tokio::test(flavor = "multi_thread")]
async fn at_fifty_times_a_move_and_an_action_take_a_fiftieth_and_the_plant_counts_plant_time() {
    let dir = tempfile::tempdir().unwrap();
    let path = plant_file(dir.path());
    let scale: TimeScale = "50".parse().unwrap();
    let plant = start_plant(&path, scale).await;
    let (conveyor, station) = (plant.address("conveyor1"), plant.address("station1"));
    let control_port = plant.control.clone();

    let moved = exchange(
        conveyor,
        "<ROBOT_CMD><ID>1</ID><ACTION>move</ACTION><PART>p-1</PART><FROM>conveyor1.load</FROM><TO>station1.port</TO></ROBOT_CMD>",
        "<RESULT>arrived</RESULT>",
    )
    .await;
    let picked = exchange(
        station,
        "<ROBOT_CMD><ID>1</ID><ACTION>pick</ACTION><PART>p-1</PART></ROBOT_CMD>",
        "<RESULT>picking_done</RESULT>",
    )
    .await;
    let view = control(&control_port, "where").await;
    assert_eq!(
        view["locations"]["station1.port"][0]["part"], "p-1",
        "{view:#}"
    );
    // 10 s of travel and 10 s of picking, in plant time, at fifty times real time.
    assert!(moved < Duration::from_secs(5), "the move took {moved:?}");
    assert!(picked < Duration::from_secs(5), "the pick took {picked:?}");
    let waits = control(&control_port, "waits").await;
    let now_ms = waits["now_ms"].as_u64().unwrap();
    assert!(
        now_ms >= 20_000,
        "the plant's time is plant time: {waits:#}"
    );
    // A command naming no part works on the part at the port.
    exchange(
        station,
        "<ROBOT_CMD><ID>2</ID><ACTION>place</ACTION></ROBOT_CMD>",
        "<RESULT>placing_done</RESULT>",
    )
    .await;
    eprintln!("at 50x: move {moved:?}, pick {picked:?} of wall time; plant time now {now_ms} ms");
    plant.shutdown.cancel();

    // The trace has each action in plant time: the move's 10 s of travel, the pick's
    // 10 s, one after the other.
    let trace: Vec<TraceRecord> = std::fs::read_to_string(dir.path().join("trace.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let [moving, picking, placing] = &trace[..] else {
        panic!("three actions traced: {trace:#?}");
    };
    assert_eq!(
        (
            moving.resource.as_str(),
            moving.action.as_str(),
            moving.part.as_deref()
        ),
        ("conveyor1", "move", Some("p-1"))
    );
    assert!(moving.carrier.is_some() && moving.done, "{moving:?}");
    assert!(moving.end_ms - moving.begin_ms >= 10_000, "{moving:?}");
    assert_eq!(
        (
            picking.resource.as_str(),
            picking.action.as_str(),
            picking.part.as_deref()
        ),
        ("station1", "pick", Some("p-1"))
    );
    assert!(picking.end_ms - picking.begin_ms >= 10_000, "{picking:?}");
    assert!(picking.begin_ms >= moving.end_ms, "{trace:#?}");
    assert_eq!(placing.part.as_deref(), Some("p-1"), "{placing:?}");
}

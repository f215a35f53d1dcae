//! A conveyor whose controller moves several pallets at once (`actions_at_once` in the
//! plant file), against the plant simulator over TCP: two moves begun at once on one
//! conveyor travel together in the plant, each is answered with its own reply when its
//! own part arrives, and the plant's control port (`where`) finds both parts where they
//! went. A plant file that sets it to 0 is refused, naming it.

use std::path::Path;
use std::time::{Duration, Instant};

use robot_bridge::client::{CommandFailure, ControllerEvent, ControllerStatus};
use robot_bridge::plant::PlantError;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

mod common;
use common::plant::{
    control, control_line, loop_conveyor, move_to_buffer, one_conveyor_plant, start_plant,
};
use common::{reply, Harness};

/// The longest wait for anything.
const WAIT: Duration = Duration::from_secs(10);

fn plant_file(dir: &Path, actions_at_once: usize) -> std::path::PathBuf {
    one_conveyor_plant(
        dir,
        &loop_conveyor(3),
        &format!("actions_at_once = {actions_at_once}\n"),
    )
}

/// Reads from `stream` until `received` holds `needle`.
async fn read_until(stream: &mut tokio::net::TcpStream, received: &mut String, needle: &str) {
    while !received.contains(needle) {
        let mut buffer = [0u8; 4096];
        let n = tokio::time::timeout(WAIT, stream.read(&mut buffer))
            .await
            .unwrap_or_else(|_| panic!("no {needle} in time: {received}"))
            .unwrap();
        assert!(n > 0, "the controller closed: {received}");
        received.push_str(&String::from_utf8_lossy(&buffer[..n]));
    }
}

fn parts_in(view: &serde_json::Value, location: &str) -> Vec<String> {
    let mut parts: Vec<String> = view["locations"][location]
        .as_array()
        .unwrap_or_else(|| panic!("no {location}: {view:#}"))
        .iter()
        .map(|held| held["part"].as_str().unwrap().to_string())
        .collect();
    parts.sort();
    parts
}

#[tokio::test(flavor = "multi_thread")]
async fn two_moves_on_one_conveyor_begun_at_once_both_arrive() {
    let dir = tempfile::tempdir().unwrap();
    let path = plant_file(dir.path(), 2);
    let plant = start_plant(&path, schemas::TimeScale::REAL).await;
    let (conveyor, control_port) = (
        plant.address("conveyor1").to_string(),
        plant.control.clone(),
    );
    let shutdown = plant.shutdown.clone();

    let mut link = tokio::net::TcpStream::connect(&conveyor).await.unwrap();
    let mv = |id: u64, part: &str| {
        format!("<ROBOT_CMD><ID>{id}</ID><ACTION>move</ACTION><PART>{part}</PART><FROM>conveyor1.load</FROM><TO>conveyor1.buffer</TO></ROBOT_CMD>")
    };
    link.write_all(format!("{}{}", mv(1, "p-1"), mv(2, "p-2")).as_bytes())
        .await
        .unwrap();
    // Both on their way in the plant at once, each on a pallet of its own.
    let riding = both_riding(&control_port).await;
    let mut carriers: Vec<&str> = riding
        .iter()
        .map(|t| t["load"]["carrier"].as_str().unwrap())
        .collect();
    carriers.dedup();
    assert_eq!(carriers.len(), 2, "{riding:#?}");
    // Each is answered with its own reply, once its own part has arrived.
    let mut received = String::new();
    for id in [1, 2] {
        let reply = format!("<ROBOT_REPLY><ID>{id}</ID><RESULT>arrived</RESULT></ROBOT_REPLY>");
        read_until(&mut link, &mut received, &reply).await;
    }
    assert!(!received.contains("error"), "{received}");
    let view = control(&control_port, "where").await;
    assert_eq!(
        parts_in(&view, "conveyor1.buffer"),
        ["p-1", "p-2"],
        "{view:#}"
    );
    assert!(
        view["in_transit"].as_array().unwrap().is_empty(),
        "{view:#}"
    );

    // Both back at once, and out of the plant at the loading point.
    let back = |id: u64, part: &str| {
        format!("<ROBOT_CMD><ID>{id}</ID><ACTION>move</ACTION><PART>{part}</PART><FROM>conveyor1.buffer</FROM><TO>conveyor1.load</TO></ROBOT_CMD>")
    };
    link.write_all(format!("{}{}", back(3, "p-2"), back(4, "p-1")).as_bytes())
        .await
        .unwrap();
    for id in [3, 4] {
        let reply = format!("<ROBOT_REPLY><ID>{id}</ID><RESULT>arrived</RESULT></ROBOT_REPLY>");
        read_until(&mut link, &mut received, &reply).await;
    }
    let view = control(&control_port, "where").await;
    assert!(parts_in(&view, "conveyor1.buffer").is_empty(), "{view:#}");
    assert_eq!(view["shipped"], 2, "{view:#}");
    let counts = control(&control_port, "counts").await;
    assert_eq!(counts["conveyor1"]["executed"], 4, "{counts:#}");
    shutdown.cancel();
}

/// Both moves on their way in the plant (polled on the control port): each one's
/// transit.
async fn both_riding(control_port: &str) -> Vec<serde_json::Value> {
    let deadline = Instant::now() + WAIT;
    loop {
        let view = control(control_port, "where").await;
        let riding = view["in_transit"].as_array().unwrap().clone();
        if riding.len() == 2 {
            return riding;
        }
        assert!(
            Instant::now() < deadline,
            "the two moves never travelled together: {view:#}"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// Two moves under way when the controller's links are cut (held on a jammed track, so
/// that both surely are): each goes on in the plant and its part arrives once the track
/// is cleared, each counted executed, neither answered.
#[tokio::test(flavor = "multi_thread")]
async fn a_cut_leaves_each_move_under_way_to_end_in_the_plant() {
    let dir = tempfile::tempdir().unwrap();
    let path = plant_file(dir.path(), 2);
    let plant = start_plant(&path, schemas::TimeScale::REAL).await;
    let (conveyor, control_port) = (
        plant.address("conveyor1").to_string(),
        plant.control.clone(),
    );
    let shutdown = plant.shutdown.clone();
    assert_eq!(control_line(&control_port, "jam conveyor1.buf").await, "ok");
    let mut link = tokio::net::TcpStream::connect(&conveyor).await.unwrap();
    let mv = |id: u64, part: &str| {
        format!("<ROBOT_CMD><ID>{id}</ID><ACTION>move</ACTION><PART>{part}</PART><FROM>conveyor1.load</FROM><TO>conveyor1.buffer</TO></ROBOT_CMD>")
    };
    link.write_all(format!("{}{}", mv(1, "p-1"), mv(2, "p-2")).as_bytes())
        .await
        .unwrap();
    both_riding(&control_port).await;
    assert_eq!(control_line(&control_port, "cut conveyor1").await, "ok");
    let mut received = String::new();
    loop {
        let mut buffer = [0u8; 4096];
        let n = tokio::time::timeout(WAIT, link.read(&mut buffer))
            .await
            .expect("the link closed in time")
            .unwrap_or(0);
        if n == 0 {
            break;
        }
        received.push_str(&String::from_utf8_lossy(&buffer[..n]));
    }
    assert!(!received.contains("ROBOT_REPLY"), "{received}");
    assert_eq!(
        control_line(&control_port, "clear conveyor1.buf").await,
        "ok"
    );
    let deadline = Instant::now() + WAIT;
    loop {
        let view = control(&control_port, "where").await;
        let counts = control(&control_port, "counts").await;
        if parts_in(&view, "conveyor1.buffer") == ["p-1", "p-2"]
            && counts["conveyor1"]["executed"] == 2
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the moves did not end in the plant: {view:#} {counts:#}"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    shutdown.cancel();
}

/// Two moves at once through the controller client, the first one's pallet silent (its
/// move ends in the plant unsaid): the first times out alone, while the controller
/// answers the second, and the second arrives on the same connection. A pallet that
/// stops reporting is that pallet's trouble: the connection is kept, and the other
/// moves on it are not failed with it (a reset would fail every one of them
/// `controller_disconnected`, and an unfenced transporter's order would take each
/// part to be lost).
#[tokio::test(flavor = "multi_thread")]
async fn a_silent_pallets_timeout_fails_its_move_alone() {
    let dir = tempfile::tempdir().unwrap();
    let plant = start_plant(&plant_file(dir.path(), 2), schemas::TimeScale::REAL).await;
    // A move takes about 1 s (1 m at 1 m/s); its command times out after 1.5 s.
    let mut h = Harness::start(
        plant.address("conveyor1").to_string(),
        Duration::from_millis(1500),
    );
    h.wait_ready().await;
    h.commands.send(move_to_buffer(1, "p-1")).await.unwrap();
    assert_eq!(h.answer().await, ControllerEvent::Departed { id: 1 });
    let view = control(&plant.control, "where").await;
    let pallet = view["in_transit"][0]["load"]["carrier"]
        .as_str()
        .unwrap_or_else(|| panic!("p-1 rides no pallet: {view:#}"))
        .to_string();
    assert_eq!(
        control_line(&plant.control, &format!("silence {pallet}")).await,
        "ok"
    );
    // The second begins 0.6 s after the first: it departs before the first times
    // out, and arrives after.
    tokio::time::sleep(Duration::from_millis(600)).await;
    h.commands.send(move_to_buffer(2, "p-2")).await.unwrap();
    let mut events = Vec::new();
    loop {
        let event = h.next().await;
        events.push(event.clone());
        if matches!(event, ControllerEvent::Reply { id: 2, .. }) {
            break;
        }
        assert!(
            !matches!(event, ControllerEvent::CommandFailed { id: 2, .. }),
            "the second move failed with the first: {events:?}"
        );
    }
    let answers: Vec<&ControllerEvent> = events
        .iter()
        .filter(|e| !matches!(e, ControllerEvent::Status(..)))
        .collect();
    assert_eq!(
        answers,
        [
            &ControllerEvent::Departed { id: 2 },
            &ControllerEvent::CommandFailed {
                id: 1,
                failure: CommandFailure::Timeout(Duration::from_millis(1500)),
            },
            &reply(2, "arrived"),
        ],
        "{events:?}"
    );
    assert!(
        !events.contains(&ControllerEvent::Status(
            ControllerStatus::Disconnected,
            None
        )),
        "the connection was reset: {events:?}"
    );
    let view = control(&plant.control, "where").await;
    assert_eq!(
        parts_in(&view, "conveyor1.buffer"),
        ["p-1", "p-2"],
        "{view:#}"
    );
    h.stop().await;
    plant.shutdown.cancel();
}

#[test]
fn a_plant_file_with_no_action_at_once_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = plant_file(dir.path(), 0);
    match robot_bridge::plant::prepare(&path, Default::default(), schemas::TimeScale::REAL) {
        Err(PlantError::Invalid { why, .. }) => {
            assert!(why.contains("actions_at_once"), "{why}")
        }
        Err(other) => panic!("{other}"),
        Ok(_) => panic!("a plant with actions_at_once = 0 was prepared"),
    }
}

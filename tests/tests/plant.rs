//! The plant simulator (docs/material-flow.md, "The plant"): one physical truth behind
//! every controller of the cell. Real holons drive it through their own controller
//! connections and dialect: a part rides a conveyor pallet to a station, the station
//! works on it only where it physically is, a pallet sent to a full port waits at its
//! stopper until the port has a place, and the state file says where every part and
//! pallet is.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use holarchy_tests::*;
use schemas::{HolonId, MessageType, Service};

/// Books `service_type` on `resource` for `order` with `info`, starts it, and returns
/// its result (`done` or `failed`).
async fn job(
    cell: &Cell,
    inbox: &mut Inbox,
    resource: &str,
    service_type: &str,
    conversation: &str,
    info: serde_json::Value,
) -> Service {
    let order = HolonId::order("o-1").unwrap();
    for kind in [MessageType::BookingReq, MessageType::Start] {
        let request = Service::request(kind, service_type, conversation, order.clone())
            .with_reply_to(cell.keys.inbox("o-1"))
            .with_info(info.as_object().unwrap().clone());
        let answer = cell.service(resource, &request).await.unwrap();
        assert_eq!(answer.result, Some(true), "{kind:?} refused: {answer:?}");
    }
    let (result, departed) = inbox.next_result().await.unwrap();
    // A move done on a pallet said once, before its result, that it left its origin
    // (one that failed on the way may have); a station's step never says so.
    let said = departed.len();
    match (service_type, result.message_type) {
        ("transport", MessageType::Done) => assert_eq!(said, 1, "{departed:?} before {result:?}"),
        ("transport", _) => assert!(said <= 1, "{departed:?} before {result:?}"),
        _ => assert_eq!(said, 0, "{departed:?} before {result:?}"),
    }
    for word in &departed {
        assert_eq!(word.conversation_id, conversation, "{word:?}");
        assert_eq!(word.provider, Some(HolonId::resource(resource).unwrap()));
    }
    result
}

fn poses() -> serde_json::Value {
    serde_json::json!({
        "pick": {"x": 1.0, "y": 2.0, "z": 3.0},
        "place": {"x": 4.0, "y": 5.0, "z": 6.0},
    })
}

fn with(mut info: serde_json::Value, more: serde_json::Value) -> serde_json::Value {
    for (k, v) in more.as_object().unwrap() {
        info[k] = v.clone();
    }
    info
}

#[tokio::test(flavor = "multi_thread")]
async fn parts_ride_pallets_and_are_worked_on_only_where_they_are() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    let robot_config = small_robot1(dir.path());
    let plant = PlantProcess::start(dir.path(), SMALL_PLANT);
    let cell = Cell::open("t-plant").await.unwrap();
    let mut nodes = Vec::new();
    for (name, config) in [
        ("conveyor1", dir.path().join("conveyor1.toml")),
        ("robot1", robot_config),
    ] {
        let controller = &plant.controllers[name];
        nodes.push(
            start_node(
                dir.path(),
                &config,
                "t-plant",
                &cell.endpoint,
                controller,
                &[],
            )
            .unwrap(),
        );
        cell.wait_alive(&HolonId::resource(name).unwrap())
            .await
            .unwrap();
        cell.wait_serving(name).await.unwrap();
    }
    let mut inbox = cell.inbox("o-1", 0).await.unwrap();
    let state = plant.state();
    assert_eq!(free_pallets(&state, "conveyor1"), 2, "{state:#}");

    // Nothing at robot1's port: a pick there fails, in the plant's words.
    let failed = job(
        &cell,
        &mut inbox,
        "robot1",
        "pick_n_place",
        "o-1/1/1",
        with(poses(), serde_json::json!({"part": "p-1"})),
    )
    .await;
    assert_eq!(failed.message_type, MessageType::Failed, "{failed:?}");
    let said = serde_json::to_string(&failed).unwrap();
    assert!(
        said.contains("part p-1 is not at robot1.port (not in the plant)"),
        "{said}"
    );

    // The conveyor brings it on a pallet from the loading point.
    let moved = job(
        &cell,
        &mut inbox,
        "conveyor1",
        "transport",
        "o-1/2/1",
        serde_json::json!({"part": "p-1", "from": "conveyor1.load", "to": "robot1.port"}),
    )
    .await;
    assert_eq!(moved.message_type, MessageType::Done, "{moved:?}");
    let state = plant.state();
    let at_robot = state["locations"]["robot1.port"].as_array().unwrap();
    assert_eq!(at_robot.len(), 1, "{state:#}");
    assert_eq!(at_robot[0]["part"], "p-1", "{state:#}");
    assert!(
        at_robot[0]["carrier"]
            .as_str()
            .unwrap()
            .starts_with("conveyor1/p"),
        "{state:#}"
    );

    // Now the robot works on it.
    let done = job(
        &cell,
        &mut inbox,
        "robot1",
        "pick_n_place",
        "o-1/1/2",
        with(poses(), serde_json::json!({"part": "p-1"})),
    )
    .await;
    assert_eq!(done.message_type, MessageType::Done, "{done:?}");

    // Back to the loading point: it leaves the plant, its pallet free again.
    let shipped = job(
        &cell,
        &mut inbox,
        "conveyor1",
        "transport",
        "o-1/4/1",
        serde_json::json!({"part": "p-1", "from": "robot1.port", "to": "conveyor1.load"}),
    )
    .await;
    assert_eq!(shipped.message_type, MessageType::Done, "{shipped:?}");
    let state = plant.state();
    assert_eq!(state["shipped"], 1, "{state:#}");
    assert_eq!(free_pallets(&state, "conveyor1"), 2, "{state:#}");
    assert!(
        state["locations"]["robot1.port"]
            .as_array()
            .unwrap()
            .is_empty(),
        "{state:#}"
    );
    assert!(
        state["in_transit"].as_array().unwrap().is_empty(),
        "{state:#}"
    );
    drop(nodes);
}

#[test]
fn plant_sim_checks_its_file_and_layout() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    small_robot1(dir.path());
    let plant = dir.path().join("plant.toml");
    let check = |text: &str| {
        std::fs::write(&plant, text).unwrap();
        let output = Command::new(bin("plant-sim"))
            .arg("--plant")
            .arg(&plant)
            .arg("--check")
            .output()
            .unwrap();
        (
            output.status.code(),
            String::from_utf8_lossy(&output.stdout).into_owned()
                + &String::from_utf8_lossy(&output.stderr),
        )
    };
    // The demo's plant is valid.
    let demo = Command::new(bin("plant-sim"))
        .arg("--plant")
        .arg(workspace_root().join("deploy/cells/demo/plant.toml"))
        .arg("--check")
        .output()
        .unwrap();
    assert!(
        demo.status.success(),
        "{}",
        String::from_utf8_lossy(&demo.stderr)
    );
    let controllers = "[[controller]]\nresource = \"robot1\"\nlisten = \"127.0.0.1:0\"\n";
    let (code, said) = check(&format!(
        "layout = [\"conveyor1.toml\", \"robot1.toml\"]\n{controllers}"
    ));
    assert_eq!(code, Some(0), "{said}");
    assert!(said.contains("is valid"), "{said}");
    // Without the conveyor, robot1's dock names nothing: the plant refuses to start.
    let (code, said) = check(&format!("layout = [\"robot1.toml\"]\n{controllers}"));
    assert_eq!(code, Some(2), "{said}");
    assert!(
        said.contains(
            "robot1: layout.locations[0].dock: conveyor1: no conveyor of that name in the layout"
        ),
        "{said}"
    );
    let (code, said) = check(&format!(
        "layout = [\"robot1.toml\"]\nwhat = 1\n{controllers}"
    ));
    assert_eq!(code, Some(2), "{said}");
    assert!(said.contains("unknown field `what`"), "{said}");
    let (code, said) = check(&format!(
        "layout = [\"conveyor1.toml\", \"robot1.toml\"]\n{controllers}dialect = \"fanuc\"\n"
    ));
    assert_eq!(code, Some(2), "{said}");
    assert!(said.contains("controller[0] (robot1): dialect:"), "{said}");
}

/// A transporter config: `layout` as its part, one `transport` service moving parts.
fn transporter(dir: &Path, name: &str, layout: &str) -> PathBuf {
    let path = dir.join(format!("{name}.toml"));
    let text = SMALL_CONVEYOR
        .replace("name = \"conveyor1\"", &format!("name = \"{name}\""))
        .split("[[layout.locations]]")
        .next()
        .unwrap()
        .to_string();
    std::fs::write(&path, format!("{text}{layout}")).unwrap();
    path
}

/// Transporters propose a move with its travel time from the cell's layout (the queue
/// ahead and the travel), so an order has a real choice between the conveyor and a
/// transfer robot; a move a transporter cannot make is refused, saying why.
#[tokio::test(flavor = "multi_thread")]
async fn transporters_propose_their_travel_and_refuse_what_they_cannot_reach() {
    let dir = tempfile::tempdir().unwrap();
    let station = |name: &str, dock: &str| {
        let path = resource_config(dir.path(), name, 5000).unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        let layout = format!(
            "\n[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n"
        );
        std::fs::write(&path, format!("{text}{layout}")).unwrap();
        path
    };
    let configs = [
        ("conveyor1", {
            std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR.replace(
                "stoppers = [{ name = \"load\", at_mm = 0 }, { name = \"s1\", at_mm = 1000 }]",
                "stoppers = [{ name = \"load\", at_mm = 0 }, { name = \"s1\", at_mm = 1000 }, { name = \"s2\", at_mm = 1500 }]",
            )).unwrap();
            dir.path().join("conveyor1.toml")
        }),
        ("robot1", station("robot1", "conveyor1.s1")),
        ("robot2", station("robot2", "conveyor1.s2")),
        (
            "mover1",
            transporter(
                dir.path(),
                "mover1",
                "[layout.transfer]\nbetween = [\"robot1.port\", \"robot2.port\"]\nmove_ms = 100\n",
            ),
        ),
    ];
    let cell = Cell::open("t-transporters").await.unwrap();
    let mut running = Vec::new();
    for (name, config) in &configs {
        let sim = Sim::start(dir.path(), &format!("{name}-sim"), "127.0.0.1:0", &[]).unwrap();
        running.push(
            start_node(
                dir.path(),
                config,
                "t-transporters",
                &cell.endpoint,
                &sim.address,
                &[],
            )
            .unwrap(),
        );
        running.push(sim.process);
        cell.wait_serving(name).await.unwrap();
    }
    let ask = |from: &str, to: &str| {
        let info = serde_json::json!({"part": "p-1", "from": from, "to": to});
        Service::request(
            MessageType::ProposalReq,
            "transport",
            "o-1/1/1",
            HolonId::order("o-1").unwrap(),
        )
        .with_info(info.as_object().unwrap().clone())
    };
    // Between the two robots: the conveyor (500 mm at 4 m/s: 125 ms) and the transfer
    // robot (100 ms) both propose, each with its own travel, once they know the layout.
    let deadline = tokio::time::Instant::now() + WAIT;
    let by = loop {
        let proposals = cell
            .wait_proposals(&ask("robot1.port", "robot2.port"), 2)
            .await
            .unwrap();
        let by: std::collections::BTreeMap<String, serde_json::Value> = proposals
            .iter()
            .map(|p| {
                (
                    p.provider.as_ref().unwrap().name().to_string(),
                    p.info["duration_ms"].clone(),
                )
            })
            .collect();
        if by["conveyor1"] == 125 && by["mover1"] == 100 {
            break by;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the transporters never timed the move by the layout: {by:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    assert_eq!(by.len(), 2, "{by:?}");
    // From the loading point only the conveyor can: the transfer robot says why not.
    let proposals = cell
        .proposals(&ask("conveyor1.load", "robot2.port"))
        .await
        .unwrap();
    let mover = proposals
        .iter()
        .find(|p| p.provider.as_ref().is_some_and(|h| h.name() == "mover1"))
        .unwrap_or_else(|| panic!("{proposals:?}"));
    assert_eq!(mover.result, Some(false), "{mover:?}");
    assert_eq!(
        mover.info["detail"],
        "mover1 does not move parts from conveyor1.load to robot2.port (as the cell's layout stands)"
    );
    let conveyor = proposals
        .iter()
        .find(|p| p.provider.as_ref().is_some_and(|h| h.name() == "conveyor1"))
        .unwrap_or_else(|| panic!("{proposals:?}"));
    assert_eq!(conveyor.result, Some(true), "{conveyor:?}");
    assert_eq!(conveyor.info["duration_ms"], 375, "{conveyor:?}");
    drop(running);
}

/// The plant's faults, played on its control port: a jammed track holds a move until it
/// is cleared; a pallet that stops reporting arrives without its controller saying so,
/// and the control's view then differs from the plant's truth (the part is there; the
/// step failed).
#[tokio::test(flavor = "multi_thread")]
async fn a_jammed_track_holds_a_move_and_a_silent_pallet_arrives_unreported() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("conveyor1.toml"),
        SMALL_CONVEYOR.replace("command_timeout_ms = 5000", "command_timeout_ms = 2000"),
    )
    .unwrap();
    let robot_config = small_robot1(dir.path());
    let plant = PlantProcess::start(dir.path(), SMALL_PLANT);
    let cell = Cell::open("t-plant-faults").await.unwrap();
    let mut nodes = Vec::new();
    for (name, config) in [
        ("conveyor1", dir.path().join("conveyor1.toml")),
        ("robot1", robot_config),
    ] {
        let controller = &plant.controllers[name];
        nodes.push(
            start_node(
                dir.path(),
                &config,
                "t-plant-faults",
                &cell.endpoint,
                controller,
                &[],
            )
            .unwrap(),
        );
        cell.wait_serving(name).await.unwrap();
    }
    let mut inbox = cell.inbox("o-1", 0).await.unwrap();
    assert!(plant
        .command("jam conveyor9.s1")
        .starts_with("error conveyor9.s1: no such conveyor stopper"));
    assert!(plant.command("fly away").starts_with("error "));
    // The track to s1 jammed: the move to robot1's port does not end.
    assert_eq!(plant.command("jam conveyor1.s1"), "ok");
    let order = HolonId::order("o-1").unwrap();
    let info = serde_json::json!({"part": "p-1", "from": "conveyor1.load", "to": "robot1.port"});
    for kind in [MessageType::BookingReq, MessageType::Start] {
        let request = Service::request(kind, "transport", "o-1/1/1", order.clone())
            .with_reply_to(cell.keys.inbox("o-1"))
            .with_info(info.as_object().unwrap().clone());
        assert_eq!(
            cell.service("conveyor1", &request).await.unwrap().result,
            Some(true)
        );
    }
    assert!(
        inbox.silent_for(Duration::from_millis(1000)).await,
        "a move along a jammed track ended"
    );
    let state: serde_json::Value = serde_json::from_str(&plant.command("where")).unwrap();
    assert_eq!(state["in_transit"][0]["load"]["part"], "p-1", "{state:#}");
    assert_eq!(state["jammed"][0], "conveyor1.s1", "{state:#}");
    // Cleared: it leaves (said only now: the jam kept its pallet docked, the order's
    // place at the loading point held), goes on and arrives.
    assert_eq!(plant.command("clear conveyor1.s1"), "ok");
    let (done, departed) = inbox.next_result().await.unwrap();
    assert_eq!(done.message_type, MessageType::Done, "{done:?}");
    assert_eq!(departed.len(), 1, "{departed:?}");
    // The conveyor's e-stop, pressed for 1.5 s: its holon hears estop at once (on
    // the connection it has), then ready again.
    assert!(plant
        .command("estop conveyor9 100")
        .starts_with("error conveyor9: no controller"));
    assert_eq!(plant.command("estop conveyor1 1500"), "ok");
    cell.wait_state("conveyor1", "its controller in estop", |s| {
        s["controller"] == "estop"
    })
    .await
    .unwrap();
    assert_eq!(plant.state()["estopped"][0], "conveyor1");
    cell.wait_state("conveyor1", "its controller ready again", |s| {
        s["controller"] == "ready"
    })
    .await
    .unwrap();
    // An e-stop aborts the PackML unit (docs/packml.md): an operator clears, resets
    // and starts it again.
    cell.wait_packml("conveyor1", 9).await.unwrap();
    for command in ["clear", "reset", "start"] {
        cell.packml("conveyor1", command).await.unwrap();
    }
    cell.wait_serving("conveyor1").await.unwrap();
    let state = plant.state();
    let pallet = state["locations"]["robot1.port"][0]["carrier"]
        .as_str()
        .unwrap()
        .to_string();
    // Its pallet stops reporting: the move back to the loading point happens, unsaid.
    assert_eq!(plant.command(&format!("silence {pallet}")), "ok");
    let back = job(
        &cell,
        &mut inbox,
        "conveyor1",
        "transport",
        "o-1/2/1",
        serde_json::json!({"part": "p-1", "from": "robot1.port", "to": "conveyor1.load"}),
    )
    .await;
    assert_eq!(back.message_type, MessageType::Failed, "{back:?}");
    let state = plant.state();
    assert_eq!(
        state["shipped"], 1,
        "the plant's truth: the part left: {state:#}"
    );
    assert_eq!(state["silent"][0], pallet, "{state:#}");
    drop(nodes);
}

/// A move goes on in the plant when its transporter's holon dies mid-move: the part
/// arrives where the pallet was going (the plant's truth the control must catch up with).
#[tokio::test(flavor = "multi_thread")]
async fn a_move_goes_on_in_the_plant_when_its_holon_is_killed() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    let robot_config = small_robot1(dir.path());
    let plant = PlantProcess::start(dir.path(), SMALL_PLANT);
    let cell = Cell::open("t-plant-kill").await.unwrap();
    // robot1 serves: its port is in the layout the conveyor knows.
    let _robot = start_node(
        dir.path(),
        &robot_config,
        "t-plant-kill",
        &cell.endpoint,
        &plant.controllers["robot1"],
        &[],
    )
    .unwrap();
    cell.wait_serving("robot1").await.unwrap();
    let mut conveyor = start_node(
        dir.path(),
        &dir.path().join("conveyor1.toml"),
        "t-plant-kill",
        &cell.endpoint,
        &plant.controllers["conveyor1"],
        &[],
    )
    .unwrap();
    cell.wait_serving("conveyor1").await.unwrap();
    let _inbox = cell.inbox("o-1", 0).await.unwrap();
    // Held on a jammed track, so that it is surely under way when the holon dies.
    assert_eq!(plant.command("jam conveyor1.s1"), "ok");
    let info = serde_json::json!({"part": "p-1", "from": "conveyor1.load", "to": "robot1.port"});
    for kind in [MessageType::BookingReq, MessageType::Start] {
        let request =
            Service::request(kind, "transport", "o-1/1/1", HolonId::order("o-1").unwrap())
                .with_reply_to(cell.keys.inbox("o-1"))
                .with_info(info.as_object().unwrap().clone());
        assert_eq!(
            cell.service("conveyor1", &request).await.unwrap().result,
            Some(true)
        );
    }
    let deadline = tokio::time::Instant::now() + WAIT;
    while plant.state()["in_transit"].as_array().unwrap().is_empty() {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the move never began"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    conveyor.kill();
    assert_eq!(plant.command("clear conveyor1.s1"), "ok");
    loop {
        let state = plant.state();
        if state["locations"]["robot1.port"][0]["part"] == "p-1" {
            assert!(
                state["in_transit"].as_array().unwrap().is_empty(),
                "{state:#}"
            );
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the part never arrived: {state:#}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// A pallet sent to a full port is not refused: it rides there and waits at the port's
/// stopper, first on its track, and the state file says what it waits for and since
/// when; once the port is emptied (a transfer robot takes its part to a shelf) it docks
/// and its move ends. Driven through the plant's controllers as holons would, without
/// holons.
#[test]
fn a_pallet_waits_at_a_full_port_and_goes_on_once_it_is_emptied() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    small_robot1(dir.path());
    let shelf = resource_config(dir.path(), "shelf1", 5000).unwrap();
    let text = std::fs::read_to_string(&shelf).unwrap();
    let layout = "\n[[layout.locations]]\nname = \"shelf\"\nrole = \"buffer\"\ncapacity = 2\n";
    std::fs::write(&shelf, format!("{text}{layout}")).unwrap();
    transporter(
        dir.path(),
        "mover1",
        "[layout.transfer]\nbetween = [\"robot1.port\", \"shelf1.shelf\"]\nmove_ms = 100\n",
    );
    let plant = PlantProcess::start(
        dir.path(),
        r#"
layout = ["conveyor1.toml", "robot1.toml", "shelf1.toml", "mover1.toml"]

[[controller]]
resource = "conveyor1"
listen = "127.0.0.1:0"

[[controller]]
resource = "mover1"
listen = "127.0.0.1:0"
"#,
    );
    let mut conveyor = ControllerLink::connect(&plant.controllers["conveyor1"]);
    let mut mover = ControllerLink::connect(&plant.controllers["mover1"]);
    let first = conveyor.send_move("p-1", "conveyor1.load", "robot1.port");
    let reply = conveyor.reply(first, WAIT).expect("p-1's move ends");
    assert!(reply.contains("<RESULT>arrived</RESULT>"), "{reply}");
    // robot1's port holds p-1: p-2's pallet goes all the same, and waits at s1.
    let second = conveyor.send_move("p-2", "conveyor1.load", "robot1.port");
    let deadline = std::time::Instant::now() + WAIT;
    let (pallet, waiting) = loop {
        let state = plant.state();
        let waiting = state["pallets"]
            .as_object()
            .unwrap()
            .iter()
            .find(|(_, p)| p["part"] == "p-2" && p["waits"].is_string())
            .map(|(id, p)| (id.clone(), p.clone()));
        if let Some(found) = waiting {
            break found;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "p-2's pallet never waited at robot1's stopper: {state:#}"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(waiting["waits"], "robot1.port full", "{waiting:#}");
    assert_eq!(waiting["at"], "track", "{waiting:#}");
    assert_eq!(waiting["track"], "s1", "{waiting:#}");
    assert_eq!(waiting["queue_position"], 0, "{waiting:#}");
    assert_eq!(waiting["to"], "robot1.port", "{waiting:#}");
    assert!(waiting["waits_since_ms"].is_u64(), "{waiting:#}");
    let state: serde_json::Value = serde_json::from_str(&plant.command("where")).unwrap();
    assert_eq!(state["deadlocked"], false, "{state:#}");
    assert_eq!(state["in_transit"][0]["load"]["part"], "p-2", "{state:#}");
    let waits: serde_json::Value = serde_json::from_str(&plant.command("waits")).unwrap();
    assert_eq!(waits["waits"][0]["pallet"], pallet.as_str(), "{waits:#}");
    assert_eq!(waits["waits"][0]["waits"], "robot1.port full", "{waits:#}");
    assert_eq!(waits["deadlocked"], false, "{waits:#}");
    // The port is emptied: the transfer robot takes p-1 to the shelf.
    let taken = mover.send_move("p-1", "robot1.port", "shelf1.shelf");
    let reply = mover.reply(taken, WAIT).expect("the transfer ends");
    assert!(reply.contains("<RESULT>arrived</RESULT>"), "{reply}");
    // p-2's pallet docks: its move ends.
    let reply = conveyor.reply(second, WAIT).expect("p-2's move ends");
    assert!(reply.contains("<RESULT>arrived</RESULT>"), "{reply}");
    let state = plant.state();
    let port = &state["locations"]["robot1.port"];
    assert_eq!(port[0]["part"], "p-2", "{state:#}");
    assert_eq!(port[0]["carrier"], pallet.as_str(), "{state:#}");
    assert_eq!(
        state["locations"]["shelf1.shelf"][0]["part"], "p-1",
        "{state:#}"
    );
    assert_eq!(state["pallets"][&pallet]["at"], "docked", "{state:#}");
    assert!(state["pallets"][&pallet]["waits"].is_null(), "{state:#}");
    assert_eq!(state["deadlocked"], false, "{state:#}");
    assert!(state["longest_wait_ms"].as_u64().unwrap() > 0, "{state:#}");
}

/// A controller's links cut (`cut RESOURCE`, as a failed network between it and its
/// holon): every connection to it closes at once, the move it was running goes on in
/// the plant and ends there, and it takes a new connection at once. An unknown resource
/// is refused and nothing changes.
#[test]
fn a_cut_closes_the_controllers_links_and_its_move_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    small_robot1(dir.path());
    let plant = PlantProcess::start(dir.path(), SMALL_PLANT);
    let mut link = ControllerLink::connect(&plant.controllers["conveyor1"]);
    // Held on a jammed track, so that it is surely under way when the link is cut.
    assert_eq!(plant.command("jam conveyor1.s1"), "ok");
    link.send_move("p-1", "conveyor1.load", "robot1.port");
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    while plant.state()["in_transit"][0]["load"]["part"] != "p-1" {
        assert!(std::time::Instant::now() < deadline, "the move never began");
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(plant
        .command("cut conveyor9")
        .starts_with("error conveyor9: no controller"));
    assert!(!link.closed(Duration::from_millis(300)), "closed unasked");
    assert_eq!(plant.command("cut conveyor1"), "ok");
    assert!(link.closed(Duration::from_secs(5)), "the link stayed open");
    let state = plant.state();
    assert_eq!(state["in_transit"][0]["load"]["part"], "p-1", "{state:#}");
    assert_eq!(plant.command("clear conveyor1.s1"), "ok");
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let state = plant.state();
        if state["locations"]["robot1.port"][0]["part"] == "p-1" {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the move did not end in the plant: {state:#}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Connected again, it works: the part goes back to the loading point.
    let mut again = ControllerLink::connect(&plant.controllers["conveyor1"]);
    let back = again.send_move("p-1", "robot1.port", "conveyor1.load");
    let reply = again
        .reply(back, Duration::from_secs(10))
        .expect("the move back ends");
    assert!(reply.contains("<RESULT>arrived</RESULT>"), "{reply}");
}

//! The plant simulator dies and resumes (docs/material-flow.md, "When the plant
//! simulator dies"): killed with SIGKILL and started again on its state file, it goes on
//! from where it was; a state file it cannot resume from is refused.

use std::time::Duration;

use holarchy_tests::*;

/// The plant simulator killed with SIGKILL and started again on its state file goes on
/// from where it was (docs/material-flow.md, "When the plant simulator dies"): a move
/// under way (held on a jammed track) is still under way, the jam still there, the
/// plant's time goes on, an e-stop whose timer died with it is released; cleared, the
/// move ends in the plant once, in the trace once;
/// the fenced conveyor's epochs go on, and its step is known: running, then done. A
/// step done before the kill is still done, and a repeat of it is answered from the
/// record, not run again.
#[test]
fn a_killed_plant_resumes_where_it_was() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    small_robot1(dir.path());
    let fenced = SMALL_PLANT.replace(
        "resource = \"conveyor1\"\nlisten = \"127.0.0.1:0\"",
        "resource = \"conveyor1\"\nlisten = \"127.0.0.1:0\"\nfenced_lease_ms = 60000",
    );
    let mut plant = PlantProcess::start(dir.path(), &fenced);
    let mut link = ControllerLink::connect(&plant.controllers["conveyor1"]);
    let claim = |link: &mut ControllerLink| -> u64 {
        link.send_raw("<CLAIM><NAME>conveyor1</NAME></CLAIM>");
        let granted = link
            .message("<CLAIM_GRANTED>", "</CLAIM_GRANTED>", WAIT)
            .expect("the claim is granted");
        let epoch = granted
            .split("<EPOCH>")
            .nth(1)
            .and_then(|e| e.split("</EPOCH>").next())
            .and_then(|e| e.parse().ok())
            .unwrap_or_else(|| panic!("{granted}"));
        epoch
    };
    let fenced_move = |link: &mut ControllerLink,
                       id: u64,
                       epoch: u64,
                       step: &str,
                       part: &str,
                       from: &str,
                       to: &str| {
        link.send_raw(&format!(
            "<ROBOT_CMD><ID>{id}</ID><EPOCH>{epoch}</EPOCH><STEP>{step}</STEP><ACTION>move</ACTION><PART>{part}</PART><FROM>{from}</FROM><TO>{to}</TO></ROBOT_CMD>"
        ));
    };
    let step_state = |link: &mut ControllerLink, step: &str| -> String {
        link.send_raw(&format!("<STEP_STATUS><STEP>{step}</STEP></STEP_STATUS>"));
        link.message("<STEP_STATE>", "</STEP_STATE>", WAIT)
            .expect("the step's state")
    };
    let epoch = claim(&mut link);
    // A move done before the kill.
    fenced_move(
        &mut link,
        1,
        epoch,
        "c-1#0",
        "p-1",
        "conveyor1.load",
        "robot1.port",
    );
    let reply = link.reply(1, WAIT).expect("p-1's move ends");
    assert!(reply.contains("<RESULT>arrived</RESULT>"), "{reply}");
    // One under way when it dies: back to the loading point (the exit), held on a
    // jammed track.
    assert_eq!(plant.command("jam conveyor1.load"), "ok");
    fenced_move(
        &mut link,
        2,
        epoch,
        "c-2#0",
        "p-1",
        "robot1.port",
        "conveyor1.load",
    );
    let deadline = std::time::Instant::now() + WAIT;
    while plant.state()["in_transit"][0]["load"]["part"] != "p-1" {
        assert!(std::time::Instant::now() < deadline, "the move never began");
        std::thread::sleep(Duration::from_millis(20));
    }
    // An e-stop pressed for ten minutes: its timer dies with the plant.
    assert_eq!(plant.command("estop robot1 600000"), "ok");
    std::thread::sleep(Duration::from_millis(300));
    let before = plant.state();
    assert_eq!(
        before["estopped"],
        serde_json::json!(["robot1"]),
        "{before:#}"
    );
    plant.kill_and_restart(dir.path());
    assert!(link.closed(WAIT), "the old link outlived its controller");
    let after = plant.state();
    assert_eq!(after["in_transit"][0]["load"]["part"], "p-1", "{after:#}");
    assert_eq!(
        after["in_transit"][0]["command"]["step"], "c-2#0",
        "{after:#}"
    );
    assert_eq!(
        after["jammed"],
        serde_json::json!(["conveyor1.load"]),
        "{after:#}"
    );
    assert_eq!(after["pallets"], before["pallets"], "{after:#}");
    assert_eq!(
        after["estopped"],
        serde_json::json!([]),
        "released: {after:#}"
    );
    assert!(
        after["now_ms"].as_u64() >= before["now_ms"].as_u64(),
        "the plant's time went back: {} then {}",
        before["now_ms"],
        after["now_ms"]
    );
    let mut link = ControllerLink::connect(&plant.controllers["conveyor1"]);
    let again = claim(&mut link);
    assert!(again > epoch, "epoch {again} granted again after {epoch}");
    let running = step_state(&mut link, "c-2#0");
    assert!(running.contains("<STATE>running</STATE>"), "{running}");
    let done = step_state(&mut link, "c-1#0");
    assert!(done.contains("<STATE>done</STATE>"), "{done}");
    // A repeat of the step done before the kill is answered from its record.
    fenced_move(
        &mut link,
        3,
        again,
        "c-1#0",
        "p-1",
        "conveyor1.load",
        "robot1.port",
    );
    let repeat = link.reply(3, WAIT).expect("the repeat is answered");
    assert!(repeat.contains("<RESULT>arrived</RESULT>"), "{repeat}");
    assert_eq!(plant.command("clear conveyor1.load"), "ok");
    let deadline = std::time::Instant::now() + WAIT;
    loop {
        let state = step_state(&mut link, "c-2#0");
        if state.contains("<STATE>done</STATE>") {
            assert!(state.contains("<RESULT>arrived</RESULT>"), "{state}");
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the resumed move never ended: {state}; {:#}",
            plant.state()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    // Back at the loading point, which is the exit too: p-1 has left the plant.
    let state = plant.state();
    assert_eq!(state["shipped"], 1, "{state:#}");
    assert_eq!(state["in_transit"], serde_json::json!([]), "{state:#}");
    let moves = PlantProcess::done_in_trace(dir.path(), "move");
    assert_eq!(moves["conveyor1"], 2, "each move traced once: {moves:?}");
    // A grant is written before it is sent: killed straight after one, with nothing
    // else changed in the plant, the plant started again never grants that epoch again.
    plant.kill_and_restart(dir.path());
    let mut link = ControllerLink::connect(&plant.controllers["conveyor1"]);
    let granted = claim(&mut link);
    assert!(granted > again, "epoch {granted} after {again}");
    plant.kill_and_restart(dir.path());
    let mut link = ControllerLink::connect(&plant.controllers["conveyor1"]);
    let next = claim(&mut link);
    assert!(next > granted, "epoch {granted} granted again ({next})");
    // --fresh forgets it all.
    plant.process.kill();
    let fresh = std::process::Command::new(bin("plant-sim"))
        .arg("--plant")
        .arg(dir.path().join("plant.toml"))
        .arg("--state-file")
        .arg(&plant.state_file)
        .args(["--fresh", "--check"])
        .output()
        .unwrap();
    assert!(fresh.status.success(), "{fresh:?}");
}

/// A state file the plant cannot resume from is refused at start, with the reason and
/// what to do; nothing is overwritten.
#[test]
fn a_plant_refuses_a_state_file_it_cannot_resume_from() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("conveyor1.toml"), SMALL_CONVEYOR).unwrap();
    small_robot1(dir.path());
    let plant = dir.path().join("plant.toml");
    std::fs::write(&plant, SMALL_PLANT).unwrap();
    let state = dir.path().join("plant-state.json");
    let check = |text: &str| {
        std::fs::write(&state, text).unwrap();
        let out = std::process::Command::new(bin("plant-sim"))
            .arg("--plant")
            .arg(&plant)
            .arg("--state-file")
            .arg(&state)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{out:?}");
        assert_eq!(
            std::fs::read_to_string(&state).unwrap(),
            text,
            "overwritten"
        );
        String::from_utf8_lossy(&out.stderr).to_string()
    };
    let garbage = check("{not json");
    assert!(garbage.contains("not a plant's state file"), "{garbage}");
    assert!(garbage.contains("--fresh"), "{garbage}");
    let old = check("{\"now_ms\": 5, \"locations\": {}}");
    assert!(old.contains("has no memory"), "{old}");
    // A memory of another layout: a pallet this conveyor does not have.
    std::fs::remove_file(&state).unwrap();
    let first = PlantProcess::start(dir.path(), SMALL_PLANT);
    drop(first);
    let written = std::fs::read_to_string(&state).unwrap();
    let other = written.replace("conveyor1/p2", "conveyor1/p9");
    let refused = check(&other);
    assert!(
        refused.contains("conveyor1/p9 is not in the layout"),
        "{refused}"
    );
}

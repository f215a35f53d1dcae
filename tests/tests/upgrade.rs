//! Upgrading holons while the cell runs (`--take-over`, `cell upgrade`): real
//! processes, the controller simulator, journals on disk. Nothing acknowledged is lost,
//! no booking is handed back, no step is interrupted or run twice.

use std::path::Path;
use std::time::Duration;

use holarchy_tests::*;
use nix::sys::signal::Signal;
use schemas::HolonId;

/// Every order's state, as its order-node answers (the orders must all be known).
async fn order_states(cell: &Cell, orders: &[String]) -> Vec<serde_json::Value> {
    let mut states = Vec::new();
    for order in orders {
        states.push(cell.order_state(order).await.unwrap_or_default());
    }
    states
}

/// Waits (at most `limit`) until every order is done; the states as they ended.
async fn wait_all_done(cell: &Cell, orders: &[String], limit: Duration) -> Vec<serde_json::Value> {
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        let states = order_states(cell, orders).await;
        let open: Vec<_> = states
            .iter()
            .zip(orders)
            .filter(|(s, _)| s["status"] != "done")
            .map(|(s, o)| format!("{o}: {} {}", s["status"], s["reason"]))
            .collect();
        if open.is_empty() {
            return states;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "orders not done within {limit:?}: {open:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Asserts that no order rebooked, failed an attempt or was reworked.
fn assert_undisturbed(states: &[serde_json::Value]) {
    for state in states {
        assert_eq!(state["rebooks"], 0, "an order rebooked: {state}");
        assert_eq!(state["failed_attempts"], 0, "an attempt failed: {state}");
        for attempt in state["attempts"].as_array().unwrap() {
            let detail = attempt["detail"].as_str().unwrap_or_default();
            assert!(
                !detail.contains("withdrawn") && !detail.contains("interrupted"),
                "{detail}"
            );
        }
    }
}

/// Asserts that no attempt failed or was interrupted (rebooks allowed).
fn assert_none_failed_or_interrupted(states: &[serde_json::Value]) {
    for state in states {
        assert_eq!(state["failed_attempts"], 0, "an attempt failed: {state}");
        for attempt in state["attempts"].as_array().unwrap() {
            let detail = attempt["detail"].as_str().unwrap_or_default();
            assert!(!detail.contains("interrupted"), "{detail}");
        }
    }
}

/// Starts `cell up DIR` (the manifest `DIR/cell.toml`), its output in `DIR/cell-up.out`.
fn start_cell_up(dir: &Path) -> std::process::Child {
    let up_log = std::fs::File::create(dir.join("cell-up.out")).unwrap();
    std::process::Command::new(bin("cell"))
        .arg("up")
        .arg(dir)
        .stdout(up_log.try_clone().unwrap())
        .stderr(up_log)
        .spawn()
        .unwrap()
}

/// A copy of `config` in `dir` (the successor's own log and stderr go there).
fn successor_dir(dir: &Path) -> std::path::PathBuf {
    let next = dir.join("next");
    std::fs::create_dir_all(&next).unwrap();
    next
}

#[tokio::test(flavor = "multi_thread")]
async fn a_resource_hands_over_to_its_successor_without_losing_or_repeating_a_step() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-upgrade-resource").await.unwrap();
    let data = dir.join("robot-data");
    let data_arg = data.to_str().unwrap();
    let Resource {
        node: mut old,
        sim,
        config,
    } = cell
        .resource(dir, "robot1")
        .sim_flags(&["--delay-ms", "100"])
        .command_timeout_ms(10_000)
        .node_flags(&["--data-dir", data_arg])
        .start()
        .await
        .unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &dir.join("orders-data"))
        .await
        .unwrap();
    let orders = cell.submit("part", 12).await.unwrap();
    // A result in a message version the order-node does not speak is refused, and
    // says so (a holon of another release in a rolling upgrade). The last order's
    // inbox: it is still there when a loaded machine gets to ask, once its node says
    // it holds the order (its task runs, its inbox is open).
    let last = orders.last().unwrap();
    cell.wait_held(last).await.unwrap();
    let mut other_version = serde_json::to_value(schemas::Service::request(
        schemas::MessageType::Done,
        "pick_n_place",
        &format!("{last}/1/1"),
        HolonId::order(last).unwrap(),
    ))
    .unwrap();
    other_version["v"] = serde_json::json!(2);
    let refused = cell
        .request(
            &cell.keys.inbox(last),
            serde_json::to_vec(&other_version).unwrap(),
        )
        .await
        .unwrap()
        .expect_err("another version is refused");
    assert_eq!(refused.code.as_str(), "unsupported_version", "{refused:?}");
    assert!(refused.message.contains("speaks version 1"), "{refused:?}");
    // Mid-run: a step is running and others wait on the agenda.
    sim.wait_executed("pick", 3).await.unwrap();

    // A successor with another data dir is refused, and the running holon serves on.
    let next = successor_dir(dir);
    let elsewhere = dir.join("elsewhere");
    let mut wrong = start_node(
        &next,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", elsewhere.to_str().unwrap(), "--take-over"],
    )
    .unwrap();
    let status = wrong.wait_exit(Duration::from_secs(20)).unwrap();
    // Exit code 3: refused, nothing changed (what `cell up` reports as such).
    assert_eq!(
        status.code(),
        Some(3),
        "a successor on another journal is refused: {status:?}"
    );
    assert!(wrong.stderr().contains("data dir"), "{}", wrong.stderr());

    // The real successor: same config, same data dir.
    let mut successor = start_node(
        &next,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", data_arg, "--take-over"],
    )
    .unwrap();
    let status = old.wait_exit(Duration::from_secs(30)).unwrap();
    assert!(status.success(), "the predecessor ends with 0: {status:?}");
    assert!(old.stderr().contains("handed over"), "{}", old.stderr());
    cell.wait_alive(&HolonId::resource("robot1").unwrap())
        .await
        .unwrap();

    let states = wait_all_done(&cell, &orders, Duration::from_secs(60)).await;
    assert_undisturbed(&states);
    // Every step ran exactly once, on the one controller both processes drove.
    assert_eq!(sim.wait_executed("pick", 12).await.unwrap(), 12);
    assert_eq!(sim.wait_executed("place", 12).await.unwrap(), 12);
    successor.signal(Signal::SIGTERM).unwrap();
    assert!(successor
        .wait_exit(Duration::from_secs(20))
        .unwrap()
        .success());
}

/// A successor that is released and then never serves (it died, or hangs): the
/// running holon has let go, so it stands in for its limit and exits 1, and its
/// supervisor starts it again on its journal. No order is lost, nothing is
/// interrupted, and no step is run twice.
#[tokio::test(flavor = "multi_thread")]
async fn a_holon_whose_successor_never_serves_exits_to_be_started_again() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-upgrade-no-successor").await.unwrap();
    let data = dir.join("robot-data");
    let data_arg = data.to_str().unwrap();
    let Resource {
        node: mut old,
        sim,
        config,
    } = cell
        .resource(dir, "robot1")
        .sim_flags(&["--delay-ms", "100"])
        .command_timeout_ms(10_000)
        .node_flags(&["--data-dir", data_arg])
        .start()
        .await
        .unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &dir.join("orders-data"))
        .await
        .unwrap();
    let orders = cell.submit("part", 6).await.unwrap();
    sim.wait_executed("pick", 2).await.unwrap();

    // The successor, speaking the protocol from the test's own session: it asks, is
    // released, and then does nothing more.
    let robot1 = HolonId::resource("robot1").unwrap();
    let request = holon::takeover::Request {
        successor: holon::presence::Holder::this_process(&cell.session),
        version: "0.0.0-never-serves".into(),
        data_dir: Some(std::fs::canonicalize(&data).unwrap()),
        wait_ms: 10_000,
    };
    let taken = holon::takeover::take_over(
        &cell.session,
        &cell.keys.alive(&robot1),
        "resource/robot1",
        &request,
    )
    .await
    .unwrap();
    assert!(
        matches!(taken, holon::takeover::TakenOver::From(ref reply) if reply.released),
        "{taken:?}"
    );
    let status = old.wait_exit(Duration::from_secs(60)).unwrap();
    assert_eq!(status.code(), Some(1), "{status:?}: {}", old.stderr());
    assert!(old.stderr().contains("did not serve"), "{}", old.stderr());

    // Its supervisor starts it again, on its journal: the bookings and the running
    // step's result are there.
    let again_dir = dir.join("again");
    std::fs::create_dir_all(&again_dir).unwrap();
    let mut again = start_node(
        &again_dir,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--data-dir", data_arg],
    )
    .unwrap();
    let states = wait_all_done(&cell, &orders, Duration::from_secs(90)).await;
    assert_none_failed_or_interrupted(&states);
    // Every step ran exactly once.
    assert_eq!(sim.wait_executed("pick", 6).await.unwrap(), 6);
    assert_eq!(sim.wait_executed("place", 6).await.unwrap(), 6);
    again.signal(Signal::SIGTERM).unwrap();
    assert!(again.wait_exit(Duration::from_secs(20)).unwrap().success());
}

/// Runs `cell upgrade ARGS --dir DIR`: its success and its output (stdout, stderr).
async fn cell_upgrade(dir: &Path, args: &[&str]) -> (bool, String) {
    let output = tokio::process::Command::new(bin("cell"))
        .arg("upgrade")
        .args(args)
        .arg("--dir")
        .arg(dir)
        .output()
        .await
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
    (output.status.success(), text)
}

/// A `key=value` number from the last log line of `log` that contains `what`.
fn logged_number(log: &Path, what: &str, key: &str) -> Option<u64> {
    let text = std::fs::read_to_string(log).ok()?;
    let line = text.lines().rev().find(|l| l.contains(what))?;
    let at = line.find(&format!("{key}="))? + key.len() + 1;
    line[at..]
        .chars()
        .take_while(|c| c.is_ascii_digit())
        .collect::<String>()
        .parse()
        .ok()
}

/// How long robot1 started no job because of its hand-over, beyond its running step:
/// from the state that showed it handing over with its running step finished, to the
/// first state of its successor with a job running (from the states it published).
fn resource_gap(states: &[serde_json::Value]) -> Option<u64> {
    let quiet = states
        .iter()
        .position(|s| s["handing_over"] == true && s["current"].is_null())?;
    let quiet_at = states[quiet]["at"].as_u64()?;
    let resumed = states[quiet..]
        .iter()
        .find(|s| s["handing_over"] != true && !s["current"].is_null())?;
    Some(resumed["at"].as_u64()? - quiet_at)
}

/// Fifty orders run while robot1, the order-node and the product are upgraded one after
/// another through `cell up` and `cell upgrade` (new binaries, and a new config for
/// robot1): every order is done, nothing is handed back, rebooked, interrupted or run
/// twice; a config that fails its check leaves the running process alone.
#[tokio::test(flavor = "multi_thread")]
async fn a_cell_keeps_producing_while_each_holon_is_upgraded() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-upgrade").await.unwrap();
    let sim1 = Sim::start(dir, "sim1", "127.0.0.1:0", &["--delay-ms", "250"]).unwrap();
    let sim2 = Sim::start(dir, "sim2", "127.0.0.1:0", &["--delay-ms", "250"]).unwrap();
    let robot1 = resource_config(dir, "robot1", 10_000).unwrap();
    let robot2 = resource_config(dir, "robot2", 10_000).unwrap();
    one_step_product(dir).unwrap();
    std::fs::copy(demo_config("orders1.toml"), dir.join("orders1.toml")).unwrap();
    // The new release: the same build, installed elsewhere.
    let release = dir.join("release-2");
    std::fs::create_dir_all(&release).unwrap();
    for program in ["holon-node", "order-node"] {
        std::fs::copy(bin(program), release.join(program)).unwrap();
    }
    // robot1's new config offers one more service type; a broken one fails its check.
    let mut v2 = std::fs::read_to_string(&robot1).unwrap();
    v2.push_str(
        "\n[services.inspect]\nnominal_duration_ms = 500\nsteps = [{ action = \"inspect\", until = [\"inspect_pass\", \"inspect_fail\"] }]\n",
    );
    std::fs::write(dir.join("robot1-v2.toml"), v2).unwrap();
    std::fs::write(dir.join("broken.toml"), "cell = \"t-upgrade\"\nname = 7\n").unwrap();
    // The product's new plan: its one step done twice (a changed plan).
    let plan = std::fs::read_to_string(dir.join("part.toml")).unwrap();
    let step = &plan[plan.find("[[steps]]").unwrap()..];
    std::fs::write(dir.join("part-v2.toml"), format!("{plan}\n{step}")).unwrap();
    let router = &cell.endpoint;
    let common = format!("\"--cell\", \"t-upgrade\", \"--connect\", \"{router}\"");
    std::fs::write(
        dir.join("cell.toml"),
        format!(
            r#"
cell = "t-upgrade"
[[process]]
name = "robot1"
program = "holon-node"
args = ["--config", "{robot1}", "--controller", "{sim1}", "--data-dir", "data", {common}]
[[process]]
name = "robot2"
program = "holon-node"
args = ["--config", "{robot2}", "--controller", "{sim2}", "--data-dir", "data", {common}]
[[process]]
name = "part"
program = "holon-node"
args = ["--config", "part.toml", {common}]
[[process]]
name = "orders1"
program = "order-node"
args = ["--config", "orders1.toml", "--data-dir", "data", {common}]
"#,
            robot1 = robot1.display(),
            robot2 = robot2.display(),
            sim1 = sim1.address,
            sim2 = sim2.address,
        ),
    )
    .unwrap();
    let mut up = start_cell_up(dir);
    for robot in ["robot1", "robot2"] {
        cell.wait_alive(&HolonId::resource(robot).unwrap())
            .await
            .unwrap();
        cell.wait_state(robot, "free", |s| s["state"] == "free")
            .await
            .unwrap();
    }
    cell.wait_alive(&HolonId::new(schemas::HolonKind::Product, "part").unwrap())
        .await
        .unwrap();
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await
        .unwrap();
    // robot1's states, to measure its gap.
    let states = cell
        .session
        .declare_subscriber(cell.keys.state(&HolonId::resource("robot1").unwrap()))
        .await
        .unwrap();

    let orders = cell.submit("part", 50).await.unwrap();
    assert_eq!(orders.len(), 50);
    sim1.wait_executed("pick", 2).await.unwrap();

    // A config that fails its check: nothing changes.
    let (ok, out) = cell_upgrade(dir, &["robot1", "--config", "broken.toml"]).await;
    assert!(!ok, "{out}");
    assert!(out.contains("does not pass its check"), "{out}");

    let binary = release.join("holon-node");
    let binary = binary.to_str().unwrap();
    let (ok, out) = cell_upgrade(
        dir,
        &["robot1", "--binary", binary, "--config", "robot1-v2.toml"],
    )
    .await;
    assert!(ok, "{out}");
    assert!(out.contains("upgraded robot1"), "{out}");
    cell.wait_state("robot1", "offering its new service type", |s| {
        s["services"]
            .as_array()
            .is_some_and(|t| t.iter().any(|t| t == "inspect"))
    })
    .await
    .unwrap();

    let order_node = release.join("order-node");
    let (ok, out) = cell_upgrade(dir, &["orders1", "--binary", order_node.to_str().unwrap()]).await;
    assert!(ok, "{out}");
    let (ok, out) = cell_upgrade(
        dir,
        &["part", "--binary", binary, "--config", "part-v2.toml"],
    )
    .await;
    assert!(ok, "{out}");
    let states_now = order_states(&cell, &orders).await;
    assert!(
        states_now.iter().any(|s| s["status"] != "done"),
        "the orders were all done before the last upgrade: the test proves nothing"
    );
    // An order submitted now follows the new plan; those before keep theirs.
    let mut orders = orders;
    let late = cell.submit("part", 1).await.unwrap().remove(0);
    orders.push(late);

    let ended = wait_all_done(&cell, &orders, Duration::from_secs(120)).await;
    assert_eq!(
        ended.last().unwrap()["steps"],
        2,
        "{}",
        ended.last().unwrap()
    );
    assert!(ended[..50].iter().all(|s| s["steps"] == 1));
    assert_undisturbed(&ended);
    // Each order's steps ran exactly once, on one of the two robots: 50 of one step,
    // the late one of two.
    let picks = sim1.executed("pick") + sim2.executed("pick");
    let places = sim1.executed("place") + sim2.executed("place");
    assert_eq!((picks, places), (52, 52));
    assert!(sim1.executed("pick") > 2, "robot1 worked after its upgrade");

    // The gaps, for docs/benchmarks.md.
    let mut published = Vec::new();
    while let Ok(Some(sample)) = states.try_recv() {
        if let Ok(state) = serde_json::from_slice(&sample.payload().to_bytes()) {
            published.push(state);
        }
    }
    let logs = dir.join("logs");
    println!(
        "upgrade gaps: robot1 idle beyond its running step {:?} ms (hand-over to successor serving {:?} ms); orders1 {:?} ms; part {:?} ms",
        resource_gap(&published),
        logged_number(&logs.join("robot1.log"), "the successor serves", "gap_ms"),
        logged_number(&logs.join("orders1.log"), "the successor serves", "gap_ms"),
        logged_number(&logs.join("part.log"), "the successor serves", "gap_ms"),
    );
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(up.id() as i32), Signal::SIGTERM).unwrap();
    assert!(up.wait().unwrap().success());
}

/// `cell upgrade` with a successor that takes robot1 over and then hangs (a fixture that
/// ignores SIGTERM): robot1 stands in for its limit and exits 1; `cell up` stops the
/// successor (SIGTERM, then SIGKILL), starts robot1 again from its previous command line
/// on its journal, and `cell upgrade` fails saying so. Every order is done, each step ran
/// once.
#[tokio::test(flavor = "multi_thread")]
async fn a_successor_that_never_serves_is_killed_and_the_process_started_again() {
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = Cell::open("t-upgrade-rollback").await.unwrap();
    let sim = Sim::start(dir, "sim1", "127.0.0.1:0", &["--delay-ms", "100"]).unwrap();
    let robot1 = resource_config(dir, "robot1", 10_000).unwrap();
    let router = &cell.endpoint;
    std::fs::write(
        dir.join("cell.toml"),
        format!(
            r#"
cell = "t-upgrade-rollback"
[restart]
stop_timeout_ms = 2000
[[process]]
name = "robot1"
program = "holon-node"
args = ["--config", "{robot1}", "--controller", "{sim}", "--data-dir", "data", "--cell", "t-upgrade-rollback", "--connect", "{router}"]
"#,
            robot1 = robot1.display(),
            sim = sim.address,
        ),
    )
    .unwrap();
    let mut up = start_cell_up(dir);
    let robot = HolonId::resource("robot1").unwrap();
    cell.wait_alive(&robot).await.unwrap();
    let _part_and_orders = cell
        .start_part_and_orders(dir, &demo_config("orders1.toml"), &dir.join("orders-data"))
        .await
        .unwrap();
    let orders = cell.submit("part", 6).await.unwrap();
    sim.wait_executed("pick", 2).await.unwrap();

    // The broken release: a holon-node that hangs once it has been handed over to.
    let release = dir.join("release-broken");
    std::fs::create_dir_all(&release).unwrap();
    let successor = release.join("holon-node");
    std::fs::copy(env!("CARGO_BIN_EXE_never-serving-successor"), &successor).unwrap();
    let (ok, out) = cell_upgrade(dir, &["robot1", "--binary", successor.to_str().unwrap()]).await;
    assert!(!ok, "{out}");
    assert!(out.contains("did not serve"), "{out}");
    assert!(
        out.contains("started again from its previous binary"),
        "{out}"
    );

    // robot1 runs again, from holon-node, and finishes every order.
    cell.wait_alive(&robot).await.unwrap();
    let states = wait_all_done(&cell, &orders, Duration::from_secs(90)).await;
    assert_none_failed_or_interrupted(&states);
    assert_eq!(sim.wait_executed("pick", 6).await.unwrap(), 6);
    assert_eq!(sim.wait_executed("place", 6).await.unwrap(), 6);

    // The successor ignored SIGTERM and was killed (the stop timeout after the
    // predecessor's exit).
    let deadline = std::time::Instant::now() + WAIT;
    let said = loop {
        let said = std::fs::read_to_string(dir.join("cell-up.out")).unwrap();
        if said.contains("stopped the successor of robot1") || std::time::Instant::now() > deadline
        {
            break said;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    };
    assert!(
        said.contains("the successor of robot1 did not stop within")
            && said.contains("stopped the successor of robot1 (signal: 9"),
        "{said}"
    );
    let successor_log = std::fs::read_to_string(dir.join("logs/robot1.log")).unwrap();
    assert!(successor_log.contains("SIGTERM ignored"), "{successor_log}");
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(up.id() as i32), Signal::SIGTERM).unwrap();
    assert!(up.wait().unwrap().success());
}

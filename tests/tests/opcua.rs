//! `cell opcua` with a foreign client (Python asyncua 2.1, tests/opcua/driver.py), on
//! real processes: a plain cell where an anonymous client browses, subscribes, commands
//! the resources through every PackML method and submits work orders while the orders
//! run; and a secure cell (`cell certs`, `cell up`) where only a trusted client
//! application with an operator's or an admin's password may command (its users made
//! with `cell users`, which has a test of its own). The Python comes from
//! `HOLARCHY_OPCUA_PYTHON` (default target/opcua-venv/bin/python, docs/opcua.md); without
//! it the Python tests print SKIPPED, unless HOLARCHY_REQUIRE_OPCUA=1.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use holarchy_tests::opcua::Driver;
use holarchy_tests::secure_cell::{add_user, Up};
use holarchy_tests::*;
use serde_json::Value;

async fn wait_busy(cell: &Cell, resource: &str) {
    cell.wait_state(resource, "busy", |s| s["state"] == "busy")
        .await
        .unwrap();
}

async fn wait_done(cell: &Cell, orders: &[String]) {
    for order in orders {
        cell.wait_order(order, "done", |s| s.is_some_and(|s| s["status"] == "done"))
            .await
            .unwrap();
    }
}

fn orders_of(answer: &Value, n: usize) -> Vec<String> {
    assert_eq!(answer["status"], "Good", "{answer}");
    let orders: Vec<String> = serde_json::from_value(answer["orders"].clone()).unwrap();
    assert_eq!(orders.len(), n, "{answer}");
    orders
}

/// Starts `cell opcua` on the test's cell (plain) and waits until it listens.
async fn start_server(dir: &Path, cell: &Cell) -> (Process, String) {
    let address = format!("127.0.0.1:{}", free_port());
    let server = start_program(
        dir,
        "cell",
        "opcua",
        &[
            "opcua",
            "--cell",
            cell.keys.cell(),
            "--connect",
            &cell.endpoint,
            "--listen",
            &address,
        ],
    )
    .unwrap();
    wait_listening(&address).await.unwrap();
    (server, format!("opc.tcp://{address}/"))
}

/// A plain cell, two robots, an order-node; an anonymous asyncua client does what an
/// operator's SCADA would.
#[tokio::test(flavor = "multi_thread")]
async fn a_foreign_client_watches_and_commands_the_cell_over_opcua() {
    let Some(python) = opcua_python() else { return };
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-opcua").await.unwrap();
    let robot1 = cell
        .resource(dir.path(), "robot1")
        .sim_flags(&["--delay-ms", "300"])
        // A held robot hands its bookings back after 1 s (30 s by default).
        .config("\n[packml]\nheld_bookings_ms = 1000\n")
        .start()
        .await
        .unwrap();
    let _robot2 = cell
        .resource(dir.path(), "robot2")
        .sim_flags(&["--delay-ms", "300"])
        .start()
        .await
        .unwrap();
    let (_product, _orders) = cell
        .start_part_and_orders(
            dir.path(),
            &demo_config("orders1.toml"),
            &dir.path().join("orders-data"),
        )
        .await
        .unwrap();
    let (server, url) = start_server(dir.path(), &cell).await;
    let (mut ua, connected) = Driver::start(&python, &url, "t-opcua", &[]).await;
    assert_eq!(connected["connected"], true, "{connected}");

    let resources = ua.resources().await;
    assert!(
        resources.contains(&"robot1".to_string()) && resources.contains(&"robot2".to_string()),
        "{resources:?}"
    );
    ua.wait_read("robot1 Status.StateCurrent", 6.into()).await;
    assert_eq!(
        ua.call("subscribe robot1 Status.StateCurrent").await,
        "Good"
    );

    // Hold while robot1 runs a step: Held once the step completes; the orders go on
    // on robot2, none is lost or failed.
    let first = orders_of(&ua.ask("submit part 4 0").await, 4);
    wait_busy(&cell, "robot1").await;
    assert_eq!(ua.call("call robot1 Hold").await, "Good");
    cell.wait_packml("robot1", 11).await.unwrap();
    ua.wait_read("robot1 Status.StateCurrent", 11.into()).await;
    ua.wait_read("robot1 Admin.StopReason.ID", 4.into()).await;
    let picks_held = robot1.sim.executed("pick");
    let second = orders_of(&ua.ask("submit part 3 0").await, 3);
    wait_done(&cell, &first).await;
    wait_done(&cell, &second).await;
    assert_eq!(
        robot1.sim.executed("pick"),
        picks_held,
        "a held robot starts no new step"
    );
    for order in first.iter().chain(&second) {
        let state = cell.order_state(order).await.unwrap();
        assert_eq!(
            state["failed_attempts"], 0,
            "the step running at the Hold completed: {state}"
        );
    }
    let changes = ua.ask("changes").await;
    let seen: Vec<i64> = serde_json::from_value(changes["values"].clone()).unwrap();
    assert!(seen.contains(&11), "the subscription saw Held: {changes}");
    let mut latency: Vec<f64> = serde_json::from_value(changes["latency_ms"].clone()).unwrap();
    latency.sort_by(f64::total_cmp);
    eprintln!("subscription latency (ms, sorted): {latency:?}");
    assert_eq!(ua.call("call robot1 Unhold").await, "Good");
    cell.wait_packml("robot1", 6).await.unwrap();
    ua.wait_read("robot1 Status.StateCurrent", 6.into()).await;

    // Abort mid-step: Aborted, the controller told, the step failed and rebooked.
    let third = orders_of(&ua.ask("submit part 4 0").await, 4);
    wait_busy(&cell, "robot1").await;
    assert_eq!(ua.call("call robot1 Abort").await, "Good");
    cell.wait_packml("robot1", 9).await.unwrap();
    ua.wait_read("robot1 Status.StateCurrent", 9.into()).await;
    wait_done(&cell, &third).await;
    assert!(
        robot1.sim.counts()["aborted"].as_u64().unwrap_or(0) >= 1,
        "the simulator saw the abort: {}",
        robot1.sim.counts()
    );
    let mut failed_attempts = 0;
    for order in &third {
        let state = cell.order_state(order).await.unwrap();
        failed_attempts += state["failed_attempts"].as_u64().unwrap_or(0);
    }
    assert!(
        failed_attempts >= 1,
        "the aborted step failed and was rebooked"
    );
    // Suspend is the resource's own state: not supported as a command.
    assert_eq!(ua.call("call robot1 Suspend").await, "BadNotSupported");
    assert_eq!(ua.call("call robot1 Clear").await, "Good");
    cell.wait_packml("robot1", 2).await.unwrap();

    // Modes: an unknown one is a bad argument; a change outside Stopped/Idle/Aborted
    // is refused by the state.
    assert_eq!(
        ua.call("call robot1 SetUnitMode 99").await,
        "BadInvalidArgument"
    );
    assert_eq!(ua.call("call robot1 Reset").await, "Good");
    cell.wait_packml("robot1", 4).await.unwrap();
    assert_eq!(ua.call("call robot1 Start").await, "Good");
    cell.wait_packml("robot1", 6).await.unwrap();
    assert_eq!(
        ua.call("call robot1 SetUnitMode 2").await,
        "BadInvalidState"
    );
    assert_eq!(ua.call("call robot1 Unhold").await, "BadInvalidState");

    // Stop with bookings: handed back, rebooked, all done.
    let fourth = orders_of(&ua.ask("submit part 4 0").await, 4);
    wait_busy(&cell, "robot1").await;
    assert_eq!(ua.call("call robot1 Stop").await, "Good");
    cell.wait_packml("robot1", 2).await.unwrap();
    wait_done(&cell, &fourth).await;
    ua.wait_read("robot1 Status.StateCurrent", 2.into()).await;

    // Bad work orders.
    assert_eq!(
        ua.ask("submit part 0 0").await["status"],
        "BadInvalidArgument"
    );
    assert_eq!(
        ua.ask("submit nothing-such 1 0").await["status"],
        "BadInvalidArgument"
    );
    assert_eq!(
        ua.ask("submit part 1 0 Not-A-Name").await["status"],
        "BadInvalidArgument"
    );
    // A named work order called again (an MES that retries after BadTimeout): the
    // orders made the first time, none made.
    let named = orders_of(&ua.ask("submit part 2 0 mes-77").await, 2);
    assert_eq!(orders_of(&ua.ask("submit part 2 0 mes-77").await, 2), named);
    wait_done(&cell, &named).await;
    // The figures are the order-nodes' counts, asked every second: read until they
    // caught up.
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let done = ua.ask("readcell OrdersDone").await["value"]
            .as_i64()
            .unwrap();
        if done >= 17 {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "OrdersDone {done}, never 17"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    assert_eq!(ua.ask("readcell OrdersFailed").await["value"], 0);

    // A resource hot-added appears while the client stays connected, and goes when
    // it leaves.
    let robot3 = cell
        .resource(dir.path(), "robot3")
        .sim_flags(&["--delay-ms", "100"])
        .start()
        .await
        .unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while !ua.resources().await.contains(&"robot3".to_string()) {
        assert!(
            tokio::time::Instant::now() < deadline,
            "robot3 never appeared"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    ua.wait_read("robot3 Status.StateCurrent", 6.into()).await;
    drop(robot3);
    let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
    while ua.resources().await.contains(&"robot3".to_string()) {
        assert!(tokio::time::Instant::now() < deadline, "robot3 never went");
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    ua.wait_read("robot2 Status.StateCurrent", 6.into()).await;

    // The subscription saw every state robot1 stayed in, in order, promptly (a state
    // left within one publishing interval, such as Idle between Reset and Start or
    // Stopped between Clear and Reset here, may be coalesced: the queue size is 1):
    // the server ticks every 10 ms and grants the driver's 20 ms publishing interval
    // (with async-opcua's defaults, 100 ms, the median is about 200 ms).
    let changes = ua.ask("changes").await;
    let seen: Vec<i64> = serde_json::from_value(changes["values"].clone()).unwrap();
    let stayed = [11, 6, 9, 6, 7, 2];
    let mut rest = seen.iter();
    for state in stayed {
        assert!(
            rest.any(|s| *s == state),
            "the subscription saw {stayed:?} in order: {seen:?}; the server:\n{}",
            server.stderr()
        );
    }
    let mut latency: Vec<f64> = serde_json::from_value(changes["latency_ms"].clone()).unwrap();
    latency.sort_by(f64::total_cmp);
    eprintln!("subscription latency over the run (ms, sorted): {latency:?}");
    assert!(latency.len() >= 5, "{changes}");
    let median = latency[latency.len() / 2];
    assert!(median < 150.0, "median latency {median} ms: {latency:?}");
    ua.quit().await;
    drop(server);
}

/// Refused setups: no security off loopback, a secure cell without its certificate.
#[test]
fn cell_opcua_refuses_an_insecure_or_broken_setup() {
    let open = Command::new(bin("cell"))
        .args([
            "opcua",
            "--connect",
            "tcp/127.0.0.1:1",
            "--listen",
            "0.0.0.0:0",
        ])
        .output()
        .unwrap();
    assert!(!open.status.success());
    let said = String::from_utf8_lossy(&open.stderr);
    assert!(
        said.contains("refusing to serve OPC UA without security"),
        "{said}"
    );
    let empty = tempfile::tempdir().unwrap();
    let broken = Command::new(bin("cell"))
        .args(["opcua", "--connect", "tls/127.0.0.1:1", "--pki"])
        .arg(empty.path())
        .output()
        .unwrap();
    assert!(!broken.status.success());
    let said = String::from_utf8_lossy(&broken.stderr);
    assert!(said.contains("OPC UA server certificate"), "{said}");
}

/// Runs `cell users --pki PKI ARGS` with `stdin` piped in: whether it succeeded, its
/// stdout and its stderr.
fn cell_users(pki: &Path, args: &[&str], stdin: &str) -> (bool, String, String) {
    let mut child = Command::new(bin("cell"))
        .args(["users", "--pki"])
        .arg(pki)
        .args(args)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    use std::io::Write;
    let _ = child.stdin.take().unwrap().write_all(stdin.as_bytes());
    let out = child.wait_with_output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `cell users`: every change lands in the file and in the audit trail; refusals say
/// why and change nothing; no password or hash is ever printed or recorded.
#[test]
fn cell_users_changes_the_users_file_and_records_each_change() {
    let dir = tempfile::tempdir().unwrap();
    let pki = dir.path();
    let ok = |args: &[&str], stdin: &str| {
        let (ok, out, err) = cell_users(pki, args, stdin);
        assert!(ok, "cell users {args:?}: {err}");
        out
    };
    let refused = |args: &[&str], stdin: &str| {
        let (ok, out, err) = cell_users(pki, args, stdin);
        assert!(!ok, "cell users {args:?} succeeded: {out}");
        err
    };
    ok(&["add", "root", "--role", "admin"], "root-password\n");
    ok(&["add", "anna", "--role", "operator"], "anna-password\n");
    assert!(
        refused(&["add", "anna", "--role", "observer"], "whatever1\n")
            .contains("already a user anna")
    );
    assert!(refused(&["add", "bert", "--role", "operator"], "short\n")
        .contains("at least 8 characters"));
    assert!(
        refused(&["add", "b rt", "--role", "operator"], "long-enough\n").contains("bad user name")
    );
    assert!(refused(&["add", "bert", "--role", "boss"], "long-enough\n")
        .contains("observer, operator or admin"));
    assert!(refused(&["remove", "root"], "").contains("add another admin first"));
    assert!(refused(&["role", "root", "operator"], "").contains("add another admin first"));
    assert!(refused(&["passwd", "nobody"], "long-enough\n").contains("no user nobody"));
    ok(&["passwd", "anna"], "new-anna-password\n");
    ok(&["role", "anna", "admin"], "");
    ok(&["role", "root", "observer"], "");
    ok(&["remove", "root"], "");
    let list = ok(&["list"], "");
    assert_eq!(list.lines().collect::<Vec<_>>(), ["anna  admin"], "{list}");
    let users = std::fs::read_to_string(pki.join("users.toml")).unwrap();
    assert!(
        !users.contains("anna-password") && !users.contains("root-password"),
        "{users}"
    );
    let audit = std::fs::read_to_string(pki.join("audit.jsonl")).unwrap();
    let records: Vec<Value> = audit
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let seen: Vec<(String, String, String)> = records
        .iter()
        .map(|r| {
            (
                r["action"].as_str().unwrap().to_string(),
                r["target"].as_str().unwrap_or_default().to_string(),
                r["outcome"].as_str().unwrap().to_string(),
            )
        })
        .collect();
    let done =
        |action: &str, target: &str| (action.to_string(), target.to_string(), "done".to_string());
    let no = |action: &str, target: &str| {
        (
            action.to_string(),
            target.to_string(),
            "refused".to_string(),
        )
    };
    assert_eq!(
        seen,
        [
            done("user_add", "root"),
            done("user_add", "anna"),
            no("user_add", "anna"),
            no("user_add", "bert"),
            no("user_add", "b rt"),
            no("user_remove", "root"),
            no("user_role", "root"),
            no("user_password", "nobody"),
            done("user_password", "anna"),
            done("user_role", "anna"),
            done("user_role", "root"),
            done("user_remove", "root"),
        ],
        "{audit}"
    );
    assert!(records
        .iter()
        .all(|r| r["who"].as_str().unwrap().starts_with("cli:")
            && r["from"].as_str().unwrap().starts_with("cell users on ")));
    assert!(
        !audit.contains("-password") && !audit.contains("argon2"),
        "{audit}"
    );
    // A users file others may read is refused, naming the fix.
    std::fs::set_permissions(
        pki.join("users.toml"),
        std::os::unix::fs::PermissionsExt::from_mode(0o640),
    )
    .unwrap();
    assert!(refused(&["list"], "").contains("chmod 600"));
    assert!(refused(&["add", "bert", "--role", "operator"], "long-enough\n").contains("chmod 600"));
}

/// A secure cell as docs/opcua.md sets one up: `cell certs` issues the server's
/// certificate, `cell users` makes an operator, an observer and an admin, `cell up`; the
/// client's application certificate is trusted with `cell opcua --trust`.
#[tokio::test(flavor = "multi_thread")]
async fn in_a_secure_cell_only_a_trusted_operator_commands() {
    let Some(python) = opcua_python() else { return };
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let cell = "t-opcua-sec";
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let sim_port = free_port();
    let address = format!("127.0.0.1:{}", free_port());
    let robot_config = workspace_root().join("deploy/cells/demo/robot1.toml");
    let manifest = format!(
        r#"cell = "{cell}"
[router]
listen = ["{endpoint}"]
[restart]
backoff_initial_ms = 100
stop_timeout_ms = 10000
[[process]]
name = "robot1-sim"
program = "robot-sim"
args = ["--listen", "127.0.0.1:{sim_port}", "--delay-ms", "20"]
[[process]]
name = "robot1"
identity = "resource.robot1"
program = "holon-node"
args = ["--config", "{}", "--cell", "{cell}", "--name", "robot1", "--controller", "127.0.0.1:{sim_port}", "--connect", "{endpoint}", "--pki", "pki", "--data-dir", "data"]
[[process]]
name = "opcua"
identity = "operator.opcua"
program = "cell"
args = ["opcua", "--cell", "{cell}", "--connect", "{endpoint}", "--pki", "pki", "--listen", "{address}"]
"#,
        robot_config.display()
    );
    std::fs::write(dir.join("cell.toml"), manifest).unwrap();
    let certs = Command::new(bin("cell"))
        .arg("certs")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        certs.status.success(),
        "{}",
        String::from_utf8_lossy(&certs.stderr)
    );
    let pki = dir.join("pki");
    for file in ["opcua-server.der", "opcua-server.key", "operator.opcua.pem"] {
        assert!(pki.join(file).exists(), "cell certs issued {file}");
    }
    // A PKI directory with only the old OPC UA users file: refused, saying where the
    // users live now.
    std::fs::write(pki.join("opcua-users.toml"), "").unwrap();
    let old = Command::new(bin("cell"))
        .args(["opcua", "--cell", cell, "--connect", &endpoint, "--pki"])
        .arg(&pki)
        .args(["--listen", &address])
        .output()
        .unwrap();
    assert!(!old.status.success());
    let said = String::from_utf8_lossy(&old.stderr);
    assert!(
        said.contains("users.toml") && said.contains("cell users --pki"),
        "{said}"
    );
    std::fs::remove_file(pki.join("opcua-users.toml")).unwrap();
    add_user(&pki, "anna", "operator", "anna-password");
    add_user(&pki, "wall", "observer", "wall-password");
    add_user(&pki, "root", "admin", "root-password");
    // Its owner's alone (others' read access would stop the server), every change in
    // the audit trail beside it, no password or hash in there.
    let mode = |file: &str| {
        std::os::unix::fs::PermissionsExt::mode(
            &std::fs::metadata(pki.join(file)).unwrap().permissions(),
        ) & 0o777
    };
    assert_eq!(mode("users.toml"), 0o600);
    assert_eq!(mode("audit.jsonl"), 0o600);
    let audit = std::fs::read_to_string(pki.join("audit.jsonl")).unwrap();
    assert_eq!(
        audit.matches(r#""action":"user_add""#).count(),
        3,
        "{audit}"
    );
    assert!(
        !audit.contains("password") && !audit.contains("argon2"),
        "{audit}"
    );
    let _up = Up::spawn(
        Command::new(bin("cell"))
            .arg("up")
            .arg(dir)
            .stdout(std::fs::File::create(dir.join("up.log")).unwrap())
            .stderr(std::fs::File::create(dir.join("up.stderr.log")).unwrap()),
    );
    if let Err(e) = wait_listening(&address).await {
        let log = std::fs::read_to_string(dir.join("logs/opcua.log")).unwrap_or_default();
        panic!("{e}; logs/opcua.log:\n{log}");
    }
    let url = format!("opc.tcp://{address}/");
    let client_dir = dir.join("client");
    let client_dir_s = client_dir.to_str().unwrap();
    let secure = ["--secure", client_dir_s];
    let as_user = |user: &'static str, password: &'static str| {
        let mut args = secure.to_vec();
        args.extend(["--user", user, "--password", password]);
        args
    };

    // An unknown client application is rejected, and lands in rejected/.
    let (_, first) = Driver::start(&python, &url, cell, &as_user("anna", "anna-password")).await;
    assert_eq!(first["connected"], false, "{first}");
    assert_eq!(first["status"], "BadCertificateUntrusted", "{first}");
    let rejected: Vec<PathBuf> = std::fs::read_dir(pki.join("opcua/rejected"))
        .map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).collect())
        .unwrap_or_default();
    assert_eq!(rejected.len(), 1, "{first}: rejected/ {rejected:?}");
    let trust = Command::new(bin("cell"))
        .args(["opcua", "--pki"])
        .arg(&pki)
        .arg("--trust")
        .arg(client_dir.join("client.der"))
        .output()
        .unwrap();
    assert!(
        trust.status.success(),
        "{}",
        String::from_utf8_lossy(&trust.stderr)
    );

    // Anonymous and a wrong password are refused.
    let (_, anonymous) = Driver::start(&python, &url, cell, &secure).await;
    assert_eq!(anonymous["connected"], false, "{anonymous}");
    assert!(
        anonymous["status"]
            .as_str()
            .is_some_and(|s| s.starts_with("BadIdentityToken")),
        "{anonymous}"
    );
    for (user, password) in [
        ("anna", "wall-password"),
        ("root", "anna-password"),
        ("nobody", "anna-password"),
    ] {
        let (_, wrong) = Driver::start(&python, &url, cell, &as_user(user, password)).await;
        assert_eq!(wrong["connected"], false, "{user}: {wrong}");
        assert_eq!(wrong["status"], "BadUserAccessDenied", "{user}: {wrong}");
    }

    // The operator holds robot1; the observer sees it but may not command.
    let (mut anna, connected) =
        Driver::start(&python, &url, cell, &as_user("anna", "anna-password")).await;
    assert_eq!(connected["connected"], true, "{connected}");
    anna.wait_read("robot1 Status.StateCurrent", 6.into()).await;
    assert_eq!(anna.call("call robot1 Hold").await, "Good");
    anna.wait_read("robot1 Status.StateCurrent", 11.into())
        .await;
    anna.wait_read(
        "robot1 Admin.StopReason.Message",
        "Hold by opcua:anna".into(),
    )
    .await;
    let (mut wall, connected) =
        Driver::start(&python, &url, cell, &as_user("wall", "wall-password")).await;
    assert_eq!(connected["connected"], true, "{connected}");
    wall.wait_read("robot1 Status.StateCurrent", 11.into())
        .await;
    assert_eq!(wall.call("call robot1 Unhold").await, "BadUserAccessDenied");
    assert_eq!(
        wall.ask("submit breaker 1 0").await["status"],
        "BadUserAccessDenied"
    );
    tokio::time::sleep(Duration::from_millis(300)).await;
    wall.wait_read("robot1 Status.StateCurrent", 11.into())
        .await;
    assert_eq!(anna.call("call robot1 Unhold").await, "Good");
    wall.wait_read("robot1 Status.StateCurrent", 6.into()).await;

    // An admin operates too.
    let (mut root, connected) =
        Driver::start(&python, &url, cell, &as_user("root", "root-password")).await;
    assert_eq!(connected["connected"], true, "{connected}");
    assert_eq!(root.call("call robot1 Hold").await, "Good");
    wall.wait_read("robot1 Status.StateCurrent", 11.into())
        .await;
    root.wait_read(
        "robot1 Admin.StopReason.Message",
        "Hold by opcua:root".into(),
    )
    .await;
    assert_eq!(root.call("call robot1 Unhold").await, "Good");
    wall.wait_read("robot1 Status.StateCurrent", 6.into()).await;
    root.quit().await;
    wall.quit().await;
    anna.quit().await;
}

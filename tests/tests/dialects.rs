//! A real resource holon drives robot-sim in every shipped dialect, chosen by one line
//! of config: a job is done with each step run once, a controller that answers garbage
//! fails the step with a clear reason and the holon serves the next job, an e-stopped
//! controller is sent nothing until it is ready again; and a dialect
//! file that is wrong, or cannot send one of the holon's actions, stops the holon at
//! `--check`, naming the field.

use std::path::{Path, PathBuf};
use std::process::Command;

use holarchy_tests::*;
use schemas::{MessageType, Service};

const DIALECTS: &[&str] = &["holarchy-xml", "kuka-eki", "ur-dashboard", "simple-message"];

/// The test resource config with `dialect = ...` in its controller section.
fn config_with_dialect(dir: &Path, name: &str, dialect: &str) -> PathBuf {
    let path = resource_config(dir, name, 2000).unwrap();
    let text = std::fs::read_to_string(&path).unwrap().replace(
        "[controller]\n",
        &format!("[controller]\ndialect = \"{dialect}\"\n"),
    );
    std::fs::write(&path, text).unwrap();
    path
}

struct Robot {
    cell: Cell,
    resource: Resource,
    _dir: tempfile::TempDir,
}

async fn robot(cell: &str, dialect: &str, sim_flags: &[&str]) -> Robot {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open(cell).await.unwrap();
    let resource = cell
        .resource(dir.path(), "robot1")
        .dialect(dialect)
        .sim_flags(sim_flags)
        .command_timeout_ms(2000)
        .start()
        .await
        .unwrap();
    Robot {
        cell,
        resource,
        _dir: dir,
    }
}

impl Robot {
    async fn job(&self, inbox: &mut Inbox, conversation: &str) -> Service {
        self.cell
            .job("robot1", inbox, "o-1", conversation)
            .await
            .unwrap()
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_holon_drives_every_shipped_dialect() {
    for (i, dialect) in DIALECTS.iter().enumerate() {
        let r = robot(&format!("t-dialect-{i}"), dialect, &[]).await;
        let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
        let result = r.job(&mut inbox, "c1").await;
        assert_eq!(
            result.message_type,
            MessageType::Done,
            "{dialect}: {result:?}"
        );
        assert_eq!(result.info["results"]["pick"], "picking_done", "{dialect}");
        assert_eq!(result.info["results"]["place"], "placing_done", "{dialect}");
        assert_eq!(r.resource.sim.executed("pick"), 1, "{dialect}");
        assert_eq!(r.resource.sim.executed("place"), 1, "{dialect}");
        let state = r.cell.status("robot1").await.unwrap();
        assert_eq!(state["controller"], "ready", "{dialect}: {state}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn garbage_in_any_dialect_fails_the_step_and_the_holon_serves_on() {
    for (i, dialect) in DIALECTS.iter().enumerate() {
        // The first command (job 1's pick) is answered with garbage.
        let r = robot(
            &format!("t-dialect-g{i}"),
            dialect,
            &["--garbage-after", "0"],
        )
        .await;
        let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
        let result = r.job(&mut inbox, "c1").await;
        assert_eq!(
            result.message_type,
            MessageType::Failed,
            "{dialect}: {result:?}"
        );
        assert_eq!(
            result.reason.as_ref().map(|r| r.as_str()),
            Some("controller_protocol_error"),
            "{dialect}: {result:?}"
        );
        // The holon drops a connection that spoke garbage and connects again.
        r.cell.wait_serving("robot1").await.unwrap();
        let result = r.job(&mut inbox, "c2").await;
        assert_eq!(
            result.message_type,
            MessageType::Done,
            "{dialect}: {result:?}"
        );
        assert_eq!(r.resource.sim.executed("pick"), 1, "{dialect}");
        assert_eq!(r.resource.sim.executed("place"), 1, "{dialect}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn no_command_reaches_an_e_stopped_controller_in_any_dialect() {
    for (i, dialect) in DIALECTS.iter().enumerate() {
        // The first command e-stops the robot for 1.5 s; robot-sim refuses (and counts)
        // any command of the sequence that reaches it meanwhile.
        let r = robot(
            &format!("t-dialect-e{i}"),
            dialect,
            &[
                "--fault-after",
                "0",
                "--fault-state",
                "estop",
                "--fault-for-ms",
                "1500",
            ],
        )
        .await;
        let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
        let result = r.job(&mut inbox, "c1").await;
        assert_eq!(
            result.message_type,
            MessageType::Failed,
            "{dialect}: {result:?}"
        );
        // At once the next job: a polled dialect's holon has not read the e-stop yet
        // (it asks before the step's first message); a pushed one knows and refuses it.
        match r.cell.job("robot1", &mut inbox, "o-1", "c2").await {
            Ok(result) => {
                assert_eq!(
                    result.reason.as_ref().map(|r| r.as_str()),
                    Some("controller_fault"),
                    "{dialect}: {result:?}"
                );
                assert!(
                    result.info["detail"]
                        .as_str()
                        .unwrap_or("")
                        .contains("estop"),
                    "{dialect}: {result:?}"
                );
            }
            Err(refused) => assert!(refused.to_string().contains("refused"), "{refused}"),
        }
        // PackML Aborted by the e-stop; ready again and started by an operator, it works.
        r.cell
            .wait_state("robot1", "aborted, controller ready", |s| {
                s["packml"]["state"] == "aborted" && s["controller"] == "ready"
            })
            .await
            .unwrap();
        for command in ["clear", "reset", "start"] {
            r.cell.packml("robot1", command).await.unwrap();
        }
        r.cell.wait_serving("robot1").await.unwrap();
        let result = r.job(&mut inbox, "c3").await;
        assert_eq!(
            result.message_type,
            MessageType::Done,
            "{dialect}: {result:?}"
        );
        let counts = r.resource.sim.counts();
        assert_eq!(counts["refused_while_stopped"], 0, "{dialect}: {counts}");
        assert_eq!(r.resource.sim.executed("pick"), 1, "{dialect}: {counts}");
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn the_controllers_own_words_reach_the_order_the_stop_reason_and_the_log() {
    // The worked case of docs/dialects.md 7.7: STATE ERROR <text> polled. The first job
    // faults the robot, which leaves it unanswered and says why in its state.
    let example = workspace_root().join("deploy/dialects/examples/job-ack-end.toml");
    let r = robot(
        "t-dialect-words",
        example.to_str().unwrap(),
        &["--fault-after", "0", "--fault-for-ms", "1500"],
    )
    .await;
    let words = "simulated fault (--fault-after)";
    let mut inbox = r.cell.inbox("o-1", 0).await.unwrap();
    let result = r.job(&mut inbox, "c1").await;
    assert_eq!(
        result.reason.as_ref().map(|r| r.as_str()),
        Some("controller_fault"),
        "{result:?}"
    );
    assert_eq!(
        result.info["detail"],
        format!("the controller reported fault: {words}"),
        "{result:?}"
    );
    let state = r
        .cell
        .wait_state("robot1", "aborted", |s| s["packml"]["state"] == "aborted")
        .await
        .unwrap();
    let reason = &state["packml"]["stop_reason"];
    assert_eq!(reason["id"], 100, "{state}");
    assert_eq!(
        reason["message"],
        format!("the controller reported fault: {words}"),
        "{state}"
    );
    let log = r.resource.node.stderr();
    assert!(
        log.contains("controller_said") && log.contains(words),
        "the holon's log: {log}"
    );
    // Ready again, cleared, reset and started: it works.
    r.cell
        .wait_state("robot1", "controller ready", |s| s["controller"] == "ready")
        .await
        .unwrap();
    for command in ["clear", "reset", "start"] {
        r.cell.packml("robot1", command).await.unwrap();
    }
    r.cell.wait_serving("robot1").await.unwrap();
    let result = r.job(&mut inbox, "c2").await;
    assert_eq!(result.message_type, MessageType::Done, "{result:?}");
    assert_eq!(r.resource.sim.counts()["refused_while_stopped"], 0);
}

fn check(config: &Path) -> (bool, String) {
    let out = Command::new(bin("holon-node"))
        .arg("--config")
        .arg(config)
        .args(["--connect", "tcp/127.0.0.1:1", "--check"])
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[test]
fn check_names_what_is_wrong_with_a_dialect() {
    let dir = tempfile::tempdir().unwrap();
    // A shipped dialect, and a dialect file beside the config.
    let (ok, text) = check(&config_with_dialect(dir.path(), "r1", "ur-dashboard"));
    assert!(ok, "{text}");
    let file = dir.path().join("mine.toml");
    std::fs::copy(
        workspace_root().join("deploy/dialects/kuka-eki.toml"),
        &file,
    )
    .unwrap();
    let (ok, text) = check(&config_with_dialect(dir.path(), "r2", "mine.toml"));
    assert!(ok, "{text}");
    // A template with a placeholder that does not exist.
    let broken = std::fs::read_to_string(&file).unwrap().replace(
        "Task=\"{action:eki_task}\">{?program}",
        "Task=\"{acton:eki_task}\">{?program}",
    );
    std::fs::write(&file, broken).unwrap();
    let (ok, text) = check(&config_with_dialect(dir.path(), "r3", "mine.toml"));
    assert!(!ok, "{text}");
    assert!(
        text.contains("controller.dialect")
            && text.contains("command[0] (command): {acton} is not a value here"),
        "{text}"
    );
    // An action the dialect's tables do not name is found at start, not at the first job.
    let path = config_with_dialect(dir.path(), "r4", "kuka-eki");
    let text = std::fs::read_to_string(&path)
        .unwrap()
        .replace("action = \"place\"", "action = \"weld\"")
        .replace("until = [\"placing_done\"]", "until = [\"welded\"]");
    std::fs::write(&path, text).unwrap();
    let (ok, text) = check(&path);
    assert!(!ok, "{text}");
    assert!(
        text.contains("the action \"weld\" cannot be sent in the dialect kuka-eki")
            && text.contains("[enums.eki_task]"),
        "{text}"
    );
    // No such dialect.
    let (ok, text) = check(&config_with_dialect(dir.path(), "r5", "fanuc"));
    assert!(
        !ok && text.contains("no shipped dialect is called \"fanuc\""),
        "{text}"
    );
}

#[test]
fn robot_sim_checks_a_dialect_file() {
    for dialect in DIALECTS {
        let out = Command::new(bin("robot-sim"))
            .args(["--dialect", dialect, "--check"])
            .output()
            .unwrap();
        assert!(out.status.success(), "{dialect}");
        assert_eq!(
            String::from_utf8_lossy(&out.stdout).trim(),
            format!("dialect {dialect} is valid")
        );
    }
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("bad.toml");
    std::fs::write(&file, "name = \"x\"\ncorrelation = \"id\"\n").unwrap();
    let out = Command::new(bin("robot-sim"))
        .arg("--dialect")
        .arg(&file)
        .arg("--check")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.toml: not a dialect file") && err.contains("sequence"),
        "{err}"
    );
}

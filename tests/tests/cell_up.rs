//! `cell up`: launches a cell from a manifest, restarts what dies, stops in reverse order.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use holarchy_tests::*;
use nix::sys::signal::Signal;
use schemas::HolonId;

/// Reads `cell up`'s output lines on a thread.
fn lines(child: &mut std::process::Child) -> mpsc::Receiver<String> {
    let stdout = child.stdout.take().unwrap();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    rx
}

fn wait_line(rx: &mpsc::Receiver<String>, seen: &mut Vec<String>, what: &str) -> String {
    let deadline = std::time::Instant::now() + WAIT;
    loop {
        let left = deadline.saturating_duration_since(std::time::Instant::now());
        match rx.recv_timeout(left) {
            Ok(line) => {
                seen.push(line.clone());
                if line.contains(what) {
                    return line;
                }
            }
            Err(_) => panic!("no line with {what:?}; saw {seen:#?}"),
        }
    }
}

/// The pid in a `started NAME (pid N)...` line of `cell up`.
fn pid_in(line: &str) -> i32 {
    let after = line.split("(pid ").nth(1).expect("a started line");
    after[..after.find(')').expect("(pid N)")]
        .parse()
        .expect("a pid")
}

#[tokio::test(flavor = "multi_thread")]
async fn cell_up_restarts_a_killed_holon_and_stops_in_reverse_order() {
    let dir = tempfile::tempdir().unwrap();
    let router = format!("tcp/127.0.0.1:{}", free_port());
    let sim_port = free_port();
    std::fs::copy(demo_config("robot1.toml"), dir.path().join("robot1.toml")).unwrap();
    std::fs::write(
        dir.path().join("cell.toml"),
        format!(
            r#"
cell = "t-up"
[router]
listen = ["{router}"]
[restart]
max_restarts = 3
period_ms = 60000
backoff_initial_ms = 100
[[process]]
name = "robot1-sim"
program = "robot-sim"
args = ["--listen", "127.0.0.1:{sim_port}"]
[[process]]
name = "robot1"
program = "holon-node"
args = ["--config", "robot1.toml", "--cell", "t-up", "--controller", "127.0.0.1:{sim_port}", "--connect", "{router}", "--data-dir", "data"]
"#
        ),
    )
    .unwrap();
    let mut up = Command::new(bin("cell"))
        .arg("up")
        .arg(dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let rx = lines(&mut up);
    let mut seen = Vec::new();
    let started = wait_line(&rx, &mut seen, "started robot1 (pid");
    let pid = pid_in(&started);

    // A client of the router sees the holon.
    let session = holon::ZenohSettings {
        mode: holon::Mode::Client,
        connect: vec![router.clone()],
        ..Default::default()
    }
    .open("router.local", WAIT)
    .await
    .unwrap();
    let keys = schemas::CellKeys::new("t-up").unwrap();
    let robot = HolonId::resource("robot1").unwrap();
    assert!(holon::presence::wait_alive(&session, &keys, &robot, WAIT)
        .await
        .unwrap());

    // kill -9: cell up restarts it, on the same data directory.
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid), Signal::SIGKILL).unwrap();
    wait_line(&rx, &mut seen, "robot1 exited (signal: 9");
    let again = wait_line(&rx, &mut seen, "started robot1 (pid");
    assert_ne!(again, started);
    tokio::time::sleep(Duration::from_millis(300)).await;
    assert!(holon::presence::wait_alive(&session, &keys, &robot, WAIT)
        .await
        .unwrap());
    assert!(dir.path().join("data/resource-robot1.sqlite").exists());
    assert!(dir.path().join("logs/robot1.log").exists());

    // SIGTERM: reverse order, exit 0.
    nix::sys::signal::kill(nix::unistd::Pid::from_raw(up.id() as i32), Signal::SIGTERM).unwrap();
    wait_line(&rx, &mut seen, "stopping the cell, in reverse order");
    let first = wait_line(&rx, &mut seen, "stopped ");
    assert!(first.contains("stopped robot1"), "{first}");
    let second = wait_line(&rx, &mut seen, "stopped ");
    assert!(second.contains("stopped robot1-sim"), "{second}");
    wait_line(&rx, &mut seen, "cell stopped");
    assert!(up.wait().unwrap().success());
}

/// Runs `cell up` on a manifest until it exits: its exit code and output.
fn cell_up_to_the_end(manifest: &str) -> (Option<i32>, String) {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("cell.toml"), manifest).unwrap();
    let output = Command::new(bin("cell"))
        .arg("up")
        .arg(dir.path())
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
    (output.status.code(), stdout)
}

#[test]
fn cell_up_gives_up_past_the_restart_intensity() {
    let (code, stdout) = cell_up_to_the_end(
        r#"
cell = "t-up2"
[restart]
max_restarts = 2
period_ms = 60000
backoff_initial_ms = 50
[[process]]
name = "crasher"
program = "sh"
args = ["-c", "exit 3"]
"#,
    );
    assert_eq!(code, Some(1), "{stdout}");
    assert_eq!(stdout.matches("started crasher").count(), 3, "{stdout}");
    assert!(stdout.contains("more than 2 restarts"), "{stdout}");
}

#[test]
fn cell_up_refuses_a_bad_manifest() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("cell.toml"),
        "cell = \"x\"\n[[process]]\nname = \"a\"\nprogram = \"true\"\nhost = \"far\"\n",
    )
    .unwrap();
    let output = Command::new(bin("cell"))
        .arg("up")
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("no [hosts.far] section"));
}

#[test]
fn cell_up_follows_each_process_restart_type() {
    let (code, stdout) = cell_up_to_the_end(
        r#"
cell = "t-up3"
[restart]
max_restarts = 2
period_ms = 60000
backoff_initial_ms = 50
[[process]]
name = "one-shot"
program = "sh"
args = ["-c", "exit 0"]
restart = "transient"
[[process]]
name = "best-effort"
program = "sh"
args = ["-c", "exit 4"]
restart = "temporary"
[[process]]
name = "crasher"
program = "sh"
args = ["-c", "sleep 0.3; exit 3"]
restart = "transient"
"#,
    );
    // The transient process that failed is restarted until the intensity gives up; the
    // one whose work is done and the temporary one are never restarted.
    assert_eq!(code, Some(1), "{stdout}");
    assert_eq!(stdout.matches("started crasher").count(), 3, "{stdout}");
    assert_eq!(stdout.matches("started one-shot").count(), 1, "{stdout}");
    assert_eq!(stdout.matches("started best-effort").count(), 1, "{stdout}");
    assert!(
        stdout.contains("one-shot exited (exit status: 0); transient processes are not restarted"),
        "{stdout}"
    );
    assert!(
        stdout
            .contains("best-effort exited (exit status: 4); temporary processes are not restarted"),
        "{stdout}"
    );
}

/// `cell status`'s lines for robot1's fence, as `(role, epoch)` sorted, asked through
/// `router`.
fn fence_lines(cell: &str, router: &str) -> Vec<(String, String)> {
    let status = Command::new(bin("cell"))
        .args(["status", "--cell", cell, "--connect", router])
        .output()
        .unwrap();
    let table = String::from_utf8_lossy(&status.stdout);
    let mut found: Vec<(String, String)> = table
        .lines()
        .filter(|line| line.starts_with("resource/robot1 "))
        .filter_map(|line| {
            let words: Vec<&str> = line.split_whitespace().collect();
            let role = words.iter().find(|w| ["holder", "standby"].contains(w))?;
            let epoch = words
                .iter()
                .skip_while(|w| *w != role)
                .nth(1)
                .copied()
                .unwrap_or_default();
            Some((role.to_string(), epoch.to_string()))
        })
        .collect();
    found.sort();
    found
}

/// Waits (at most [`WAIT`]) until robot1's fence in `cell status` has these roles.
async fn wait_roles(cell: &str, router: &str, roles: &[&str]) -> Vec<(String, String)> {
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let found = fence_lines(cell, router);
        let have: Vec<&str> = found.iter().map(|(role, _)| role.as_str()).collect();
        if have == roles {
            return found;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "robot1's fence is {found:?}, never {roles:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// A manifest with `standby_on`: `cell up` on the primary's host and `cell up --host b`
/// each start their copy of robot1, both fenced; the copy on b waits as a standby, and
/// serves when the primary freezes.
#[tokio::test(flavor = "multi_thread")]
async fn cell_up_starts_a_resource_and_its_standby_on_their_hosts() {
    let dir = tempfile::tempdir().unwrap();
    let router = format!("tcp/127.0.0.1:{}", free_port());
    let sim_port = free_port();
    resource_config(dir.path(), "robot1", 5000).unwrap();
    let args = |data: &str| {
        format!(
            r#"["--config", "robot1.toml", "--cell", "t-up-standby", "--controller", "127.0.0.1:{sim_port}", "--connect", "{router}", "--data-dir", "{data}"]"#
        )
    };
    std::fs::write(
        dir.path().join("cell.toml"),
        format!(
            r#"
cell = "t-up-standby"
[router]
listen = ["{router}"]
[hosts.b]
[[process]]
name = "robot1-sim"
program = "robot-sim"
args = ["--listen", "127.0.0.1:{sim_port}", "--fenced", "--lease-ms", "500"]
[[process]]
name = "robot1"
program = "holon-node"
identity = "resource.robot1"
args = {}
standby_on = "b"
standby_args = {}
"#,
            args("data-a"),
            args("data-b")
        ),
    )
    .unwrap();
    let up = |host: Option<&str>| {
        let mut command = Command::new(bin("cell"));
        command.arg("up").arg(dir.path());
        if let Some(host) = host {
            command.args(["--host", host]);
        }
        command
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .unwrap()
    };
    let mut local = up(None);
    let local_lines = lines(&mut local);
    let mut seen = Vec::new();
    let started = wait_line(&local_lines, &mut seen, "started robot1 (pid");
    assert!(!started.contains("standby"), "{started}");
    let pid = pid_in(&started);
    wait_roles("t-up-standby", &router, &["holder"]).await;
    let mut b = up(Some("b"));
    let b_lines = lines(&mut b);
    let mut b_seen = Vec::new();
    let standby = wait_line(&b_lines, &mut b_seen, "started robot1 (pid");
    assert!(standby.contains("as a standby"), "{standby}");
    let roles = wait_roles("t-up-standby", &router, &["holder", "standby"]).await;
    assert_eq!(roles[0], ("holder".to_string(), "1".to_string()));
    assert!(
        dir.path().join("data-b").exists(),
        "the standby's own journal"
    );

    // The primary freezes: after the controller's lease the standby holds the claim.
    let primary = nix::unistd::Pid::from_raw(pid);
    nix::sys::signal::kill(primary, Signal::SIGSTOP).unwrap();
    let roles = wait_roles("t-up-standby", &router, &["holder"]).await;
    assert_eq!(roles[0], ("holder".to_string(), "2".to_string()));
    nix::sys::signal::kill(primary, Signal::SIGCONT).unwrap();
    let roles = wait_roles("t-up-standby", &router, &["holder", "standby"]).await;
    assert_eq!(roles[0], ("holder".to_string(), "2".to_string()));

    for (mut up, rx, seen) in [(b, b_lines, b_seen), (local, local_lines, seen)] {
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(up.id() as i32), Signal::SIGTERM)
            .unwrap();
        let mut seen = seen;
        wait_line(&rx, &mut seen, "cell stopped");
        assert!(up.wait().unwrap().success());
    }
}

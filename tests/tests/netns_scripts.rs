//! The scripts in deploy/netns, run as a user runs them (guide.sh runs docs/deploy.md
//! sections 3-5 as written, guide-standby.sh its section 4b): they work, and whether they
//! end, fail or are interrupted, no process they started survives them and nothing of
//! theirs is left behind (namespaces, run directory).
//!
//! Needs root and iproute2 (and etcd for guide-standby.sh); without them each test says
//! SKIPPED and passes, unless HOLARCHY_REQUIRE_NETNS (HOLARCHY_REQUIRE_ETCD) is set.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use holarchy_tests::*;

/// A script run with its own namespace prefix, its output in a file.
struct Script {
    prefix: String,
    child: Child,
    output: PathBuf,
}

impl Script {
    fn start(dir: &Path, script: &str, prefix: &str, env: &[(&str, &str)]) -> Script {
        // Built first, so the script finds them.
        for program in ["cell", "holon-node", "order-node", "robot-sim"] {
            bin(program);
        }
        let output = dir.join(format!("{prefix}.out"));
        let log = std::fs::File::create(&output).unwrap();
        let child = Command::new(workspace_root().join("deploy/netns").join(script))
            .current_dir(workspace_root())
            .env("NETNS_PREFIX", prefix)
            .env("BIN", bin("cell").parent().unwrap())
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap();
        Script {
            prefix: prefix.to_string(),
            child,
            output,
        }
    }

    fn output(&self) -> String {
        let mut text = String::new();
        std::fs::File::open(&self.output)
            .unwrap()
            .read_to_string(&mut text)
            .unwrap();
        text
    }

    fn wait_for(&self, text: &str, within: Duration) {
        let deadline = Instant::now() + within;
        while !self.output().contains(text) {
            assert!(
                Instant::now() < deadline,
                "the script never printed {text:?}:\n{}",
                self.output()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    fn wait(&mut self, within: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + within;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            if Instant::now() > deadline {
                let _ = self.child.kill();
                panic!(
                    "the script did not end within {within:?}:\n{}",
                    self.output()
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// Asserts that nothing of the run is left: no namespace with its prefix, no run
    /// directory, no process working in it.
    fn assert_nothing_left(&self) {
        let namespaces = Command::new("ip").args(["netns", "list"]).output().unwrap();
        let namespaces = String::from_utf8_lossy(&namespaces.stdout).into_owned();
        assert!(
            !namespaces.contains(&self.prefix),
            "namespaces left behind:\n{namespaces}\n{}",
            self.output()
        );
        let run_dir = format!("/tmp/holarchy-{}", self.prefix);
        let mut survivors = Vec::new();
        for entry in std::fs::read_dir("/proc").unwrap().flatten() {
            let Ok(pid) = entry.file_name().to_string_lossy().parse::<u32>() else {
                continue;
            };
            let cwd = std::fs::read_link(format!("/proc/{pid}/cwd")).unwrap_or_default();
            let cmdline = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
            let cmdline = String::from_utf8_lossy(&cmdline).replace('\0', " ");
            if cwd.to_string_lossy().starts_with(&run_dir) || cmdline.contains(&run_dir) {
                survivors.push(format!("{pid}: {cmdline}"));
            }
        }
        assert!(
            survivors.is_empty(),
            "processes of the run survived it:\n{}\n{}",
            survivors.join("\n"),
            self.output()
        );
        let leftovers: Vec<_> = std::fs::read_dir("/tmp")
            .unwrap()
            .flatten()
            .filter(|e| {
                e.file_name()
                    .to_string_lossy()
                    .starts_with(&format!("holarchy-{}", self.prefix))
            })
            .collect();
        assert!(leftovers.is_empty(), "run files left: {leftovers:?}");
    }
}

fn prefix(tag: &str) -> String {
    format!("hl{tag}{}", std::process::id() % 10_000)
}

#[test]
fn the_partition_script_runs_and_leaves_nothing_behind() {
    if let Err(why) = netns_available() {
        println!("SKIPPED: needs root and network namespaces ({why})");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut script = Script::start(dir.path(), "partition.sh", &prefix("p"), &[("ORDERS", "3")]);
    let status = script.wait(Duration::from_secs(300));
    let output = script.output();
    println!("{output}");
    assert!(status.success(), "{output}");
    assert!(
        output.contains("cell factory: 6 orders: 6 done"),
        "{output}"
    );
    assert!(
        output.contains("done: nothing of this run is left running"),
        "{output}"
    );
    script.assert_nothing_left();
}

#[test]
fn an_interrupted_partition_script_stops_everything_it_started() {
    if let Err(why) = netns_available() {
        println!("SKIPPED: needs root and network namespaces ({why})");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut script = Script::start(dir.path(), "partition.sh", &prefix("i"), &[("ORDERS", "3")]);
    // Interrupted while the cell runs and orders are in flight.
    script.wait_for("== submit 3 orders", Duration::from_secs(120));
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(script.child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let status = script.wait(Duration::from_secs(120));
    let output = script.output();
    assert!(
        !status.success(),
        "an interrupted run reports failure:\n{output}"
    );
    assert!(
        output.contains("done: nothing of this run is left running"),
        "{output}"
    );
    script.assert_nothing_left();
}

#[test]
fn the_deploy_guide_works_when_its_commands_are_copied() {
    if let Err(why) = netns_available() {
        println!("SKIPPED: needs root and network namespaces ({why})");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let mut script = Script::start(dir.path(), "guide.sh", &prefix("g"), &[]);
    let status = script.wait(Duration::from_secs(400));
    let output = script.output();
    println!("{output}");
    assert!(status.success(), "{output}");
    // Every command of sections 3 and 4 ran: 3 + 2 + 2 of section 3, 3 of section 4.
    let ran = output.lines().filter(|l| l.starts_with("host ")).count();
    assert!(ran >= 13, "{output}");
    assert!(output.contains("the guide works as written"), "{output}");
    assert!(
        output.contains("done: nothing of this run is left running"),
        "{output}"
    );
    script.assert_nothing_left();
}

#[test]
fn the_deploy_guide_standby_section_works_when_its_commands_are_copied() {
    if let Err(why) = netns_available() {
        println!("SKIPPED: needs root and network namespaces ({why})");
        return;
    }
    let Some(etcd) = etcd_binary() else { return };
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let mut script = Script::start(
        dir.path(),
        "guide-standby.sh",
        &prefix("s"),
        &[("ETCD", etcd.to_str().unwrap())],
    );
    let status = script.wait(Duration::from_secs(300));
    let output = script.output();
    println!("{output}");
    println!("guide-standby.sh ran {:?}", started.elapsed());
    assert!(status.success(), "{output}");
    // Every command of section 4b ran (robot-sim, robot1 twice, cell status, etcd
    // three times, etcdctl or its skip, orders1 twice, cell status) and 5 of section 3.
    let ran = output
        .lines()
        .filter(|l| l.starts_with("host ") && !l.contains(": 10.213.77."))
        .count();
    assert!(ran >= 16, "{ran} commands:\n{output}");
    for checked in [
        "robot1's standby on c holds the controller",
        "orders1's standby on c serves",
        "orders1 on b exited deposed",
        "section 4b works as written",
        "done: nothing of this run is left running",
    ] {
        assert!(output.contains(checked), "no {checked:?}:\n{output}");
    }
    // The last cell status: robot1 held on c, b's copy a standby again.
    let last = output.rfind("FENCED RESOURCE").expect("a fence table");
    let table = &output[last..];
    let row = |role: &str, host: &str| {
        table.lines().any(|l| {
            let words: Vec<&str> = l.split_whitespace().collect();
            words.len() >= 4
                && words[0] == "resource/robot1"
                && words[1] == role
                && words[3] == host
        })
    };
    assert!(
        row("holder", "host-c") && row("standby", "host-b"),
        "{table}"
    );
    script.assert_nothing_left();
}

//! A controller simulator (`robot-sim`) as a test drives it: its counts, and the
//! resource config that points a holon at it.

use std::fs;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};

use crate::*;

/// A `robot-sim` process.
pub struct Sim {
    pub process: Process,
    pub address: String,
    pub count_file: PathBuf,
}

impl Sim {
    /// Starts `robot-sim --listen ADDRESS` with extra flags and waits for its ready line.
    pub fn start(dir: &Path, name: &str, address: &str, flags: &[&str]) -> Result<Sim> {
        let count_file = dir.join(format!("{name}.counts.json"));
        let stderr_path = dir.join(format!("{name}.stderr"));
        let mut child = Command::new(bin("robot-sim"))
            .args(["--listen", address, "--count-file"])
            .arg(&count_file)
            .args(flags)
            .stdout(Stdio::piped())
            .stderr(fs::File::create(&stderr_path)?)
            .spawn()
            .context("start robot-sim")?;
        let stdout = child.stdout.take().expect("piped stdout");
        let process = Process {
            name: name.to_string(),
            child: Some(child),
            stderr_path,
        };
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let line = rx
            .recv_timeout(WAIT)
            .map_err(|_| anyhow!("robot-sim printed no ready line"))?;
        let address = line
            .trim()
            .strip_prefix("listening on ")
            .ok_or_else(|| anyhow!("unexpected robot-sim line {line:?}"))?
            .to_string();
        Ok(Sim {
            process,
            address,
            count_file,
        })
    }

    /// The simulator's counts (`{"executed": N, "by_action": {...}, ...}`), once its
    /// count file settled (unchanged for 25 ms): the simulator rewrites the file from a
    /// thread of its own just after each reply goes out, so a reader that saw a reply's
    /// effects may be early.
    pub fn counts(&self) -> serde_json::Value {
        let read = || {
            fs::read_to_string(&self.count_file)
                .ok()
                .and_then(|t| serde_json::from_str(&t).ok())
                .unwrap_or(serde_json::Value::Null)
        };
        // A write may wait for the simulator's writer thread (a loaded machine delays
        // it by milliseconds): the counts are those that stayed the same for 25 ms.
        let mut counts = read();
        for _ in 0..40 {
            std::thread::sleep(Duration::from_millis(25));
            let again = read();
            if again == counts {
                break;
            }
            counts = again;
        }
        counts
    }

    /// The connections the simulator has accepted (`connections` in its count file,
    /// rewritten as each one is accepted).
    pub fn connections(&self) -> u64 {
        self.counts()["connections"].as_u64().unwrap_or(0)
    }

    pub fn executed(&self, action: &str) -> u64 {
        self.counts()["by_action"][action].as_u64().unwrap_or(0)
    }

    /// Waits, at most 10 s, until the simulator has executed `action` at least `n`
    /// times, and returns the settled count (more than `n` if it ran more often). The
    /// error, at the deadline, says how often it did. (A test that checks a count was
    /// *not* reached settles for a while and reads [`Sim::executed`] instead.)
    pub async fn wait_executed(&self, action: &str, n: u64) -> Result<u64> {
        const WITHIN: Duration = Duration::from_secs(10);
        let deadline = tokio::time::Instant::now() + WITHIN;
        loop {
            let executed = self.executed(action);
            if executed >= n {
                return Ok(executed);
            }
            if tokio::time::Instant::now() >= deadline {
                bail!(
                    "the simulator {} executed {action} {executed} times, never {n} within {WITHIN:?}",
                    self.process.name
                );
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Waits, at most 10 s, until the simulator has received `n` commands in all. A
    /// holon's state names a step as soon as its command is handed to the bridge,
    /// which writes it to the socket a moment later: a test that kills something
    /// mid-step waits for this first.
    pub async fn wait_received(&self, n: u64) -> Result<()> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        loop {
            let received = fs::read_to_string(&self.count_file)
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .and_then(|c| c["received"].as_u64())
                .unwrap_or(0);
            if received >= n {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                bail!("the simulator received {received} commands, never {n}");
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
}

/// Writes a resource config for tests: short timeouts, one pick_n_place robot.
pub fn resource_config(dir: &Path, name: &str, command_timeout_ms: u64) -> Result<PathBuf> {
    let path = dir.join(format!("{name}.toml"));
    fs::write(
        &path,
        format!(
            r#"
cell = "unset"
name = "{name}"

[controller]
address = "127.0.0.1:1"
reconnect_interval_ms = 100
reconnect_max_ms = 1000
command_timeout_ms = {command_timeout_ms}
connect_timeout_ms = 500

[supervisor]
strategy = "one_for_one"
max_restarts = 5
period_ms = 10000

[delivery]
retry_initial_ms = 100
retry_max_ms = 400
attempt_timeout_ms = 500

[services.pick_n_place]
nominal_duration_ms = 1000
steps = [
  {{ action = "pick", until = ["picking_done"], position = "pick" }},
  {{ action = "place", until = ["placing_done"], position = "place" }},
]
"#
        ),
    )?;
    Ok(path)
}

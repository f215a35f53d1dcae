//! `cell upgrade NAME`: replaces one process of a running `cell up` by a new build or
//! config, by a planned hand-over ([`holon::takeover`]): the running holon finishes its
//! step, keeps its bookings and hands its name and journal to its successor.
//!
//! `cell up DIR --host H` listens on the Unix socket `DIR/run/H.sock` (only its user
//! may connect). `cell upgrade` sends one [`UpgradeRequest`] as a JSON line and reads
//! one [`UpgradeOutcome`] line. `cell up` then:
//! 1. builds the successor's command line: the manifest's, with `--binary` as the
//!    program and `--config` as the value of its `--config`;
//! 2. checks it (`PROGRAM ARGS --check`): a config that fails leaves the running
//!    process untouched, and the outcome carries the check's error;
//! 3. starts `PROGRAM ARGS --take-over --take-over-wait-ms W`, supervised;
//! 4. when the predecessor exits, the successor is the process of that name (restarts
//!    use its command line for the life of `cell up`; put it in the manifest to keep
//!    it); if the successor exits first, the upgrade failed and the predecessor runs on.

use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};

/// What `cell upgrade` asks `cell up`.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct UpgradeRequest {
    /// The manifest's process name.
    pub name: String,
    /// The new program (absolute, or as `cell up` resolves a manifest's).
    pub binary: Option<PathBuf>,
    /// The new config file (absolute, or relative to the manifest's directory).
    pub config: Option<PathBuf>,
    /// How long the running process may take to finish its step and hand over.
    pub wait_ms: u64,
}

/// How it went.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct UpgradeOutcome {
    pub ok: bool,
    /// For the operator: what happened, or why not.
    pub message: String,
}

/// The control socket of `cell up DIR --host HOST`.
pub fn socket_path(dir: &Path, host: &str) -> PathBuf {
    dir.join("run").join(format!("{host}.sock"))
}

/// The programs that can hand over to a successor.
const HANDS_OVER: &[&str] = &["holon-node", "order-node"];

/// The successor's program and arguments: the running ones with `binary` and `config`
/// put in; an error when the process cannot hand over or has no `--config` to change.
pub fn successor_command(
    program: &str,
    args: &[String],
    binary: Option<&Path>,
    config: Option<&Path>,
) -> Result<(String, Vec<String>)> {
    let program = match binary {
        Some(binary) => binary.display().to_string(),
        None => program.to_string(),
    };
    let base = Path::new(&program)
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if !HANDS_OVER.contains(&base.as_str()) {
        bail!("{program} has no planned hand-over (only holon-node and order-node do); restart it instead");
    }
    let mut args = args.to_vec();
    if let Some(config) = config {
        let config = config.display().to_string();
        if let Some(at) = args.iter().position(|a| a == "--config") {
            let value = args
                .get_mut(at + 1)
                .ok_or_else(|| anyhow!("its --config has no value"))?;
            *value = config;
        } else if let Some(arg) = args.iter_mut().find(|a| a.starts_with("--config=")) {
            *arg = format!("--config={config}");
        } else {
            args.extend(["--config".to_string(), config]);
        }
    }
    Ok((program, args))
}

/// Sends `request` to the `cell up` of `dir` and `host`; its outcome.
pub async fn ask(dir: &Path, host: &str, request: &UpgradeRequest) -> Result<UpgradeOutcome> {
    let path = socket_path(dir, host);
    let stream = tokio::net::UnixStream::connect(&path).await.with_context(|| {
        format!(
            "no `cell up {}` for host {host} answers on {} (is it running?). A holon started by hand is upgraded by starting its successor with --take-over (docs/operations.md)",
            dir.display(),
            path.display()
        )
    })?;
    let (read, mut write) = stream.into_split();
    let mut line = serde_json::to_vec(request)?;
    line.push(b'\n');
    write.write_all(&line).await?;
    let mut answer = String::new();
    // The successor's check, the running step, stopping the old process's components,
    // the stand-in until the successor serves: each has its bound; the answer comes
    // within their sum.
    let limit = Duration::from_secs(30)
        + Duration::from_millis(request.wait_ms)
        + holon::takeover::RELEASE_ALLOWANCE
        + holon::takeover::STAND_IN_LIMIT
        + Duration::from_secs(30);
    tokio::time::timeout(limit, BufReader::new(read).read_line(&mut answer))
        .await
        .map_err(|_| anyhow!("cell up did not report the upgrade within {limit:?}"))??;
    serde_json::from_str(answer.trim()).with_context(|| {
        format!(
            "cell up answered something that is not an upgrade outcome: {:?}",
            answer.trim()
        )
    })
}

/// The tail of a log file, for an outcome that says why a successor failed.
pub fn log_tail(path: &Path, lines: usize) -> String {
    let text = std::fs::read_to_string(path).unwrap_or_default();
    let all: Vec<&str> = text.lines().collect();
    all[all.len().saturating_sub(lines)..].join("\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(list: &[&str]) -> Vec<String> {
        list.iter().map(|s| s.to_string()).collect()
    }

    #[test]
    fn the_successor_gets_the_new_binary_and_config() {
        let running = args(&["--config", "robot1.toml", "--data-dir", "data"]);
        let (program, new) = successor_command(
            "holon-node",
            &running,
            Some(Path::new("/opt/v2/holon-node")),
            Some(Path::new("robot1-v2.toml")),
        )
        .unwrap();
        assert_eq!(program, "/opt/v2/holon-node");
        assert_eq!(
            new,
            args(&["--config", "robot1-v2.toml", "--data-dir", "data"])
        );
        let (_, same) = successor_command("order-node", &running, None, None).unwrap();
        assert_eq!(same, running);
        let (_, equals) = successor_command(
            "holon-node",
            &args(&["--config=a.toml"]),
            None,
            Some(Path::new("b.toml")),
        )
        .unwrap();
        assert_eq!(equals, args(&["--config=b.toml"]));
    }

    #[test]
    fn a_program_without_a_hand_over_is_refused() {
        let err = successor_command("robot-sim", &[], None, None)
            .unwrap_err()
            .to_string();
        assert!(err.contains("restart it instead"), "{err}");
    }
}

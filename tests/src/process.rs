//! The children a test starts: a free port, a process killed when the test ends,
//! holon and order-node processes, and their logs for a failed run.

use std::fs;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Mutex;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};

use crate::*;

/// A free TCP port on loopback (closed again; used at once by the caller).
pub fn free_port() -> u16 {
    static USED: Mutex<Vec<u16>> = Mutex::new(Vec::new());
    loop {
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("bind an ephemeral port")
            .port();
        let mut used = USED.lock().unwrap();
        if !used.contains(&port) {
            used.push(port);
            return port;
        }
    }
}

/// A child process killed (SIGKILL) when dropped, with its output in files.
pub struct Process {
    pub name: String,
    pub(crate) child: Option<Child>,
    pub stderr_path: PathBuf,
}

impl Process {
    /// A child the test started itself, its stderr in `stderr_path`: killed when dropped
    /// as the others are.
    pub fn of(name: &str, child: Child, stderr_path: PathBuf) -> Process {
        Process {
            name: name.to_string(),
            child: Some(child),
            stderr_path,
        }
    }

    pub fn pid(&self) -> i32 {
        self.child.as_ref().map(|c| c.id() as i32).unwrap_or(0)
    }

    /// Sends a signal (e.g. SIGTERM) to the process.
    pub fn signal(&self, signal: nix::sys::signal::Signal) -> Result<()> {
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(self.pid()), signal)?;
        Ok(())
    }

    /// Kills the process (SIGKILL) and reaps it.
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Waits for the process to exit by itself, at most `timeout`.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<std::process::ExitStatus> {
        let deadline = std::time::Instant::now() + timeout;
        let child = self
            .child
            .as_mut()
            .ok_or_else(|| anyhow!("already reaped"))?;
        loop {
            if let Some(status) = child.try_wait()? {
                self.child = None;
                return Ok(status);
            }
            if std::time::Instant::now() > deadline {
                bail!("{} did not exit within {timeout:?}", self.name);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// What the process wrote to stderr so far.
    pub fn stderr(&self) -> String {
        fs::read_to_string(&self.stderr_path).unwrap_or_default()
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Starts `holon-node` with `--config FILE --cell CELL --connect ROUTER --controller ADDR`
/// and extra flags. Wait for it with [`Cell::wait_alive`].
pub fn start_node(
    dir: &Path,
    config: &Path,
    cell: &str,
    connect: &str,
    controller: &str,
    extra: &[&str],
) -> Result<Process> {
    let name = config
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stderr_path = dir.join(format!("{name}.node.stderr"));
    let child = Command::new(bin("holon-node"))
        .arg("--config")
        .arg(config)
        .args([
            "--cell",
            cell,
            "--connect",
            connect,
            "--controller",
            controller,
        ])
        .arg("--log-file")
        .arg(dir.join(format!("{name}.log.json")))
        .args(extra)
        .env("RUST_LOG", holon_log_level())
        .stdout(Stdio::null())
        .stderr(fs::File::create(&stderr_path)?)
        .spawn()
        .context("start holon-node")?;
    Ok(Process {
        name,
        child: Some(child),
        stderr_path,
    })
}

/// Starts `program` (holon-node or order-node) with `--config FILE --cell CELL --name
/// NAME --connect ENDPOINT` (a client of the test's router) and extra flags; its log goes to
/// `DIR/NAME.log.json`.
pub fn start_holon(
    dir: &Path,
    program: &str,
    config: &Path,
    name: &str,
    cell: &Cell,
    extra: &[&str],
) -> Result<Process> {
    let stderr_path = dir.join(format!("{name}.stderr"));
    let child = Command::new(bin(program))
        .arg("--config")
        .arg(config)
        .args(["--cell", cell.keys.cell(), "--name", name])
        .args(["--connect", &cell.endpoint])
        .arg("--log-file")
        .arg(dir.join(format!("{name}.log.json")))
        .args(extra)
        .env("RUST_LOG", holon_log_level())
        .stdout(Stdio::null())
        .stderr(fs::File::create(&stderr_path)?)
        .spawn()
        .with_context(|| format!("start {program}"))?;
    Ok(Process {
        name: name.to_string(),
        child: Some(child),
        stderr_path,
    })
}

/// Starts `bin(program)` with `args`, its stderr in `dir/<name>.stderr`, stdout dropped.
pub fn start_program(dir: &Path, program: &str, name: &str, args: &[&str]) -> Result<Process> {
    let stderr_path = dir.join(format!("{name}.stderr"));
    let child = Command::new(bin(program))
        .args(args)
        .stdout(Stdio::null())
        .stderr(fs::File::create(&stderr_path)?)
        .spawn()
        .with_context(|| format!("start {program}"))?;
    Ok(Process {
        name: name.to_string(),
        child: Some(child),
        stderr_path,
    })
}

/// Waits, at most [`WAIT`], until something accepts TCP connections on `address`.
pub async fn wait_listening(address: &str) -> Result<()> {
    let deadline = tokio::time::Instant::now() + WAIT;
    while tokio::net::TcpStream::connect(address).await.is_err() {
        if tokio::time::Instant::now() >= deadline {
            bail!("nothing listens on {address} after {WAIT:?}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Ok(())
}

/// Prints the end of every process's log: what a failed run on a CI machine leaves to read.
pub fn print_log_tails(dir: &Path) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    let mut logs: Vec<_> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "log"))
        .collect();
    logs.sort();
    for log in logs {
        let text = fs::read_to_string(&log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        let tail = &lines[lines.len().saturating_sub(40)..];
        println!("---- {} (last {} lines)", log.display(), tail.len());
        for line in tail {
            println!("{line}");
        }
    }
}

//! A secure cell, as `cell certs` and `cell up` make it: mutual TLS and access control,
//! with the demo's four resources (simulated controllers with 20 ms actions), the
//! product `breaker` and the order-node `orders1`, each with its own identity, and
//! the spares `resource.robot9` and `order-node.probe`.

use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use schemas::CellKeys;

use crate::{bin, free_port, workspace_root};

/// A cell's supervising process (`cell up` of the secure cell, or a `cell demo`), in a
/// process group of its own with the processes it starts: stopped (SIGTERM, then
/// SIGKILL) when dropped, and then whatever of its group is left is killed, so that one
/// that had to be killed leaves no process behind.
pub struct Up(Child);

impl Up {
    /// Starts `command` in a process group of its own.
    pub fn spawn(command: &mut Command) -> Up {
        Up(command
            .process_group(0)
            .spawn()
            .expect("start the cell's supervising process"))
    }

    /// Its process id.
    pub fn id(&self) -> u32 {
        self.0.id()
    }
}

impl Drop for SecureCell {
    fn drop(&mut self) {
        // A failed run on a CI machine leaves only this to read (the directory goes).
        if std::thread::panicking() {
            crate::print_log_tails(&self.dir);
            crate::print_log_tails(&self.dir.join("logs"));
        }
    }
}

impl Drop for Up {
    fn drop(&mut self) {
        let pid = nix::unistd::Pid::from_raw(self.0.id() as i32);
        let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
        let deadline = std::time::Instant::now() + Duration::from_secs(45);
        while std::time::Instant::now() < deadline {
            if let Ok(Some(_)) = self.0.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.0.kill();
        let _ = self.0.wait();
        // Killed rather than stopped: its holons and simulators outlived it.
        let _ = nix::sys::signal::killpg(pid, nix::sys::signal::Signal::SIGKILL);
    }
}

pub struct SecureCell {
    /// The manifest, the PKI (`pki/`), the logs and the controllers' counts.
    pub dir: PathBuf,
    /// The router's `tls/` endpoint.
    pub endpoint: String,
    pub keys: CellKeys,
    _up: Up,
}

/// Writes the manifest, issues its PKI with `cell certs` and starts `cell up`.
pub fn secure_cell(dir: &Path, cell: &str) -> SecureCell {
    let port = free_port();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let sims: Vec<(&str, u16)> = ["robot1", "robot2", "inspect1", "conveyor1"]
        .into_iter()
        .map(|n| (n, free_port()))
        .collect();
    let mut manifest = format!(
        r#"cell = "{cell}"
[router]
listen = ["{endpoint}"]
[pki]
spares = ["resource.robot9", "order-node.probe"]
[restart]
backoff_initial_ms = 100
stop_timeout_ms = 10000
"#
    );
    let demo = workspace_root().join("deploy/cells/demo");
    for (name, sim_port) in &sims {
        manifest.push_str(&format!(
            r#"[[process]]
name = "{name}-sim"
program = "robot-sim"
args = ["--listen", "127.0.0.1:{sim_port}", "--delay-ms", "20", "--count-file", "{name}.counts.json"]
"#
        ));
    }
    for (name, sim_port) in &sims {
        let config = format!("{name}.toml");
        manifest.push_str(&format!(
            r#"[[process]]
name = "{name}"
identity = "resource.{name}"
program = "holon-node"
args = ["--config", "{}", "--cell", "{cell}", "--name", "{name}", "--controller", "127.0.0.1:{sim_port}", "--connect", "{endpoint}", "--pki", "pki", "--data-dir", "data"]
"#,
            demo.join(config).display()
        ));
    }
    manifest.push_str(&format!(
        r#"[[process]]
name = "breaker"
identity = "product.breaker"
program = "holon-node"
args = ["--config", "{}", "--cell", "{cell}", "--connect", "{endpoint}", "--pki", "pki"]
[[process]]
name = "orders1"
identity = "order-node.orders1"
program = "order-node"
args = ["--config", "{}", "--cell", "{cell}", "--connect", "{endpoint}", "--pki", "pki", "--data-dir", "data"]
"#,
        crate::stationary_breaker().display(),
        demo.join("orders1.toml").display()
    ));
    std::fs::write(dir.join("cell.toml"), manifest).unwrap();
    let certs = Command::new(bin("cell"))
        .arg("certs")
        .arg(dir)
        .output()
        .unwrap();
    assert!(
        certs.status.success(),
        "cell certs: {}",
        String::from_utf8_lossy(&certs.stderr)
    );
    let up = Command::new(bin("cell"))
        .arg("up")
        .arg(dir)
        .process_group(0)
        .stdout(std::fs::File::create(dir.join("up.log")).unwrap())
        // Its own logs (warnings, a panic's message), kept for a failed run to read.
        .stderr(std::fs::File::create(dir.join("up.stderr.log")).unwrap())
        .spawn()
        .unwrap();
    SecureCell {
        dir: dir.to_path_buf(),
        endpoint,
        keys: CellKeys::new(cell).unwrap(),
        _up: Up(up),
    }
}

impl SecureCell {
    pub fn pki(&self) -> PathBuf {
        self.dir.join("pki")
    }

    /// A zenoh session with the identity `identity` of `pki`, as a client (operators,
    /// observers, holons) or a peer that listens (a holon that links directly).
    pub async fn session_as(
        &self,
        pki: &Path,
        identity: &str,
        mode: holon::Mode,
    ) -> zenoh::Result<zenoh::Session> {
        let settings = holon::ZenohSettings {
            mode,
            connect: vec![self.endpoint.clone()],
            listen: if mode == holon::Mode::Peer {
                vec!["tls/127.0.0.1:0".into()]
            } else {
                vec![]
            },
            tls: Some(holon::tls::TlsSettings {
                pki: Some(pki.to_path_buf()),
                ..Default::default()
            }),
            ..Default::default()
        };
        let session = settings
            .open(identity, Duration::from_secs(5))
            .await
            .map_err(|e| zenoh::Error::from(e.to_string()))?;
        if !holon::session::wait_connected(&session, Duration::from_secs(5)).await {
            return Err("not connected".into());
        }
        Ok(session)
    }

    pub fn cell_command(&self, args: &[&str]) -> std::process::Output {
        Command::new(bin("cell"))
            .args(args)
            .args([
                "--cell",
                self.keys.cell(),
                "--connect",
                &self.endpoint,
                "--timeout-ms",
                "3000",
            ])
            .arg("--pki")
            .arg(self.pki())
            .output()
            .unwrap()
    }

    pub fn executed(&self, sim: &str) -> u64 {
        std::fs::read_to_string(self.dir.join(format!("{sim}.counts.json")))
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .and_then(|v| v["executed"].as_u64())
            .unwrap_or(0)
    }

    pub fn total_executed(&self) -> u64 {
        ["robot1", "robot2", "inspect1", "conveyor1"]
            .iter()
            .map(|s| self.executed(s))
            .sum()
    }
}

/// Adds a user to the users file of `pki` with `cell users`, the password piped in (the
/// people of both doors, the dashboard and the OPC UA server).
pub fn add_user(pki: &Path, name: &str, role: &str, password: &str) {
    let mut child = Command::new(bin("cell"))
        .args(["users", "--pki"])
        .arg(pki)
        .args(["add", name, "--role", role])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    use std::io::Write;
    writeln!(child.stdin.take().unwrap(), "{password}").unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "cell users add {name}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

//! `cell dashboard` started for a test: a plain, operator dashboard on loopback.

use std::io::BufRead;
use std::path::Path;
use std::process::{Command, Stdio};

use crate::{bin, Process};

/// Starts `cell dashboard --operator` of cell `cell` at `endpoint` on a free loopback
/// port, with `extra` arguments: the process (killed when dropped) and its address
/// (`127.0.0.1:PORT`). Its stderr goes to DIR/dashboard.stderr.
pub fn start_dashboard(
    dir: &Path,
    cell: &str,
    endpoint: &str,
    extra: &[&str],
) -> (Process, String) {
    let stderr = dir.join("dashboard.stderr");
    let mut child = Command::new(bin("cell"))
        .args(["dashboard", "--cell", cell])
        .args(["--connect", endpoint, "--listen", "127.0.0.1:0"])
        .arg("--operator")
        .args(extra)
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(&stderr).expect("create the dashboard's stderr"))
        .spawn()
        .expect("start cell dashboard");
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("piped"))
        .read_line(&mut line)
        .expect("the dashboard's first line");
    let address = line
        .trim()
        .rsplit("http://")
        .next()
        .unwrap_or_default()
        .trim_end_matches('/')
        .to_string();
    (Process::of("dashboard", child, stderr), address)
}

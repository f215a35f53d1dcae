//! What a test needs of the machine that is not a Rust crate: network namespaces
//! (root) and Python's asyncua for the OPC UA tests.

use std::path::PathBuf;
use std::process::{Command, Stdio};

use crate::*;

/// Whether this machine can run the network-namespace tests (the multi-host test and the
/// netns scripts): root, and `ip netns` works (a namespace is made and deleted). `Err`
/// says why not, and the test skips, unless `HOLARCHY_REQUIRE_NETNS` is set (CI sets it,
/// as root): then a machine that cannot run them fails the test instead.
pub fn netns_available() -> std::result::Result<(), String> {
    let available = netns_probe();
    if let Err(why) = &available {
        if std::env::var_os("HOLARCHY_REQUIRE_NETNS").is_some() {
            panic!(
                "HOLARCHY_REQUIRE_NETNS is set but network namespaces cannot be used here: {why}"
            );
        }
    }
    available
}

/// Root, and a namespace can be made and deleted.
fn netns_probe() -> std::result::Result<(), String> {
    if !nix::unistd::Uid::effective().is_root() {
        return Err("not root".into());
    }
    // Unique per call: tests of one binary probe at the same time.
    static PROBES: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = PROBES.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    let probe = format!("hlpr{}x{n}", std::process::id() % 100_000);
    match Command::new("ip").args(["netns", "add", &probe]).status() {
        Ok(s) if s.success() => {
            let _ = Command::new("ip").args(["netns", "del", &probe]).status();
            Ok(())
        }
        Ok(_) => Err("ip netns add is refused".into()),
        Err(e) => Err(format!("no `ip` command (apt-get install iproute2): {e}")),
    }
}

/// The Python with asyncua for the OPC UA tests (docs/opcua.md, "Testing"): env
/// `HOLARCHY_OPCUA_PYTHON`, default `target/opcua-venv/bin/python`. `None` when it is
/// missing or has no asyncua (the test then skips), unless `HOLARCHY_REQUIRE_OPCUA=1`:
/// then it panics.
pub fn opcua_python() -> Option<PathBuf> {
    let python = std::env::var_os("HOLARCHY_OPCUA_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target/opcua-venv/bin/python"));
    let works = Command::new(&python)
        .args(["-c", "import asyncua"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if works {
        return Some(python);
    }
    let why = format!(
        "no Python with asyncua at {} (python3 -m venv target/opcua-venv && target/opcua-venv/bin/pip install asyncua==2.1.0, or set HOLARCHY_OPCUA_PYTHON)",
        python.display()
    );
    if std::env::var("HOLARCHY_REQUIRE_OPCUA").is_ok_and(|v| v == "1") {
        panic!("HOLARCHY_REQUIRE_OPCUA=1 but {why}");
    }
    eprintln!("SKIPPED: {why}");
    None
}

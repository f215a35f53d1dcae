//! The OPC UA section: how soon a plant's OPC UA client sees a resource's PackML state
//! change after the holon publishes it, set beside `cell status` (what an operator had
//! before: a process that joins the cell and asks).
//!
//! A real `cell opcua` serves the run's cell; a Python asyncua client (the venv of the
//! tests: `HOLARCHY_OPCUA_PYTHON`, default `target/opcua-venv/bin/python`) subscribes to
//! `robot-opcua`'s `Status.StateCurrent` with a 20 ms publishing interval and prints the
//! wall-clock time of every notification; this process hears the holon's state
//! publications over zenoh and notes when each arrived. The resource is held and
//! unheld 40 times; each change's latency is the client's notification time minus the
//! publication's arrival here (one machine, one clock).

use std::io::{BufRead, BufReader, Write};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{anyhow, bail, Context, Result};
use holarchy_tests::{resource_config, Sim};
use serde_json::json;

use crate::run::Run;
use crate::stats::Latency;

/// Hold and unhold this many times each.
const CHANGES: usize = 40;

/// The client: subscribes, then prints `<epoch ms> <value>` per notification.
const CLIENT: &str = r#"
import asyncio, sys, time
from asyncua import Client

class Handler:
    def datachange_notification(self, node, val, data):
        print(f"{time.time() * 1000:.3f} {val}", flush=True)

async def main(url, cell, resource):
    async with Client(url=url) as client:
        idx = await client.get_namespace_index(f"urn:holarchy:{cell}")
        node = client.get_node(f"ns={idx};s=PackMLObjects.{resource}.Status.StateCurrent")
        sub = await client.create_subscription(20, Handler())
        await sub.subscribe_data_change(node)
        print("ready", flush=True)
        while True:
            await asyncio.sleep(3600)

asyncio.run(main(*sys.argv[1:4]))
"#;

/// A child process killed when dropped.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        if let Err(e) = self.0.kill() {
            eprintln!("cannot stop a child of the OPC UA section: {e}");
        }
        if let Err(e) = self.0.wait() {
            eprintln!("cannot reap a child of the OPC UA section: {e}");
        }
    }
}

fn python() -> Option<PathBuf> {
    let path = std::env::var_os("HOLARCHY_OPCUA_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            holarchy_tests::workspace_root()
                .join("target")
                .join("opcua-venv")
                .join("bin")
                .join("python")
        });
    path.exists().then_some(path)
}

fn epoch_ms() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64() * 1000.0)
        .unwrap_or(0.0)
}

pub async fn section(run: &mut Run) -> Result<()> {
    let Some(python) = python() else {
        println!(
            "opcua: skipped (no Python venv with asyncua: python3 -m venv target/opcua-venv && target/opcua-venv/bin/pip install asyncua==2.1.0)"
        );
        return Ok(());
    };
    let dir = run.dir.join("opcua");
    std::fs::create_dir_all(&dir)?;
    let cell = &run.cell;
    let name = "robot-opcua";
    let sim = Sim::start(&dir, "opcua-sim", "127.0.0.1:0", &[])?;
    let config = resource_config(&dir, name, 5000)?;
    let _robot = cell
        .start_free_resource(&dir, &config, &sim.address, &[])
        .await?;
    let (server, listen) = start_the_server(&dir, cell).await?;
    let script = dir.join("subscribe.py");
    std::fs::write(&script, CLIENT)?;
    let mut client = Killed(
        Command::new(&python)
            .arg(&script)
            .args([&format!("opc.tcp://{listen}/"), cell.keys.cell(), name])
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(dir.join("client.stderr"))?)
            .spawn()
            .context("cannot start the asyncua client")?,
    );
    // The client's lines, read on a thread of their own.
    let (lines_tx, lines) = mpsc::channel::<String>();
    let stdout = client.0.stdout.take().expect("piped");
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            if lines_tx.send(line).is_err() {
                return;
            }
        }
    });
    let latency = changes_seen(cell, name, &lines).await?;
    let status = cell_status_times(cell)?;
    drop(client);
    drop(server);
    std::io::stdout().flush()?;
    run.table.add(
        "OPC UA: a state change seen by a subscriber",
        format!(
            "p50 {:.1} ms, p90 {:.1} ms, max {:.1} ms ({} changes)",
            latency.pct(0.5) / 1e3,
            latency.pct(0.9) / 1e3,
            latency.pct(1.0) / 1e3,
            2 * CHANGES
        ),
        format!(
            "target 100 ms; cell status takes {:.0} ms (p50 of 5)",
            status.pct(0.5) / 1e3
        ),
        json!({
            "latency": latency.json(),
            "cell_status": status.json(),
            "publishing_interval_ms": 20,
        }),
    );
    Ok(())
}

/// `cell opcua` on a free port of loopback, once it listens; the process and where.
async fn start_the_server(
    dir: &std::path::Path,
    cell: &holarchy_tests::Cell,
) -> Result<(Killed, String)> {
    let port = holarchy_tests::free_port();
    let listen = format!("127.0.0.1:{port}");
    let server = Killed(
        Command::new(holarchy_tests::bin("cell"))
            .args(["opcua", "--cell", cell.keys.cell(), "--connect"])
            .arg(&cell.endpoint)
            .args(["--listen", &listen])
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.join("opcua.stderr"))?)
            .spawn()
            .context("cannot start cell opcua")?,
    );
    let deadline = Instant::now() + Duration::from_secs(20);
    while std::net::TcpStream::connect(&listen).is_err() {
        if Instant::now() > deadline {
            bail!("cell opcua did not listen on {listen} within 20 s");
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    Ok((server, listen))
}

/// Holds and unholds the resource [`CHANGES`] times each; for each change, from its
/// publication arriving here to the client's notification of it.
async fn changes_seen(
    cell: &holarchy_tests::Cell,
    name: &str,
    lines: &mpsc::Receiver<String>,
) -> Result<Latency> {
    let next_line = |within: Duration| {
        lines
            .recv_timeout(within)
            .map_err(|_| anyhow!("the asyncua client said nothing within {within:?}"))
    };
    while next_line(Duration::from_secs(20))? != "ready" {}
    // Its first notification is the value as it is (6, Execute).
    let _initial = next_line(Duration::from_secs(5))?;
    // The holon's publications, and when each arrived here.
    let publications = cell
        .session
        .declare_subscriber(cell.keys.state(&schemas::HolonId::resource(name)?))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut samples = Vec::new();
    let started = Instant::now();
    for i in 0..2 * CHANGES {
        let (command, state) = if i % 2 == 0 {
            ("hold", 11)
        } else {
            ("unhold", 6)
        };
        cell.packml(name, command).await?;
        // The publication that says so, and when it arrived.
        let published = loop {
            let sample = tokio::time::timeout(Duration::from_secs(5), publications.recv_async())
                .await
                .map_err(|_| anyhow!("no state publication within 5 s after {command}"))?
                .map_err(|e| anyhow!("{e}"))?;
            let arrived = epoch_ms();
            let snapshot: serde_json::Value = serde_json::from_slice(&sample.payload().to_bytes())?;
            if snapshot["packml"]["state_number"] == state {
                break arrived;
            }
        };
        // The client's notification of it.
        let seen = loop {
            let line = next_line(Duration::from_secs(5))?;
            let mut parts = line.split_whitespace();
            let (Some(at), Some(value)) = (parts.next(), parts.next()) else {
                continue;
            };
            if value == state.to_string() {
                break at.parse::<f64>()?;
            }
        };
        samples.push(Duration::from_secs_f64(
            ((seen - published).max(0.0)) / 1000.0,
        ));
    }
    let total = started.elapsed();
    let latency = Latency::new(samples, total);
    Ok(latency)
}

/// Beside it: `cell status`, a process that joins the cell and asks, 5 times.
fn cell_status_times(cell: &holarchy_tests::Cell) -> Result<Latency> {
    let mut status_times = Vec::new();
    for _ in 0..5 {
        let t = Instant::now();
        let output = Command::new(holarchy_tests::bin("cell"))
            .args(["status", "--cell", cell.keys.cell(), "--connect"])
            .arg(&cell.endpoint)
            .output()?;
        if !output.status.success() {
            bail!(
                "cell status failed: {}",
                String::from_utf8_lossy(&output.stderr)
            );
        }
        status_times.push(t.elapsed());
    }
    let status = Latency::new(status_times, Duration::ZERO);
    Ok(status)
}

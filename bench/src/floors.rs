//! The floors every figure is set against: raw TCP, raw zenoh `get`, a journal commit and
//! the controller's; then the simulator and `robot1` the sections share.

use std::path::Path;
use std::time::Instant;

use anyhow::{anyhow, Result};
use holarchy_tests::{pick_n_place, resource_config, Sim};
use schemas::{CellKeys, HolonId, MessageType};
use serde_json::json;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

use crate::cells::{get_once, router};
use crate::controller;
use crate::echo::{spawn_helper, ECHO_KEY};
use crate::run::{Ours, Run, Table};
use crate::stats::Latency;

/// The baselines: raw TCP, raw zenoh `get`, a controller command, a journal commit;
/// then starts the simulator and `robot1` the sections share.
pub async fn floors(dir: &Path, samples: usize) -> Result<Run> {
    let mut table = Table {
        rows: Vec::new(),
        json: serde_json::Map::new(),
    };
    println!("{:<46} {:<40} BASELINE (same run)", "FIGURE", "VALUE");
    let cell = router("bench", None).await?;
    let service_size = pick_n_place(&cell.keys, MessageType::BookingReq, "bench", "bench/1/1")
        .to_json()
        .len();

    // Floors: raw TCP and raw zenoh round trips, a Service-sized payload.
    let (mut tcp_child, line) = spawn_helper(&["echo-tcp"])?;
    let address = line
        .strip_prefix("listening on ")
        .ok_or_else(|| anyhow!("echo-tcp: {line}"))?
        .to_string();
    let mut socket = tokio::net::TcpStream::connect(&address).await?;
    socket.set_nodelay(true)?;
    let payload = vec![b'x'; service_size];
    let mut buf = vec![0u8; service_size];
    let mut times = Vec::with_capacity(samples);
    let started = Instant::now();
    for _ in 0..samples {
        let t = Instant::now();
        socket.write_all(&payload).await?;
        socket.read_exact(&mut buf).await?;
        times.push(t.elapsed());
    }
    let tcp = Latency::new(times, started.elapsed());
    let _ = tcp_child.kill();
    table.add(
        "floor: TCP round trip (loopback)",
        tcp.p50_p99(),
        format!("{service_size} B payload"),
        tcp.json(),
    );

    // The echo helper stays up for the whole run: booking series interleave with it.
    let (echo, _) = spawn_helper(&["echo-zenoh", "--connect", &cell.endpoint, "--key", ECHO_KEY])?;
    cell.wait_token(&format!("{ECHO_KEY}/alive")).await?;
    for _ in 0..100 {
        get_once(&cell, ECHO_KEY, payload.clone()).await?;
    }
    let mut times = Vec::with_capacity(samples);
    let started = Instant::now();
    for _ in 0..samples {
        let t = Instant::now();
        get_once(&cell, ECHO_KEY, payload.clone()).await?;
        times.push(t.elapsed());
    }
    let floor = Latency::new(times, started.elapsed());
    table.add(
        "floor: zenoh get round trip (2 processes)",
        floor.p50_p99(),
        format!("TCP p50 {:.0} us", tcp.pct(0.5)),
        floor.json(),
    );

    // A journal commit of a booking-sized record, both durabilities, on the disk the
    // holons write to: what a journalled answer cannot go below.
    let journal_floor = (
        journal_commits(dir, holon::journal::Durability::PowerLoss, samples)?,
        journal_commits(dir, holon::journal::Durability::ProcessCrash, samples)?,
    );
    table.add(
        "floor: journal commit (power_loss | process_crash)",
        format!(
            "p50 {:.0} | {:.0} us, p99 {:.0} | {:.0} us",
            journal_floor.0.pct(0.5),
            journal_floor.1.pct(0.5),
            journal_floor.0.pct(0.99),
            journal_floor.1.pct(0.99)
        ),
        format!("{service_size} B record, SQLite WAL"),
        json!({"power_loss": journal_floor.0.json(), "process_crash": journal_floor.1.json()}),
    );

    let sim = Sim::start(dir, "sim1", "127.0.0.1:0", &[])?;
    controller::section(&mut table, dir, &sim.address, samples, &tcp).await?;

    let config = resource_config(dir, "robot1", 5000)?;
    let launched = Instant::now();
    let robot1 = holarchy_tests::start_node(
        dir,
        &config,
        "bench",
        &cell.endpoint,
        &sim.address,
        &["--data-dir", dir.join("data").to_str().unwrap()],
    )?;
    cell.wait_alive(&HolonId::resource("robot1")?).await?;
    let robot1_ready = launched.elapsed();
    cell.wait_state("robot1", "free", |s| s["state"] == "free")
        .await?;
    Ok(Run {
        dir: dir.to_path_buf(),
        cell,
        table,
        floor,
        journal_floor,
        sim,
        robot1,
        robot1_ready,
        samples,
        echo,
        ours: Ours::default(),
    })
}

/// `samples` commits of one booking-sized record through the holons' journal.
fn journal_commits(
    dir: &Path,
    durability: holon::journal::Durability,
    samples: usize,
) -> Result<Latency> {
    let journal = holon::journal::Journal::open(
        &dir.join("journal-floor"),
        &format!("{durability:?}.sqlite"),
        durability,
    )?;
    let keys = CellKeys::new("bench")?;
    let mut times = Vec::with_capacity(samples);
    let started = Instant::now();
    for i in 0..samples {
        // A record that differs from the one it replaces: SQLite writes nothing (and
        // syncs nothing) when an update leaves the page as it was.
        let record = pick_n_place(
            &keys,
            MessageType::BookingReq,
            "bench",
            &format!("bench/{i}/1"),
        );
        let t = Instant::now();
        journal.put("booking", &format!("b{}", i % 64), &record)?;
        times.push(t.elapsed());
    }
    Ok(Latency::new(times, started.elapsed()))
}

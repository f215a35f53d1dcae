//! The cells and holons the sections start (a router, robots, the product and the
//! order-node), one round trip through a cell, and failure detection of a holon.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use holarchy_tests::{free_port, resource_config, Cell, Process, Sim};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use schemas::{CellKeys, HolonId};

pub async fn router(cell: &str, lease_ms: Option<u64>) -> Result<Cell> {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Router,
        listen: vec![endpoint.clone()],
        lease_ms,
        ..Default::default()
    };
    open_cell(&settings, "router.local", cell, endpoint).await
}

/// A session opened with `settings` as `identity`, seen as a [`Cell`] named `cell` whose
/// processes connect to `endpoint`.
pub async fn open_cell(
    settings: &holon::ZenohSettings,
    identity: &str,
    cell: &str,
    endpoint: String,
) -> Result<Cell> {
    let session = settings
        .open(identity, Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    Ok(Cell {
        session,
        keys: CellKeys::new(cell)?,
        endpoint,
    })
}

/// One round trip: the reply's payload (an error reply is an error).
pub async fn get_once(cell: &Cell, key: &str, payload: Vec<u8>) -> Result<Vec<u8>> {
    cell.ask(key, payload)
        .await?
        .map_err(|_| anyhow!("error reply from {key}"))
}

/// The product `part` and the order-node `orders1` of `config` (its journal in
/// `DIR/data`), both in the cell.
pub async fn start_product_and_orders(
    dir: &Path,
    cell: &Cell,
    config: &Path,
) -> Result<(Process, Process)> {
    cell.start_part_and_orders(dir, config, &dir.join("data"))
        .await
}

pub async fn detect_kill(
    cell: &Cell,
    process: &mut Process,
    holon: &HolonId,
    signal: Signal,
) -> Result<Duration> {
    let subscriber = cell
        .session
        .liveliness()
        .declare_subscriber(cell.keys.alive(holon))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let t = Instant::now();
    kill(Pid::from_raw(process.pid()), signal)?;
    loop {
        let sample = tokio::time::timeout(Duration::from_secs(30), subscriber.recv_async())
            .await
            .map_err(|_| anyhow!("{holon} never vanished"))?
            .map_err(|e| anyhow!("{e}"))?;
        if sample.kind() == zenoh::sample::SampleKind::Delete {
            let elapsed = t.elapsed();
            if signal == Signal::SIGKILL {
                process.kill();
            }
            return Ok(elapsed);
        }
    }
}

/// Starts `robot0`..`robot{n-1}` on `cell`, each with its own controller simulator
/// (started with `sim_flags`), and waits until each is alive and free.
pub async fn start_robots(
    cell: &Cell,
    dir: &Path,
    n: usize,
    sim_flags: &[&str],
) -> Result<Vec<(Sim, Process)>> {
    let mut robots = Vec::new();
    for i in 0..n {
        let name = format!("robot{i}");
        let sim = Sim::start(dir, &format!("{name}-sim"), "127.0.0.1:0", sim_flags)?;
        let config = resource_config(dir, &name, 5000)?;
        let node = holarchy_tests::start_node(
            dir,
            &config,
            cell.keys.cell(),
            &cell.endpoint,
            &sim.address,
            &[],
        )?;
        cell.wait_alive(&HolonId::resource(&name)?).await?;
        cell.wait_state(&name, "free", |s| s["state"] == "free")
            .await?;
        robots.push((sim, node));
    }
    Ok(robots)
}

/// Every order-node's counts of its orders, summed (a listing page of none from each,
/// `schemas::listing`).
pub async fn order_counts(cell: &Cell) -> Result<schemas::OrderCounts> {
    let request = schemas::OrderListRequest::first(schemas::OrderFilter::All, 0);
    let replies = cell
        .session
        .get(cell.keys.node_listing_all())
        .payload(serde_json::to_vec(&request)?)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut counts = schemas::OrderCounts::default();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            let page: schemas::OrderPage = serde_json::from_slice(&sample.payload().to_bytes())?;
            counts.merge(&page.counts);
        }
    }
    Ok(counts)
}

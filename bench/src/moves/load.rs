//! Many transporters and many parts in flight: waves of orders submitted at once, each
//! part moved in by its station's transfer, worked, moved out; every process's CPU and
//! memory while they are in flight, and the memory again once they are done, wave after
//! wave (memory should be set by the parts in flight, not by the parts done).

use std::collections::{BTreeMap, HashSet};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use holarchy_tests::Cell;
use schemas::{OrderSnapshot, OrderStatus};
use serde::Serialize;

use crate::process::{cpu_time, status_field};

/// How often memory is sampled while a wave runs.
const SAMPLE_EVERY: Duration = Duration::from_millis(500);
/// How long a wave may take before the run fails.
const WAVE_WITHIN: Duration = Duration::from_secs(600);
/// The pause after a wave before its memory is read (the node settles).
const SETTLE: Duration = Duration::from_secs(2);

/// One process's memory at a moment, in KiB.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct Memory {
    /// Resident (`VmRSS`): the binary's shared pages included.
    pub rss_kib: u64,
    /// Its own memory (`RssAnon`): what grows with what it holds.
    pub anon_kib: u64,
}

/// One process's figures over the waves.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ProcessLoad {
    /// Before the first wave.
    pub idle: Memory,
    /// The highest while each wave's parts were in flight.
    pub peak_in_flight: Vec<Memory>,
    /// After each wave was done (and the node settled).
    pub after_done: Vec<Memory>,
    /// Its share of a core over each wave, from submission to the last order done.
    pub cpu_share: Vec<f64>,
}

/// What the waves measured.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Load {
    /// Every process by name (`orders1`, `plant-sim`, the product, the resources).
    pub processes: BTreeMap<String, ProcessLoad>,
    /// Each wave's time from submission to the last order done.
    pub wave_s: Vec<f64>,
    /// Orders per wave.
    pub orders: u32,
}

fn memory(pid: i32) -> Memory {
    Memory {
        rss_kib: status_field(pid, "VmRSS:").unwrap_or(0),
        anon_kib: status_field(pid, "RssAnon:").unwrap_or(0),
    }
}

/// The larger of two readings, field by field.
fn peak(a: Memory, b: Memory) -> Memory {
    Memory {
        rss_kib: a.rss_kib.max(b.rss_kib),
        anon_kib: a.anon_kib.max(b.anon_kib),
    }
}

/// `waves` waves of `orders` orders of `product`, submitted at once; `processes` the
/// cell's processes by name and pid.
pub async fn waves(
    cell: &Cell,
    processes: &[(String, i32)],
    product: &str,
    orders: u32,
    waves: usize,
) -> Result<Load> {
    let states = cell
        .session
        .declare_subscriber(cell.keys.order_states())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut load = Load {
        orders,
        ..Load::default()
    };
    for (name, pid) in processes {
        load.processes.insert(
            name.clone(),
            ProcessLoad {
                idle: memory(*pid),
                ..ProcessLoad::default()
            },
        );
    }
    for wave in 0..waves {
        let cpu_before: Vec<Duration> = processes
            .iter()
            .map(|(_, pid)| cpu_time(*pid).unwrap_or_default())
            .collect();
        let mut peaks: Vec<Memory> = processes.iter().map(|(_, pid)| memory(*pid)).collect();
        let t = Instant::now();
        let mut running: HashSet<String> =
            cell.submit(product, orders).await?.into_iter().collect();
        let mut next_sample = Instant::now();
        while !running.is_empty() {
            if Instant::now() >= next_sample {
                for ((_, pid), top) in processes.iter().zip(peaks.iter_mut()) {
                    *top = peak(*top, memory(*pid));
                }
                next_sample += SAMPLE_EVERY;
            }
            if t.elapsed() > WAVE_WITHIN {
                bail!(
                    "wave {wave}: {} of {orders} orders still running after {WAVE_WITHIN:?}",
                    running.len()
                );
            }
            let Ok(sample) = tokio::time::timeout(SAMPLE_EVERY, states.recv_async()).await else {
                continue;
            };
            let sample = sample.map_err(|e| anyhow!("{e}"))?;
            let snapshot: OrderSnapshot = serde_json::from_slice(&sample.payload().to_bytes())?;
            match snapshot.status {
                OrderStatus::Running => {}
                OrderStatus::Done => {
                    running.remove(snapshot.holon.name());
                }
                other if running.contains(snapshot.holon.name()) => {
                    bail!("{} ended {other:?}: {:?}", snapshot.holon, snapshot.reason)
                }
                _ => {}
            }
        }
        let took = t.elapsed();
        load.wave_s.push(took.as_secs_f64());
        let cpu_after: Vec<Duration> = processes
            .iter()
            .map(|(_, pid)| cpu_time(*pid).unwrap_or_default())
            .collect();
        tokio::time::sleep(SETTLE).await;
        for (i, (name, pid)) in processes.iter().enumerate() {
            let figures = load.processes.get_mut(name).expect("inserted above");
            figures.peak_in_flight.push(peaks[i]);
            figures.after_done.push(memory(*pid));
            figures.cpu_share.push(
                cpu_after[i].saturating_sub(cpu_before[i]).as_secs_f64() / took.as_secs_f64(),
            );
        }
        println!(
            "  wave {}: {orders} orders done in {:.1} s",
            wave + 1,
            took.as_secs_f64()
        );
    }
    Ok(load)
}

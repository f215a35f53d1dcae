//! Scale and the topology it needs. Holons are clients of their host's router (the
//! default of `cell up`, `cell demo` and deploy/): one link per process, so memory and
//! sockets stay flat as the cell grows, for one router hop more between two holons.
//!
//! - `scale_out`: N resource holon processes on this host, started together like `cell
//!   up` starts them: when the last is visible to an order (a client session of the
//!   router, as an order-node is), a proposal round with all N replying, and each
//!   process's memory and CPU to start.
//! - `router_hop`: what the hop costs: a booking from a client of the router (the path
//!   between an order-node and a resource in a cell) beside a booking from the router's
//!   own session (one link, the path of the other booking figures), each with its own
//!   interleaved zenoh floor.

use std::collections::HashSet;
use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use holarchy_tests::{pick_n_place, resource_config, Cell, Sim};
use schemas::MessageType;
use serde_json::json;

use crate::booking::booking_series;
use crate::cells::{open_cell, router};
use crate::process::{footprint, on_cpu, proportional};
use crate::run::Run;
use crate::stats::Latency;

/// Controller simulators the scaled-out holons share.
const SIMULATORS: usize = 4;
/// How long the last holon may take to become visible before the run fails.
const VISIBLE_WITHIN: Duration = Duration::from_secs(120);
/// Proposal rounds timed once every holon offers.
const ROUNDS: usize = 50;

pub async fn section(run: &mut Run, holons: usize) -> Result<()> {
    router_hop(run).await?;
    let scaled = scale_out(&run.dir, holons).await?;
    let per_holon_mib = scaled.rss_kib.iter().sum::<u64>() as f64 / 1024.0 / holons as f64;
    let pss_mib = scaled.pss_kib.iter().sum::<u64>() as f64 / 1024.0 / holons as f64;
    let max_mib = scaled.rss_kib.iter().max().copied().unwrap_or(0) as f64 / 1024.0;
    run.table.add(
        &format!("scale: {holons} resource holons, all visible to an order"),
        format!(
            "{:.2} s after the last started",
            scaled.visible_after_last.as_secs_f64()
        ),
        format!(
            "spawning all took {:.2} s; clients of one router",
            scaled.spawned.as_secs_f64()
        ),
        json!({
            "holons": holons,
            "spawn_s": scaled.spawned.as_secs_f64(),
            "all_visible_after_last_spawn_s": scaled.visible_after_last.as_secs_f64(),
            "topology": "clients of the host's router",
        }),
    );
    run.table.add(
        &format!("scale: {holons} resource holons, memory and start"),
        format!("{per_holon_mib:.1} MiB resident each (max {max_mib:.1})"),
        format!(
            "PSS {pss_mib:.1} MiB each (code shared); CPU to start {:.1} ms each",
            scaled.start_cpu.as_secs_f64() * 1e3 / holons as f64
        ),
        json!({
            "holons": holons,
            "rss_mean_mib": per_holon_mib,
            "pss_mean_mib": pss_mib,
            "rss_max_mib": max_mib,
            "start_cpu_ms_each": scaled.start_cpu.as_secs_f64() * 1e3 / holons as f64,
        }),
    );
    run.table.add(
        &format!("scale: proposal round with {holons} repliers"),
        format!(
            "p50 {:.1} ms, p99 {:.1} ms",
            scaled.round.pct(0.5) / 1e3,
            scaled.round.pct(0.99) / 1e3
        ),
        format!(
            "{} of {ROUNDS} rounds complete; {:.0}x zenoh floor p50",
            scaled.round.samples.len(),
            run.ratio(&scaled.round)
        ),
        scaled.round.json(),
    );
    Ok(())
}

/// A booking across the router (client -> router -> robot1) beside a booking on one
/// link (router -> robot1), in the same run.
async fn router_hop(run: &mut Run) -> Result<()> {
    let order_side = client_of(&run.cell).await?;
    let direct = booking_series(&run.cell, "robot1", run.samples / 2).await?;
    let across = booking_series(&order_side, "robot1", run.samples / 2).await?;
    run.table.add(
        "topology: booking across the router (2 links)",
        across.booking.p50_p99(),
        format!(
            "on one link p50 {:.0} us; floors {:.0} | {:.0} us",
            direct.booking.pct(0.5),
            across.floor.pct(0.5),
            direct.floor.pct(0.5)
        ),
        json!({
            "across_router": {"booking": across.booking.json(), "floor": across.floor.json()},
            "one_link": {"booking": direct.booking.json(), "floor": direct.floor.json()},
        }),
    );
    Ok(())
}

/// A client session of `cell`'s router, as an order-node is: what it sees and asks
/// crosses the router.
async fn client_of(cell: &Cell) -> Result<Cell> {
    let settings = holon::ZenohSettings {
        connect: vec![cell.endpoint.clone()],
        ..Default::default()
    };
    open_cell(
        &settings,
        "order-node.bench",
        cell.keys.cell(),
        cell.endpoint.clone(),
    )
    .await
}

/// What `scale_out` measured.
struct ScaledOut {
    /// From the first spawn to the last.
    spawned: Duration,
    /// From the last spawn until the order side saw every holon's token.
    visible_after_last: Duration,
    /// A proposal round with every holon replying.
    round: Latency,
    /// Each holon's resident memory (KiB) once all offered.
    rss_kib: Vec<u64>,
    /// Each holon's proportional memory (KiB): the binary's pages shared out.
    pss_kib: Vec<u64>,
    /// CPU time all holons used until every one was visible.
    start_cpu: Duration,
}

/// Starts `n` resource holons (sharing the simulators), clients of a fresh router, and
/// watches them from a client of that router.
async fn scale_out(dir: &Path, n: usize) -> Result<ScaledOut> {
    let cell = router("bench-scale", None).await?;
    let order_side = client_of(&cell).await?;
    let dir = dir.join("scale");
    std::fs::create_dir_all(&dir)?;
    let sims: Vec<Sim> = (0..SIMULATORS)
        .map(|i| Sim::start(&dir, &format!("sim{i}"), "127.0.0.1:0", &[]))
        .collect::<Result<_>>()?;
    let subscriber = order_side
        .session
        .liveliness()
        .declare_subscriber(order_side.keys.alive_kind(schemas::HolonKind::Resource))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let configs = (0..n)
        .map(|i| resource_config(&dir, &format!("r{i}"), 5000))
        .collect::<Result<Vec<_>>>()?;
    let first = Instant::now();
    let mut nodes = Vec::new();
    for (i, config) in configs.iter().enumerate() {
        nodes.push(holarchy_tests::start_node(
            &dir,
            config,
            "bench-scale",
            &cell.endpoint,
            &sims[i % SIMULATORS].address,
            &[],
        )?);
    }
    let last = Instant::now();
    let mut seen = HashSet::new();
    while seen.len() < n {
        let sample = tokio::time::timeout(VISIBLE_WITHIN, subscriber.recv_async())
            .await
            .map_err(|_| {
                anyhow!(
                    "only {} of {n} holons visible after {VISIBLE_WITHIN:?}",
                    seen.len()
                )
            })?
            .map_err(|e| anyhow!("{e}"))?;
        seen.insert(sample.key_expr().to_string());
    }
    let visible_after_last = last.elapsed();
    let start_cpu = nodes.iter().filter_map(|p| on_cpu(p.pid()).ok()).sum();
    // Wait until all offer (their controllers ready), then time proposal rounds.
    let ask = pick_n_place(&cell.keys, MessageType::ProposalReq, "bench", "scale/1/1");
    order_side.wait_proposals(&ask, n).await?;
    let mut times = Vec::new();
    let started = Instant::now();
    for _ in 0..ROUNDS {
        let t = Instant::now();
        let count = order_side.proposals(&ask).await?.len();
        if count == n {
            times.push(t.elapsed());
        }
    }
    let round = Latency::new(times, started.elapsed());
    let rss_kib = nodes
        .iter()
        .filter_map(|p| footprint(p.pid()).ok())
        .map(|(rss, _)| rss)
        .collect();
    let pss_kib = nodes
        .iter()
        .filter_map(|p| proportional(p.pid()).ok())
        .collect();
    drop(nodes);
    drop(sims);
    Ok(ScaledOut {
        spawned: last - first,
        visible_after_last,
        round,
        rss_kib,
        pss_kib,
        start_cpu,
    })
}

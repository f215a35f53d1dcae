//! The holon section: an idle resource holon's footprint and start, hot-add and
//! SIGKILL detection of fresh holons.

use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use holarchy_tests::{pick_n_place, resource_config};
use nix::sys::signal::Signal;
use schemas::{HolonId, MessageType, Service};
use serde_json::json;

use crate::cells::{detect_kill, get_once};
use crate::process::{footprint, status_field};
use crate::run::Run;
use crate::stats::Latency;

/// Footprint and start of `robot1`; hot-add and SIGKILL detection of fresh holons.
pub async fn section(run: &mut Run) -> Result<()> {
    let (rss, threads) = footprint(run.robot1.pid())?;
    let anonymous = status_field(run.robot1.pid(), "RssAnon:")?;
    run.table.add(
        "footprint: idle resource holon",
        format!("{:.1} MiB resident, {threads} threads", rss as f64 / 1024.0),
        format!(
            "{:.1} MiB of it its own (anonymous); the rest the binary's pages",
            anonymous as f64 / 1024.0
        ),
        json!({"rss_kib": rss, "anonymous_kib": anonymous, "threads": threads}),
    );
    run.table.add(
        "start to ready: resource holon (token visible)",
        format!("{:.1} ms", run.robot1_ready.as_secs_f64() * 1e3),
        "-".into(),
        json!({"ms": run.robot1_ready.as_secs_f64() * 1e3}),
    );

    // Hot-add: from spawning a resource process to its first accepted booking; then
    // failure detection: SIGKILL to its token vanishing.
    let cell = &run.cell;
    let (mut hot, mut killed) = (Vec::new(), Vec::new());
    for i in 0..5 {
        let name = format!("hot{i}");
        let config = resource_config(&run.dir, &name, 5000)?;
        let t = Instant::now();
        let mut process = holarchy_tests::start_node(
            &run.dir,
            &config,
            "bench",
            &cell.endpoint,
            &run.sim.address,
            &[],
        )?;
        let key = cell.keys.service(&name);
        loop {
            let book = pick_n_place(
                &cell.keys,
                MessageType::BookingReq,
                "bench",
                &format!("hot/{i}/1"),
            );
            if let Ok(reply) = get_once(cell, &key, book.to_json()).await {
                if Service::from_json(&reply)?.result == Some(true) {
                    break;
                }
            }
            if t.elapsed() > Duration::from_secs(20) {
                bail!("{name} never accepted a booking");
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        hot.push(t.elapsed());
        killed.push(
            detect_kill(
                cell,
                &mut process,
                &HolonId::resource(&name)?,
                Signal::SIGKILL,
            )
            .await?,
        );
    }
    let hot = Latency::new(hot, Duration::from_secs(1));
    let killed = Latency::new(killed, Duration::from_secs(1));
    run.table.add(
        "hot-add: spawn to first accepted booking",
        format!("median {:.1} ms (5 runs)", hot.pct(0.5) / 1e3),
        "-".into(),
        hot.json(),
    );
    run.table.add(
        "failure detection: SIGKILL to token gone",
        format!("median {:.1} ms (5 runs)", killed.pct(0.5) / 1e3),
        "-".into(),
        killed.json(),
    );
    Ok(())
}

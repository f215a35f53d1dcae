//! The rebook section: from SIGKILL of a booked resource to the order's booking
//! elsewhere, through a real order-node.

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use holarchy_tests::{pick_n_place, resource_config, Sim};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use schemas::{HolonId, MessageType, Service};

use crate::cells::{get_once, router, start_product_and_orders};
use crate::run::Run;
use crate::stats::Latency;

/// From SIGKILL of the resource an order is booked on (waiting behind another job) to
/// that order's booking on another resource, through a real order-node: 5 runs.
pub async fn section(run: &mut Run) -> Result<()> {
    let cell = router("bench-rebook", None).await?;
    let dir = run.dir.join("rebook");
    std::fs::create_dir_all(&dir)?;
    // `held` robots run one job for as long as the run lasts.
    let slow = Sim::start(&dir, "slow", "127.0.0.1:0", &["--delay-ms", "600000"])?;
    let (_product, _orders) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;
    let mut times = Vec::new();
    for i in 0..5 {
        let held = format!("held{i}");
        let config = resource_config(&dir, &held, 600_000)?;
        let mut held_node = holarchy_tests::start_node(
            &dir,
            &config,
            "bench-rebook",
            &cell.endpoint,
            &slow.address,
            &[],
        )?;
        cell.wait_state(&held, "free", |s| s["state"] == "free")
            .await?;
        // Keep it busy with a job of ours, then let an order book it (behind that job).
        let conversation = format!("held/{i}/1");
        let key = cell.keys.service(&held);
        for kind in [MessageType::BookingReq, MessageType::Start] {
            let message = pick_n_place(&cell.keys, kind, "bench", &conversation);
            let answer = Service::from_json(&get_once(&cell, &key, message.to_json()).await?)?;
            if answer.result != Some(true) {
                bail!("{held} refused {kind}: {answer:?}");
            }
        }
        cell.submit("part", 1).await?;
        cell.wait_state(&held, "an order's booking", |s| {
            s["agenda"].as_array().is_some_and(|a| a.len() == 1)
        })
        .await?;
        // The spare comes up; the order stays where it is booked.
        let spare = format!("spare{i}");
        let config = resource_config(&dir, &spare, 5000)?;
        let mut spare_node = holarchy_tests::start_node(
            &dir,
            &config,
            "bench-rebook",
            &cell.endpoint,
            &run.sim.address,
            &[],
        )?;
        cell.wait_state(&spare, "free", |s| s["state"] == "free")
            .await?;
        let states = cell
            .session
            .declare_subscriber(cell.keys.state(&HolonId::resource(&spare)?))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let t = Instant::now();
        kill(Pid::from_raw(held_node.pid()), Signal::SIGKILL)?;
        loop {
            let sample = tokio::time::timeout(Duration::from_secs(30), states.recv_async())
                .await
                .map_err(|_| anyhow!("the order was not rebooked on {spare} within 30 s"))?
                .map_err(|e| anyhow!("{e}"))?;
            let snapshot: schemas::ResourceSnapshot =
                serde_json::from_slice(&sample.payload().to_bytes())?;
            if !snapshot.agenda.is_empty() || snapshot.current.is_some() {
                times.push(t.elapsed());
                break;
            }
        }
        held_node.kill();
        // Let the order finish on the spare before the next run.
        cell.wait_state(&spare, "idle", |s| {
            s["state"] == "free"
                && s["undelivered"] == 0
                && s["agenda"].as_array().is_some_and(|a| a.is_empty())
        })
        .await?;
        spare_node.kill();
    }
    let times = Latency::new(times, Duration::from_secs(1));
    run.table.add(
        "rebooking: SIGKILL of the booked resource to the booking elsewhere",
        format!(
            "median {:.1} ms, max {:.1} ms (5 runs)",
            times.pct(0.5) / 1e3,
            times.pct(1.0) / 1e3
        ),
        "through order-node; a started step waits vanished_grace_ms first".into(),
        times.json(),
    );
    Ok(())
}

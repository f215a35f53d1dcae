//! The soak: a cell that runs for a long time as a plant does, and whether its processes'
//! memory stays flat (docs/reliability.md, "Memory while running").
//!
//! Two robots (simulators at `--delay-ms 5`), the product `part` and the order-node
//! `orders1` with its journal on disk; waves of orders submitted every few seconds, and
//! an operator's screen listing the orders (`cell orders`) every half second. Every
//! 10 s each process's resident memory is sampled, and the orders finished so far (the
//! node's counts, a listing page of none). Writes the samples as CSV and a summary as
//! JSON; prints each process's memory at 1, 2, 5, 10, 20 and 30 minutes and its growth
//! per 1,000 finished orders after the first `settle` minutes (a least-squares slope).

use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use serde_json::json;

use crate::cells::{order_counts, router, start_product_and_orders, start_robots};
use crate::process::status_field;

/// How often memory is sampled.
const SAMPLE_EVERY: Duration = Duration::from_secs(10);

/// What the soak runs.
pub struct Soak {
    /// How long orders are submitted.
    pub minutes: u64,
    /// Orders per wave.
    pub wave: u32,
    /// Seconds between waves.
    pub every_s: u64,
    /// Minutes after which the memory is expected flat (the slope is fitted after them).
    pub settle: u64,
}

/// One sample: seconds since the start, orders finished, and each process's RSS (KiB).
struct Sample {
    t: f64,
    finished: u64,
    rss: Vec<u64>,
}

/// Least-squares slope of `y` over `x`.
fn slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    if n < 2.0 {
        return 0.0;
    }
    let (sx, sy) = points
        .iter()
        .fold((0.0, 0.0), |(sx, sy), (x, y)| (sx + x, sy + y));
    let (mx, my) = (sx / n, sy / n);
    let (num, den) = points.iter().fold((0.0, 0.0), |(num, den), (x, y)| {
        (num + (x - mx) * (y - my), den + (x - mx) * (x - mx))
    });
    if den == 0.0 {
        0.0
    } else {
        num / den
    }
}

pub async fn run(soak: &Soak, out: &Path) -> Result<()> {
    let dir = soak_dir()?;
    let cell = router("soak", None).await?;
    let robots = start_robots(&cell, &dir, 2, &["--delay-ms", "5"]).await?;
    let (product, node) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;
    let mut watched: Vec<(String, i32)> = vec![
        ("order-node".into(), node.pid()),
        ("product".into(), product.pid()),
    ];
    for (i, (_, robot)) in robots.iter().enumerate() {
        watched.push((format!("robot{i}"), robot.pid()));
    }
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (listings, incomplete) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let screen = operators_screen(&cell, stop.clone(), listings.clone(), incomplete.clone());
    let (samples, submitted) = waves(soak, &cell, &watched).await;
    let last = last_orders_finished(&cell).await?;
    stop.store(true, Ordering::SeqCst);
    screen.await.map_err(|e| anyhow!("{e}"))?;

    let csv_path = write_samples(out, &watched, &samples)?;
    let processes = per_process(soak, &watched, &samples);
    println!(
        "orders: {submitted} submitted, {} done, {} failed, {} scrapped, {} cancelled; {} listings, {} incomplete",
        last.done,
        last.failed,
        last.scrapped,
        last.cancelled,
        listings.load(Ordering::SeqCst),
        incomplete.load(Ordering::SeqCst)
    );
    let summary = json!({
        "minutes": soak.minutes,
        "wave": soak.wave,
        "every_s": soak.every_s,
        "submitted": submitted,
        "counts": last,
        "listings": listings.load(Ordering::SeqCst),
        "incomplete_listings": incomplete.load(Ordering::SeqCst),
        "processes": processes,
        "samples_csv": csv_path.display().to_string(),
    });
    std::fs::write(out, serde_json::to_string_pretty(&summary)?)?;
    println!("wrote {} and {}", out.display(), csv_path.display());
    drop((robots, product, node));
    Ok(())
}

/// The soak's directory: a temporary one, kept with `HOLARCHY_BENCH_KEEP`.
fn soak_dir() -> Result<std::path::PathBuf> {
    let dir = tempfile::Builder::new().prefix("holarchy-soak").tempdir()?;
    Ok(if std::env::var_os("HOLARCHY_BENCH_KEEP").is_some() {
        let kept = dir.keep();
        println!("keeping the soak's directory: {}", kept.display());
        kept
    } else {
        dir.path().to_path_buf()
    })
}

/// The operator's screen: `cell orders` every half second until `stop`, counting the
/// listings and the incomplete ones.
fn operators_screen(
    cell: &holarchy_tests::Cell,
    stop: Arc<std::sync::atomic::AtomicBool>,
    listings: Arc<AtomicU64>,
    incomplete: Arc<AtomicU64>,
) -> tokio::task::JoinHandle<()> {
    let (name, endpoint) = (cell.keys.cell().to_string(), cell.endpoint.clone());
    tokio::spawn(async move {
        while !stop.load(Ordering::SeqCst) {
            let began = Instant::now();
            let output = tokio::process::Command::new(holarchy_tests::bin("cell"))
                .args(["orders", "--cell", &name, "--connect", &endpoint])
                .output()
                .await;
            listings.fetch_add(1, Ordering::SeqCst);
            if !output.is_ok_and(|o| o.status.success()) {
                incomplete.fetch_add(1, Ordering::SeqCst);
            }
            tokio::time::sleep(Duration::from_millis(500).saturating_sub(began.elapsed())).await;
        }
    })
}

/// The waves of orders for the soak's minutes, and the watched processes' memory every
/// [`SAMPLE_EVERY`]; the samples and how many orders were submitted.
async fn waves(
    soak: &Soak,
    cell: &holarchy_tests::Cell,
    watched: &[(String, i32)],
) -> (Vec<Sample>, u64) {
    let started = Instant::now();
    let until = started + Duration::from_secs(soak.minutes * 60);
    let mut samples: Vec<Sample> = Vec::new();
    let mut submitted = 0u64;
    let mut next_wave = started;
    let mut next_sample = started;
    println!(
        "soak: waves of {} orders every {} s for {} min; memory every {SAMPLE_EVERY:?}",
        soak.wave, soak.every_s, soak.minutes
    );
    while Instant::now() < until {
        let now = Instant::now();
        if now >= next_wave {
            match cell.submit("part", soak.wave).await {
                Ok(orders) => submitted += orders.len() as u64,
                Err(e) => println!("a wave was refused: {e:#}"),
            }
            next_wave += Duration::from_secs(soak.every_s);
        }
        if now >= next_sample {
            let finished = order_counts(cell).await.map(|c| c.finished()).unwrap_or(0);
            let rss = watched
                .iter()
                .map(|(_, pid)| status_field(*pid, "VmRSS:").unwrap_or(0))
                .collect::<Vec<_>>();
            let t = started.elapsed().as_secs_f64();
            println!(
                "{:>6.0} s  {:>6} finished  {}",
                t,
                finished,
                watched
                    .iter()
                    .zip(&rss)
                    .map(|((name, _), kib)| format!("{name} {:.1} MiB", *kib as f64 / 1024.0))
                    .collect::<Vec<_>>()
                    .join("  ")
            );
            samples.push(Sample { t, finished, rss });
            next_sample += SAMPLE_EVERY;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    (samples, submitted)
}

/// The counts once no order runs (the last wave's orders finish), within 120 s.
async fn last_orders_finished(cell: &holarchy_tests::Cell) -> Result<schemas::OrderCounts> {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        let c = order_counts(cell).await?;
        if c.running == 0 {
            return Ok(c);
        }
        if Instant::now() > deadline {
            bail!(
                "{} orders still running 120 s after the last wave",
                c.running
            );
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
}

/// Writes the samples as CSV beside `out`; its path.
fn write_samples(
    out: &Path,
    watched: &[(String, i32)],
    samples: &[Sample],
) -> Result<std::path::PathBuf> {
    let mut csv = format!(
        "t_s,finished,{}\n",
        watched
            .iter()
            .map(|(n, _)| format!("{n}_rss_kib"))
            .collect::<Vec<_>>()
            .join(",")
    );
    for s in samples {
        csv.push_str(&format!(
            "{:.0},{},{}\n",
            s.t,
            s.finished,
            s.rss
                .iter()
                .map(u64::to_string)
                .collect::<Vec<_>>()
                .join(",")
        ));
    }
    let csv_path = out.with_extension("csv");
    std::fs::write(&csv_path, csv)?;
    Ok(csv_path)
}

/// Each watched process's memory at marked minutes and its growth per 1,000 finished
/// orders once settled, printed and as JSON.
fn per_process(
    soak: &Soak,
    watched: &[(String, i32)],
    samples: &[Sample],
) -> Vec<serde_json::Value> {
    let at_minute = |m: u64| {
        samples
            .iter()
            .find(|s| s.t >= (m * 60) as f64 - 5.0)
            .map(|s| s.rss.clone())
    };
    let mut processes = Vec::new();
    for (i, (name, _)) in watched.iter().enumerate() {
        let settled: Vec<(f64, f64)> = samples
            .iter()
            .filter(|s| s.t >= (soak.settle * 60) as f64)
            .map(|s| (s.finished as f64, s.rss[i] as f64))
            .collect();
        let per_thousand = slope(&settled) * 1000.0;
        let marks: Vec<(u64, f64)> = [1, 2, 5, 10, 20, 30, 60]
            .into_iter()
            .filter(|m| *m <= soak.minutes)
            .filter_map(|m| at_minute(m).map(|rss| (m, rss[i] as f64 / 1024.0)))
            .collect();
        println!(
            "{name}: {}; after minute {}: {per_thousand:+.1} KiB per 1,000 finished orders",
            marks
                .iter()
                .map(|(m, mib)| format!("{m} min {mib:.1} MiB"))
                .collect::<Vec<_>>()
                .join(", "),
            soak.settle
        );
        processes.push(json!({
            "process": name,
            "rss_mib_at_minute": marks,
            "kib_per_1000_finished_after_settle": per_thousand,
        }));
    }
    processes
}

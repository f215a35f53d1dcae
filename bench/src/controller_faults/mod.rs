//! The controller fault campaign (issue 41's "Done when"): a real cell (the order-node
//! `orders1`, the product `part`, the resource `robot1` on a dialect, robot-sim as its
//! controller) kept busy with orders while robot-sim plays the faults it can, one kind
//! per phase in rotation ([`phases::ROTATION`]), started again every `restart_s` on the
//! same address (so the holon reconnects, and the faults that happen once per process
//! happen again). An operator clears, resets and starts the resource whenever a fault
//! aborted it (PackML), reading its stop reason.
//!
//! Checked, per phase and in total, and any miss makes the run fail:
//! - robot-sim's `refused_while_stopped` is 0: no command written to a stopped controller;
//! - the holon never reconnected sooner than the backoff allows ([`backoff`]), and its
//!   connections are at most the most the rule allows in the phase's time;
//! - every failed step's reason, as the operator reads it in the order (`cell orders
//!   --detail`, the order's snapshot) carries the controller's own words where it spoke
//!   ([`phases::SPOKEN`]), and says what happened where it did not; every PackML stop
//!   reason of a fault carries them too;
//! - every order ended done, or failed with a reason: none lost, none stuck;
//! - the dialect passes `robot-sim --check` and `holon-node --check`, the first job of
//!   the clean start is done, no step of the clean phase fails, and no step ever fails
//!   for a reason `--check` could have seen ([`phases::CHECKABLE`]).

mod backoff;
mod orders;
mod phases;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use holarchy_tests::{free_port, Cell, Sim};
use serde::Serialize;
use serde_json::json;

use crate::cells::{order_counts, router, start_product_and_orders};
use backoff::{Judged, Rule};
use phases::{FaultKind, PLAYED, ROTATION};

/// The resource's reconnect backoff in the campaign's config.
const RECONNECT_INTERVAL: Duration = Duration::from_millis(200);
const RECONNECT_MAX: Duration = Duration::from_millis(1600);
/// How long every action takes on robot-sim.
const DELAY_MS: u64 = 20;

/// What the campaign runs.
pub struct Campaign {
    pub minutes: f64,
    /// Seconds per phase (one kind of fault each).
    pub phase_s: u64,
    /// robot-sim is started again every this many seconds within a phase.
    pub restart_s: u64,
    /// Orders kept running.
    pub in_flight: u64,
    /// The dialect (a file or a shipped name).
    pub dialect: String,
}

/// What one phase did and showed.
#[derive(Debug, Default, Serialize)]
pub struct PhaseReport {
    pub phase: usize,
    pub kind: String,
    pub flags: String,
    pub seconds: f64,
    pub sim_runs: u64,
    pub received: u64,
    pub executed: u64,
    pub refused_while_stopped: u64,
    pub backoff: Judged,
    /// Faults robot-sim played, by kind (from its log).
    pub played: BTreeMap<String, u64>,
    /// Unix ms the phase began and ended (attempts are counted by when they ended).
    pub from_ms: u64,
    pub to_ms: u64,
    /// Failed step attempts by reason, as the orders recorded them.
    pub failed_attempts: BTreeMap<String, u64>,
    /// Failed attempts whose detail did not carry the controller's words.
    pub reasons_without_words: u64,
}

/// What the operator saw of PackML: a stop reason of an Aborted resource.
#[derive(Debug, Clone, Serialize)]
pub struct StopSeen {
    pub id: i64,
    pub message: String,
    pub at: u64,
}

/// What the cell's background tasks share.
struct Shared {
    cell: Arc<Cell>,
    stop: AtomicBool,
    feeding: AtomicBool,
    in_flight: u64,
    submitted: Mutex<Vec<String>>,
    refused_waves: Mutex<u64>,
    stops: Mutex<Vec<StopSeen>>,
    /// Clear/reset/start sequences the operator completed.
    restarts: Mutex<u64>,
}

pub fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

pub async fn run(campaign: &Campaign, out: &Path) -> Result<()> {
    let dir = tempfile::Builder::new()
        .prefix("holarchy-controller-faults")
        .tempdir()?;
    let dir = if std::env::var_os("HOLARCHY_BENCH_KEEP").is_some() {
        let kept = dir.keep();
        println!("keeping the campaign's directory: {}", kept.display());
        kept
    } else {
        dir.path().to_path_buf()
    };
    let dialect = dialect_spec(&campaign.dialect);
    let config = resource_config(&dir, &dialect)?;
    let checks = check_dialect(&dialect, &config)?;
    let address = format!("127.0.0.1:{}", free_port());
    let cell = Arc::new(router("faults", None).await?);
    let mut violations: Vec<String> = Vec::new();
    // The clean start: robot-sim without faults, the resource on it.
    let first = start_sim(&dir, "p00-clean-0", &address, &dialect, &[])?;
    let node = cell
        .start_free_resource(&dir, &config, &address, &[])
        .await
        .context("robot1 on robot-sim")?;
    let (product, order_node) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;
    let shared = Arc::new(Shared {
        cell: cell.clone(),
        stop: AtomicBool::new(false),
        feeding: AtomicBool::new(true),
        in_flight: campaign.in_flight,
        submitted: Mutex::new(Vec::new()),
        refused_waves: Mutex::new(0),
        stops: Mutex::new(Vec::new()),
        restarts: Mutex::new(0),
    });
    let feeder = tokio::spawn(feed(shared.clone()));
    let operator = tokio::spawn(operate(shared.clone()));
    let started = Instant::now();
    let phases = ((campaign.minutes * 60.0) / campaign.phase_s as f64)
        .ceil()
        .max(1.0) as usize;
    println!(
        "controller-faults: {phases} phases of {} s on {} (robot-sim started again every {} s), {} orders in flight",
        campaign.phase_s, campaign.dialect, campaign.restart_s, campaign.in_flight
    );
    let mut reports = Vec::new();
    let mut first = Some(first);
    for phase in 0..phases {
        let kind = ROTATION[phase % ROTATION.len()];
        let runs = Runs {
            dir: &dir,
            address: &address,
            dialect: &dialect,
            phase,
            kind,
            from_ms: reports
                .last()
                .map_or_else(unix_ms, |r: &PhaseReport| r.to_ms),
        };
        let report = runs
            .play(
                first.take(),
                Duration::from_secs(campaign.phase_s),
                Duration::from_secs(campaign.restart_s),
            )
            .await?;
        println!("{}", line(&report));
        reports.push(report);
    }
    // The last orders end on a controller without faults.
    shared.feeding.store(false, Ordering::SeqCst);
    let drain = Runs {
        dir: &dir,
        address: &address,
        dialect: &dialect,
        phase: phases,
        kind: FaultKind {
            name: "drain",
            flags: &[],
        },
        from_ms: reports.last().map_or_else(unix_ms, |r| r.to_ms),
    };
    let report = drain.drain(&cell, &mut violations).await?;
    println!("{}", line(&report));
    reports.push(report);
    let minutes = started.elapsed().as_secs_f64() / 60.0;
    shared.stop.store(true, Ordering::SeqCst);
    feeder.await?;
    operator.await?;
    let settings = json!({
        "minutes": minutes,
        "phase_s": campaign.phase_s,
        "restart_s": campaign.restart_s,
        "in_flight": campaign.in_flight,
        "dialect": campaign.dialect,
        "reconnect_interval_ms": RECONNECT_INTERVAL.as_millis() as u64,
        "reconnect_max_ms": RECONNECT_MAX.as_millis() as u64,
        "checks": checks,
    });
    let concluded = conclude(&cell, &shared, settings, reports, violations, out).await;
    drop((node, product, order_node));
    concluded
}

/// Judges the orders, the phases and the stop reasons, writes the results and says
/// whether anything was missed.
async fn conclude(
    cell: &Cell,
    shared: &Shared,
    mut summary: serde_json::Value,
    mut reports: Vec<PhaseReport>,
    mut violations: Vec<String>,
    out: &Path,
) -> Result<()> {
    let submitted = shared.submitted.lock().unwrap().clone();
    let stops = shared.stops.lock().unwrap().clone();
    let orders = orders::judge(cell, &submitted, &mut reports, &mut violations).await;
    judge_phases(&reports, &stops, &mut violations);
    let mut stop_reasons: BTreeMap<String, u64> = BTreeMap::new();
    for stop in &stops {
        *stop_reasons
            .entry(format!("{} {}", stop.id, stop.message))
            .or_default() += 1;
    }
    let more = json!({
        "orders": orders,
        "refused_waves": *shared.refused_waves.lock().unwrap(),
        "packml_stops": stops.len(),
        "packml_stop_reasons": stop_reasons,
        "packml_restarts": *shared.restarts.lock().unwrap(),
        "totals": totals(&reports),
        "phases": reports,
        "violations": violations,
    });
    if let (Some(summary), serde_json::Value::Object(more)) = (summary.as_object_mut(), more) {
        summary.extend(more);
    }
    write_results(out, &summary, &reports)?;
    println!(
        "{:.1} min, {} orders: {}",
        summary["minutes"].as_f64().unwrap_or(0.0),
        submitted.len(),
        serde_json::to_string(&summary["totals"])?
    );
    if !violations.is_empty() {
        for v in &violations {
            println!("VIOLATION: {v}");
        }
        bail!("{} violations (see {})", violations.len(), out.display());
    }
    println!("no violations");
    Ok(())
}

/// A shipped name as it is, a file made absolute (robot-sim and the holon run elsewhere).
fn dialect_spec(dialect: &str) -> String {
    let path = Path::new(dialect);
    if dialect.contains('/') || dialect.ends_with(".toml") {
        std::fs::canonicalize(path)
            .map(|p| p.display().to_string())
            .unwrap_or_else(|_| dialect.to_string())
    } else {
        dialect.to_string()
    }
}

/// The resource `robot1`'s config: the harness's, on `dialect`, with the campaign's
/// backoff and a command timeout of 2 s.
fn resource_config(dir: &Path, dialect: &str) -> Result<PathBuf> {
    let config = holarchy_tests::resource_config(dir, "robot1", 2000)?;
    let text = std::fs::read_to_string(&config)?.replacen(
        "reconnect_interval_ms = 100\nreconnect_max_ms = 1000\n",
        &format!(
            "reconnect_interval_ms = {}\nreconnect_max_ms = {}\ndialect = {dialect:?}\n",
            RECONNECT_INTERVAL.as_millis(),
            RECONNECT_MAX.as_millis()
        ),
        1,
    );
    if !text.contains("dialect = ") {
        bail!("the harness's resource config changed: no backoff lines to replace");
    }
    std::fs::write(&config, text)?;
    Ok(config)
}

/// `robot-sim --check` and `holon-node --check` of the dialect: both must pass.
fn check_dialect(dialect: &str, config: &Path) -> Result<serde_json::Value> {
    let run = |program: &str, args: &[&str]| -> Result<String> {
        let output = std::process::Command::new(holarchy_tests::bin(program))
            .args(args)
            .output()
            .with_context(|| format!("run {program} --check"))?;
        let said = format!(
            "{}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
        if !output.status.success() {
            bail!("{program} --check refused the dialect: {said}");
        }
        Ok(said.trim().to_string())
    };
    let sim = run("robot-sim", &["--dialect", dialect, "--check"])?;
    let config = config.to_str().context("a config path that is UTF-8")?;
    // As the campaign starts it (the config names neither the cell nor its router).
    let node = run(
        "holon-node",
        &[
            "--config",
            config,
            "--cell",
            "faults",
            "--connect",
            "tcp/127.0.0.1:7447",
            "--check",
        ],
    )?;
    println!("robot-sim --check: {sim}\nholon-node --check: {node}");
    Ok(json!({"robot_sim": sim, "holon_node": node}))
}

/// Starts robot-sim on `address` (tries again for a moment while the port is taken).
fn start_sim(dir: &Path, name: &str, address: &str, dialect: &str, flags: &[&str]) -> Result<Sim> {
    let delay = DELAY_MS.to_string();
    let mut all = vec!["--dialect", dialect, "--delay-ms", &delay];
    all.extend_from_slice(flags);
    let mut tries = 0;
    loop {
        match Sim::start(dir, name, address, &all) {
            Ok(sim) => return Ok(sim),
            Err(e) if tries < 50 => {
                tries += 1;
                tracing::debug!(error = %e, "robot-sim did not start; again");
                std::thread::sleep(Duration::from_millis(100));
            }
            Err(e) => return Err(e.context(format!("robot-sim {name} on {address}"))),
        }
    }
}

/// The robot-sim runs of one phase.
struct Runs<'a> {
    dir: &'a Path,
    address: &'a str,
    dialect: &'a str,
    phase: usize,
    kind: FaultKind,
    /// When the phase's window begins (Unix ms): where the last one's ended.
    from_ms: u64,
}

impl Runs<'_> {
    /// Plays the phase for `time`, robot-sim started again every `restart` (the first
    /// run may be given, already started).
    async fn play(
        &self,
        mut given: Option<Sim>,
        time: Duration,
        restart: Duration,
    ) -> Result<PhaseReport> {
        let mut report = self.report();
        let began = Instant::now();
        // The clean phase is one run: its jobs meet no fault, not even a restart.
        let restart = if self.kind.flags.is_empty() {
            time
        } else {
            restart
        };
        let mut run = 0;
        while began.elapsed() < time {
            let name = format!("p{:02}-{}-{run}", self.phase, self.kind.name);
            let sim = match given.take() {
                Some(sim) => sim,
                None => start_sim(self.dir, &name, self.address, self.dialect, self.kind.flags)?,
            };
            let ran = Instant::now();
            let until = restart.min(time.saturating_sub(began.elapsed()));
            tokio::time::sleep(until).await;
            if began.elapsed() >= time {
                // What the last stop breaks is the next phase's (its window begins here).
                report.to_ms = unix_ms();
            }
            self.stop(sim, ran.elapsed(), &mut report)?;
            run += 1;
        }
        report.seconds = began.elapsed().as_secs_f64();
        Ok(report)
    }

    /// A clean robot-sim until no order runs (at most 180 s).
    async fn drain(&self, cell: &Cell, violations: &mut Vec<String>) -> Result<PhaseReport> {
        let mut report = self.report();
        let began = Instant::now();
        let sim = start_sim(self.dir, "drain", self.address, self.dialect, &[])?;
        loop {
            let running = order_counts(cell).await.map(|c| c.running).unwrap_or(1);
            if running == 0 {
                break;
            }
            if began.elapsed() > Duration::from_secs(180) {
                violations.push(format!(
                    "{running} orders still running 180 s after the last phase"
                ));
                break;
            }
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
        self.stop(sim, began.elapsed(), &mut report)?;
        report.seconds = began.elapsed().as_secs_f64();
        report.to_ms = unix_ms();
        Ok(report)
    }

    fn report(&self) -> PhaseReport {
        PhaseReport {
            phase: self.phase,
            kind: self.kind.name.to_string(),
            flags: self.kind.flags.join(" "),
            from_ms: self.from_ms,
            ..PhaseReport::default()
        }
    }

    /// Stops one robot-sim run and adds its counts, its faults and its connections.
    fn stop(&self, mut sim: Sim, ran: Duration, report: &mut PhaseReport) -> Result<()> {
        sim.process.signal(nix::sys::signal::Signal::SIGTERM)?;
        if sim.process.wait_exit(Duration::from_secs(10)).is_err() {
            sim.process.kill();
        }
        let counts = sim.counts();
        let count = |key: &str| counts[key].as_u64().unwrap_or(0);
        report.sim_runs += 1;
        report.received += count("received");
        report.executed += count("executed");
        report.refused_while_stopped += count("refused_while_stopped");
        let log = sim.process.stderr();
        for (kind, said) in PLAYED {
            let n = log.lines().filter(|l| l.contains(said)).count() as u64;
            if n > 0 {
                *report.played.entry(kind.to_string()).or_default() += n;
            }
        }
        let rule = Rule {
            interval: RECONNECT_INTERVAL,
            max: RECONNECT_MAX,
            tolerance: Duration::from_millis(DELAY_MS + 30),
        };
        let judged = rule.judge(&backoff::connections(&log), ran);
        let b = &mut report.backoff;
        b.connections += judged.connections;
        b.served += judged.served;
        b.allowed += judged.allowed;
        b.too_soon.extend(judged.too_soon);
        b.longest_pause_ms = b.longest_pause_ms.max(judged.longest_pause_ms);
        Ok(())
    }
}

/// Keeps `in_flight` orders running while feeding.
async fn feed(shared: Arc<Shared>) {
    while !shared.stop.load(Ordering::SeqCst) {
        if shared.feeding.load(Ordering::SeqCst) {
            match order_counts(&shared.cell).await {
                Ok(counts) if counts.running < shared.in_flight => {
                    let wanted = (shared.in_flight - counts.running) as u32;
                    match shared.cell.submit("part", wanted).await {
                        Ok(orders) => shared.submitted.lock().unwrap().extend(orders),
                        Err(e) => {
                            tracing::warn!(error = %e, "a work order was refused");
                            *shared.refused_waves.lock().unwrap() += 1;
                        }
                    }
                }
                Ok(_) => {}
                Err(e) => tracing::warn!(error = %e, "cannot count the orders"),
            }
        }
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
}

/// The operator: reads robot1's PackML state and, when a fault aborted it, keeps its
/// stop reason and clears, resets and starts it, one command per state it finds
/// (Clear waits in Clearing until the controller no longer reports the fault).
async fn operate(shared: Arc<Shared>) {
    let cell = &shared.cell;
    while !shared.stop.load(Ordering::SeqCst) {
        tokio::time::sleep(Duration::from_millis(200)).await;
        let Ok(state) = cell.status("robot1").await else {
            continue;
        };
        let command = match state["packml"]["state"].as_str() {
            Some("aborted") => {
                let reason = &state["packml"]["stop_reason"];
                let seen = StopSeen {
                    id: reason["id"].as_i64().unwrap_or(0),
                    message: reason["message"].as_str().unwrap_or("").to_string(),
                    at: reason["at"].as_u64().unwrap_or(0),
                };
                let mut stops = shared.stops.lock().unwrap();
                if stops.last().is_none_or(|last| last.at != seen.at) {
                    stops.push(seen);
                }
                "clear"
            }
            Some("stopped") => "reset",
            Some("idle") => "start",
            _ => continue,
        };
        match cell.packml("robot1", command).await {
            Ok(_) if command == "start" => *shared.restarts.lock().unwrap() += 1,
            Ok(_) => {}
            Err(e) => tracing::info!(error = %e, command, "the operator tries again"),
        }
    }
}

/// The checks of robot-sim's counts and connections, and of the stop reasons.
fn judge_phases(reports: &[PhaseReport], stops: &[StopSeen], violations: &mut Vec<String>) {
    for r in reports {
        let at = format!("phase {} ({})", r.phase, r.kind);
        if r.refused_while_stopped > 0 {
            violations.push(format!(
                "{at}: {} commands written while the controller was stopped",
                r.refused_while_stopped
            ));
        }
        if !r.backoff.too_soon.is_empty() {
            violations.push(format!(
                "{at}: {} reconnections sooner than the backoff allows (gap ms, least ms): {:?}",
                r.backoff.too_soon.len(),
                &r.backoff.too_soon[..r.backoff.too_soon.len().min(5)]
            ));
        }
        if r.backoff.connections > r.backoff.allowed {
            violations.push(format!(
                "{at}: {} connections, the backoff allows {}",
                r.backoff.connections, r.backoff.allowed
            ));
        }
    }
    for stop in stops {
        let words = match stop.id {
            100 => stop.message.contains("simulated fault"),
            101 => {
                stop.message.to_lowercase().contains("estop")
                    || stop.message.contains("emergency stop")
            }
            _ => !stop.message.is_empty(),
        };
        if !words {
            violations.push(format!(
                "a PackML stop reason without the controller's words: {} {:?}",
                stop.id, stop.message
            ));
        }
    }
}

fn totals(reports: &[PhaseReport]) -> serde_json::Value {
    let sum = |f: &dyn Fn(&PhaseReport) -> u64| reports.iter().map(f).sum::<u64>();
    let mut played: BTreeMap<String, u64> = BTreeMap::new();
    let mut failed: BTreeMap<String, u64> = BTreeMap::new();
    for r in reports {
        for (k, v) in &r.played {
            *played.entry(k.clone()).or_default() += v;
        }
        for (k, v) in &r.failed_attempts {
            *failed.entry(k.clone()).or_default() += v;
        }
    }
    json!({
        "received": sum(&|r| r.received),
        "executed": sum(&|r| r.executed),
        "refused_while_stopped": sum(&|r| r.refused_while_stopped),
        "sim_runs": sum(&|r| r.sim_runs),
        "connections": sum(&|r| r.backoff.connections),
        "served": sum(&|r| r.backoff.served),
        "allowed": sum(&|r| r.backoff.allowed),
        "too_soon": sum(&|r| r.backoff.too_soon.len() as u64),
        "longest_pause_ms": reports.iter().map(|r| r.backoff.longest_pause_ms).max().unwrap_or(0),
        "played": played,
        "failed_attempts": failed,
        "reasons_without_words": sum(&|r| r.reasons_without_words),
    })
}

fn line(r: &PhaseReport) -> String {
    format!(
        "phase {:>2} {:<21} {:>5.0} s  {} runs  {:>5} received {:>5} executed  refused_while_stopped {}  connections {} (served {}, allowed {}, too soon {})  played {:?}",
        r.phase,
        r.kind,
        r.seconds,
        r.sim_runs,
        r.received,
        r.executed,
        r.refused_while_stopped,
        r.backoff.connections,
        r.backoff.served,
        r.backoff.allowed,
        r.backoff.too_soon.len(),
        r.played
    )
}

/// The summary as JSON at `out`, and a row per phase as CSV beside it.
fn write_results(out: &Path, summary: &serde_json::Value, reports: &[PhaseReport]) -> Result<()> {
    let mut csv = String::from(
        "phase,kind,seconds,sim_runs,received,executed,refused_while_stopped,connections,served,allowed,too_soon,longest_pause_ms,played,failed_attempts,reasons_without_words\n",
    );
    let map = |m: &BTreeMap<String, u64>| {
        m.iter()
            .map(|(k, v)| format!("{k}={v}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    for r in reports {
        csv.push_str(&format!(
            "{},{},{:.0},{},{},{},{},{},{},{},{},{},{},{},{}\n",
            r.phase,
            r.kind,
            r.seconds,
            r.sim_runs,
            r.received,
            r.executed,
            r.refused_while_stopped,
            r.backoff.connections,
            r.backoff.served,
            r.backoff.allowed,
            r.backoff.too_soon.len(),
            r.backoff.longest_pause_ms,
            map(&r.played),
            map(&r.failed_attempts),
            r.reasons_without_words
        ));
    }
    let csv_path = out.with_extension("csv");
    std::fs::write(&csv_path, csv)?;
    std::fs::write(out, serde_json::to_string_pretty(summary)?)?;
    println!("wrote {} and {}", out.display(), csv_path.display());
    Ok(())
}

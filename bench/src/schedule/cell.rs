//! The scheduling benchmark on a shipped cell (the AIP-PRIMECA cell's scenarios,
//! `deploy/scenarios/aip-*.toml`): the whole cell started by `cell up` on its plant at
//! the scenario's time scale, once by contract net alone and once with its staff
//! holon; the orders released, and the events played, at their moments of plant time.
//!
//! Every figure is in plant time and comes from the plant's own trace (each action of
//! each controller, its begin and end): makespan (first release to last exit), mean
//! flow time, the rush orders' flow, tardiness, each station's and the shuttles'
//! utilisation, and the gap to a lower bound ([`bound`]) computed from the cell's
//! files. Each run writes its Gantt chart ([`gantt`]) beside the JSON.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use holarchy_tests::{bin, free_port};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use schemas::{CellKeys, HolonId, HolonKind};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};

pub mod bound;
pub mod critical_path;
pub mod gantt;
pub mod manifest;
pub mod metrics;
pub mod report;
pub mod scenario;
pub mod usage;

use bound::{Bound, CellModel};
use critical_path::CriticalPath;
use manifest::CellCopy;
use metrics::{CellFigures, Endings, Released};
use report::{print_header, print_row};
use scenario::{CellScenario, Event, Happening};
use usage::{ProcessUsage, Sampler};

/// How the orders were scheduled on the cell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CellMode {
    /// Contract net alone: the cell's staff holons are not started.
    ContractNet,
    /// Contract net with the cell's staff holon advising the orders.
    Staff,
}

impl CellMode {
    pub fn as_str(self) -> &'static str {
        match self {
            CellMode::ContractNet => "contract net",
            CellMode::Staff => "with staff",
        }
    }

    fn dir_name(self) -> &'static str {
        match self {
            CellMode::ContractNet => "cnet",
            CellMode::Staff => "staff",
        }
    }
}

/// One run's result.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CellRun {
    pub scenario: String,
    pub description: String,
    pub mode: CellMode,
    pub time_scale: u32,
    pub figures: CellFigures,
    pub bound: Bound,
    /// The makespan over the bound, less one.
    pub gap: f64,
    /// The wall time the run took, from the first release.
    pub wall_s: f64,
    /// Its Gantt chart.
    pub gantt: PathBuf,
    /// What each of the cell's processes used over the run.
    pub processes: Vec<ProcessUsage>,
    /// How its orders ended.
    pub endings: Endings,
    /// Its critical path and the control's plant time on it.
    pub critical_path: Option<CriticalPath>,
}

/// What a run of cell scenarios is asked (`bench schedule` on a cell).
#[derive(Debug, Clone)]
pub struct CellOptions {
    /// Its time scale, overriding each scenario's.
    pub time_scale: Option<u32>,
    /// The modes to run, each once.
    pub modes: Vec<CellMode>,
    /// Where the Gantt charts go.
    pub charts: PathBuf,
}

/// Runs every cell scenario of `paths` as `options` say, printing a row per run.
pub async fn run_all(paths: &[PathBuf], options: &CellOptions) -> Result<Vec<CellRun>> {
    println!();
    print_header();
    let mut runs = Vec::new();
    for path in paths {
        runs.extend(run(path, &options.modes, options.time_scale, &options.charts).await?);
    }
    Ok(runs)
}

/// Runs the cell scenario at `path` in each of `modes`; `scale` overrides its time
/// scale. Charts go to `charts`.
pub async fn run(
    path: &Path,
    modes: &[CellMode],
    scale: Option<u32>,
    charts: &Path,
) -> Result<Vec<CellRun>> {
    let mut scenario = CellScenario::load(path)?;
    if let Some(scale) = scale {
        scenario.time_scale = scale;
    }
    let work = tempfile::Builder::new()
        .prefix("holarchy-cell-bench")
        .tempdir()?;
    let keep = std::env::var_os("HOLARCHY_BENCH_KEEP").is_some();
    let mut runs = Vec::new();
    for mode in modes {
        let dir = work.path().join(mode.dir_name());
        let run = run_once(&scenario, *mode, &dir, charts).await;
        match run {
            Ok(run) => {
                print_row(&run);
                runs.push(run);
            }
            Err(e) => {
                let kept = work.keep();
                return Err(e.context(format!(
                    "{} {}: the run's files kept in {}",
                    scenario.name,
                    mode.as_str(),
                    kept.display()
                )));
            }
        }
    }
    if keep {
        println!("the runs' files kept in {}", work.keep().display());
    }
    Ok(runs)
}

/// One run of the scenario in `mode`, in `dir`.
async fn run_once(
    scenario: &CellScenario,
    mode: CellMode,
    dir: &Path,
    charts: &Path,
) -> Result<CellRun> {
    let control = format!("127.0.0.1:{}", free_port());
    let copy = manifest::copy(&scenario.cell, dir, &control, mode == CellMode::Staff)?;
    let mut stations: Vec<String> = copy.resources.clone();
    stations.extend(scenario.added());
    let model = CellModel::load(dir, &stations, &copy.products)?;
    let mut cell = Running::start(&copy, scenario.time_scale)?;
    let outcome = drive(scenario, &copy, &mut cell).await;
    let processes = cell.stop();
    let (released, endings, wall) = outcome?;
    let trace = metrics::read_trace(&copy.trace)?;
    let figures = metrics::figures(
        &trace,
        &released,
        &model.transporter,
        model.conveyor.pallets,
    );
    let start = released.iter().map(|r| r.at_ms).min().unwrap_or(0);
    let jobs: Vec<(String, u64)> = released
        .iter()
        .map(|r| (r.product.clone(), r.at_ms - start))
        .collect();
    let bound = model.bound(&jobs)?;
    let critical_path =
        critical_path::critical_path(&trace, start, &model.transporter, scenario.time_scale);
    std::fs::create_dir_all(charts)?;
    let gantt = charts.join(format!(
        "{}-{}-{}x.svg",
        scenario.name,
        mode.dir_name(),
        scenario.time_scale
    ));
    let product_of: BTreeMap<String, String> = released
        .iter()
        .map(|r| (r.order.clone(), r.product.clone()))
        .collect();
    let title = format!(
        "{}, {}, {}x: makespan {:.1} s (plant time), lower bound {:.1} s",
        scenario.name,
        mode.as_str(),
        scenario.time_scale,
        figures.makespan_ms as f64 / 1000.0,
        bound.makespan_ms as f64 / 1000.0
    );
    std::fs::write(
        &gantt,
        gantt::svg(&title, &trace, start, &product_of, &model.transporter),
    )?;
    let gap = figures.makespan_ms as f64 / bound.makespan_ms.max(1) as f64 - 1.0;
    Ok(CellRun {
        scenario: scenario.name.clone(),
        description: scenario.description.clone(),
        mode,
        time_scale: scenario.time_scale,
        figures,
        bound,
        gap,
        wall_s: wall.as_secs_f64(),
        gantt,
        processes,
        endings,
        critical_path,
    })
}

/// The cell's processes: `cell up` and any station hot-added.
struct Running {
    /// `cell up`, which runs the cell's router and starts its processes.
    up: Child,
    /// The stations the bench hot-added.
    added: Vec<Child>,
    /// The cell's copy.
    dir: PathBuf,
    /// The plant's time scale, given to a hot-added station.
    scale: u32,
    /// Samples what every process uses.
    sampler: Option<Sampler>,
}

impl Running {
    fn start(copy: &CellCopy, scale: u32) -> Result<Running> {
        let log = std::fs::File::create(copy.dir.join("cell-up.log"))?;
        let cell = bin("cell");
        let up = Command::new(&cell)
            .args(["up", ".", "--time-scale", &scale.to_string()])
            .current_dir(&copy.dir)
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("cannot start {} up", cell.display()))?;
        let sampler = Sampler::start(up.id(), copy.dir.join("cell-up.log"));
        Ok(Running {
            up,
            added: Vec::new(),
            dir: copy.dir.clone(),
            scale,
            sampler: Some(sampler),
        })
    }

    /// Starts the resource holon of `station` as an operator would (its controller
    /// is in plant.toml already).
    fn hot_add(&mut self, station: &str, endpoint: &str) -> Result<()> {
        std::fs::create_dir_all(self.dir.join("logs"))?;
        let log = std::fs::File::create(self.dir.join(format!("logs/{station}.log")))?;
        let child = Command::new(bin("holon-node"))
            .args([
                "--config",
                &format!("{station}.toml"),
                "--connect",
                endpoint,
            ])
            .args([
                "--data-dir",
                "data",
                "--time-scale",
                &self.scale.to_string(),
            ])
            .current_dir(&self.dir)
            .stdout(log.try_clone()?)
            .stderr(log)
            .spawn()
            .with_context(|| format!("cannot start {station}"))?;
        if let Some(sampler) = &self.sampler {
            sampler.add(child.id(), station);
        }
        self.added.push(child);
        Ok(())
    }

    /// Stops everything as Ctrl-C would: SIGTERM, then a wait. What each process used
    /// until then.
    fn stop(&mut self) -> Vec<ProcessUsage> {
        let usage = self
            .sampler
            .take()
            .map(|s| s.finish(&self.dir.join("cell-up.log")))
            .unwrap_or_default();
        for child in self.added.iter_mut().chain(std::iter::once(&mut self.up)) {
            if let Err(e) = kill(Pid::from_raw(child.id() as i32), Signal::SIGTERM) {
                eprintln!("cannot stop process {}: {e}", child.id());
            }
        }
        let deadline = Instant::now() + Duration::from_secs(90);
        for child in self.added.iter_mut().chain(std::iter::once(&mut self.up)) {
            loop {
                match child.try_wait() {
                    Ok(Some(_)) => break,
                    Ok(None) if Instant::now() < deadline => {
                        std::thread::sleep(Duration::from_millis(100))
                    }
                    _ => {
                        eprintln!("process {} did not stop: killed", child.id());
                        if let Err(e) = child.kill().and_then(|()| child.wait().map(drop)) {
                            eprintln!("cannot kill process {}: {e}", child.id());
                        }
                        break;
                    }
                }
            }
        }
        usage
    }
}

/// What the plant's control port says.
struct PlantControl {
    address: String,
}

impl PlantControl {
    async fn command(&self, line: &str) -> Result<String> {
        let stream = tokio::time::timeout(
            Duration::from_secs(5),
            tokio::net::TcpStream::connect(&self.address),
        )
        .await
        .map_err(|_| anyhow!("the plant's control port did not answer"))??;
        let (read, mut write) = stream.into_split();
        write.write_all(format!("{line}\n").as_bytes()).await?;
        let mut answer = String::new();
        tokio::time::timeout(
            Duration::from_secs(5),
            BufReader::new(read).read_line(&mut answer),
        )
        .await
        .map_err(|_| anyhow!("the plant did not answer {line}"))??;
        Ok(answer.trim().to_string())
    }

    /// The plant's clock, in plant ms.
    async fn now_ms(&self) -> Result<u64> {
        let waits: serde_json::Value = serde_json::from_str(&self.command("waits").await?)?;
        waits["now_ms"]
            .as_u64()
            .ok_or_else(|| anyhow!("the plant's waits without now_ms: {waits}"))
    }
}

/// Waits for the cell, releases the orders and plays the events at their moments,
/// and waits until every order has ended: the releases, how they ended, and the wall
/// time from the first release.
async fn drive(
    scenario: &CellScenario,
    copy: &CellCopy,
    cell: &mut Running,
) -> Result<(Vec<Released>, Endings, Duration)> {
    let plant = PlantControl {
        address: copy.control.clone(),
    };
    let session = holon::ZenohSettings {
        mode: holon::Mode::Client,
        connect: vec![copy.endpoint.clone()],
        ..holon::ZenohSettings::default()
    }
    .open("bench.schedule", Duration::from_secs(60))
    .await
    .map_err(|e| anyhow!("cannot join the cell at {}: {e}", copy.endpoint))?;
    let keys = CellKeys::new(&copy.cell)?;
    wait_ready(&session, &keys, copy).await?;
    let start_ms = plant.now_ms().await?;
    let started = Instant::now();
    let mut released = Vec::new();
    // The releases of one moment are submitted together (each `cell submit` takes a
    // tenth of a second of wall time: one after the other, the seventh of seven would
    // be released 35 s of plant time late at 50x), and their ids read before the next
    // moment's.
    let mut submitting = Vec::new();
    for (at_s, happening) in scenario.timeline() {
        let at_ms = start_ms + (at_s * 1000.0) as u64;
        if plant.now_ms().await? < at_ms {
            released.extend(submitted(scenario, std::mem::take(&mut submitting))?);
        }
        loop {
            let now = plant.now_ms().await?;
            if now >= at_ms {
                break;
            }
            let wall = (at_ms - now) / u64::from(scenario.time_scale);
            tokio::time::sleep(Duration::from_millis(wall.clamp(1, 1000))).await;
        }
        match happening {
            Happening::Release(i) => {
                let r = &scenario.releases[i];
                let now = plant.now_ms().await?;
                let due_ms = r.due_s.map(|d| start_ms + (d * 1000.0) as u64);
                let due_in = due_ms.map(|d| d.saturating_sub(now) / u64::from(scenario.time_scale));
                let child = submit(copy, &r.product, r.count, r.priority, due_in)?;
                submitting.push((child, i, now, due_ms));
                continue;
            }
            Happening::Event(Event::Breakdown {
                station, repair_s, ..
            }) => {
                let ms = (repair_s * 1000.0) as u64;
                let answer = plant.command(&format!("estop {station} {ms}")).await?;
                if answer != "ok" {
                    bail!("the plant refused the breakdown of {station}: {answer}");
                }
            }
            Happening::Event(Event::InspectionFail { station, count, .. }) => {
                let answer = plant.command(&format!("fail {station} {count}")).await?;
                if answer != "ok" {
                    bail!("the plant refused to fail {station}'s inspections: {answer}");
                }
            }
            Happening::Event(Event::ShuttleOut { shuttle, .. }) => {
                let answer = plant.command(&format!("retire {shuttle}")).await?;
                if answer != "ok" {
                    bail!("the plant refused to take {shuttle} out: {answer}");
                }
                carrier(copy, &shuttle, "--out")?;
            }
            Happening::ShuttleBack { shuttle } => {
                let answer = plant.command(&format!("restore {shuttle}")).await?;
                if answer != "ok" {
                    bail!("the plant refused to put {shuttle} back: {answer}");
                }
                carrier(copy, &shuttle, "--back")?;
            }
            Happening::Event(Event::HotAdd { station, .. }) => {
                cell.hot_add(&station, &copy.endpoint)?
            }
            Happening::Repaired { station } => {
                for command in ["clear", "reset", "start"] {
                    packml(copy, &station, command).await?;
                }
            }
        }
    }
    released.extend(submitted(scenario, submitting)?);
    let endings = wait_ended(&session, &keys, &released, scenario).await?;
    Ok((released, endings, started.elapsed()))
}

/// Tells the conveyor that `shuttle` (`monorail/p3`) is out of service or back
/// (`word`: `--out`, `--back`), as the operator who took it off the track would (`cell
/// carrier`): the conveyor then lets in only as many parts as shuttles are in service.
fn carrier(copy: &CellCopy, shuttle: &str, word: &str) -> Result<()> {
    let (conveyor, _) = shuttle
        .split_once('/')
        .ok_or_else(|| anyhow::anyhow!("{shuttle}: not CONVEYOR/PALLET"))?;
    let output = Command::new(bin("cell"))
        .args(["carrier", conveyor, shuttle, word])
        .args(["--cell", &copy.cell, "--connect", &copy.endpoint])
        .stdin(Stdio::null())
        .output()?;
    if !output.status.success() {
        bail!(
            "cell carrier {conveyor} {shuttle} {word} refused: {}{}",
            String::from_utf8_lossy(&output.stdout),
            String::from_utf8_lossy(&output.stderr)
        );
    }
    Ok(())
}

/// Commands `station`'s PackML unit as its operator would (`cell packml`), asked
/// again while the unit is not yet in a state that allows it (a controller that is
/// not yet ready again after its e-stop keeps it in Clearing).
async fn packml(copy: &CellCopy, station: &str, command: &str) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let output = Command::new(bin("cell"))
            .args(["packml", station, command])
            .args(["--cell", &copy.cell, "--connect", &copy.endpoint])
            .stdin(Stdio::null())
            .output()?;
        if output.status.success() {
            return Ok(());
        }
        if Instant::now() > deadline {
            bail!(
                "cell packml {station} {command} refused for 60 s: {}{}",
                String::from_utf8_lossy(&output.stdout),
                String::from_utf8_lossy(&output.stderr)
            );
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// Waits until every holon of the cell copy is alive, and an order-node serves.
async fn wait_ready(session: &zenoh::Session, keys: &CellKeys, copy: &CellCopy) -> Result<()> {
    let holons = copy
        .resources
        .iter()
        .map(|r| HolonId::new(HolonKind::Resource, r))
        .chain(
            copy.products
                .iter()
                .map(|p| HolonId::new(HolonKind::Product, p)),
        )
        .chain(copy.staff.iter().map(|s| HolonId::new(HolonKind::Staff, s)));
    for holon in holons {
        let holon = holon?;
        let alive = holon::presence::wait_alive(session, keys, &holon, Duration::from_secs(120))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        if !alive {
            bail!("{holon} did not start within 120 s (see logs/ in the run's directory)");
        }
    }
    // An order-node answers the listing once it serves.
    let deadline = Instant::now() + Duration::from_secs(120);
    while ::cell::client::listing::all_orders(session, keys, Duration::from_secs(2))
        .await
        .is_err()
    {
        if Instant::now() > deadline {
            bail!("no order-node served within 120 s (see logs/ in the run's directory)");
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    Ok(())
}

/// Starts submitting `count` orders of `product` with `cell submit`.
fn submit(
    copy: &CellCopy,
    product: &str,
    count: u32,
    priority: i32,
    due_in_ms: Option<u64>,
) -> Result<Child> {
    let mut command = Command::new(bin("cell"));
    command
        .args(["submit", product, "--count", &count.to_string()])
        .args(["--priority", &priority.to_string()])
        .args(["--cell", &copy.cell, "--connect", &copy.endpoint]);
    if let Some(ms) = due_in_ms {
        command.args(["--due-in", &format!("{}ms", ms.max(1))]);
    }
    command
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .context("cannot run cell submit")
}

/// The orders of the submissions under way (each with its release's index, plant ms
/// and due time), once each has answered: an error naming the first refused.
fn submitted(
    scenario: &CellScenario,
    submitting: Vec<(Child, usize, u64, Option<u64>)>,
) -> Result<Vec<Released>> {
    let mut released = Vec::new();
    for (child, i, at_ms, due_ms) in submitting {
        let r = &scenario.releases[i];
        let output = child.wait_with_output()?;
        let stdout = String::from_utf8_lossy(&output.stdout);
        if !output.status.success() {
            bail!(
                "cell submit {} failed: {}{stdout}",
                r.product,
                String::from_utf8_lossy(&output.stderr)
            );
        }
        let ids: Vec<&str> = stdout
            .split_whitespace()
            .filter(|w| w.contains('-'))
            .collect();
        if ids.len() != r.count as usize {
            bail!(
                "cell submit printed {} ids for {} orders: {stdout}",
                ids.len(),
                r.count
            );
        }
        released.extend(ids.into_iter().map(|order| Released {
            order: order.to_string(),
            product: r.product.clone(),
            at_ms,
            due_ms,
            rush: r.priority > 0,
        }));
    }
    Ok(released)
}

/// Waits until every released order has ended (done, scrapped, failed or
/// cancelled): how they ended. An error after a generous bound of wall time.
async fn wait_ended(
    session: &zenoh::Session,
    keys: &CellKeys,
    released: &[Released],
    scenario: &CellScenario,
) -> Result<Endings> {
    // Every order alone in the cell, one after another, at the slowest plausible
    // pace: far beyond any real run.
    let limit = Duration::from_secs(
        600 + u64::from(scenario.orders()) * 1200 / u64::from(scenario.time_scale),
    );
    let started = Instant::now();
    loop {
        tokio::time::sleep(Duration::from_secs(1)).await;
        let listed =
            ::cell::client::listing::all_orders(session, keys, Duration::from_secs(5)).await;
        if let Ok(orders) = listed {
            if let Some(endings) = Endings::of(&orders, released) {
                return Ok(endings);
            }
            if started.elapsed() > limit {
                let running = orders
                    .iter()
                    .filter(|o| !o.status.is_final())
                    .filter(|o| released.iter().any(|r| r.order == o.holon.name()))
                    .count();
                bail!(
                    "{running} of {} orders still running after {:?}",
                    released.len(),
                    started.elapsed()
                );
            }
        }
    }
}

//! The scheduling benchmark: a scenario (resources with their speeds and changeover
//! costs, a product mix with variants, a stream of orders with some rush orders) run
//! on real processes three times per seed: by contract net alone, with a staff holon
//! advising the orders, and (the cell as it was before priorities) by contract net on
//! agendas that serve in booking order (`agenda.max_overtakes = 0`). Each run of a
//! seed has the same orders at the same moments.
//!
//!     cargo run --release -p bench -- schedule     # deploy/scenarios/*.toml, 3 seeds
//!
//! Figures per run: makespan (first submission to last order done), mean and p95 flow
//! time (submission to done), the rush orders' mean flow time, each resource's
//! utilisation (its controller's busy time over the makespan) and the changeovers.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use holarchy_tests::{demo_config, start_holon, start_node, Process, Sim};
use schemas::{HolonId, HolonKind, OrderSnapshot, OrderStatus, WorkOrder};
use serde::Deserialize;
use serde_json::{json, Value};

use crate::cells::router;

mod arrivals;
pub mod cell;

use arrivals::{arrivals, Arrival};
pub use cell::scenario::CellScenario;
pub use cell::{CellMode, CellOptions};

/// A scenario file (`deploy/scenarios/*.toml` documents the format).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub resources: Vec<ResourceSpec>,
    pub products: Vec<ProductSpec>,
    pub orders: OrderStream,
}

/// One resource: what it offers, what its config says each service takes (the
/// nominal duration contract net ranks by), and what its controller really takes.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResourceSpec {
    pub name: String,
    /// Service types, each one of `pick_n_place` (actions pick, place), `inspect`
    /// (inspect) or `transport` (move).
    pub services: Vec<String>,
    /// Per service type, its config's `nominal_duration_ms`.
    pub nominal_ms: BTreeMap<String, u64>,
    /// Per controller action, how long it takes (robot-sim `--action-ms`).
    pub action_ms: BTreeMap<String, u64>,
    /// What a change of program costs on this controller (robot-sim `--changeover-ms`).
    #[serde(default)]
    pub changeover_ms: u64,
}

/// One product: its steps (service types, in order) and its program (the variant).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProductSpec {
    pub name: String,
    pub program: String,
    pub steps: Vec<String>,
    /// Its share of the orders (relative to the other products' weights).
    #[serde(default = "one")]
    pub weight: u32,
}

fn one() -> u32 {
    1
}

/// The orders: how many, how often they arrive, which are rush orders.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OrderStream {
    pub count: u32,
    /// The mean time between two arrivals (exponentially distributed, by the seed).
    pub mean_interval_ms: u64,
    /// Every Nth order is a rush order (0: none).
    #[serde(default)]
    pub rush_every: u32,
    /// A rush order's priority.
    #[serde(default = "rush_priority")]
    pub rush_priority: i32,
}

fn rush_priority() -> i32 {
    100
}

impl Scenario {
    pub fn load(path: &Path) -> Result<Scenario> {
        let text = std::fs::read_to_string(path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let scenario: Scenario =
            toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
        for resource in &scenario.resources {
            for service in &resource.services {
                let actions = actions(service)
                    .ok_or_else(|| anyhow!("{}: unknown service {service}", resource.name))?;
                for action in actions {
                    if !resource.action_ms.contains_key(*action) {
                        bail!("{}: action_ms lacks {action}", resource.name);
                    }
                }
            }
        }
        if scenario.products.iter().all(|p| p.weight == 0) {
            bail!("{}: every product has weight 0", scenario.name);
        }
        Ok(scenario)
    }
}

/// The controller actions of a service type the benchmark knows.
fn actions(service: &str) -> Option<&'static [&'static str]> {
    Some(match service {
        "pick_n_place" => &["pick", "place"],
        "inspect" => &["inspect"],
        "transport" => &["move"],
        _ => return None,
    })
}

/// How the orders were scheduled.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// Contract net, agendas serving by priority.
    ContractNet,
    /// Contract net and a staff holon's advice, agendas serving by priority.
    Staff,
    /// Contract net on agendas that serve in booking order (priority ignored).
    InBookingOrder,
}

/// Every mode, in the order each seed runs them.
const MODES: [Mode; 3] = [Mode::ContractNet, Mode::Staff, Mode::InBookingOrder];

impl Mode {
    fn as_str(self) -> &'static str {
        match self {
            Mode::ContractNet => "contract net",
            Mode::Staff => "with staff",
            Mode::InBookingOrder => "cnet, fifo",
        }
    }

    fn dir_name(self) -> &'static str {
        match self {
            Mode::ContractNet => "cnet",
            Mode::Staff => "staff",
            Mode::InBookingOrder => "fifo",
        }
    }
}

/// What one run measured.
#[derive(Debug, Clone)]
pub struct Outcome {
    pub makespan: Duration,
    pub mean_flow: Duration,
    pub p95_flow: Duration,
    pub rush_mean_flow: Option<Duration>,
    /// Per resource: its controller's busy time over the makespan.
    pub utilisation: BTreeMap<String, f64>,
    pub changeovers: u64,
    /// Steps booked on the staff's advice.
    pub advised: u32,
    pub steps: usize,
}

/// Runs every scenario in `paths`: one on a cell (it names one) in each of the cell
/// options' modes, any other for `seeds` seeds in every mode; prints the tables and
/// writes the JSON to `out`.
pub async fn run(paths: &[PathBuf], seeds: u64, out: &Path, cells: &CellOptions) -> Result<()> {
    let (on_cells, simulated): (Vec<PathBuf>, Vec<PathBuf>) =
        paths.iter().cloned().partition(|p| CellScenario::is_one(p));
    let mut json = serde_json::Map::new();
    if !simulated.is_empty() {
        json.insert(
            "scenarios".into(),
            Value::from(run_simulated(&simulated, seeds).await?),
        );
    }
    if !on_cells.is_empty() {
        let runs = cell::run_all(&on_cells, cells).await?;
        json.insert("cells".into(), serde_json::to_value(&runs)?);
    }
    std::fs::write(out, serde_json::to_string_pretty(&Value::Object(json))?)?;
    println!("written to {}", out.display());
    Ok(())
}

/// Runs the scenarios on simulated robots (`resources`, `products`) for `seeds` seeds
/// in every mode: their summaries.
async fn run_simulated(paths: &[PathBuf], seeds: u64) -> Result<Vec<Value>> {
    let dir = tempfile::Builder::new()
        .prefix("holarchy-schedule")
        .tempdir()?;
    let keep = std::env::var_os("HOLARCHY_BENCH_KEEP").is_some();
    let mut results = Vec::new();
    println!(
        "{:<12} {:>4} {:<13} {:>9} {:>9} {:>9} {:>10} {:>11} {:>9}  utilisation",
        "scenario",
        "seed",
        "mode",
        "makespan",
        "mean flow",
        "p95 flow",
        "rush flow",
        "changeovers",
        "advised"
    );
    for path in paths {
        let scenario = Scenario::load(path)?;
        let mut pairs = Vec::new();
        for seed in 1..=seeds {
            let mut pair = Vec::new();
            for mode in MODES {
                let run_dir =
                    dir.path()
                        .join(format!("{}-{seed}-{}", scenario.name, mode.dir_name()));
                std::fs::create_dir_all(&run_dir)?;
                let outcome = run_once(&scenario, seed, mode, &run_dir)
                    .await
                    .with_context(|| {
                        format!(
                            "{} seed {seed} {}: logs in {}",
                            scenario.name,
                            mode.as_str(),
                            run_dir.display()
                        )
                    });
                let outcome = match outcome {
                    Ok(outcome) => outcome,
                    Err(e) => {
                        let kept = dir.keep();
                        bail!("{e:#} (kept {})", kept.display());
                    }
                };
                print_row(&scenario.name, seed, mode, &outcome);
                pair.push(outcome);
            }
            pairs.push(pair);
        }
        results.push(summarise(&scenario, &pairs));
    }
    println!();
    for result in &results {
        println!(
            "{}: staff vs contract net over {} seeds: makespan {:+.1}%, mean flow {:+.1}%, p95 flow {:+.1}%, rush flow {}; vs contract net on agendas in booking order: makespan {:+.1}%, rush flow {}",
            result["scenario"].as_str().unwrap_or(""),
            seeds,
            result["makespan_change_pct"].as_f64().unwrap_or(0.0),
            result["mean_flow_change_pct"].as_f64().unwrap_or(0.0),
            result["p95_flow_change_pct"].as_f64().unwrap_or(0.0),
            result["rush_flow_change_pct"]
                .as_f64()
                .map(|p| format!("{p:+.1}%"))
                .unwrap_or_else(|| "-".into()),
            result["vs_fifo_makespan_change_pct"].as_f64().unwrap_or(0.0),
            result["vs_fifo_rush_flow_change_pct"]
                .as_f64()
                .map(|p| format!("{p:+.1}%"))
                .unwrap_or_else(|| "-".into()),
        );
    }
    if keep {
        println!("logs kept in {}", dir.keep().display());
    }
    Ok(results)
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

fn print_row(scenario: &str, seed: u64, mode: Mode, o: &Outcome) {
    let utilisation: Vec<String> = o
        .utilisation
        .iter()
        .map(|(r, u)| format!("{r} {:.0}%", u * 100.0))
        .collect();
    println!(
        "{scenario:<12} {seed:>4} {:<13} {:>7.2} s {:>7.2} s {:>7.2} s {:>10} {:>11} {:>9}  {}",
        mode.as_str(),
        o.makespan.as_secs_f64(),
        o.mean_flow.as_secs_f64(),
        o.p95_flow.as_secs_f64(),
        o.rush_mean_flow
            .map(|d| format!("{:.2} s", d.as_secs_f64()))
            .unwrap_or_else(|| "-".into()),
        o.changeovers,
        format!("{}/{}", o.advised, o.steps),
        utilisation.join(", ")
    );
}

/// A scenario's runs, and the staff's change against contract net over the seeds
/// (the mean of the per-seed ratios, each seed's runs on the same orders).
fn summarise(scenario: &Scenario, pairs: &[Vec<Outcome>]) -> Value {
    let change_against = |baseline: usize, figure: &dyn Fn(&Outcome) -> Option<Duration>| {
        let ratios: Vec<f64> = pairs
            .iter()
            .filter_map(|runs| Some(ms(figure(&runs[1])?) / ms(figure(&runs[baseline])?)))
            .collect();
        (!ratios.is_empty())
            .then(|| (ratios.iter().sum::<f64>() / ratios.len() as f64 - 1.0) * 100.0)
    };
    let change = |figure: &dyn Fn(&Outcome) -> Option<Duration>| change_against(0, figure);
    let runs: Vec<Value> = pairs
        .iter()
        .enumerate()
        .flat_map(|(seed, pair)| {
            pair.iter().zip(MODES).map(move |(o, mode)| {
                json!({
                    "seed": seed + 1,
                    "mode": mode.as_str(),
                    "makespan_ms": ms(o.makespan),
                    "mean_flow_ms": ms(o.mean_flow),
                    "p95_flow_ms": ms(o.p95_flow),
                    "rush_mean_flow_ms": o.rush_mean_flow.map(ms),
                    "utilisation": o.utilisation,
                    "changeovers": o.changeovers,
                    "advised_steps": o.advised,
                    "steps": o.steps,
                })
            })
        })
        .collect();
    json!({
        "scenario": scenario.name,
        "description": scenario.description,
        "seeds": pairs.len(),
        "makespan_change_pct": change(&|o| Some(o.makespan)),
        "mean_flow_change_pct": change(&|o| Some(o.mean_flow)),
        "p95_flow_change_pct": change(&|o| Some(o.p95_flow)),
        "rush_flow_change_pct": change(&|o| o.rush_mean_flow),
        "vs_fifo_makespan_change_pct": change_against(2, &|o| Some(o.makespan)),
        "vs_fifo_mean_flow_change_pct": change_against(2, &|o| Some(o.mean_flow)),
        "vs_fifo_rush_flow_change_pct": change_against(2, &|o| o.rush_mean_flow),
        "runs": runs,
    })
}

/// The resource config of `spec` for the benchmark's cell; its agenda lets a booking
/// be passed `max_overtakes` times (`None`: the default).
fn resource_config(dir: &Path, spec: &ResourceSpec, max_overtakes: Option<u32>) -> Result<PathBuf> {
    let overtakes = max_overtakes
        .map(|n| format!("max_overtakes = {n}\n"))
        .unwrap_or_default();
    let mut services = String::new();
    for service in &spec.services {
        let steps = match service.as_str() {
            "pick_n_place" => {
                r#"[
  { action = "pick", until = ["picking_done"], position = "pick" },
  { action = "place", until = ["placing_done"], position = "place" },
]"#
            }
            "inspect" => r#"[{ action = "inspect", until = ["inspect_pass", "inspect_fail"] }]"#,
            _ => r#"[{ action = "move", until = ["arrived"], position = "destination" }]"#,
        };
        let nominal = spec.nominal_ms.get(service).copied().unwrap_or(1000);
        services.push_str(&format!(
            "\n[services.{service}]\nnominal_duration_ms = {nominal}\nsteps = {steps}\n"
        ));
    }
    let path = dir.join(format!("{}.toml", spec.name));
    std::fs::write(
        &path,
        format!(
            r#"cell = "unset"
name = "{}"

[controller]
address = "127.0.0.1:1"
reconnect_interval_ms = 100
command_timeout_ms = 30000
connect_timeout_ms = 500

[agenda]
capacity = 256
{overtakes}{services}"#,
            spec.name
        ),
    )?;
    Ok(path)
}

/// The product config of `spec`: its steps, each with its program.
fn product_config(dir: &Path, spec: &ProductSpec) -> Result<PathBuf> {
    let mut steps = String::new();
    for service in &spec.steps {
        let info = match service.as_str() {
            "pick_n_place" => format!(
                "{{ program = \"{}\", pick = {{ x = 1.0, y = 2.0, z = 3.0 }}, place = {{ x = 4.0, y = 5.0, z = 6.0 }} }}",
                spec.program
            ),
            "transport" => format!(
                "{{ program = \"{}\", destination = {{ x = 0.0, y = 1200.0, z = 0.0 }} }}",
                spec.program
            ),
            _ => format!("{{ program = \"{}\" }}", spec.program),
        };
        steps.push_str(&format!(
            "\n[[steps]]\nservice_type = \"{service}\"\ninfo = {info}\n"
        ));
    }
    let path = dir.join(format!("{}.toml", spec.name));
    std::fs::write(
        &path,
        format!(
            "cell = \"unset\"\nname = \"{}\"\nkind = \"product\"\n{steps}",
            spec.name
        ),
    )?;
    Ok(path)
}

/// One run of `scenario`'s order stream of `seed` in `mode`, on a cell of its own.
async fn run_once(scenario: &Scenario, seed: u64, mode: Mode, dir: &Path) -> Result<Outcome> {
    let cell_name = format!("sched-{}", scenario.name.replace('_', "-"));
    let cell = router(&cell_name, None).await?;
    let (mut processes, sims) = start_resources(scenario, mode, dir, &cell).await?;
    start_the_rest(scenario, mode, dir, &cell, &mut processes).await?;
    let states = cell
        .session
        .declare_subscriber(cell.keys.order_states())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let stream = arrivals(scenario, seed);
    let total = stream.len();
    let submitter = submit_as_they_arrive(&cell, stream, scenario.orders.rush_priority);
    let done = await_all_done(&states, total).await?;
    let submitted = submitter.await??;
    let outcome = figures(scenario, &submitted, &done, &sims)?;
    drop(processes);
    drop(sims);
    Ok(outcome)
}

/// The scenario's resources, each on a controller simulator of its own, until each is
/// alive and free.
async fn start_resources(
    scenario: &Scenario,
    mode: Mode,
    dir: &Path,
    cell: &holarchy_tests::Cell,
) -> Result<(Vec<Process>, Vec<(String, Sim)>)> {
    let mut processes: Vec<Process> = Vec::new();
    let mut sims: Vec<(String, Sim)> = Vec::new();
    for spec in &scenario.resources {
        let mut flags: Vec<String> = Vec::new();
        for (action, ms) in &spec.action_ms {
            flags.push("--action-ms".into());
            flags.push(format!("{action}={ms}"));
        }
        flags.push("--changeover-ms".into());
        flags.push(spec.changeover_ms.to_string());
        let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
        let sim = Sim::start(dir, &format!("{}-sim", spec.name), "127.0.0.1:0", &flags)?;
        let max_overtakes = (mode == Mode::InBookingOrder).then_some(0);
        let config = resource_config(dir, spec, max_overtakes)?;
        processes.push(start_node(
            dir,
            &config,
            cell.keys.cell(),
            &cell.endpoint,
            &sim.address,
            &[],
        )?);
        sims.push((spec.name.clone(), sim));
    }
    for spec in &scenario.resources {
        cell.wait_alive(&HolonId::resource(&spec.name)?).await?;
        cell.wait_state(&spec.name, "free", |s| s["state"] == "free")
            .await?;
    }
    Ok((processes, sims))
}

/// The scenario's products, the planner (in `Mode::Staff`) and the order-node, each
/// alive before the next.
async fn start_the_rest(
    scenario: &Scenario,
    mode: Mode,
    dir: &Path,
    cell: &holarchy_tests::Cell,
    processes: &mut Vec<Process>,
) -> Result<()> {
    for spec in &scenario.products {
        let config = product_config(dir, spec)?;
        processes.push(start_holon(
            dir,
            "holon-node",
            &config,
            &spec.name,
            cell,
            &[],
        )?);
        cell.wait_alive(&HolonId::new(HolonKind::Product, &spec.name)?)
            .await?;
    }
    if mode == Mode::Staff {
        processes.push(start_holon(
            dir,
            "holon-node",
            &demo_config("planner.toml"),
            "planner",
            cell,
            &[],
        )?);
        cell.wait_alive(&HolonId::staff("planner")?).await?;
    }
    let data = dir.join("data");
    let data = data.to_str().context("a UTF-8 directory")?;
    processes.push(start_holon(
        dir,
        "order-node",
        &demo_config("orders1.toml"),
        "orders1",
        cell,
        &["--data-dir", data],
    )?);
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await?;
    // The order-node sees the staff before the first order asks.
    tokio::time::sleep(Duration::from_millis(300)).await;

    Ok(())
}

/// Submits the stream's orders in a task of its own, at the stream's moments, whatever
/// the cell does; each order's name, when it was submitted and whether it was a rush.
fn submit_as_they_arrive(
    cell: &holarchy_tests::Cell,
    stream: Vec<Arrival>,
    rush_priority: i32,
) -> tokio::task::JoinHandle<Result<Vec<(String, Instant, bool)>>> {
    let started = Instant::now();
    let session = cell.session.clone();
    let keys = cell.keys.clone();
    tokio::spawn(async move {
        let mut submitted: Vec<(String, Instant, bool)> = Vec::new();
        for arrival in stream {
            tokio::time::sleep_until((started + arrival.at).into()).await;
            let work = WorkOrder {
                product: arrival.product.clone(),
                count: 1,
                priority: if arrival.rush { rush_priority } else { 0 },
                due: None,
                queue: false,
                submit_id: None,
            };
            let at = Instant::now();
            let names = holarchy_tests::submit_on(&session, &keys, &work).await?;
            for name in names {
                submitted.push((name, at, arrival.rush));
            }
        }
        anyhow::Ok(submitted)
    })
}

/// Each order's end (when it was seen done, and its last snapshot), once all `total` are
/// done; an order that ends otherwise fails the run.
async fn await_all_done(
    states: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    total: usize,
) -> Result<BTreeMap<String, (Instant, OrderSnapshot)>> {
    let mut done: BTreeMap<String, (Instant, OrderSnapshot)> = BTreeMap::new();
    let deadline = Instant::now() + Duration::from_secs(300);
    while done.len() < total {
        let sample = tokio::time::timeout_at(deadline.into(), states.recv_async())
            .await
            .map_err(|_| anyhow!("{} of {total} orders done after 300 s", done.len()))?
            .map_err(|e| anyhow!("{e}"))?;
        let Ok(order) = serde_json::from_slice::<OrderSnapshot>(&sample.payload().to_bytes())
        else {
            continue;
        };
        if order.status.is_final() {
            if order.status != OrderStatus::Done {
                bail!(
                    "{} ended {}: {}",
                    order.holon,
                    order.status.as_str(),
                    order.reason.as_ref().map_or("", |r| r.as_str())
                );
            }
            done.entry(order.holon.name().to_string())
                .or_insert((Instant::now(), order));
        }
    }
    Ok(done)
}

/// The run's figures: makespan, flow times, each resource's utilisation, changeovers.
fn figures(
    scenario: &Scenario,
    submitted: &[(String, Instant, bool)],
    done: &BTreeMap<String, (Instant, OrderSnapshot)>,
    sims: &[(String, Sim)],
) -> Result<Outcome> {
    let first = submitted
        .iter()
        .map(|(_, at, _)| *at)
        .min()
        .context("no order")?;
    let last = done.values().map(|(at, _)| *at).max().context("no order")?;
    let makespan = last - first;
    let mut flows: Vec<Duration> = Vec::new();
    let mut rush: Vec<Duration> = Vec::new();
    for (name, at, is_rush) in submitted {
        let (end, _) = done.get(name).with_context(|| format!("{name} not done"))?;
        flows.push(*end - *at);
        if *is_rush {
            rush.push(*end - *at);
        }
    }
    flows.sort();
    let mean = |v: &[Duration]| v.iter().sum::<Duration>() / v.len().max(1) as u32;
    let p95 = flows[((flows.len() as f64 * 0.95).ceil() as usize).clamp(1, flows.len()) - 1];
    let mut utilisation = BTreeMap::new();
    let mut changeovers = 0;
    for (name, sim) in sims {
        let counts = sim.counts();
        let spec = scenario
            .resources
            .iter()
            .find(|r| &r.name == name)
            .expect("a resource of the scenario");
        let mut busy_ms = 0u64;
        if let Some(by_action) = counts["by_action"].as_object() {
            for (action, n) in by_action {
                busy_ms +=
                    n.as_u64().unwrap_or(0) * spec.action_ms.get(action).copied().unwrap_or(0);
            }
        }
        let changed = counts["changeovers"].as_u64().unwrap_or(0);
        busy_ms += changed * spec.changeover_ms;
        changeovers += changed;
        utilisation.insert(name.clone(), busy_ms as f64 / ms(makespan));
    }
    let advised = done.values().map(|(_, o)| o.advised).sum();
    let steps = done.values().map(|(_, o)| o.completed.len()).sum();
    Ok(Outcome {
        makespan,
        mean_flow: mean(&flows),
        p95_flow: p95,
        rush_mean_flow: (!rush.is_empty()).then(|| mean(&rush)),
        utilisation,
        changeovers,
        advised,
        steps,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_scenarios_load_and_a_seed_gives_the_same_orders() {
        for file in ["mixed.toml", "identical.toml"] {
            let path = holarchy_tests::workspace_root()
                .join("deploy/scenarios")
                .join(file);
            let scenario = Scenario::load(&path).unwrap();
            let a = arrivals(&scenario, 7);
            let b = arrivals(&scenario, 7);
            assert_eq!(a.len(), scenario.orders.count as usize);
            assert!(a
                .iter()
                .zip(&b)
                .all(|(x, y)| x.at == y.at && x.product == y.product));
            let c = arrivals(&scenario, 8);
            assert!(a.iter().zip(&c).any(|(x, y)| x.at != y.at));
        }
    }
}

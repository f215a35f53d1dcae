//! The upgrade benchmark: what replacing a holon's process costs the cell while orders
//! run. Each round runs a fresh cell (robot1 on a simulator, the product `part`, the
//! order-node `orders1`, forty orders) and replaces robot1, then the order-node, then
//! the product, in one of two ways:
//!
//! - **take-over**: the successor is started with `--take-over` (what `cell upgrade`
//!   does): the running process finishes its step, keeps its bookings and hands over;
//! - **restart** (the baseline, the only way before): SIGTERM, and the new process
//!   started as soon as the old one has exited (what a service manager does).
//!
//! Figures per holon: how long no process held its name (its token's absence, as a
//! client of the cell sees it), and for robot1 how long it started no job (from the
//! first state without a running job to the next with one: the running step's end to
//! the next step's start, what an order waits beyond the running step). Orders' rebooks
//! and failed attempts, and steps run, are counted: the take-over must have none extra.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use holarchy_tests::{demo_config, resource_config, start_holon, start_node, Cell, Process, Sim};
use nix::sys::signal::Signal;
use schemas::{HolonId, HolonKind};
use serde_json::{json, Value};

use crate::cells::router;

/// How a process is replaced.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Way {
    TakeOver,
    Restart,
}

impl Way {
    fn name(self) -> &'static str {
        match self {
            Way::TakeOver => "take-over",
            Way::Restart => "restart",
        }
    }
}

/// The figures of one round.
#[derive(Debug, Default, Clone, serde::Serialize)]
struct Round {
    /// Per holon: ms without a process holding its name.
    away_ms: BTreeMap<String, f64>,
    /// ms robot1 started no job around its replacement.
    robot_idle_ms: f64,
    /// The usual pause between two of robot1's jobs (median), for scale.
    robot_usual_idle_ms: f64,
    rebooks: u64,
    failed_attempts: u64,
    /// Steps the controller ran, against the orders' steps.
    steps_run: u64,
    steps_ordered: u64,
}

/// Liveliness changes and robot1's states as they arrive, stamped here.
#[derive(Default)]
struct Watch {
    tokens: Vec<(Instant, String, bool)>,
    /// (when, a job is running)
    robot: Vec<(Instant, bool)>,
}

const ORDERS: u32 = 40;

pub async fn run(rounds: usize, out: &Path) -> Result<()> {
    let mut all: BTreeMap<&str, Vec<Round>> = BTreeMap::new();
    for round in 0..rounds {
        // Alternate which way goes first: neither always runs on a warmer machine.
        let ways = if round % 2 == 0 {
            [Way::TakeOver, Way::Restart]
        } else {
            [Way::Restart, Way::TakeOver]
        };
        for way in ways {
            let figures = one_round(way, round)
                .await
                .with_context(|| format!("round {round}, {}", way.name()))?;
            println!("round {round} {:>9}: {figures:?}", way.name());
            all.entry(way.name()).or_default().push(figures);
        }
    }
    let summary = summarize(&all);
    println!("\n{}", table(&summary));
    let text = serde_json::to_string_pretty(&json!({
        "rounds": all,
        "summary": summary,
    }))?;
    std::fs::write(out, text).with_context(|| format!("cannot write {}", out.display()))?;
    println!("written to {}", out.display());
    Ok(())
}

async fn one_round(way: Way, round: usize) -> Result<Round> {
    let dir = tempfile::tempdir()?;
    let dir = dir.path();
    let cell = router(&format!("bench-upgrade-{round}"), None).await?;
    let sim = Sim::start(dir, "sim1", "127.0.0.1:0", &["--delay-ms", "100"])?;
    let robot_config = resource_config(dir, "robot1", 10_000)?;
    let robot_data = dir.join("robot-data");
    let robot_data = robot_data.to_str().context("a UTF-8 path")?.to_string();
    let robot_args = ["--data-dir", robot_data.as_str()];
    let mut robot = cell
        .start_free_resource(dir, &robot_config, &sim.address, &robot_args)
        .await?;
    let orders_data = dir.join("orders-data");
    let orders_config = demo_config("orders1.toml");
    let (mut product, mut orders) = cell
        .start_part_and_orders(dir, &orders_config, &orders_data)
        .await?;
    let orders_data = orders_data.to_str().context("a UTF-8 path")?.to_string();
    let product_config = dir.join("part.toml");

    let watch = Arc::new(Mutex::new(Watch::default()));
    let (tokens, states) = watch_the_cell(&cell, &watch).await?;

    let names = cell.submit("part", ORDERS).await?;
    sim.wait_executed("pick", 3).await?;
    let next = dir.join("next");
    std::fs::create_dir_all(&next)?;

    // robot1.
    let robot_from = Instant::now();
    robot = replace(way, robot, "robot1", || {
        let mut args = robot_args.to_vec();
        if way == Way::TakeOver {
            args.push("--take-over");
        }
        start_node(
            &next,
            &robot_config,
            cell.keys.cell(),
            &cell.endpoint,
            &sim.address,
            &args,
        )
    })
    .await?;
    cell.wait_alive(&HolonId::resource("robot1")?).await?;
    tokio::time::sleep(Duration::from_millis(1500)).await;

    // The order-node.
    orders = replace(way, orders, "orders1", || {
        let mut args = vec!["--data-dir", orders_data.as_str()];
        if way == Way::TakeOver {
            args.push("--take-over");
        }
        start_holon(&next, "order-node", &orders_config, "orders1", &cell, &args)
    })
    .await?;
    cell.wait_token(&cell.keys.host("order-node", "orders1"))
        .await?;
    tokio::time::sleep(Duration::from_millis(1500)).await;

    // The product.
    product = replace(way, product, "part", || {
        let args: &[&str] = if way == Way::TakeOver {
            &["--take-over"]
        } else {
            &[]
        };
        start_holon(&next, "holon-node", &product_config, "part", &cell, args)
    })
    .await?;
    cell.wait_alive(&HolonId::new(HolonKind::Product, "part")?)
        .await?;

    let ended = wait_done(&cell, &names).await?;
    drop((tokens, states));
    let figures = round_figures(&lock(&watch), &sim, &ended, robot_from)?;
    drop((robot, orders, product));
    Ok(figures)
}

/// What the round watches of the cell: every liveliness token's comings and goings,
/// and whether robot1 runs a step, each with when it was seen.
async fn watch_the_cell(
    cell: &holarchy_tests::Cell,
    watch: &Arc<Mutex<Watch>>,
) -> Result<(zenoh::pubsub::Subscriber<()>, zenoh::pubsub::Subscriber<()>)> {
    let tokens = {
        let watch = watch.clone();
        let prefix = format!("holarchy/{}/", cell.keys.cell());
        cell.session
            .liveliness()
            .declare_subscriber(format!("{prefix}**"))
            .callback(move |sample| {
                let key = sample
                    .key_expr()
                    .as_str()
                    .trim_start_matches(&prefix)
                    .to_string();
                let put = sample.kind() == zenoh::sample::SampleKind::Put;
                lock(&watch).tokens.push((Instant::now(), key, put));
            })
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?
    };
    let states = {
        let watch = watch.clone();
        cell.session
            .declare_subscriber(cell.keys.state(&HolonId::resource("robot1")?))
            .callback(move |sample| {
                if let Ok(state) = serde_json::from_slice::<Value>(&sample.payload().to_bytes()) {
                    let running = !state["current"].is_null();
                    lock(&watch).robot.push((Instant::now(), running));
                }
            })
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?
    };
    Ok((tokens, states))
}

/// The round's figures from what was watched: robot1's idle time, the steps run, how
/// long each holon's token was away, the rebooks and failed attempts.
fn round_figures(watch: &Watch, sim: &Sim, ended: &[Value], robot_from: Instant) -> Result<Round> {
    let mut figures = Round {
        robot_idle_ms: longest_idle(&watch.robot, robot_from),
        robot_usual_idle_ms: usual_idle(&watch.robot, robot_from),
        steps_run: sim.executed("pick"),
        steps_ordered: ORDERS as u64,
        ..Round::default()
    };
    for (holon, key) in [
        ("robot1", "alive/resource/robot1"),
        ("orders1", "host/order-node/orders1"),
        ("part", "alive/product/part"),
    ] {
        figures
            .away_ms
            .insert(holon.to_string(), away(&watch.tokens, key)?);
    }
    for state in ended {
        figures.rebooks += state["rebooks"].as_u64().unwrap_or(0);
        figures.failed_attempts += state["failed_attempts"].as_u64().unwrap_or(0);
    }
    Ok(figures)
}

/// Replaces the running `process` (holon `name`) by the one `start` starts, `way`.
async fn replace(
    way: Way,
    mut process: Process,
    name: &str,
    start: impl FnOnce() -> Result<Process>,
) -> Result<Process> {
    match way {
        Way::TakeOver => {
            let successor = start()?;
            let status = process.wait_exit(Duration::from_secs(30))?;
            if !status.success() {
                bail!(
                    "{name} ended {status} on its hand-over: {}",
                    process.stderr()
                );
            }
            Ok(successor)
        }
        Way::Restart => {
            process.signal(Signal::SIGTERM)?;
            let status = process.wait_exit(Duration::from_secs(30))?;
            if !status.success() {
                bail!("{name} ended {status} on SIGTERM: {}", process.stderr());
            }
            start()
        }
    }
}

/// Waits until every order has ended; their states.
async fn wait_done(cell: &Cell, names: &[String]) -> Result<Vec<Value>> {
    let deadline = Instant::now() + Duration::from_secs(180);
    loop {
        let mut states = Vec::new();
        for name in names {
            states.push(cell.order_state(name).await.unwrap_or_default());
        }
        if states.iter().all(|s| s["status"] == "done") {
            return Ok(states);
        }
        if Instant::now() > deadline {
            bail!("orders not done within 180 s");
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// How long the token `key` was away (Delete to the next Put), in ms.
fn away(tokens: &[(Instant, String, bool)], key: &str) -> Result<f64> {
    let gone = tokens
        .iter()
        .find(|(_, k, put)| k == key && !put)
        .with_context(|| format!("{key} never went away"))?;
    let back = tokens
        .iter()
        .find(|(at, k, put)| k == key && *put && *at > gone.0)
        .with_context(|| format!("{key} never came back"))?;
    Ok(ms(back.0 - gone.0))
}

/// The longest time after `from` between a state without a running job and the next
/// with one.
fn longest_idle(states: &[(Instant, bool)], from: Instant) -> f64 {
    idle_spells(states, from).into_iter().fold(0.0, f64::max)
}

/// The median pause between jobs before `until`.
fn usual_idle(states: &[(Instant, bool)], until: Instant) -> f64 {
    let before: Vec<(Instant, bool)> = states
        .iter()
        .copied()
        .filter(|(at, _)| *at < until)
        .collect();
    let mut spells = idle_spells(&before, before.first().map(|s| s.0).unwrap_or(until));
    median(&mut spells)
}

fn idle_spells(states: &[(Instant, bool)], from: Instant) -> Vec<f64> {
    let mut spells = Vec::new();
    let mut idle_since: Option<Instant> = None;
    for &(at, running) in states.iter().filter(|(at, _)| *at >= from) {
        match (running, idle_since) {
            (false, None) => idle_since = Some(at),
            (true, Some(since)) => {
                spells.push(ms(at - since));
                idle_since = None;
            }
            _ => {}
        }
    }
    spells
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    values.sort_by(|a, b| a.total_cmp(b));
    values[values.len() / 2]
}

fn lock(watch: &Mutex<Watch>) -> std::sync::MutexGuard<'_, Watch> {
    watch.lock().unwrap_or_else(|e| e.into_inner())
}

/// Medians per way, and the take-over's against the restart's.
fn summarize(all: &BTreeMap<&str, Vec<Round>>) -> Value {
    let figure = |way: &str, pick: &dyn Fn(&Round) -> f64| -> f64 {
        let mut values: Vec<f64> = all.get(way).into_iter().flatten().map(pick).collect();
        median(&mut values)
    };
    let total = |way: &str, pick: &dyn Fn(&Round) -> u64| -> u64 {
        all.get(way).into_iter().flatten().map(pick).sum()
    };
    let mut rows = serde_json::Map::new();
    let mut row = |name: &str, pick: &dyn Fn(&Round) -> f64| {
        let (ours, base) = (figure("take-over", pick), figure("restart", pick));
        rows.insert(
            name.to_string(),
            json!({"take_over": ours, "restart": base, "ratio": if base > 0.0 { ours / base } else { 0.0 }}),
        );
    };
    row("robot1 idle beyond its step (ms)", &|r| r.robot_idle_ms);
    row("robot1 usual pause between jobs (ms)", &|r| {
        r.robot_usual_idle_ms
    });
    for holon in ["robot1", "orders1", "part"] {
        row(&format!("{holon} away (ms)"), &|r| {
            r.away_ms.get(holon).copied().unwrap_or(0.0)
        });
    }
    for (name, pick) in [
        ("rebooks", (|r: &Round| r.rebooks) as fn(&Round) -> u64),
        ("failed attempts", |r| r.failed_attempts),
        ("steps run beyond those ordered", |r| {
            r.steps_run.saturating_sub(r.steps_ordered)
        }),
    ] {
        rows.insert(
            name.to_string(),
            json!({"take_over": total("take-over", &pick), "restart": total("restart", &pick)}),
        );
    }
    Value::Object(rows)
}

fn table(summary: &Value) -> String {
    let mut text = format!(
        "{:<40} {:>12} {:>12} {:>8}\n",
        "figure (median; counts summed)", "take-over", "restart", "ratio"
    );
    for (name, row) in summary.as_object().into_iter().flatten() {
        let cell = |v: &Value| match v.as_f64() {
            Some(f) if v.is_f64() => format!("{f:.1}"),
            _ => v.to_string(),
        };
        let ratio = row
            .get("ratio")
            .and_then(Value::as_f64)
            .map(|r| format!("{r:.2}"))
            .unwrap_or_default();
        text.push_str(&format!(
            "{name:<40} {:>12} {:>12} {ratio:>8}\n",
            cell(&row["take_over"]),
            cell(&row["restart"])
        ));
    }
    text
}

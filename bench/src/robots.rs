//! Robots that take time: K robots whose actions take 20 ms (a `pick_n_place` step is a
//! pick and a place: 40 ms), 20 one-step orders per robot submitted at once through a
//! real order-node. The ideal is K steps per step time; what the control adds (proposal
//! rounds, bookings, starts, deliveries, journals) shows as the distance to it, and as
//! the CPU time the whole cell spent per completed order.

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use schemas::{OrderSnapshot, OrderStatus};
use serde_json::json;

use crate::cells::{router, start_product_and_orders, start_robots};
use crate::process::cpu_time;
use crate::run::Run;

/// How long each robot action takes.
const ACTION: Duration = Duration::from_millis(20);
/// Actions per `pick_n_place` step.
const ACTIONS_PER_STEP: u32 = 2;
/// Orders per robot.
const ORDERS_PER_ROBOT: u32 = 20;

pub async fn section(run: &mut Run) -> Result<()> {
    for robots in [1usize, 2, 4, 8] {
        let figure = working_robots(run, robots).await?;
        let ideal = robots as f64 / (ACTION * ACTIONS_PER_STEP).as_secs_f64();
        run.table.add(
            &format!("robots that take time: {robots} robot(s), 20 ms actions"),
            format!(
                "{:.1} orders/s, {:.0}% of ideal; flowing {:.0}%",
                figure.orders_per_s,
                figure.orders_per_s / ideal * 100.0,
                figure.flowing_per_s / ideal * 100.0
            ),
            format!(
                "ideal {ideal:.1}/s (K / 40 ms step); flowing: from the K-th done to the last; CPU {:.1} ms per order, all processes; first done after {:.0} ms; {}-{} steps per robot",
                figure.cpu_per_order.as_secs_f64() * 1e3,
                figure.first_done.as_secs_f64() * 1e3,
                figure.jobs_per_robot.0,
                figure.jobs_per_robot.1,
            ),
            json!({
                "robots": robots,
                "orders": figure.orders,
                "orders_per_s": figure.orders_per_s,
                "ideal_per_s": ideal,
                "share_of_ideal": figure.orders_per_s / ideal,
                "flowing_per_s": figure.flowing_per_s,
                "flowing_share_of_ideal": figure.flowing_per_s / ideal,
                "cpu_ms_per_order": figure.cpu_per_order.as_secs_f64() * 1e3,
                "first_done_ms": figure.first_done.as_secs_f64() * 1e3,
                "steps_per_robot_min": figure.jobs_per_robot.0,
                "steps_per_robot_max": figure.jobs_per_robot.1,
            }),
        );
    }
    Ok(())
}

struct Figure {
    orders: u32,
    orders_per_s: f64,
    cpu_per_order: Duration,
    /// From the submission to the first order done: the start, plus one step.
    first_done: Duration,
    /// Orders done per second once they flow: after the K-th done (every robot has
    /// finished a first step, near enough), to the last; the start left out.
    flowing_per_s: f64,
    /// Steps done by the robot that did the fewest, and by the one that did the most:
    /// the busiest robot decides when the last order ends.
    jobs_per_robot: (usize, usize),
}

/// CPU time of the cell's processes (`pids`) and of this one (the cell's router runs
/// here; so does the measuring, a small share).
fn cell_cpu(pids: &[i32]) -> Duration {
    pids.iter()
        .chain([std::process::id() as i32].iter())
        .filter_map(|pid| cpu_time(*pid).ok())
        .sum()
}

async fn working_robots(run: &Run, robots: usize) -> Result<Figure> {
    let cell_name = format!("bench-k{robots}");
    let cell = router(&cell_name, None).await?;
    let dir = run.dir.join(&cell_name);
    std::fs::create_dir_all(&dir)?;
    let delay = ACTION.as_millis().to_string();
    let keep = start_robots(&cell, &dir, robots, &["--delay-ms", &delay]).await?;
    let (product, order_node) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;
    let pids: Vec<i32> = keep
        .iter()
        .flat_map(|(sim, node)| [sim.process.pid(), node.pid()])
        .chain([product.pid(), order_node.pid()])
        .collect();
    // Every order's end, as it is published.
    let states = cell
        .session
        .declare_subscriber(cell.keys.order_states())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let orders = ORDERS_PER_ROBOT * robots as u32;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let cpu_before = cell_cpu(&pids);
    let t = Instant::now();
    cell.submit("part", orders).await?;
    let mut done = std::collections::HashSet::new();
    let mut first_done = None;
    let mut done_at = Vec::new();
    let mut jobs: std::collections::HashMap<schemas::HolonId, usize> = Default::default();
    while done.len() < orders as usize {
        let sample = tokio::time::timeout(Duration::from_secs(120), states.recv_async())
            .await
            .map_err(|_| anyhow!("{} of {orders} orders done after 120 s", done.len()))?
            .map_err(|e| anyhow!("{e}"))?;
        let snapshot: OrderSnapshot = serde_json::from_slice(&sample.payload().to_bytes())?;
        match snapshot.status {
            OrderStatus::Done => {
                first_done.get_or_insert_with(|| t.elapsed());
                if done.insert(snapshot.holon) {
                    done_at.push(t.elapsed());
                    for (_, resource) in snapshot.completed {
                        *jobs.entry(resource).or_default() += 1;
                    }
                }
            }
            OrderStatus::Running => {}
            other => bail!("{} ended {other:?}: {:?}", snapshot.holon, snapshot.reason),
        }
    }
    let elapsed = t.elapsed();
    let cpu = cell_cpu(&pids).saturating_sub(cpu_before);
    drop((keep, product, order_node));
    Ok(Figure {
        orders,
        orders_per_s: orders as f64 / elapsed.as_secs_f64(),
        cpu_per_order: cpu / orders,
        first_done: first_done.unwrap_or(elapsed),
        flowing_per_s: (done_at.len() - robots) as f64
            / elapsed
                .saturating_sub(done_at[robots - 1])
                .as_secs_f64()
                .max(1e-3),
        jobs_per_robot: (
            jobs.values().copied().min().unwrap_or(0),
            jobs.values().copied().max().unwrap_or(0),
        ),
    })
}

//! The throughput section: orders per second through cells of 1, 2 and 4 robots.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use serde_json::json;

use crate::cells::{order_counts, router, start_product_and_orders, start_robots};
use crate::run::Run;

/// Cell throughput with 1, 2 and 4 robots, 40 concurrent one-step orders each.
pub async fn section(run: &mut Run) -> Result<()> {
    for robots in [1usize, 2, 4] {
        let figure = throughput(&run.dir, robots, 40).await?;
        run.table.add(
            &format!("cell throughput: {robots} robot(s), 40 concurrent orders"),
            format!("{:.1} orders/s", figure),
            "one pick_n_place step each, 0 ms actions".into(),
            json!({"robots": robots, "orders": 40, "orders_per_s": figure}),
        );
    }
    Ok(())
}

/// Orders per second through a cell of `robots` robots with one-step orders.
async fn throughput(dir: &Path, robots: usize, orders: u32) -> Result<f64> {
    let cell_name = format!("bench-t{robots}");
    let cell = router(&cell_name, None).await?;
    let dir = dir.join(&cell_name);
    std::fs::create_dir_all(&dir)?;
    let _robots = start_robots(&cell, &dir, robots, &[]).await?;
    let (_product, _orders) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;
    let t = Instant::now();
    cell.submit("part", orders).await?;
    loop {
        let done = order_counts(&cell).await?.done as u32;
        if done == orders {
            return Ok(orders as f64 / t.elapsed().as_secs_f64());
        }
        if t.elapsed() > Duration::from_secs(120) {
            bail!("{done} of {orders} orders done after 120 s");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

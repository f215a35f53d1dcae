//! The orders section: an order-node's memory, threads and CPU while it hosts waiting
//! orders, against the same node idle.

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use holarchy_tests::{resource_config, Sim};
use serde_json::json;

use crate::cells::{router, start_product_and_orders};
use crate::process::{cpu_time, footprint};
use crate::run::Run;

/// An order-node hosting `orders` orders that wait for a robot (one robot, busy with a
/// long job, agenda full): its memory, threads and CPU, against the same node idle.
pub async fn section(run: &mut Run, orders: u32) -> Result<()> {
    let cell = router("bench-orders", None).await?;
    let dir = run.dir.join("orders");
    std::fs::create_dir_all(&dir)?;
    let slow = Sim::start(&dir, "slow", "127.0.0.1:0", &["--delay-ms", "600000"])?;
    let config = resource_config(&dir, "robot1", 600_000)?;
    let _robot = holarchy_tests::start_node(
        &dir,
        &config,
        "bench-orders",
        &cell.endpoint,
        &slow.address,
        &[],
    )?;
    cell.wait_state("robot1", "free", |s| s["state"] == "free")
        .await?;
    // The demo's order-node, with orders that wait for a resource for up to 10 minutes.
    let config = dir.join("orders1.toml");
    let demo = std::fs::read_to_string(holarchy_tests::demo_config("orders1.toml"))?;
    std::fs::write(
        &config,
        demo.replace(
            "no_resource_timeout_ms = 60000",
            "no_resource_timeout_ms = 600000",
        ),
    )?;
    let (_product, node) = start_product_and_orders(&dir, &cell, &config).await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (idle_rss, idle_threads) = footprint(node.pid())?;
    cell.submit("part", orders).await?;
    // Until the node reports every order (an order waiting for a resource holds no
    // token: it declares one when it books), then let them settle into waiting.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let replies = cell
            .session
            .get(cell.keys.order_states())
            .timeout(Duration::from_secs(5))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let mut hosted = 0;
        while let Ok(reply) = replies.recv_async().await {
            hosted += usize::from(reply.result().is_ok());
        }
        if hosted >= orders as usize {
            break;
        }
        if Instant::now() > deadline {
            bail!("only {hosted} of {orders} orders reported after 60 s");
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    tokio::time::sleep(Duration::from_secs(2)).await;
    let window = Duration::from_secs(5);
    let cpu_before = cpu_time(node.pid())?;
    tokio::time::sleep(window).await;
    let cpu = (cpu_time(node.pid())? - cpu_before).as_secs_f64() / window.as_secs_f64();
    let (rss, threads) = footprint(node.pid())?;
    run.table.add(
        &format!("footprint: order-node hosting {orders} waiting orders"),
        format!("{:.1} MiB resident, {threads} threads, {:.0}% of a core", rss as f64 / 1024.0, cpu * 100.0),
        format!("idle node {:.1} MiB, {idle_threads} threads", idle_rss as f64 / 1024.0),
        json!({"orders": orders, "rss_kib": rss, "threads": threads, "cpu_share": cpu, "idle_rss_kib": idle_rss, "idle_threads": idle_threads}),
    );
    Ok(())
}

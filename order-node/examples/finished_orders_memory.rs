//! How an order-node's resident memory grows with finished orders: starts an
//! order-node (journal in a temporary directory), reads its VmRSS idle, has it finish N
//! orders and reads it again, then once more after a read of every order's state (what
//! `cell orders` and the dashboard ask), and after a restart on the same journal (idle,
//! then after a read of every order's state).
//!
//! The orders get a plan of the demo breaker's steps from a product answered here, find
//! no resource and fail (`no resource could be booked`), so each finished order holds a
//! plan and an attempt history, as in a real cell, without robots.
//!
//! ```text
//! cargo build -p order-node
//! cargo run -p order-node --example finished_orders_memory -- [ORDERS [BATCH [ORDER_NODE_BINARY]]]
//! ```
//!
//! ORDERS defaults to 10000; they are submitted BATCH at a time (default 100), each
//! batch once the last has finished, so that few orders are unfinished at once as in
//! a running cell (the memory of a thousand orders running at once stays with the
//! process's allocator, and would hide what finished orders keep). The growth per
//! finished order is counted from the first batch on (the node warmed up). The binary
//! defaults to `target/debug/order-node`. Linux only (reads `/proc/<pid>/status`). A
//! measurement, not a test: it prints figures and asserts none.

use std::collections::HashSet;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use schemas::{CellKeys, OrderSnapshot, SubmitReply, WorkOrder};

/// The plan every order gets: the demo breaker's.
const PLAN: &str = r#"{"product": "membench", "steps": [
  {"service_type": "transport", "info": {"destination": {"x": 0.0, "y": 1200.0, "z": 0.0}}},
  {"service_type": "pick_n_place", "info": {"pick": {"x": 100.0, "y": 20.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 0.0}, "place": {"x": 300.0, "y": 40.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 90.0}}},
  {"service_type": "inspect", "info": {"program": "breaker-v1"}, "reject_results": ["inspect_fail"], "on_reject": {"rework": {"from_step": 2, "max_reworks": 2}}},
  {"service_type": "transport", "info": {"destination": {"x": 0.0, "y": 0.0, "z": 0.0}}}
]}"#;

/// The order-node under measurement; killed when dropped.
struct Node(Child);

impl Drop for Node {
    fn drop(&mut self) {
        if let Err(e) = self.0.kill() {
            eprintln!("cannot stop the order-node: {e}");
        }
        if let Err(e) = self.0.wait() {
            eprintln!("cannot wait for the order-node: {e}");
        }
    }
}

/// The resident memory of `pid`, in KiB.
fn rss_kib(pid: u32) -> anyhow::Result<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status"))?;
    let line = status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .context("no VmRSS line")?;
    Ok(line
        .split_whitespace()
        .nth(1)
        .context("no VmRSS figure")?
        .parse()?)
}

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let orders: u32 = args.next().map_or(Ok(10_000), |a| a.parse())?;
    // At most the node's default limit of orders per work order.
    let batch: u32 = args.next().map_or(Ok(100), |a| a.parse())?.clamp(1, 1000);
    let binary = args
        .next()
        .unwrap_or_else(|| "target/debug/order-node".to_string());
    let dir = std::env::temp_dir().join(format!("finished-orders-memory-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let port = std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port();
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let config = dir.join("orders1.toml");
    std::fs::write(
        &config,
        format!(
            r#"cell = "membench"
name = "orders1"
[zenoh]
mode = "peer"
listen = ["{endpoint}"]
multicast_scouting = false
[orders]
no_resource_timeout_ms = 200
[journal]
durability = "process_crash"
"#
        ),
    )?;
    let start = || -> anyhow::Result<Node> {
        Ok(Node(
            Command::new(&binary)
                .arg("--config")
                .arg(&config)
                .arg("--data-dir")
                .arg(dir.join("data"))
                .env("RUST_LOG", "warn")
                .stdout(Stdio::null())
                .stderr(
                    std::fs::OpenOptions::new()
                        .create(true)
                        .append(true)
                        .open(dir.join("orders1.stderr"))?,
                )
                .spawn()
                .with_context(|| format!("start {binary}"))?,
        ))
    };
    let node = start()?;
    let pid = node.0.id();

    let keys = CellKeys::new("membench")?;
    let mut zenoh_config = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"peer\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        ("listen/endpoints", "[]".to_string()),
        ("connect/endpoints", format!("[\"{endpoint}\"]")),
    ] {
        zenoh_config
            .insert_json5(key, &value)
            .map_err(|e| anyhow::anyhow!("{key}: {e}"))?;
    }
    let session = zenoh::open(zenoh_config)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let _plan = session
        .declare_queryable(keys.plan("membench"))
        .callback(|query| {
            use zenoh::Wait;
            if let Err(e) = query.reply(query.key_expr().clone(), PLAN).wait() {
                eprintln!("cannot answer a plan request: {e}");
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let (finished_tx, mut finished_rx) = tokio::sync::mpsc::unbounded_channel::<String>();
    let _states = session
        .declare_subscriber(keys.node_orders("orders1", "state"))
        .callback(move |sample| {
            if let Ok(state) = serde_json::from_slice::<OrderSnapshot>(&sample.payload().to_bytes())
            {
                if state.status.is_final()
                    && finished_tx.send(state.holon.name().to_string()).is_err()
                {
                    eprintln!("the counter of finished orders is gone");
                }
            }
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;

    wait_ready(&session, &keys, &dir).await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let idle = rss_kib(pid)?;
    println!("idle: {:.1} MiB", mib(idle));

    let started = Instant::now();
    let mut finished = HashSet::new();
    let mut submitted = 0;
    let mut warm: Option<(u32, u64)> = None;
    while submitted < orders {
        let count = batch.min(orders - submitted);
        let work = WorkOrder {
            product: "membench".into(),
            count,
            priority: 0,
            due: None,
            queue: true,
            submit_id: None,
        };
        let replies = session
            .get(keys.orders_submit())
            .payload(serde_json::to_vec(&work)?)
            .timeout(Duration::from_secs(10))
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let sample = reply
            .result()
            .map_err(|e| anyhow::anyhow!("submit refused: {:?}", e.payload().try_to_string()))?;
        let created: SubmitReply = serde_json::from_slice(&sample.payload().to_bytes())?;
        submitted += created.orders.len() as u32;
        // One batch at a time: the node's limit of unfinished orders is not reached.
        let deadline = Instant::now() + Duration::from_secs(300);
        while finished.len() < submitted as usize {
            match tokio::time::timeout_at(deadline.into(), finished_rx.recv()).await {
                Ok(Some(name)) => {
                    finished.insert(name);
                }
                Ok(None) => bail!("the state subscriber ended"),
                Err(_) => bail!(
                    "only {} of {submitted} orders finished within 300 s",
                    finished.len()
                ),
            }
        }
        let now = rss_kib(pid)?;
        if warm.is_none() {
            println!(
                "after the first {submitted} finished orders: {:.1} MiB",
                mib(now)
            );
            warm = Some((submitted, now));
        }
        if submitted % 1000 == 0 {
            eprintln!("{submitted} orders finished ({:.1} MiB)", mib(now));
        }
    }
    let took = started.elapsed();
    tokio::time::sleep(Duration::from_secs(3)).await;
    let after = rss_kib(pid)?;
    let (warm_orders, warm_kib) = warm.unwrap_or((0, idle));
    println!(
        "after {orders} finished orders ({:.0} s): {:.1} MiB, {:+.1} MiB against idle; {:.0} bytes per finished order after the first batch",
        took.as_secs_f64(),
        mib(after),
        mib(after) - mib(idle),
        (after as f64 - warm_kib as f64) * 1024.0 / (orders - warm_orders).max(1) as f64
    );

    // What `cell orders` and the dashboard ask: every order's state.
    let states = read_states(&session, &keys).await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let read = rss_kib(pid)?;
    println!(
        "after a read of every order's state ({states} states): {:.1} MiB, {:+.1} MiB against idle",
        mib(read),
        mib(read) - mib(idle)
    );
    drop(node);

    // Restarted on the same journal.
    let node = start()?;
    let pid = node.0.id();
    wait_ready(&session, &keys, &dir).await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let restarted = rss_kib(pid)?;
    println!(
        "restarted with {orders} finished orders in its journal: {:.1} MiB",
        mib(restarted)
    );
    let states = read_states(&session, &keys).await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    println!(
        "restarted, after a read of every order's state ({states} states): {:.1} MiB",
        mib(rss_kib(pid)?)
    );
    drop(node);
    if let Err(e) = std::fs::remove_dir_all(&dir) {
        eprintln!("cannot remove {}: {e}", dir.display());
    }
    Ok(())
}

/// Waits until the order-node's token is there.
async fn wait_ready(
    session: &zenoh::Session,
    keys: &CellKeys,
    dir: &std::path::Path,
) -> anyhow::Result<()> {
    let ready = Instant::now() + Duration::from_secs(30);
    loop {
        if Instant::now() > ready {
            bail!("the order-node did not come up (see {})", dir.display());
        }
        let alive = session
            .liveliness()
            .get(keys.host("order-node", "orders1"))
            .timeout(Duration::from_secs(1))
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        if alive.recv_async().await.is_ok() {
            return Ok(());
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// Reads every order's state, as `cell orders` does: how many answered.
async fn read_states(session: &zenoh::Session, keys: &CellKeys) -> anyhow::Result<usize> {
    let replies = session
        .get(keys.node_orders("orders1", "state"))
        .timeout(Duration::from_secs(60))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut states = 0;
    while let Ok(reply) = replies.recv_async().await {
        if reply.result().is_ok() {
            states += 1;
        }
    }
    Ok(states)
}

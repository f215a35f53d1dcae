//! The dashboard at scale: `holons` resource holon processes, the product `part` and
//! an order-node, `orders` work orders submitted at once, and `cell dashboard` watching
//! it all. Measured: the dashboard process's resident memory (idle, and its peak while
//! the orders run), the views it pushes (how many, how large), and, with Chromium,
//! the page itself: how long it takes to render one view, how long a script waits for
//! the page's main thread while the orders run (its responsiveness), and its JS heap.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use holarchy_tests::{pick_n_place, resource_config, webdriver};
use schemas::MessageType;
use serde_json::{json, Value};

use crate::cells::{router, start_product_and_orders};
use crate::process::{cpu_time, footprint};
use crate::run::Run;
use crate::stats::Latency;

/// A `cell dashboard` process, killed when dropped.
struct Dashboard {
    child: Child,
    address: String,
}

impl Drop for Dashboard {
    fn drop(&mut self) {
        if let Err(e) = self.child.kill() {
            eprintln!("cannot stop the dashboard: {e}");
        }
        if let Err(e) = self.child.wait() {
            eprintln!("cannot reap the dashboard: {e}");
        }
    }
}

impl Dashboard {
    fn start(cell: &str, endpoint: &str) -> Result<Dashboard> {
        let mut child = Command::new(holarchy_tests::bin("cell"))
            .args(["dashboard", "--cell", cell, "--connect", endpoint])
            .args(["--listen", "127.0.0.1:0", "--operator"])
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .context("cannot start cell dashboard")?;
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("piped")).read_line(&mut line)?;
        let address = line
            .trim()
            .rsplit("http://")
            .next()
            .unwrap_or_default()
            .trim_end_matches('/')
            .to_string();
        if !address.starts_with("127.0.0.1:") {
            bail!("the dashboard did not say where it listens: {line:?}");
        }
        Ok(Dashboard { child, address })
    }

    fn pid(&self) -> i32 {
        self.child.id() as i32
    }

    /// `GET path` as JSON.
    fn json(&self, path: &str) -> Result<Value> {
        let mut stream = TcpStream::connect(&self.address)?;
        stream.set_read_timeout(Some(Duration::from_secs(10)))?;
        write!(
            stream,
            "GET {path} HTTP/1.1\r\nHost: {}\r\nConnection: close\r\n\r\n",
            self.address
        )?;
        let mut response = String::new();
        stream.read_to_string(&mut response)?;
        let body = response
            .split_once("\r\n\r\n")
            .map(|(_, b)| b)
            .ok_or_else(|| anyhow!("{path}: no body"))?;
        serde_json::from_str(body).with_context(|| format!("{path}: not JSON"))
    }
}

/// What the server-sent events of one page brought: views and their sizes.
#[derive(Default)]
struct Pushed {
    views: AtomicU64,
    bytes: AtomicU64,
    largest: AtomicU64,
}

/// Reads `/events` until `stop`, counting the views (a page's share of the traffic).
fn follow_events(address: String, pushed: Arc<Pushed>, stop: Arc<AtomicBool>) -> Result<()> {
    let mut stream = TcpStream::connect(&address)?;
    stream.set_read_timeout(Some(Duration::from_millis(500)))?;
    write!(
        stream,
        "GET /events HTTP/1.1\r\nHost: {address}\r\nAccept: text/event-stream\r\n\r\n"
    )?;
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    while !stop.load(Ordering::Relaxed) {
        line.clear();
        match reader.read_line(&mut line) {
            Ok(0) => break,
            Ok(_) => {
                if let Some(data) = line.strip_prefix("data:") {
                    let size = data.len() as u64;
                    pushed.views.fetch_add(1, Ordering::Relaxed);
                    pushed.bytes.fetch_add(size, Ordering::Relaxed);
                    pushed.largest.fetch_max(size, Ordering::Relaxed);
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(e) => return Err(e.into()),
        }
    }
    Ok(())
}

/// The page in Chromium, while the orders run: how long a script waits for the page's
/// main thread (sampled every 100 ms), and what the page recorded of its renders.
struct PageFigures {
    /// Before the orders: the baseline.
    idle_waits: Latency,
    /// What the page recorded of its renders before the orders.
    idle_renders: Value,
    waits: Latency,
    renders: Value,
    heap_bytes: Option<u64>,
}

/// CPU time used so far by each of the browser's processes (Chromium's and
/// ChromeDriver's, found by name: the bench machine runs no other).
fn browser_cpu() -> std::collections::HashMap<i32, Duration> {
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Default::default();
    };
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<i32>().ok())
        .filter(|pid| {
            std::fs::read_to_string(format!("/proc/{pid}/comm"))
                .is_ok_and(|comm| comm.starts_with("chrom"))
        })
        .filter_map(|pid| Some((pid, cpu_time(pid).ok()?)))
        .collect()
}

/// The browser's CPU time since `before` (of the processes still running).
fn browser_cpu_since(before: &std::collections::HashMap<i32, Duration>) -> Duration {
    browser_cpu()
        .into_iter()
        .map(|(pid, now)| now.saturating_sub(before.get(&pid).copied().unwrap_or_default()))
        .sum()
}

/// `n` WebDriver scripts run in the page, 100 ms apart: how long each waited.
fn script_waits(browser: &webdriver::Browser, n: usize) -> Result<Latency> {
    let started = Instant::now();
    let mut waits = Vec::new();
    for _ in 0..n {
        let t = Instant::now();
        browser.execute("return document.readyState")?;
        waits.push(t.elapsed());
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(Latency::new(waits, started.elapsed()))
}

pub async fn section(run: &mut Run, holons: usize, orders: u32) -> Result<()> {
    let cell = router("bench-dash", None).await?;
    let dir = run.dir.join("dashboard");
    std::fs::create_dir_all(&dir)?;
    let (sims, nodes) = start_resources(&dir, &cell, holons).await?;
    let (_product, _orders) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;

    let dashboard = Dashboard::start("bench-dash", &cell.endpoint)?;
    let all_shown = all_shown(&dashboard, holons).await?;
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (idle_rss, _) = footprint(dashboard.pid())?;

    let browser = open_the_page(&dir, &dashboard)?;
    let stop = Arc::new(AtomicBool::new(false));
    let pushed = Arc::new(Pushed::default());
    let events = {
        let (address, pushed, stop) = (dashboard.address.clone(), pushed.clone(), stop.clone());
        std::thread::spawn(move || follow_events(address, pushed, stop))
    };
    let peak = sample_peak_rss(dashboard.pid(), stop.clone());
    let page = browser.map(|(browser, idle_waits, idle_renders)| {
        sample_the_page(browser, idle_waits, idle_renders, stop.clone())
    });

    let browser_cpu_before = browser_cpu();
    let t = Instant::now();
    let done: Result<Duration> = run_the_orders(&cell, &dashboard, orders, t).await;
    if done.is_ok() {
        // A last view settles; then everything stops.
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    // Also when the orders failed: the page's thread ends and closes the browser
    // (left running, Chromium and its driver would outlive the bench).
    stop.store(true, Ordering::Relaxed);
    let done = match done {
        Ok(done) => done,
        Err(e) => {
            if let Some(page) = page {
                if page.join().is_err() {
                    eprintln!("the page's reader panicked");
                }
            }
            return Err(e);
        }
    };
    let peak_rss = peak.join().map_err(|_| anyhow!("the sampler panicked"))?;
    events
        .join()
        .map_err(|_| anyhow!("the events reader panicked"))??;
    let (after_rss, _) = footprint(dashboard.pid())?;
    let browser_share =
        browser_cpu_since(&browser_cpu_before).as_secs_f64() / t.elapsed().as_secs_f64();
    let name = format!("dashboard: {holons} holons, {orders} orders");
    let mib = |kib: u64| kib as f64 / 1024.0;
    run.table.add(
        &format!("{name}: process"),
        format!(
            "peak {:.1} MiB resident ({:.1} MiB idle, {:.1} after)",
            mib(peak_rss),
            mib(idle_rss),
            mib(after_rss)
        ),
        "bound 50 MiB".into(),
        json!({"holons": holons, "orders": orders, "idle_rss_kib": idle_rss, "peak_rss_kib": peak_rss, "after_rss_kib": after_rss, "all_shown_s": all_shown.as_secs_f64(), "orders_done_s": done.as_secs_f64()}),
    );
    report_views(run, &name, &pushed, done, all_shown);
    report_page(run, &name, page, browser_share)?;
    drop(dashboard);
    drop(nodes);
    drop(sims);
    Ok(())
}

/// Four controllers and `holons` resources on them, until every resource answers a
/// proposal. Their 5 ms actions make the orders take a few seconds to run, so the page
/// is watched while the cell works, not after.
async fn start_resources(
    dir: &std::path::Path,
    cell: &holarchy_tests::Cell,
    holons: usize,
) -> Result<(Vec<holarchy_tests::Sim>, Vec<holarchy_tests::Process>)> {
    let sims: Vec<holarchy_tests::Sim> = (0..4)
        .map(|i| {
            holarchy_tests::Sim::start(dir, &format!("sim{i}"), "127.0.0.1:0", &["--delay-ms", "5"])
        })
        .collect::<Result<_>>()?;
    let mut nodes = Vec::new();
    for i in 0..holons {
        let name = format!("r{i}");
        let config = resource_config(dir, &name, 5000)?;
        nodes.push(holarchy_tests::start_node(
            dir,
            &config,
            "bench-dash",
            &cell.endpoint,
            &sims[i % 4].address,
            &[],
        )?);
    }
    let ask = pick_n_place(&cell.keys, MessageType::ProposalReq, "bench", "dash/1/1");
    cell.wait_proposals(&ask, holons).await?;
    Ok((sims, nodes))
}

/// How long the dashboard took to show every holon live (the resources and the product).
async fn all_shown(dashboard: &Dashboard, holons: usize) -> Result<Duration> {
    let t = Instant::now();
    loop {
        let shown = dashboard.json("/api/holons")?;
        let live = shown
            .as_array()
            .map_or(0, |h| h.iter().filter(|h| h["live"] == true).count());
        if live > holons {
            return Ok(t.elapsed());
        }
        if t.elapsed() > Duration::from_secs(60) {
            bail!(
                "the dashboard shows {live} of {} holons after 60 s",
                holons + 1
            );
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// The page in Chromium, if there is one, with its idle cell's script waits and renders.
fn open_the_page(
    dir: &std::path::Path,
    dashboard: &Dashboard,
) -> Result<Option<(webdriver::Browser, Latency, Value)>> {
    match webdriver::browser_available() {
        Ok(()) => {
            let browser = webdriver::Browser::start(&dir.join("profile"))?;
            browser.goto(&format!("http://{}/", dashboard.address))?;
            browser.wait_for("tr[data-holon=\"resource/r0\"]", Duration::from_secs(10))?;
            let idle_waits = script_waits(&browser, 30)?;
            // The renders so far (the idle cell's views) are the baseline; count anew.
            let idle_renders = browser.execute(
                "const r = window.holarchyRenders; const idle = Object.assign({}, r); \
                 r.count = 0; r.total_ms = 0; r.max_ms = 0; return idle",
            )?;
            Ok(Some((browser, idle_waits, idle_renders)))
        }
        Err(why) => {
            println!("(the page's figures need Chromium: {why})");
            Ok(None)
        }
    }
}

/// The dashboard's peak resident memory (KiB) until `stop`, sampled every 100 ms.
fn sample_peak_rss(pid: i32, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<u64> {
    std::thread::spawn(move || {
        let mut peak = 0;
        while !stop.load(Ordering::Relaxed) {
            if let Ok((rss, _)) = footprint(pid) {
                peak = peak.max(rss);
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        peak
    })
}

/// The page's script waits until `stop`, then its renders and heap.
fn sample_the_page(
    browser: webdriver::Browser,
    idle_waits: Latency,
    idle_renders: Value,
    stop: Arc<AtomicBool>,
) -> std::thread::JoinHandle<Result<PageFigures>> {
    std::thread::spawn(move || -> Result<PageFigures> {
        let started = Instant::now();
        let mut waits = Vec::new();
        while !stop.load(Ordering::Relaxed) {
            let t = Instant::now();
            browser.execute("return document.readyState")?;
            waits.push(t.elapsed());
            std::thread::sleep(Duration::from_millis(100));
        }
        let renders = browser.execute("return window.holarchyRenders")?;
        let heap_bytes = browser
            .execute("return performance.memory ? performance.memory.usedJSHeapSize : null")?
            .as_u64();
        Ok(PageFigures {
            idle_waits,
            idle_renders,
            waits: Latency::new(waits, started.elapsed()),
            renders,
            heap_bytes,
        })
    })
}

/// The orders, in batches of 100 (one reply each), until the dashboard shows them done;
/// how long from `t`.
async fn run_the_orders(
    cell: &holarchy_tests::Cell,
    dashboard: &Dashboard,
    orders: u32,
    t: Instant,
) -> Result<Duration> {
    let mut submitted = 0;
    while submitted < orders {
        let batch = (orders - submitted).min(100);
        cell.submit("part", batch).await?;
        submitted += batch;
    }
    loop {
        let view = dashboard.json("/api/view")?;
        let done = view["order_counts"]["done"].as_u64().unwrap_or(0);
        if done >= orders as u64 {
            return Ok(t.elapsed());
        }
        if t.elapsed() > Duration::from_secs(600) {
            bail!("the dashboard shows {done} of {orders} orders done after 600 s");
        }
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
}

/// The views the dashboard pushed while the orders ran.
fn report_views(run: &mut Run, name: &str, pushed: &Pushed, done: Duration, all_shown: Duration) {
    let views = pushed.views.load(Ordering::Relaxed);
    let mean_kb = pushed.bytes.load(Ordering::Relaxed) as f64 / views.max(1) as f64 / 1e3;
    let largest_kb = pushed.largest.load(Ordering::Relaxed) as f64 / 1e3;
    run.table.add(
        &format!("{name}: views pushed"),
        format!(
            "{views} in {:.1} s, mean {mean_kb:.0} kB, largest {largest_kb:.0} kB",
            done.as_secs_f64()
        ),
        format!(
            "at most 4/s by design (every 250 ms); all holons shown {:.2} s after its start",
            all_shown.as_secs_f64()
        ),
        json!({"views": views, "mean_kb": mean_kb, "largest_kb": largest_kb}),
    );
}

/// The page's figures in Chromium, or that there was none.
fn report_page(
    run: &mut Run,
    name: &str,
    page: Option<std::thread::JoinHandle<Result<PageFigures>>>,
    browser_share: f64,
) -> Result<()> {
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let load_1min: f64 = load
        .split_whitespace()
        .next()
        .and_then(|l| l.parse().ok())
        .unwrap_or(f64::NAN);
    match page {
        Some(page) => {
            let page = page
                .join()
                .map_err(|_| anyhow!("the page's sampler panicked"))??;
            let renders = &page.renders;
            let count = renders["count"].as_f64().unwrap_or(0.0);
            let mean_ms = renders["total_ms"].as_f64().unwrap_or(0.0) / count.max(1.0);
            let max_ms = renders["max_ms"].as_f64().unwrap_or(f64::NAN);
            let heap_mb = page.heap_bytes.map(|b| b as f64 / 1e6);
            let idle = &page.idle_renders;
            let idle_mean_ms = idle["total_ms"].as_f64().unwrap_or(0.0)
                / idle["count"].as_f64().unwrap_or(0.0).max(1.0);
            run.table.add(
                &format!("{name}: page in Chromium"),
                format!(
                    "render mean {mean_ms:.0} ms, max {max_ms:.0} ms; script waits p50 {:.0} ms, p99 {:.0} ms, max {:.0} ms",
                    page.waits.pct(0.5) / 1e3,
                    page.waits.pct(0.99) / 1e3,
                    page.waits.pct(1.0) / 1e3
                ),
                format!(
                    "idle cell: render mean {idle_mean_ms:.0} ms, script waits p50 {:.0} ms; browser {:.0}% of a core under a load average of {load_1min:.0}; {count:.0} renders; JS heap {}",
                    page.idle_waits.pct(0.5) / 1e3,
                    browser_share * 100.0,
                    heap_mb.map_or("unknown".into(), |mb| format!("{mb:.1} MB"))
                ),
                json!({"renders": count, "render_mean_ms": mean_ms, "render_max_ms": max_ms, "script_wait_p50_us": page.waits.pct(0.5), "script_wait_max_us": page.waits.pct(1.0), "script_wait_p99_us": page.waits.pct(0.99), "idle_render_mean_ms": idle_mean_ms, "browser_cpu_share": browser_share, "load_average_1min": load_1min, "idle_script_wait_p50_us": page.idle_waits.pct(0.5), "heap_bytes": page.heap_bytes}),
            );
        }
        None => run.table.add(
            &format!("{name}: page in Chromium"),
            "skipped: no Chromium".into(),
            "apt-get install chromium chromium-driver".into(),
            json!(null),
        ),
    }
    Ok(())
}

//! `bench`: how fast a holarchy books, executes, reconfigures and recovers, against the
//! middleware floor measured in the same run. Every figure comes from real processes on
//! loopback (robot-sim, holon-node, order-node, and two echo helpers of this binary).
//!
//!     cargo run --release -p bench -- all            # the whole table, JSON in bench-results.json
//!
//! Topology, as in a cell: this process runs the zenoh router; every holon is a client
//! of it (the echo helper a peer). The floors use the same path as the holons: one link
//! from this process's router session; `scale` measures the path across the router.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

mod dashboard;
mod erlang;
mod robots;
mod scale;
mod schedule;
mod upgrade;

use anyhow::{anyhow, bail, Context, Result};
use clap::{Parser, Subcommand};
use holarchy_tests::{free_port, pick_n_place, resource_config, Cell, Process, Sim};
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use schemas::{CellKeys, HolonId, MessageType, Service};
use serde_json::{json, Value};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

#[derive(Debug, Parser)]
#[command(
    name = "bench",
    version,
    about = "holarchy's benchmarks (see docs/benchmarks.md)"
)]
struct Args {
    #[command(subcommand)]
    command: Commands,
}

#[derive(Debug, Subcommand)]
enum Commands {
    /// Run every benchmark, print the table and write it as JSON.
    All {
        /// Where the JSON goes.
        #[arg(long, default_value = "bench-results.json")]
        out: PathBuf,
        /// Round trips per latency figure.
        #[arg(long, default_value_t = 2000)]
        samples: usize,
        /// Resource holon processes for the scale and dashboard figures (0 skips them;
        /// the dashboard section runs at most 100).
        #[arg(long, default_value_t = 100)]
        scale: usize,
        /// Run only these sections (comma-separated; the floors always run): booking,
        /// tls, cycle, erlang, holon, rebook, lease, throughput, robots, orders, scale,
        /// dashboard.
        #[arg(long, value_delimiter = ',')]
        only: Vec<String>,
        /// The seed's resource holon in Erlang/OTP (a directory with its run.sh): run it
        /// in the same sitting and set our booking and cycle beside it (needs `erl`;
        /// skipped with a note otherwise).
        #[arg(long, value_name = "DIR")]
        erlang_peer: Option<PathBuf>,
    },
    /// The scheduling benchmark: each scenario's order stream run by contract net alone
    /// and with a staff holon, for several seeds (docs/scheduling.md).
    Schedule {
        /// Scenario files (default: every deploy/scenarios/*.toml).
        #[arg(long = "scenario", value_name = "FILE")]
        scenarios: Vec<PathBuf>,
        /// Seeds per scenario; each seed's orders run in both modes.
        #[arg(long, default_value_t = 3)]
        seeds: u64,
        /// Where the JSON goes.
        #[arg(long, default_value = "schedule-results.json")]
        out: PathBuf,
    },
    /// The upgrade benchmark: robot1, the order-node and the product replaced while
    /// orders run, by a planned hand-over (--take-over) and, as the baseline, by SIGTERM
    /// and a new start; how long each is away and robot1 starts no job
    /// (docs/benchmarks.md, "Upgrades").
    Upgrade {
        /// Rounds per way.
        #[arg(long, default_value_t = 5)]
        rounds: usize,
        /// Where the JSON goes.
        #[arg(long, default_value = "upgrade-results.json")]
        out: PathBuf,
    },
    /// (helper) A TCP echo server: prints `listening on ADDR`.
    EchoTcp {
        #[arg(long, default_value = "127.0.0.1:0")]
        listen: String,
    },
    /// (helper) A zenoh peer with a queryable that answers every query with its payload.
    EchoZenoh {
        #[arg(long)]
        connect: String,
        #[arg(long)]
        key: String,
    },
}

#[tokio::main(flavor = "multi_thread")]
async fn main() -> Result<()> {
    match Args::parse().command {
        Commands::All {
            out,
            samples,
            scale,
            only,
            erlang_peer,
        } => all(&out, samples, scale, &only, erlang_peer.as_deref()).await,
        Commands::Schedule {
            scenarios,
            seeds,
            out,
        } => {
            let scenarios = if scenarios.is_empty() {
                let dir = holarchy_tests::workspace_root().join("deploy/scenarios");
                let mut found: Vec<PathBuf> = std::fs::read_dir(&dir)
                    .with_context(|| format!("cannot list {}", dir.display()))?
                    .flatten()
                    .map(|e| e.path())
                    .filter(|p| p.extension().is_some_and(|e| e == "toml"))
                    .collect();
                found.sort();
                found
            } else {
                scenarios
            };
            schedule::run(&scenarios, seeds, &out).await
        }
        Commands::Upgrade { rounds, out } => upgrade::run(rounds, &out).await,
        Commands::EchoTcp { listen } => echo_tcp(&listen).await,
        Commands::EchoZenoh { connect, key } => echo_zenoh(&connect, &key).await,
    }
}

async fn echo_tcp(listen: &str) -> Result<()> {
    let listener = tokio::net::TcpListener::bind(listen).await?;
    println!("listening on {}", listener.local_addr()?);
    loop {
        let (mut socket, _) = listener.accept().await?;
        socket.set_nodelay(true)?;
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65536];
            while let Ok(n) = socket.read(&mut buf).await {
                if n == 0 || socket.write_all(&buf[..n]).await.is_err() {
                    break;
                }
            }
        });
    }
}

async fn echo_zenoh(connect: &str, key: &str) -> Result<()> {
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Peer,
        connect: vec![connect.to_string()],
        listen: vec!["tcp/127.0.0.1:0".into()],
        ..Default::default()
    };
    let session = settings
        .open("router.local", Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let queryable = session
        .declare_queryable(key)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let _token = session
        .liveliness()
        .declare_token(format!("{key}/alive"))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    println!("ready");
    while let Ok(query) = queryable.recv_async().await {
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let _ = query.reply(query.key_expr().clone(), payload).await;
    }
    Ok(())
}

/// Latency distribution of a series of round trips.
#[derive(Debug, Clone)]
struct Latency {
    samples: Vec<Duration>,
    total: Duration,
}

impl Latency {
    fn new(mut samples: Vec<Duration>, total: Duration) -> Self {
        samples.sort();
        Latency { samples, total }
    }

    fn pct(&self, p: f64) -> f64 {
        if self.samples.is_empty() {
            return f64::NAN;
        }
        let i = ((self.samples.len() as f64 - 1.0) * p).round() as usize;
        self.samples[i].as_secs_f64() * 1e6
    }

    fn rate(&self) -> f64 {
        self.samples.len() as f64 / self.total.as_secs_f64()
    }

    fn json(&self) -> Value {
        json!({"n": self.samples.len(), "p50_us": self.pct(0.5), "p99_us": self.pct(0.99), "rate_per_s": self.rate()})
    }
}

struct Table {
    rows: Vec<(String, String, String)>,
    json: serde_json::Map<String, Value>,
}

impl Table {
    fn add(&mut self, name: &str, figure: String, baseline: String, data: Value) {
        println!("{name:<46} {figure:<40} {baseline}");
        self.rows.push((name.into(), figure, baseline));
        self.json.insert(name.into(), data);
    }
}

fn spawn_helper(args: &[&str]) -> Result<(Child, String)> {
    use std::io::BufRead;
    let mut child = Command::new(std::env::current_exe()?)
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()?;
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("piped")).read_line(&mut line)?;
    Ok((child, line.trim().to_string()))
}

/// Proportional memory (KiB) of a process: its private pages plus its share of the
/// pages it shares (the binary's code, mapped by every holon process), from /proc.
fn proportional(pid: i32) -> Result<u64> {
    let rollup = std::fs::read_to_string(format!("/proc/{pid}/smaps_rollup"))?;
    rollup
        .lines()
        .find(|l| l.starts_with("Pss:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| anyhow!("no Pss in /proc/{pid}/smaps_rollup"))
}

/// Resident memory (KiB) and threads of a process, from /proc.
fn footprint(pid: i32) -> Result<(u64, u64)> {
    Ok((status_field(pid, "VmRSS:")?, status_field(pid, "Threads:")?))
}

/// One number of /proc/PID/status (`VmRSS:`, `RssAnon:`, `Threads:`...).
fn status_field(pid: i32, name: &str) -> Result<u64> {
    std::fs::read_to_string(format!("/proc/{pid}/status"))?
        .lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| anyhow!("no {name} in /proc/{pid}/status"))
}

async fn router(cell: &str, lease_ms: Option<u64>) -> Result<Cell> {
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Router,
        listen: vec![endpoint.clone()],
        lease_ms,
        ..Default::default()
    };
    open_cell(&settings, "router.local", cell, endpoint).await
}

/// A session opened with `settings` as `identity`, seen as a [`Cell`] named `cell` whose
/// processes connect to `endpoint`.
async fn open_cell(
    settings: &holon::ZenohSettings,
    identity: &str,
    cell: &str,
    endpoint: String,
) -> Result<Cell> {
    let session = settings
        .open(identity, Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    Ok(Cell {
        session,
        keys: CellKeys::new(cell)?,
        endpoint,
    })
}

/// One round trip: the reply's payload (an error reply is an error).
async fn get_once(cell: &Cell, key: &str, payload: Vec<u8>) -> Result<Vec<u8>> {
    cell.ask(key, payload)
        .await?
        .map_err(|_| anyhow!("error reply from {key}"))
}

/// What a booking series measured.
struct BookingSeries {
    booking: Latency,
    book_and_cancel: Latency,
    /// A raw zenoh `get` to the echo helper just before each booking: the floor under
    /// the same load at the same moment, so the ratio survives a noisy machine.
    floor: Latency,
}

impl BookingSeries {
    fn ratio(&self) -> f64 {
        self.booking.pct(0.5) / self.floor.pct(0.5)
    }
}

/// One `booking_req` then its `booking_cancel`: how long the booking took, and the pair.
async fn book_and_cancel(
    cell: &Cell,
    resource: &str,
    conversation: &str,
) -> Result<(Duration, Duration)> {
    let key = cell.keys.service(resource);
    let book = pick_n_place(&cell.keys, MessageType::BookingReq, "bench", conversation);
    let cancel = pick_n_place(
        &cell.keys,
        MessageType::BookingCancel,
        "bench",
        conversation,
    );
    let t = Instant::now();
    let answer = Service::from_json(&get_once(cell, &key, book.to_json()).await?)?;
    let booked = t.elapsed();
    if answer.result != Some(true) {
        bail!("booking refused by {resource}: {answer:?}");
    }
    get_once(cell, &key, cancel.to_json()).await?;
    Ok((booked, t.elapsed()))
}

/// Eight orders booking `resource` at the same moment (their bookings share a journal
/// write), against the same eight one after another: until all eight are booked,
/// `rounds` times each, after 5 warm-up rounds; each round's bookings are cancelled.
async fn eight_at_once(cell: &Cell, resource: &str, rounds: usize) -> Result<(Latency, Latency)> {
    let key = cell.keys.service(resource);
    let (mut together, mut in_turn) = (Vec::new(), Vec::new());
    let started = Instant::now();
    for round in 0..rounds + 5 {
        let requests = |how: &str, kind: MessageType| -> Vec<Vec<u8>> {
            (0..8)
                .map(|i| {
                    let order = format!("eight{i}");
                    pick_n_place(&cell.keys, kind, &order, &format!("{order}/{how}{round}/1"))
                        .to_json()
                })
                .collect()
        };
        let t = Instant::now();
        let answers = futures_util::future::try_join_all(
            requests("a", MessageType::BookingReq)
                .into_iter()
                .map(|book| get_once(cell, &key, book)),
        )
        .await?;
        let at_once = t.elapsed();
        let t = Instant::now();
        for book in requests("b", MessageType::BookingReq) {
            get_once(cell, &key, book).await?;
        }
        let one_by_one = t.elapsed();
        for answer in answers {
            if Service::from_json(&answer)?.result != Some(true) {
                bail!(
                    "a booking of 8 at once was refused: {}",
                    String::from_utf8_lossy(&answer)
                );
            }
        }
        for how in ["a", "b"] {
            for cancel in requests(how, MessageType::BookingCancel) {
                get_once(cell, &key, cancel).await?;
            }
        }
        if round >= 5 {
            together.push(at_once);
            in_turn.push(one_by_one);
        }
    }
    let total = started.elapsed();
    Ok((Latency::new(together, total), Latency::new(in_turn, total)))
}

/// `booking_req` then `booking_cancel` to `resource`, `samples` times after 100 warm-up
/// pairs, each after a raw `get` to the echo helper (the interleaved floor).
async fn booking_series(cell: &Cell, resource: &str, samples: usize) -> Result<BookingSeries> {
    let echo = vec![
        b'x';
        pick_n_place(&cell.keys, MessageType::BookingReq, "bench", "bench/1/1")
            .to_json()
            .len()
    ];
    let (mut book_times, mut pair_times, mut floor_times) = (Vec::new(), Vec::new(), Vec::new());
    let started = Instant::now();
    for i in 0..samples + 100 {
        let t = Instant::now();
        get_once(cell, ECHO_KEY, echo.clone()).await?;
        let floor = t.elapsed();
        let (booked, pair) = book_and_cancel(cell, resource, &format!("{resource}/{i}/1")).await?;
        if i >= 100 {
            book_times.push(booked);
            pair_times.push(pair);
            floor_times.push(floor);
        }
    }
    let total = started.elapsed();
    Ok(BookingSeries {
        booking: Latency::new(book_times, total),
        book_and_cancel: Latency::new(pair_times, total),
        floor: Latency::new(floor_times, total),
    })
}

/// The most resource holons the dashboard section runs (`--scale` beyond it still
/// applies to the scale section).
const DASHBOARD_HOLONS: usize = 100;

/// The echo helper's key: a queryable that answers with the query's payload.
const ECHO_KEY: &str = "holarchy/bench/echo";

/// The sections `--only` can pick; the floors always run (every figure's baseline).
const SECTIONS: &[&str] = &[
    "booking",
    "tls",
    "cycle",
    "holon",
    "rebook",
    "lease",
    "throughput",
    "robots",
    "orders",
    "scale",
    "dashboard",
    "erlang",
];

/// What every section shares: the run's directory, the cell (this process is its
/// router), the floors measured first, a controller simulator and `robot1`.
struct Run {
    dir: PathBuf,
    cell: Cell,
    table: Table,
    floor: Latency,
    journal_floor: (Latency, Latency),
    sim: Sim,
    robot1: Process,
    robot1_ready: Duration,
    samples: usize,
    echo: Child,
    /// Our figures the Erlang peer's are set beside.
    ours: Ours,
}

/// Our booking (`process_crash`) and cycle, p50 and p99 in µs, once measured.
#[derive(Default)]
struct Ours {
    booking: Option<(f64, f64)>,
    /// Booking starting on its turn (what orders do by default).
    cycle: Option<(f64, f64)>,
    /// Booking, then a separate `start`.
    cycle_by_request: Option<(f64, f64)>,
}

impl Drop for Run {
    fn drop(&mut self) {
        let _ = self.echo.kill();
        let _ = self.echo.wait();
    }
}

impl Run {
    fn ratio(&self, latency: &Latency) -> f64 {
        latency.pct(0.5) / self.floor.pct(0.5)
    }
}

async fn all(
    out: &Path,
    samples: usize,
    scale: usize,
    only: &[String],
    erlang_peer: Option<&Path>,
) -> Result<()> {
    for section in only {
        if !SECTIONS.contains(&section.as_str()) {
            bail!(
                "unknown section {section:?} (one of {})",
                SECTIONS.join(", ")
            );
        }
    }
    let wants = |section: &str| only.is_empty() || only.iter().any(|s| s == section);
    let tempdir = tempfile::tempdir()?;
    // HOLARCHY_BENCH_KEEP=1 keeps the run's directory (configs, journals, every
    // process's log) for a look afterwards.
    let dir = if std::env::var_os("HOLARCHY_BENCH_KEEP").is_some() {
        let kept = tempdir.keep();
        println!("keeping the run's files in {}", kept.display());
        kept
    } else {
        tempdir.path().to_path_buf()
    };
    let mut run = floors(&dir, samples).await?;
    if wants("booking") {
        booking(&mut run).await?;
    }
    if wants("tls") {
        tls_booking(&mut run).await?;
    }
    if wants("cycle") {
        cycle(&mut run).await?;
    }
    if wants("erlang") {
        erlang::section(&mut run, erlang_peer)?;
    }
    if wants("holon") {
        holon_figures(&mut run).await?;
    }
    if wants("rebook") {
        rebook(&mut run).await?;
    }
    if wants("lease") {
        lease(&mut run).await?;
    }
    if wants("throughput") {
        for robots in [1usize, 2, 4] {
            let figure = throughput(&run.dir, robots, 40).await?;
            run.table.add(
                &format!("cell throughput: {robots} robot(s), 40 concurrent orders"),
                format!("{:.1} orders/s", figure),
                "one pick_n_place step each, 0 ms actions".into(),
                json!({"robots": robots, "orders": 40, "orders_per_s": figure}),
            );
        }
    }
    if wants("robots") {
        robots::section(&mut run).await?;
    }
    if wants("orders") {
        order_node_footprint(&mut run, 1000).await?;
    }
    if wants("scale") && scale > 0 {
        scale::section(&mut run, scale).await?;
    }
    if wants("dashboard") && scale > 0 {
        // At most 100 holons: 1,000 orders whose proposal rounds each ask every holon
        // saturate 2 cores long before that (at 300, a submit got no answer in 5 s);
        // the page's figures are what this section measures, not the cell's.
        dashboard::section(&mut run, scale.min(DASHBOARD_HOLONS), 1000).await?;
    }

    let machine = json!({
        "cores": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0),
        "profile": holarchy_tests::bin_dir().file_name().map(|n| n.to_string_lossy().into_owned()),
        "sections": if only.is_empty() { SECTIONS.to_vec() } else { only.iter().map(String::as_str).collect() },
    });
    let mut json = std::mem::take(&mut run.table.json);
    json.insert("machine".into(), machine);
    std::fs::write(out, serde_json::to_string_pretty(&Value::Object(json))?)
        .with_context(|| format!("cannot write {}", out.display()))?;
    println!("\nJSON written to {}", out.display());
    Ok(())
}

/// The baselines: raw TCP, raw zenoh `get`, a controller command, a journal commit;
/// then starts the simulator and `robot1` the sections share.
async fn floors(dir: &Path, samples: usize) -> Result<Run> {
    let mut table = Table {
        rows: Vec::new(),
        json: serde_json::Map::new(),
    };
    println!("{:<46} {:<40} BASELINE (same run)", "FIGURE", "VALUE");
    let cell = router("bench", None).await?;
    let service_size = pick_n_place(&cell.keys, MessageType::BookingReq, "bench", "bench/1/1")
        .to_json()
        .len();

    // Floors: raw TCP and raw zenoh round trips, a Service-sized payload.
    let (mut tcp_child, line) = spawn_helper(&["echo-tcp"])?;
    let address = line
        .strip_prefix("listening on ")
        .ok_or_else(|| anyhow!("echo-tcp: {line}"))?
        .to_string();
    let mut socket = tokio::net::TcpStream::connect(&address).await?;
    socket.set_nodelay(true)?;
    let payload = vec![b'x'; service_size];
    let mut buf = vec![0u8; service_size];
    let mut times = Vec::with_capacity(samples);
    let started = Instant::now();
    for _ in 0..samples {
        let t = Instant::now();
        socket.write_all(&payload).await?;
        socket.read_exact(&mut buf).await?;
        times.push(t.elapsed());
    }
    let tcp = Latency::new(times, started.elapsed());
    let _ = tcp_child.kill();
    table.add(
        "floor: TCP round trip (loopback)",
        format!("p50 {:.0} us, p99 {:.0} us", tcp.pct(0.5), tcp.pct(0.99)),
        format!("{service_size} B payload"),
        tcp.json(),
    );

    // The echo helper stays up for the whole run: booking series interleave with it.
    let (echo, _) = spawn_helper(&["echo-zenoh", "--connect", &cell.endpoint, "--key", ECHO_KEY])?;
    cell.wait_token(&format!("{ECHO_KEY}/alive")).await?;
    for _ in 0..100 {
        get_once(&cell, ECHO_KEY, payload.clone()).await?;
    }
    let mut times = Vec::with_capacity(samples);
    let started = Instant::now();
    for _ in 0..samples {
        let t = Instant::now();
        get_once(&cell, ECHO_KEY, payload.clone()).await?;
        times.push(t.elapsed());
    }
    let floor = Latency::new(times, started.elapsed());
    table.add(
        "floor: zenoh get round trip (2 processes)",
        format!(
            "p50 {:.0} us, p99 {:.0} us",
            floor.pct(0.5),
            floor.pct(0.99)
        ),
        format!("TCP p50 {:.0} us", tcp.pct(0.5)),
        floor.json(),
    );

    // A journal commit of a booking-sized record, both durabilities, on the disk the
    // holons write to: what a journalled answer cannot go below.
    let journal_floor = (
        journal_commits(dir, holon::journal::Durability::PowerLoss, samples)?,
        journal_commits(dir, holon::journal::Durability::ProcessCrash, samples)?,
    );
    table.add(
        "floor: journal commit (power_loss | process_crash)",
        format!(
            "p50 {:.0} | {:.0} us, p99 {:.0} | {:.0} us",
            journal_floor.0.pct(0.5),
            journal_floor.1.pct(0.5),
            journal_floor.0.pct(0.99),
            journal_floor.1.pct(0.99)
        ),
        format!("{service_size} B record, SQLite WAL"),
        json!({"power_loss": journal_floor.0.json(), "process_crash": journal_floor.1.json()}),
    );

    let sim = Sim::start(dir, "sim1", "127.0.0.1:0", &[])?;
    let controller = controller_floor(&sim.address, samples).await?;
    table.add(
        "floor: controller command (robot-bridge <-> robot-sim)",
        format!(
            "p50 {:.0} us, p99 {:.0} us",
            controller.pct(0.5),
            controller.pct(0.99)
        ),
        format!("TCP p50 {:.0} us", tcp.pct(0.5)),
        controller.json(),
    );

    let config = resource_config(dir, "robot1", 5000)?;
    let launched = Instant::now();
    let robot1 = holarchy_tests::start_node(
        dir,
        &config,
        "bench",
        &cell.endpoint,
        &sim.address,
        &["--data-dir", dir.join("data").to_str().unwrap()],
    )?;
    cell.wait_alive(&HolonId::resource("robot1")?).await?;
    let robot1_ready = launched.elapsed();
    cell.wait_state("robot1", "free", |s| s["state"] == "free")
        .await?;
    Ok(Run {
        dir: dir.to_path_buf(),
        cell,
        table,
        floor,
        journal_floor,
        sim,
        robot1,
        robot1_ready,
        samples,
        echo,
        ours: Ours::default(),
    })
}

/// `samples` commits of one booking-sized record through the holons' journal.
fn journal_commits(
    dir: &Path,
    durability: holon::journal::Durability,
    samples: usize,
) -> Result<Latency> {
    let journal = holon::journal::Journal::open(
        &dir.join("journal-floor"),
        &format!("{durability:?}.sqlite"),
        durability,
    )?;
    let keys = CellKeys::new("bench")?;
    let mut times = Vec::with_capacity(samples);
    let started = Instant::now();
    for i in 0..samples {
        // A record that differs from the one it replaces: SQLite writes nothing (and
        // syncs nothing) when an update leaves the page as it was.
        let record = pick_n_place(
            &keys,
            MessageType::BookingReq,
            "bench",
            &format!("bench/{i}/1"),
        );
        let t = Instant::now();
        journal.put("booking", &format!("b{}", i % 64), &record)?;
        times.push(t.elapsed());
    }
    Ok(Latency::new(times, started.elapsed()))
}

/// Booking round trips to `robot1` (journal `power_loss`) and to a second holon with
/// `process_crash`.
async fn booking(run: &mut Run) -> Result<()> {
    let series = booking_series(&run.cell, "robot1", run.samples).await?;
    booking_row(
        run,
        "booking round trip (booking_req, journal power_loss)",
        &series,
        0,
    );
    let (together, in_turn) = eight_at_once(&run.cell, "robot1", run.samples / 20).await?;
    run.table.add(
        "8 orders booking at once (power_loss)",
        format!(
            "all 8 booked in p50 {:.0} us, p99 {:.0} us",
            together.pct(0.5),
            together.pct(0.99)
        ),
        format!(
            "the same 8 one after another: p50 {:.0} us ({:.1}x)",
            in_turn.pct(0.5),
            in_turn.pct(0.5) / together.pct(0.5)
        ),
        json!({"at_once": together.json(), "one_after_another": in_turn.json()}),
    );

    // The same with the journal's `process_crash` durability (no fsync per commit): the
    // difference is what the fsyncs of `power_loss` cost.
    let mut fast = start_process_crash_robot(run, "robot9").await?;
    let series = booking_series(&run.cell, "robot9", run.samples).await?;
    fast.kill();
    run.ours.booking = Some((series.booking.pct(0.5), series.booking.pct(0.99)));
    booking_row(
        run,
        "booking round trip (journal process_crash)",
        &series,
        1,
    );
    Ok(())
}

/// A resource holon `name` on the run's controller with the journal's
/// `process_crash` durability (no fsync per commit), free.
async fn start_process_crash_robot(run: &Run, name: &str) -> Result<Process> {
    let config = resource_config(&run.dir, name, 5000)?;
    let text = std::fs::read_to_string(&config)?;
    std::fs::write(
        &config,
        format!("{text}\n[journal]\ndurability = \"process_crash\"\n"),
    )?;
    let robot = holarchy_tests::start_node(
        &run.dir,
        &config,
        "bench",
        &run.cell.endpoint,
        &run.sim.address,
        &["--data-dir", run.dir.join("data").to_str().unwrap()],
    )?;
    run.cell
        .wait_state(name, "free", |s| s["state"] == "free")
        .await?;
    Ok(robot)
}

/// Booking over mutual TLS with access control against plain TCP, in the same run: a
/// second cell (`cell certs` identities, a TLS router in this process, `robot7` with
/// `--pki`) beside the plain one, one TLS booking and one TCP booking in turn.
async fn tls_booking(run: &mut Run) -> Result<()> {
    let dir = run.dir.join("tls");
    std::fs::create_dir_all(&dir)?;
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    std::fs::write(
        dir.join("cell.toml"),
        format!(
            "cell = \"bench\"\n[router]\nlisten = [\"{endpoint}\"]\n[[process]]\nname = \"robot7\"\nprogram = \"holon-node\"\nidentity = \"resource.robot7\"\n"
        ),
    )?;
    let certs = std::process::Command::new(holarchy_tests::bin("cell"))
        .arg("certs")
        .arg(&dir)
        .output()?;
    if !certs.status.success() {
        bail!("cell certs: {}", String::from_utf8_lossy(&certs.stderr));
    }
    let pki = dir.join("pki");
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Router,
        listen: vec![endpoint.clone()],
        tls: Some(holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            ..Default::default()
        }),
        ..Default::default()
    };
    let session = settings
        .open("router.local", Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let tls_cell = Cell {
        session,
        keys: CellKeys::new("bench")?,
        endpoint: endpoint.clone(),
    };
    let config = resource_config(&run.dir, "robot7", 5000)?;
    let mut robot7 = std::process::Command::new(holarchy_tests::bin("holon-node"))
        .arg("--config")
        .arg(&config)
        .args(["--cell", "bench", "--connect", &endpoint])
        .args(["--controller", &run.sim.address])
        .arg("--pki")
        .arg(&pki)
        .arg("--data-dir")
        .arg(dir.join("data"))
        .env("RUST_LOG", holarchy_tests::holon_log_level())
        .stdout(std::process::Stdio::null())
        .stderr(std::fs::File::create(dir.join("robot7.stderr"))?)
        .spawn()?;
    let ready = tls_cell
        .wait_state("robot7", "free", |s| s["state"] == "free")
        .await;
    if let Err(e) = ready {
        let _ = robot7.kill();
        bail!("robot7 (TLS) did not come up: {e}");
    }
    let (mut tls_times, mut tcp_times) = (Vec::new(), Vec::new());
    let started = Instant::now();
    for i in 0..run.samples + 100 {
        for (cell, resource, times) in [
            (&tls_cell, "robot7", &mut tls_times),
            (&run.cell, "robot1", &mut tcp_times),
        ] {
            let (booked, _) = book_and_cancel(cell, resource, &format!("tls/{i}/1")).await?;
            if i >= 100 {
                times.push(booked);
            }
        }
    }
    let total = started.elapsed();
    let _ = robot7.kill();
    let _ = robot7.wait();
    let tls = Latency::new(tls_times, total);
    let tcp = Latency::new(tcp_times, total);
    run.table.add(
        "booking round trip over mutual TLS + access control (power_loss)",
        format!("p50 {:.0} us, p99 {:.0} us", tls.pct(0.5), tls.pct(0.99)),
        format!(
            "{:.2}x plain TCP interleaved (p50 {:.0} us, p99 {:.0} us)",
            tls.pct(0.5) / tcp.pct(0.5),
            tcp.pct(0.5),
            tcp.pct(0.99)
        ),
        json!({"tls": tls.json(), "tcp": tcp.json(), "ratio_p50": tls.pct(0.5) / tcp.pct(0.5)}),
    );
    if let Err(e) = tls_cell.session.close().await {
        eprintln!("closing the TLS router: {e}");
    }
    Ok(())
}

/// A booking figure against the floors: `journal` 0 for power_loss, 1 for process_crash.
fn booking_row(run: &mut Run, name: &str, series: &BookingSeries, journal: usize) {
    let journal_floor = if journal == 0 {
        &run.journal_floor.0
    } else {
        &run.journal_floor.1
    };
    let above = series.booking.pct(0.5) - series.floor.pct(0.5) - journal_floor.pct(0.5);
    run.table.add(
        name,
        format!(
            "p50 {:.0} us, p99 {:.0} us, {:.0} book+cancel/s",
            series.booking.pct(0.5),
            series.booking.pct(0.99),
            series.book_and_cancel.rate()
        ),
        format!(
            "{:.2}x interleaved zenoh floor (p50 {:.0} us); {above:.0} us above it + journal commit",
            series.ratio(),
            series.floor.pct(0.5)
        ),
        json!({
            "booking": series.booking.json(),
            "book_and_cancel": series.book_and_cancel.json(),
            "interleaved_floor": series.floor.json(),
            "ratio_to_floor_p50": series.ratio(),
            "above_floors_us": above,
        }),
    );
}

/// Service cycles: book (starting on its turn, as orders do by default), two controller
/// steps, `done` acknowledged; beside it, interleaved cycle by cycle so that both see the
/// same machine, the same with a separate `start`.
async fn cycle(run: &mut Run) -> Result<()> {
    // `process_crash` (the target's), both ways; then `power_loss` (robot1) beside it.
    let mut fast = start_process_crash_robot(run, "robot8").await?;
    cycle_on(
        run,
        "robot8",
        "process_crash",
        &[Starting::OnTurn, Starting::ByRequest],
    )
    .await?;
    fast.kill();
    cycle_on(run, "robot1", "power_loss", &[Starting::OnTurn]).await
}

/// How a cycle's job is started.
#[derive(Clone, Copy, PartialEq)]
enum Starting {
    /// The `booking_req` asks to start on its turn: one request books and starts.
    OnTurn,
    /// `booking_req`, then `start`: two requests.
    ByRequest,
}

/// Where one cycle's time went: until booked, until started, until `done` arrived.
struct CycleTimes {
    booked: Duration,
    started: Duration,
    done: Duration,
}

/// One cycle of `conversation` on the resource at `key`, started the `starting` way.
async fn one_cycle(
    cell: &Cell,
    key: &str,
    inbox: &mut holarchy_tests::Inbox,
    conversation: &str,
    starting: Starting,
) -> Result<CycleTimes> {
    let t = Instant::now();
    let mut book = pick_n_place(&cell.keys, MessageType::BookingReq, "bench", conversation);
    if starting == Starting::OnTurn {
        book = book.with_start_on_turn();
    }
    let answer = Service::from_json(&get_once(cell, key, book.to_json()).await?)?;
    let booked = t.elapsed();
    match starting {
        Starting::OnTurn if !answer.started() => bail!("not started on its turn: {answer:?}"),
        Starting::OnTurn => {}
        Starting::ByRequest => {
            let start = pick_n_place(&cell.keys, MessageType::Start, "bench", conversation);
            let answer = Service::from_json(&get_once(cell, key, start.to_json()).await?)?;
            if answer.result != Some(true) {
                bail!("start refused: {answer:?}");
            }
        }
    }
    let started = t.elapsed();
    while inbox.next().await?.conversation_id != conversation {}
    Ok(CycleTimes {
        booked,
        started,
        done: t.elapsed(),
    })
}

/// Service cycles on `robot`, whose journal has `durability`: for each cycle, one of
/// each way in `ways`, one after the other; a row (and where its time goes) per way.
async fn cycle_on(run: &mut Run, robot: &str, durability: &str, ways: &[Starting]) -> Result<()> {
    let cell = &run.cell;
    let key = cell.keys.service(robot);
    let mut inbox = cell.inbox("bench", 0).await?;
    let cycles = run.samples / 4;
    let mut measured: Vec<Vec<CycleTimes>> = ways.iter().map(|_| Vec::new()).collect();
    for i in 0..cycles + 20 {
        for (way, starting) in ways.iter().enumerate() {
            let conversation = format!("cycle-{durability}-{way}/{i}/1");
            let times = one_cycle(cell, &key, &mut inbox, &conversation, *starting).await?;
            if i >= 20 {
                measured[way].push(times);
            }
        }
    }
    for (starting, times) in ways.iter().zip(measured) {
        // Its rate: cycles of this way back to back, the time of each its own.
        let own: Duration = times.iter().map(|t| t.done).sum();
        let cycle = Latency::new(times.iter().map(|t| t.done).collect(), own);
        let part = |f: fn(&CycleTimes) -> Duration| {
            Latency::new(times.iter().map(f).collect(), Duration::from_secs(1))
        };
        let (book, start, until_done) = (
            part(|t| t.booked),
            part(|t| t.started - t.booked),
            part(|t| t.done - t.started),
        );
        let ratio = run.ratio(&cycle);
        if durability == "process_crash" {
            let figure = Some((cycle.pct(0.5), cycle.pct(0.99)));
            match starting {
                Starting::OnTurn => run.ours.cycle = figure,
                Starting::ByRequest => run.ours.cycle_by_request = figure,
            }
        }
        let (how, gets, parts, split) = match starting {
            Starting::OnTurn => (
                "book starting on its turn",
                2,
                "book and start | until done",
                format!("p50 {:.0} | {:.0} us", book.pct(0.5), until_done.pct(0.5)),
            ),
            Starting::ByRequest => (
                "book, start",
                3,
                "book | start | until done",
                format!(
                    "p50 {:.0} | {:.0} | {:.0} us",
                    book.pct(0.5),
                    start.pct(0.5),
                    until_done.pct(0.5)
                ),
            ),
        };
        let interleaved = if ways.len() > 1 {
            ", interleaved with the other way"
        } else {
            ""
        };
        run.table.add(
            &format!("service cycle, {durability} ({how}, 2 TCP/XML steps, done acked)"),
            format!(
                "p50 {:.0} us, p99 {:.0} us, {:.0} cycles/s",
                cycle.pct(0.5),
                cycle.pct(0.99),
                cycle.rate()
            ),
            format!(
                "{ratio:.1}x zenoh floor p50 ({gets} gets + 2 controller commands){interleaved}"
            ),
            cycle.json(),
        );
        run.table.add(
            &format!("  where it goes: {parts}"),
            split,
            "the last: 2 controller steps + result delivery".into(),
            json!({"book": book.json(), "start": start.json(), "until_done": until_done.json()}),
        );
    }
    Ok(())
}

/// Footprint and start of `robot1`; hot-add and SIGKILL detection of fresh holons.
async fn holon_figures(run: &mut Run) -> Result<()> {
    let (rss, threads) = footprint(run.robot1.pid())?;
    let anonymous = status_field(run.robot1.pid(), "RssAnon:")?;
    run.table.add(
        "footprint: idle resource holon",
        format!("{:.1} MiB resident, {threads} threads", rss as f64 / 1024.0),
        format!(
            "{:.1} MiB of it its own (anonymous); the rest the binary's pages",
            anonymous as f64 / 1024.0
        ),
        json!({"rss_kib": rss, "anonymous_kib": anonymous, "threads": threads}),
    );
    run.table.add(
        "start to ready: resource holon (token visible)",
        format!("{:.1} ms", run.robot1_ready.as_secs_f64() * 1e3),
        "-".into(),
        json!({"ms": run.robot1_ready.as_secs_f64() * 1e3}),
    );

    // Hot-add: from spawning a resource process to its first accepted booking; then
    // failure detection: SIGKILL to its token vanishing.
    let cell = &run.cell;
    let (mut hot, mut killed) = (Vec::new(), Vec::new());
    for i in 0..5 {
        let name = format!("hot{i}");
        let config = resource_config(&run.dir, &name, 5000)?;
        let t = Instant::now();
        let mut process = holarchy_tests::start_node(
            &run.dir,
            &config,
            "bench",
            &cell.endpoint,
            &run.sim.address,
            &[],
        )?;
        let key = cell.keys.service(&name);
        loop {
            let book = pick_n_place(
                &cell.keys,
                MessageType::BookingReq,
                "bench",
                &format!("hot/{i}/1"),
            );
            if let Ok(reply) = get_once(cell, &key, book.to_json()).await {
                if Service::from_json(&reply)?.result == Some(true) {
                    break;
                }
            }
            if t.elapsed() > Duration::from_secs(20) {
                bail!("{name} never accepted a booking");
            }
            tokio::time::sleep(Duration::from_millis(1)).await;
        }
        hot.push(t.elapsed());
        killed.push(
            detect_kill(
                cell,
                &mut process,
                &HolonId::resource(&name)?,
                Signal::SIGKILL,
            )
            .await?,
        );
    }
    let hot = Latency::new(hot, Duration::from_secs(1));
    let killed = Latency::new(killed, Duration::from_secs(1));
    run.table.add(
        "hot-add: spawn to first accepted booking",
        format!("median {:.1} ms (5 runs)", hot.pct(0.5) / 1e3),
        "-".into(),
        hot.json(),
    );
    run.table.add(
        "failure detection: SIGKILL to token gone",
        format!("median {:.1} ms (5 runs)", killed.pct(0.5) / 1e3),
        "-".into(),
        killed.json(),
    );
    Ok(())
}

/// From SIGKILL of the resource an order is booked on (waiting behind another job) to
/// that order's booking on another resource, through a real order-node: 5 runs.
async fn rebook(run: &mut Run) -> Result<()> {
    let cell = router("bench-rebook", None).await?;
    let dir = run.dir.join("rebook");
    std::fs::create_dir_all(&dir)?;
    // `held` robots run one job for as long as the run lasts.
    let slow = Sim::start(&dir, "slow", "127.0.0.1:0", &["--delay-ms", "600000"])?;
    let (_product, _orders) =
        start_product_and_orders(&dir, &cell, &holarchy_tests::demo_config("orders1.toml")).await?;
    let mut times = Vec::new();
    for i in 0..5 {
        let held = format!("held{i}");
        let config = resource_config(&dir, &held, 600_000)?;
        let mut held_node = holarchy_tests::start_node(
            &dir,
            &config,
            "bench-rebook",
            &cell.endpoint,
            &slow.address,
            &[],
        )?;
        cell.wait_state(&held, "free", |s| s["state"] == "free")
            .await?;
        // Keep it busy with a job of ours, then let an order book it (behind that job).
        let conversation = format!("held/{i}/1");
        let key = cell.keys.service(&held);
        for kind in [MessageType::BookingReq, MessageType::Start] {
            let message = pick_n_place(&cell.keys, kind, "bench", &conversation);
            let answer = Service::from_json(&get_once(&cell, &key, message.to_json()).await?)?;
            if answer.result != Some(true) {
                bail!("{held} refused {kind}: {answer:?}");
            }
        }
        cell.submit("part", 1).await?;
        cell.wait_state(&held, "an order's booking", |s| {
            s["agenda"].as_array().is_some_and(|a| a.len() == 1)
        })
        .await?;
        // The spare comes up; the order stays where it is booked.
        let spare = format!("spare{i}");
        let config = resource_config(&dir, &spare, 5000)?;
        let mut spare_node = holarchy_tests::start_node(
            &dir,
            &config,
            "bench-rebook",
            &cell.endpoint,
            &run.sim.address,
            &[],
        )?;
        cell.wait_state(&spare, "free", |s| s["state"] == "free")
            .await?;
        let states = cell
            .session
            .declare_subscriber(cell.keys.state(&HolonId::resource(&spare)?))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let t = Instant::now();
        kill(Pid::from_raw(held_node.pid()), Signal::SIGKILL)?;
        loop {
            let sample = tokio::time::timeout(Duration::from_secs(30), states.recv_async())
                .await
                .map_err(|_| anyhow!("the order was not rebooked on {spare} within 30 s"))?
                .map_err(|e| anyhow!("{e}"))?;
            let snapshot: schemas::ResourceSnapshot =
                serde_json::from_slice(&sample.payload().to_bytes())?;
            if !snapshot.agenda.is_empty() || snapshot.current.is_some() {
                times.push(t.elapsed());
                break;
            }
        }
        held_node.kill();
        // Let the order finish on the spare before the next run.
        cell.wait_state(&spare, "idle", |s| {
            s["state"] == "free"
                && s["undelivered"] == 0
                && s["agenda"].as_array().is_some_and(|a| a.is_empty())
        })
        .await?;
        spare_node.kill();
    }
    let times = Latency::new(times, Duration::from_secs(1));
    run.table.add(
        "rebooking: SIGKILL of the booked resource to the booking elsewhere",
        format!(
            "median {:.1} ms, max {:.1} ms (5 runs)",
            times.pct(0.5) / 1e3,
            times.pct(1.0) / 1e3
        ),
        "through order-node; a started step waits vanished_grace_ms first".into(),
        times.json(),
    );
    Ok(())
}

/// A frozen process: only the lease detects it.
async fn lease(run: &mut Run) -> Result<()> {
    let lease_cell = router("bench-lease", Some(1000)).await?;
    let config = resource_config(&run.dir, "frozen", 5000)?;
    let mut frozen = holarchy_tests::start_node(
        &run.dir,
        &config,
        "bench-lease",
        &lease_cell.endpoint,
        &run.sim.address,
        &["--lease-ms", "1000"],
    )?;
    lease_cell.wait_alive(&HolonId::resource("frozen")?).await?;
    let stopped = detect_kill(
        &lease_cell,
        &mut frozen,
        &HolonId::resource("frozen")?,
        Signal::SIGSTOP,
    )
    .await?;
    let _ = kill(Pid::from_raw(frozen.pid()), Signal::SIGKILL);
    frozen.kill();
    run.table.add(
        "failure detection: SIGSTOP to token gone",
        format!("{:.0} ms", stopped.as_secs_f64() * 1e3),
        "lease 1000 ms".into(),
        json!({"ms": stopped.as_secs_f64() * 1e3, "lease_ms": 1000}),
    );
    Ok(())
}

/// An order-node hosting `orders` orders that wait for a robot (one robot, busy with a
/// long job, agenda full): its memory, threads and CPU, against the same node idle.
async fn order_node_footprint(run: &mut Run, orders: u32) -> Result<()> {
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

/// The time a process's threads have been on a CPU, in ns (`/proc/PID/task/*/schedstat`).
/// Precise for short bursts, where [`cpu_time`] counts 10 ms ticks; threads that ended
/// are not counted, so it suits a process's first moments (its start), not a long run.
fn on_cpu(pid: i32) -> Result<Duration> {
    let mut total = Duration::ZERO;
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))? {
        let schedstat = std::fs::read_to_string(task?.path().join("schedstat"))?;
        let ns: u64 = schedstat
            .split_whitespace()
            .next()
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| anyhow!("unreadable schedstat of {pid}"))?;
        total += Duration::from_nanos(ns);
    }
    Ok(total)
}

/// CPU time (user + system) a process has used, from /proc: every thread it ever ran,
/// in 10 ms ticks (fine over a run of seconds; see [`on_cpu`] for a start).
fn cpu_time(pid: i32) -> Result<Duration> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // Fields after the command name (which may hold spaces) start at ") ".
    let rest = stat
        .rsplit_once(") ")
        .map(|(_, r)| r)
        .ok_or_else(|| anyhow!("unreadable /proc/{pid}/stat"))?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = fields[11].parse::<u64>()? + fields[12].parse::<u64>()?;
    let per_second = nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)?.unwrap_or(100) as u64;
    Ok(Duration::from_secs_f64(ticks as f64 / per_second as f64))
}

/// The product `part` and the order-node `orders1` of `config` (its journal in
/// `DIR/data`), both in the cell.
async fn start_product_and_orders(
    dir: &Path,
    cell: &Cell,
    config: &Path,
) -> Result<(Process, Process)> {
    cell.start_part_and_orders(dir, config, &dir.join("data"))
        .await
}

async fn detect_kill(
    cell: &Cell,
    process: &mut Process,
    holon: &HolonId,
    signal: Signal,
) -> Result<Duration> {
    let subscriber = cell
        .session
        .liveliness()
        .declare_subscriber(cell.keys.alive(holon))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let t = Instant::now();
    kill(Pid::from_raw(process.pid()), signal)?;
    loop {
        let sample = tokio::time::timeout(Duration::from_secs(30), subscriber.recv_async())
            .await
            .map_err(|_| anyhow!("{holon} never vanished"))?
            .map_err(|e| anyhow!("{e}"))?;
        if sample.kind() == zenoh::sample::SampleKind::Delete {
            let elapsed = t.elapsed();
            if signal == Signal::SIGKILL {
                process.kill();
            }
            return Ok(elapsed);
        }
    }
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
        let replies = cell
            .session
            .get(cell.keys.order_states())
            .timeout(Duration::from_secs(2))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let mut done = 0;
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                let snapshot: schemas::OrderSnapshot =
                    serde_json::from_slice(&sample.payload().to_bytes())?;
                if snapshot.status == schemas::OrderStatus::Done {
                    done += 1;
                }
            }
        }
        if done == orders {
            return Ok(orders as f64 / t.elapsed().as_secs_f64());
        }
        if t.elapsed() > Duration::from_secs(120) {
            bail!("{done} of {orders} orders done after 120 s");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Starts `robot0`..`robot{n-1}` on `cell`, each with its own controller simulator
/// (started with `sim_flags`), and waits until each is alive and free.
async fn start_robots(
    cell: &Cell,
    dir: &Path,
    n: usize,
    sim_flags: &[&str],
) -> Result<Vec<(Sim, Process)>> {
    let mut robots = Vec::new();
    for i in 0..n {
        let name = format!("robot{i}");
        let sim = Sim::start(dir, &format!("{name}-sim"), "127.0.0.1:0", sim_flags)?;
        let config = resource_config(dir, &name, 5000)?;
        let node = holarchy_tests::start_node(
            dir,
            &config,
            cell.keys.cell(),
            &cell.endpoint,
            &sim.address,
            &[],
        )?;
        cell.wait_alive(&HolonId::resource(&name)?).await?;
        cell.wait_state(&name, "free", |s| s["state"] == "free")
            .await?;
        robots.push((sim, node));
    }
    Ok(robots)
}

/// One controller command's round trip through the controller client and robot-sim,
/// without a holon: the floor of an execution step.
async fn controller_floor(address: &str, samples: usize) -> Result<Latency> {
    use robot_bridge::client::{self, ClientConfig, ControllerEvent};
    let (commands, mut command_rx) = tokio::sync::mpsc::channel(16);
    let (event_tx, mut events) = tokio::sync::mpsc::channel(16);
    let shutdown = tokio_util::sync::CancellationToken::new();
    let config = ClientConfig::new(address);
    let task = tokio::spawn({
        let shutdown = shutdown.clone();
        async move { client::run(config, &mut command_rx, event_tx, shutdown).await }
    });
    loop {
        match events.recv().await {
            Some(ControllerEvent::Status(s)) if s.is_ready() => break,
            Some(_) => continue,
            None => bail!("controller client stopped"),
        }
    }
    let mut times = Vec::new();
    let started = Instant::now();
    for id in 0..samples as u64 {
        let t = Instant::now();
        commands
            .send(schemas::RobotCommand {
                id,
                action: "pick".into(),
                pos: Some(schemas::Pose {
                    x: 1.0,
                    y: 2.0,
                    z: 3.0,
                    ..Default::default()
                }),
                program: None,
            })
            .await?;
        match events.recv().await {
            Some(ControllerEvent::Reply { .. }) => times.push(t.elapsed()),
            other => bail!("unexpected {other:?}"),
        }
    }
    shutdown.cancel();
    let _ = task.await;
    Ok(Latency::new(times, started.elapsed()))
}

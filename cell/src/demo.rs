//! `cell demo`: a complete demo cell on this machine, with no other install.
//!
//! In its own process it runs the cell's zenoh router; it starts, as real processes, the
//! plant simulator (every controller of the cell over one physical state: where each
//! part and pallet is), two robots, an inspection station, a conveyor and a transfer
//! robot between robot2 and the inspection station (resource holons, each over its own
//! controller connection), the breaker (a product holon whose parts ride the conveyor's
//! pallets from station to station, or the transfer robot between its two), with `--staff` a staff holon
//! that advises the orders, and an order-node. It submits the work orders, shows every
//! order's progress and where its part goes, hot-adds a third robot once half of the
//! orders are finished, prints a summary, stops everything it started (in reverse
//! order) and exits 0 only if every order completed (`done`, or `scrapped` by its plan).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use schemas::{CellKeys, HolonId, OrderSnapshot, OrderStatus, WorkOrder};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tokio_util::sync::CancellationToken;

mod report;
mod servers;

use report::{print_progress, Report};

const ROBOT: &str = include_str!("../../deploy/cells/demo/robot1.toml");
const ROBOT2: &str = include_str!("../../deploy/cells/demo/robot2.toml");
const INSPECTION: &str = include_str!("../../deploy/cells/demo/inspect1.toml");
const CONVEYOR: &str = include_str!("../../deploy/cells/demo/conveyor1.toml");
const TRANSFER: &str = include_str!("../../deploy/cells/demo/transfer1.toml");
const PRODUCT: &str = include_str!("../../deploy/cells/demo/breaker.toml");
const ORDERS: &str = include_str!("../../deploy/cells/demo/orders1.toml");
const PLANNER: &str = include_str!("../../deploy/cells/demo/planner.toml");

/// The plant's state file in the demo's directory: where every part and pallet is.
const PLANT_STATE: &str = "plant-state.json";

/// How long anything the demo starts may take to come up.
const STARTUP: Duration = Duration::from_secs(15);

#[derive(Debug, Clone)]
pub struct DemoOptions {
    pub cell: String,
    pub orders: u32,
    /// Simulated duration of a robot action (the conveyor and the inspection station
    /// take a third of it).
    pub action_delay: Duration,
    /// Every Nth inspection fails (the plan reworks the part); 0: none fail.
    pub inspect_fail_every: u64,
    /// Hot-add a third robot once half of the orders are finished.
    pub hot_add: bool,
    /// Where configs and logs go; a temporary directory when not given.
    pub dir: Option<PathBuf>,
    /// Mutual TLS and access control: a PKI is issued into `<dir>/pki` and every
    /// process, the router included, uses its own identity.
    pub secure: bool,
    /// Serve the cell's dashboard (operator) on this address while the demo runs.
    pub dashboard: Option<std::net::SocketAddr>,
    /// Keep the cell up after the summary, until Ctrl-C or SIGTERM.
    pub keep: bool,
    /// Run a staff holon (`staff/planner`) whose advice the orders take.
    pub staff: bool,
    /// Serve the cell over OPC UA (`cell opcua`, in this process) on this address while
    /// the demo runs.
    pub opcua: Option<std::net::SocketAddr>,
}

/// The manifest `cell certs` issues the secure demo's identities from.
fn secure_manifest(cell: &str, endpoint: &str, opcua: bool) -> String {
    let mut text = format!(
        "cell = \"{cell}\"\n[router]\nlisten = [\"{endpoint}\"]\n[pki]\nspares = [\"resource.robot3\"]\n"
    );
    for identity in [
        "staff.planner",
        "resource.robot1",
        "resource.robot2",
        "resource.inspect1",
        "resource.conveyor1",
        "resource.transfer1",
        "product.breaker",
        "order-node.orders1",
    ] {
        let name = identity.split_once('.').map_or(identity, |(_, n)| n);
        text.push_str(&format!(
            "[[process]]\nname = \"{name}\"\nprogram = \"holon-node\"\nidentity = \"{identity}\"\n"
        ));
    }
    // `cell certs` issues the OPC UA server's certificate for a manifest running it.
    if opcua {
        text.push_str(
            "[[process]]\nname = \"opcua\"\nprogram = \"cell\"\nargs = [\"opcua\"]\nidentity = \"operator.opcua\"\n",
        );
    }
    text
}

/// A child process stopped with SIGTERM (then killed) when the demo ends.
struct Managed {
    name: String,
    child: Child,
}

impl Managed {
    async fn stop(mut self) -> Result<std::process::ExitStatus> {
        if let Some(pid) = self.child.id() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(pid as i32),
                nix::sys::signal::Signal::SIGTERM,
            );
        }
        match tokio::time::timeout(Duration::from_secs(40), self.child.wait()).await {
            Ok(status) => Ok(status?),
            Err(_) => {
                self.child.kill().await?;
                bail!("{} did not stop within 40 s; killed", self.name)
            }
        }
    }
}

pub fn sibling_binary(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().context("cannot find this executable")?;
    let path = exe
        .parent()
        .ok_or_else(|| anyhow!("executable has no directory"))?
        .join(name);
    if !path.exists() {
        bail!(
            "{} not found next to cell; build the workspace (cargo build --bins)",
            path.display()
        );
    }
    Ok(path)
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// The processes of the demo cell, in start order.
struct Cell {
    dir: PathBuf,
    endpoint: String,
    /// The PKI directory of a secure demo.
    pki: Option<PathBuf>,
    keys: CellKeys,
    session: zenoh::Session,
    started: Vec<Managed>,
    /// Each resource's controller in the plant, by resource.
    controllers: BTreeMap<String, String>,
}

impl Cell {
    /// Starts `plant-sim` on the plant file `plant` (every controller of the cell over
    /// one physical state, docs/material-flow.md): each controller's address, by
    /// resource, once it says it is ready.
    async fn plant(&mut self, plant: &str) -> Result<BTreeMap<String, String>> {
        let file = self.dir.join("plant.toml");
        std::fs::write(&file, plant)?;
        let mut child = Command::new(sibling_binary("plant-sim")?)
            .arg("--plant")
            .arg(&file)
            .arg("--state-file")
            .arg(self.dir.join(PLANT_STATE))
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(self.dir.join("plant-sim.log"))?)
            .kill_on_drop(true)
            .spawn()
            .context("cannot start plant-sim")?;
        let stdout = child.stdout.take().expect("piped");
        self.started.push(Managed {
            name: "plant-sim".into(),
            child,
        });
        let mut lines = BufReader::new(stdout).lines();
        let mut controllers = BTreeMap::new();
        loop {
            let line = tokio::time::timeout(STARTUP, lines.next_line())
                .await
                .context("plant-sim did not start in time")??
                .ok_or_else(|| {
                    anyhow!(
                        "plant-sim ended before it was ready; see {}",
                        self.dir.join("plant-sim.log").display()
                    )
                })?;
            if line == "plant ready" {
                return Ok(controllers);
            }
            if let Some((resource, address)) = line
                .strip_prefix("controller ")
                .and_then(|l| l.split_once(" listening on "))
            {
                controllers.insert(resource.to_string(), address.to_string());
            }
        }
    }

    /// Starts `program --config FILE` for a holon and waits for its token.
    async fn holon(
        &mut self,
        program: &str,
        config_text: &str,
        holon: &HolonId,
        extra: &[String],
        ready_key: Option<String>,
    ) -> Result<Duration> {
        let config = self.dir.join(format!("{}.toml", holon.name()));
        std::fs::write(&config, config_text)?;
        let launched = Instant::now();
        let child = Command::new(sibling_binary(program)?)
            .arg("--config")
            .arg(&config)
            .args(["--cell", self.keys.cell(), "--name", holon.name()])
            .args(["--connect", &self.endpoint])
            .args(
                self.pki
                    .iter()
                    .flat_map(|p| [std::ffi::OsStr::new("--pki"), p.as_os_str()]),
            )
            .arg("--log-file")
            .arg(self.dir.join(format!("{}.log.json", holon.name())))
            .arg("--data-dir")
            .arg(self.dir.join("data"))
            .args(extra)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(
                self.dir.join(format!("{}.log", holon.name())),
            )?)
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("cannot start {program}"))?;
        self.started.push(Managed {
            name: holon.to_string(),
            child,
        });
        let key = ready_key.unwrap_or_else(|| self.keys.alive(holon));
        if !wait_token(&self.session, &key, STARTUP).await? {
            bail!(
                "{holon} did not come up; see {}",
                self.dir.join(format!("{}.log", holon.name())).display()
            );
        }
        Ok(launched.elapsed())
    }

    async fn stop_all(self) {
        for managed in self.started.into_iter().rev() {
            let name = managed.name.clone();
            match managed.stop().await {
                Ok(status) if status.success() => {}
                Ok(status) => println!("  {name} exited with {status}"),
                Err(e) => println!("  {name}: {e}"),
            }
        }
        let _ = self.session.close().await;
    }
}

async fn wait_token(session: &zenoh::Session, key: &str, timeout: Duration) -> Result<bool> {
    holon::presence::wait_token(session, key, timeout)
        .await
        .map_err(|e| anyhow!("{e}"))
}

/// Runs the demo; returns whether every order completed.
pub async fn run(options: DemoOptions, shutdown: CancellationToken) -> Result<bool> {
    let keys = CellKeys::new(&options.cell)?;
    let (dir, mut temp) = working_dir(&options)?;
    let (mut cell, _announced) = open_the_cell(&options, &dir, keys).await?;
    if options.dashboard.is_some() || options.opcua.is_some() {
        servers::demo_operator(&cell)?;
    }
    let dashboard = match options.dashboard {
        Some(listen) => Some(servers::start_dashboard(&cell, listen).await?),
        None => None,
    };
    let opcua = match options.opcua {
        Some(listen) => Some(servers::start_opcua(&cell, listen)?),
        None => None,
    };
    let outcome = tokio::select! {
        outcome = operate(&mut cell, &options) => outcome,
        _ = shutdown.cancelled() => Err(anyhow!("interrupted")),
    };
    // With --keep the summary comes now, and the cell stays up for its user.
    let printed = match (&outcome, options.keep) {
        (Ok(report), true) => {
            report.print(&dir);
            println!();
            stay_up(&cell, &options, dashboard.is_some(), &shutdown).await;
            true
        }
        _ => false,
    };
    println!("stopping everything the demo started, in reverse order ...");
    servers::stop(opcua, dashboard).await;
    cell.stop_all().await;
    let report = outcome?;
    if !printed {
        report.print(&dir);
    }
    let success = report.failed == 0 && report.completed() == options.orders as usize;
    if let (Some(temp), false) = (temp.as_mut(), success) {
        temp.keep = true;
        println!("  logs kept in    {}", dir.display());
    }
    Ok(success)
}

/// Where the demo keeps its configs and logs: `--dir`, or a new temporary directory.
fn working_dir(options: &DemoOptions) -> Result<(PathBuf, Option<TempDir>)> {
    match &options.dir {
        Some(dir) => {
            std::fs::create_dir_all(dir)?;
            Ok((dir.clone(), None))
        }
        None => {
            let made = tempdir()?;
            Ok((made.path.clone(), Some(made)))
        }
    }
}

/// The cell's router, embedded in this process (with its identities issued first in a
/// secure demo) and announced in the cell; the announcement lasts while the guard does.
async fn open_the_cell(
    options: &DemoOptions,
    dir: &std::path::Path,
    keys: CellKeys,
) -> Result<(Cell, zenoh::liveliness::LivelinessToken)> {
    let scheme = if options.secure { "tls" } else { "tcp" };
    let endpoint = format!("{scheme}/127.0.0.1:{}", free_port()?);
    let pki = if options.secure {
        std::fs::write(
            dir.join("cell.toml"),
            secure_manifest(&options.cell, &endpoint, options.opcua.is_some()),
        )?;
        crate::security::certs::run(dir, &crate::security::certs::CertsOptions::default())?;
        Some(dir.join("pki"))
    } else {
        None
    };
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Router,
        listen: vec![endpoint.clone()],
        tls: pki.as_ref().map(|pki| holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            ..holon::tls::TlsSettings::default()
        }),
        ..holon::ZenohSettings::default()
    };
    let session = settings
        .open(
            &holon::role::identity(holon::role::Role::Router, "local"),
            STARTUP,
        )
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let announced = crate::router::announce(&session, &keys, &holon::presence::host_name()).await?;
    println!(
        "cell {}: zenoh router on {endpoint}; configs and logs in {}",
        options.cell,
        dir.display()
    );
    if options.secure {
        println!(
            "mutual TLS and access control on: identities in {}",
            dir.join("pki").display()
        );
    }
    let cell = Cell {
        dir: dir.to_path_buf(),
        endpoint,
        pki,
        keys,
        session,
        started: Vec::new(),
        controllers: BTreeMap::new(),
    };
    Ok((cell, announced))
}

/// `--keep`: says how to use the cell that stays up, and waits for Ctrl-C.
async fn stay_up(
    cell: &Cell,
    options: &DemoOptions,
    dashboard: bool,
    shutdown: &CancellationToken,
) {
    // Every hint must work when pasted: a secure cell needs its PKI.
    let pki = cell
        .pki
        .as_ref()
        .map(|pki| format!(" --pki {}", pki.display()))
        .unwrap_or_default();
    println!(
        "the cell stays up (--keep): submit more with `cell submit breaker --count 5 --cell {} --connect {}{pki}`{}; Ctrl-C stops it",
        options.cell,
        cell.endpoint,
        if dashboard { " or from the dashboard" } else { "" }
    );
    shutdown.cancelled().await;
}

async fn operate(cell: &mut Cell, options: &DemoOptions) -> Result<Report> {
    start_holons(cell, options).await?;
    // Watch every order's state before submitting.
    let states = cell
        .session
        .declare_subscriber(cell.keys.order_states())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let started = Instant::now();
    let work = WorkOrder {
        product: "breaker".into(),
        count: options.orders,
        priority: 0,
        due: None,
        queue: false,
        submit_id: None,
    };
    let ids = crate::client::submit::submit(&cell.session, &cell.keys, &work, "cell demo", STARTUP)
        .await?;
    println!(
        "submitted {} orders of breaker: {} .. {}",
        ids.len(),
        ids.first().map(String::as_str).unwrap_or(""),
        ids.last().map(String::as_str).unwrap_or("")
    );

    let mut orders: BTreeMap<HolonId, OrderSnapshot> = BTreeMap::new();
    let mut report = Report {
        orders: BTreeMap::new(),
        failed: 0,
        elapsed: Duration::ZERO,
        hot_added: None,
        staff: options.staff,
        transports: BTreeMap::new(),
    };
    let mut hot_added = None;
    let mut advised_shown = BTreeMap::new();
    let deadline =
        Instant::now() + Duration::from_secs(60) + options.action_delay * 10 * options.orders;
    loop {
        let finished = orders.values().filter(|o| o.status.is_final()).count();
        if finished == ids.len() {
            break;
        }
        if options.hot_add && hot_added.is_none() && finished * 2 >= ids.len() {
            hot_add_robot3(cell, ids.len() - finished).await?;
            hot_added = Some(started.elapsed());
        }
        let sample = match tokio::time::timeout_at(deadline.into(), states.recv_async()).await {
            Ok(Ok(sample)) => sample,
            Ok(Err(e)) => bail!("order states: {e}"),
            Err(_) => bail!("orders still running after {:?}", deadline - started),
        };
        let Ok(snapshot) = serde_json::from_slice::<OrderSnapshot>(&sample.payload().to_bytes())
        else {
            continue;
        };
        print_progress(
            orders.get(&snapshot.holon),
            &snapshot,
            started.elapsed(),
            &mut advised_shown,
        );
        report.count_move(orders.get(&snapshot.holon), &snapshot);
        orders.insert(snapshot.holon.clone(), snapshot);
    }
    report.failed = orders
        .values()
        .filter(|o| o.status == OrderStatus::Failed)
        .count();
    report.orders = orders;
    report.elapsed = started.elapsed();
    report.hot_added = hot_added;
    Ok(report)
}

/// The demo's plant file: the layout of every resource config (robot3's too: its port
/// on the free stopper is there physically before its holon starts) and a controller
/// per resource, timed by the demo's options.
fn plant_file(options: &DemoOptions) -> String {
    let robot = options.action_delay.as_millis();
    let short = (options.action_delay / 3).as_millis();
    let mut text = String::from(
        "layout = [\"robot1.toml\", \"robot2.toml\", \"robot3.toml\", \"inspect1.toml\", \"conveyor1.toml\", \"transfer1.toml\"]\n",
    );
    for (resource, delay) in [
        ("robot1", robot),
        ("robot2", robot),
        ("robot3", robot),
        ("inspect1", short),
        ("conveyor1", short),
        ("transfer1", short),
    ] {
        text.push_str(&format!(
            "[[controller]]\nresource = \"{resource}\"\nlisten = \"127.0.0.1:0\"\ndelay_ms = {delay}\n"
        ));
        if resource == "conveyor1" {
            // As many moves at once as its holon runs (conveyor1.toml's jobs_at_once).
            text.push_str("actions_at_once = 4\n");
        }
        if resource == "inspect1" && options.inspect_fail_every > 0 {
            text.push_str(&format!(
                "inspect_fail_every = {}\n",
                options.inspect_fail_every
            ));
        }
    }
    text
}

/// robot3's config: robot1's, docked at the conveyor's free stopper (it joins the layout
/// by starting).
fn robot3_config() -> String {
    ROBOT
        .replace("name = \"robot1\"", "name = \"robot3\"")
        .replace("dock = \"conveyor1.s1\"", "dock = \"conveyor1.s3\"")
}

/// Starts the plant, then the cell's holons: each resource on its controller in the
/// plant, the product, the order-node; prints how long each took to appear.
async fn start_holons(cell: &mut Cell, options: &DemoOptions) -> Result<()> {
    let robot3 = robot3_config();
    let resources = [
        ("robot1", ROBOT),
        ("robot2", ROBOT2),
        ("inspect1", INSPECTION),
        ("conveyor1", CONVEYOR),
        ("transfer1", TRANSFER),
        ("robot3", robot3.as_str()),
    ];
    // The plant reads the configs' [layout] before any holon starts.
    for (name, config) in resources {
        std::fs::write(cell.dir.join(format!("{name}.toml")), config)?;
    }
    cell.controllers = cell.plant(&plant_file(options)).await?;
    println!(
        "  {:<22} every controller over one physical state ({})",
        "plant-sim",
        cell.dir.join(PLANT_STATE).display()
    );
    for (name, config) in resources.into_iter().filter(|(n, _)| *n != "robot3") {
        start_resource(cell, name, config).await?;
    }
    let product = HolonId::new(schemas::HolonKind::Product, "breaker")?;
    let took = cell
        .holon("holon-node", PRODUCT, &product, &[], None)
        .await?;
    println!("  {product:<22} alive after {:>4} ms", took.as_millis());
    if options.staff {
        let planner = HolonId::staff("planner")?;
        let took = cell
            .holon("holon-node", PLANNER, &planner, &[], None)
            .await?;
        println!(
            "  {planner:<22} alive after {:>4} ms (steps booked on its advice are marked *)",
            took.as_millis()
        );
    }
    let orders_key = cell.keys.host("order-node", "orders1");
    let took = cell
        .holon(
            "order-node",
            ORDERS,
            &HolonId::order("orders1")?,
            &[],
            Some(orders_key),
        )
        .await?;
    println!(
        "  {:<22} alive after {:>4} ms",
        "order-node orders1",
        took.as_millis()
    );
    Ok(())
}

/// Starts the resource holon `name` on its controller in the plant; returns how long
/// it took to appear.
async fn start_resource(cell: &mut Cell, name: &str, config: &str) -> Result<Duration> {
    let controller = cell
        .controllers
        .get(name)
        .cloned()
        .ok_or_else(|| anyhow!("the plant has no controller for {name}"))?;
    let holon = HolonId::resource(name)?;
    let took = cell
        .holon(
            "holon-node",
            config,
            &holon,
            &["--controller".into(), controller.clone()],
            None,
        )
        .await?;
    println!(
        "  {holon:<22} alive after {:>4} ms (controller {controller})",
        took.as_millis()
    );
    Ok(took)
}

/// Hot-adds robot3 (its controller is in the plant already) while `running` orders run.
async fn hot_add_robot3(cell: &mut Cell, running: usize) -> Result<()> {
    let took = start_resource(cell, "robot3", &robot3_config()).await?;
    println!(
        "+ hot-added resource/robot3 while {running} orders run (alive after {} ms)",
        took.as_millis()
    );
    Ok(())
}

/// A temporary directory removed when dropped, unless kept for its logs.
struct TempDir {
    path: PathBuf,
    keep: bool,
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if !self.keep {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

fn tempdir() -> Result<TempDir> {
    let path = std::env::temp_dir().join(format!(
        "holarchy-demo-{}-{}",
        std::process::id(),
        schemas::unix_ms()
    ));
    std::fs::create_dir_all(&path)?;
    Ok(TempDir { path, keep: false })
}

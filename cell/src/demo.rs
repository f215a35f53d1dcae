//! `cell demo`: a complete demo cell on this machine, with no other install.
//!
//! In its own process it runs the cell's zenoh router; it starts, as real processes, a
//! controller simulator per resource, two robots, an inspection station, a conveyor
//! (resource holons), the breaker (a product holon), with `--staff` a staff holon that
//! advises the orders, and an order-node. It submits the
//! work orders, shows every order's progress, hot-adds a third robot once half of the
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
const PRODUCT: &str = include_str!("../../deploy/cells/demo/breaker.toml");
const ORDERS: &str = include_str!("../../deploy/cells/demo/orders1.toml");
const PLANNER: &str = include_str!("../../deploy/cells/demo/planner.toml");

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
}

impl Cell {
    async fn sim(&mut self, name: &str, delay: Duration, extra: &[String]) -> Result<String> {
        let mut child = Command::new(sibling_binary("robot-sim")?)
            .args(["--listen", "127.0.0.1:0", "--delay-ms"])
            .arg(delay.as_millis().to_string())
            .arg("--count-file")
            .arg(self.dir.join(format!("{name}.counts.json")))
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(self.dir.join(format!("{name}.log")))?)
            .kill_on_drop(true)
            .spawn()
            .context("cannot start robot-sim")?;
        let stdout = child.stdout.take().expect("piped");
        let mut line = String::new();
        tokio::time::timeout(STARTUP, BufReader::new(stdout).read_line(&mut line))
            .await
            .context("robot-sim did not start in time")??;
        let address = line
            .trim()
            .strip_prefix("listening on ")
            .ok_or_else(|| anyhow!("robot-sim said {line:?}"))?
            .to_string();
        self.started.push(Managed {
            name: name.into(),
            child,
        });
        Ok(address)
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
    let mut temp = None;
    let dir = match &options.dir {
        Some(dir) => {
            std::fs::create_dir_all(dir)?;
            dir.clone()
        }
        None => {
            let made = tempdir()?;
            let path = made.path.clone();
            temp = Some(made);
            path
        }
    };
    let scheme = if options.secure { "tls" } else { "tcp" };
    let endpoint = format!("{scheme}/127.0.0.1:{}", free_port()?);
    let pki = if options.secure {
        std::fs::write(
            dir.join("cell.toml"),
            secure_manifest(&options.cell, &endpoint, options.opcua.is_some()),
        )?;
        crate::certs::run(&dir, &crate::certs::CertsOptions::default())?;
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
    let _announced =
        crate::router::announce(&session, &keys, &holon::presence::host_name()).await?;
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
    let mut cell = Cell {
        dir: dir.clone(),
        endpoint,
        pki,
        keys: keys.clone(),
        session: session.clone(),
        started: Vec::new(),
    };
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
                if dashboard.is_some() { " or from the dashboard" } else { "" }
            );
            shutdown.cancelled().await;
            true
        }
        _ => false,
    };
    println!("stopping everything the demo started, in reverse order ...");
    if let Some((stop, task)) = opcua {
        stop.cancel();
        match tokio::time::timeout(Duration::from_secs(10), task).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => println!("the OPC UA server stopped with an error: {e:#}"),
            Ok(Err(e)) => println!("the OPC UA server's task ended abnormally: {e}"),
            Err(_) => println!("the OPC UA server did not stop within 10 s"),
        }
    }
    if let Some((stop, task)) = dashboard {
        stop.cancel();
        match task.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => println!("the dashboard stopped with an error: {e:#}"),
            Err(e) => println!("the dashboard's task ended abnormally: {e}"),
        }
    }
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
    };
    let ids = crate::submit::submit(&cell.session, &cell.keys, &work, "cell demo", STARTUP).await?;
    println!(
        "submitted {} orders of breaker: {} .. {}",
        ids.len(),
        ids.first().map(String::as_str).unwrap_or(""),
        ids.last().map(String::as_str).unwrap_or("")
    );

    let mut orders: BTreeMap<HolonId, OrderSnapshot> = BTreeMap::new();
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
            hot_add_robot3(cell, options, ids.len() - finished).await?;
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
        orders.insert(snapshot.holon.clone(), snapshot);
    }
    let failed = orders
        .values()
        .filter(|o| o.status == OrderStatus::Failed)
        .count();
    Ok(Report {
        orders,
        failed,
        elapsed: started.elapsed(),
        hot_added,
        staff: options.staff,
    })
}

/// Starts the cell's holons: each resource after its simulator, the product, the
/// order-node; prints how long each took to appear.
async fn start_holons(cell: &mut Cell, options: &DemoOptions) -> Result<()> {
    let robot_delay = options.action_delay;
    let short_delay = options.action_delay / 3;
    let inspect_flags = if options.inspect_fail_every > 0 {
        vec![
            "--inspect-fail-every".into(),
            options.inspect_fail_every.to_string(),
        ]
    } else {
        vec![]
    };
    let resources: Vec<(&str, &str, Duration, Vec<String>)> = vec![
        ("robot1", ROBOT, robot_delay, vec![]),
        ("robot2", ROBOT2, robot_delay, vec![]),
        ("inspect1", INSPECTION, short_delay, inspect_flags),
        ("conveyor1", CONVEYOR, short_delay, vec![]),
    ];
    for (name, config, delay, sim_flags) in &resources {
        let controller = cell.sim(&format!("{name}-sim"), *delay, sim_flags).await?;
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

/// Hot-adds robot3 (its simulator, then its holon) while `running` orders run.
async fn hot_add_robot3(cell: &mut Cell, options: &DemoOptions, running: usize) -> Result<()> {
    let controller = cell.sim("robot3-sim", options.action_delay, &[]).await?;
    let robot3 = HolonId::resource("robot3")?;
    // robot1's config, docked at the conveyor's free stopper: it joins the layout by
    // starting.
    let config = ROBOT.replace("dock = \"conveyor1.s1\"", "dock = \"conveyor1.s3\"");
    let took = cell
        .holon(
            "holon-node",
            &config,
            &robot3,
            &["--controller".into(), controller],
            None,
        )
        .await?;
    println!(
        "+ hot-added {robot3} while {running} orders run (alive after {} ms)",
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

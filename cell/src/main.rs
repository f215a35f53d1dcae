//! `cell`: the operator's command.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{anyhow, Result};
use clap::{Parser, Subcommand};
use holon::LogFormat;

/// The operator's command for a holarchy cell.
#[derive(Debug, Parser)]
#[command(name = "cell", version)]
struct Args {
    #[command(subcommand)]
    command: Commands,
}

#[derive(Debug, Subcommand)]
enum Commands {
    /// Run a complete demo cell on this machine: an embedded zenoh router, two robots,
    /// an inspection station and a conveyor (each with its controller simulator), the
    /// breaker product and an order-node, all as real processes; submit the orders, show
    /// their progress, hot-add a third robot midway, print a summary and stop
    /// everything. Exits 0 only if every order completed (done, or scrapped by its plan).
    Demo {
        /// The cell's name (all keys live under holarchy/<cell>/).
        #[arg(long, default_value = "demo")]
        cell: String,
        /// How many breakers to order.
        #[arg(long, default_value_t = 10)]
        orders: u32,
        /// Simulated duration of a robot action in milliseconds (the conveyor and the
        /// inspection station take a third of it).
        #[arg(long, default_value_t = 300)]
        delay_ms: u64,
        /// Every Nth inspection fails and the plan reworks the part (0: none fail).
        #[arg(long, default_value_t = 7)]
        inspect_fail_every: u64,
        /// Do not hot-add the third robot.
        #[arg(long)]
        no_hot_add: bool,
        /// Keep configs and logs in this directory (default: a temporary directory,
        /// removed after a successful run and kept after a failed one).
        #[arg(long, value_name = "DIR")]
        dir: Option<PathBuf>,
    },
    /// Launch and supervise the processes of a cell from the manifest DIR/cell.toml
    /// (deploy/cells/demo/cell.toml documents it): restart a process that dies, with a
    /// backoff and a restart intensity; Ctrl-C or SIGTERM stops them in reverse order.
    /// Each process's output goes to DIR/logs/<name>.log. Exits 1 when the restart
    /// intensity is exceeded.
    Up {
        /// The directory holding cell.toml; processes run with it as working directory.
        dir: PathBuf,
        /// Start only what the manifest assigns to this host (its router and processes).
        #[arg(long, default_value = "local")]
        host: String,
    },
    /// Run a zenoh router (for hosts without zenohd): from a zenohd config file, or from
    /// the endpoints given here. Prints `router ZID listening on ...` when ready; runs
    /// until SIGTERM or Ctrl-C.
    Router {
        /// A zenohd config file (JSON5), e.g. deploy/routers/router-a.json5.
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// An endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; replaces the file's).
        #[arg(long, value_name = "ENDPOINT")]
        listen: Vec<String>,
        /// Another router to connect to (repeatable; replaces the file's).
        #[arg(long, value_name = "ENDPOINT")]
        connect: Vec<String>,
        /// The link lease in ms (how long a silent peer keeps its tokens).
        #[arg(long, value_name = "MS")]
        lease_ms: Option<u64>,
    },
    /// List every order of a cell with its status, step and resource (from any host).
    Orders {
        /// The cell's name.
        #[arg(long, default_value = "demo")]
        cell: String,
        /// The endpoint of a zenoh router of the cell (repeatable).
        #[arg(long, value_name = "ENDPOINT", required = true)]
        connect: Vec<String>,
        /// How long to wait for answers, in milliseconds.
        #[arg(long, default_value_t = 2000)]
        timeout_ms: u64,
    },
    /// Submit work orders to a running cell and print the new orders' ids.
    Submit {
        /// The product to make, e.g. breaker.
        product: String,
        /// How many.
        #[arg(long, default_value_t = 1)]
        count: u32,
        /// Priority (kept with the order; scheduling by priority is not implemented yet).
        #[arg(long, default_value_t = 0)]
        priority: i32,
        /// The cell's name.
        #[arg(long, default_value = "demo")]
        cell: String,
        /// The endpoint of a zenoh router of the cell (repeatable).
        #[arg(long, value_name = "ENDPOINT", required = true)]
        connect: Vec<String>,
        /// How long to wait for an order-node to answer, in milliseconds.
        #[arg(long, default_value_t = 5000)]
        timeout_ms: u64,
    },
    /// List the live holons of a cell with their kind, state and agenda length.
    Status {
        /// The cell's name.
        #[arg(long, default_value = "demo")]
        cell: String,
        /// The endpoint of a zenoh router of the cell, e.g. tcp/127.0.0.1:7447 (repeatable);
        /// `cell status` joins as a client, so the router answers for the whole cell.
        #[arg(long, value_name = "ENDPOINT", required = true)]
        connect: Vec<String>,
        /// How long to wait for answers, in milliseconds.
        #[arg(long, default_value_t = 2000)]
        timeout_ms: u64,
    },
}

fn main() -> ExitCode {
    let args = Args::parse();
    // The demo's own output is its progress; logs go to stderr at warn unless RUST_LOG says otherwise.
    if std::env::var_os("RUST_LOG").is_none() {
        // zenoh's own warnings (a query to a host that was cut off) are not the operator's.
        std::env::set_var("RUST_LOG", "warn,zenoh=error");
    }
    if let Err(e) = holon::logging::init(LogFormat::Text, None) {
        eprintln!("cell: {e}");
        return ExitCode::FAILURE;
    }
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("cell: cannot start the tokio runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(args)) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("cell: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run(args: Args) -> Result<bool> {
    match args.command {
        Commands::Demo {
            cell,
            orders,
            delay_ms,
            inspect_fail_every,
            no_hot_add,
            dir,
        } => {
            let shutdown = holon::shutdown_on_signals();
            let options = cell::demo::DemoOptions {
                cell,
                orders,
                action_delay: Duration::from_millis(delay_ms),
                inspect_fail_every,
                hot_add: !no_hot_add,
                dir,
            };
            cell::demo::run(options, shutdown).await
        }
        Commands::Up { dir, host } => {
            let shutdown = holon::shutdown_on_signals();
            cell::up::run(&dir, &host, shutdown).await
        }
        Commands::Router {
            config,
            listen,
            connect,
            lease_ms,
        } => {
            let shutdown = holon::shutdown_on_signals();
            let options = cell::router::RouterOptions {
                config,
                listen,
                connect,
                lease_ms,
            };
            cell::router::run(options, shutdown).await?;
            Ok(true)
        }
        Commands::Orders {
            cell,
            connect,
            timeout_ms,
        } => {
            let keys = schemas::CellKeys::new(&cell)?;
            let timeout = Duration::from_millis(timeout_ms);
            let session = client_session(&connect, timeout).await?;
            let orders = cell::status::orders(&session, &keys, timeout).await?;
            print!("{}", cell::status::render_orders(&cell, &orders));
            let _ = session.close().await;
            Ok(true)
        }
        Commands::Submit {
            product,
            count,
            priority,
            cell,
            connect,
            timeout_ms,
        } => {
            let keys = schemas::CellKeys::new(&cell)?;
            let work = schemas::WorkOrder {
                product,
                count,
                priority,
            };
            work.validate()?;
            let session = client_session(&connect, Duration::from_millis(timeout_ms)).await?;
            let ids = cell::demo::submit(&session, &keys, &work, Duration::from_millis(timeout_ms))
                .await?;
            println!("{}", ids.join("\n"));
            let _ = session.close().await;
            Ok(true)
        }
        Commands::Status {
            cell,
            connect,
            timeout_ms,
        } => {
            let keys = schemas::CellKeys::new(&cell)?;
            let timeout = Duration::from_millis(timeout_ms);
            let session = client_session(&connect, timeout).await?;
            let rows = cell::status::collect(&session, &keys, timeout).await?;
            print!("{}", cell::status::render(&cell, &rows));
            let _ = session.close().await;
            Ok(true)
        }
    }
}

/// A zenoh client of the cell: everything it asks is routed by the router it connects to.
async fn client_session(connect: &[String], timeout: Duration) -> Result<zenoh::Session> {
    let settings = holon::ZenohSettings {
        mode: "client".into(),
        connect: connect.to_vec(),
        ..holon::ZenohSettings::default()
    };
    let session = settings
        .open(Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    if !holon::session::wait_connected(&session, timeout).await {
        return Err(anyhow!("cannot reach the cell at {}", connect.join(", ")));
    }
    Ok(session)
}

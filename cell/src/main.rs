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
    /// Run a demo cell on this machine: a controller simulator and a pick-'n-place
    /// resource holon as real processes, and `--jobs` jobs through the whole contract
    /// (proposal, booking, start, done). Exits 0 only if every job completed.
    Demo {
        /// The cell's name (all keys live under holarchy/<cell>/).
        #[arg(long, default_value = "demo")]
        cell: String,
        /// How many pick-'n-place jobs to run.
        #[arg(long, default_value_t = 10)]
        jobs: u32,
        /// Simulated duration of each controller action, in milliseconds.
        #[arg(long, default_value_t = 100)]
        delay_ms: u64,
        /// Keep configs and logs in this directory (default: a temporary directory,
        /// removed after a successful run and kept after a failed one).
        #[arg(long, value_name = "DIR")]
        dir: Option<PathBuf>,
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
        std::env::set_var("RUST_LOG", "warn");
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
            jobs,
            delay_ms,
            dir,
        } => {
            let shutdown = holon::shutdown_on_signals();
            let options = cell::demo::DemoOptions {
                cell,
                jobs,
                action_delay: Duration::from_millis(delay_ms),
                dir,
            };
            cell::demo::run(options, shutdown).await
        }
        Commands::Status {
            cell,
            connect,
            timeout_ms,
        } => {
            let keys = schemas::CellKeys::new(&cell)?;
            // A client: everything it asks is routed by the router it connects to.
            let settings = holon::ZenohSettings {
                mode: "client".into(),
                connect: connect.clone(),
                ..holon::ZenohSettings::default()
            };
            let session = settings
                .open(Duration::from_secs(10))
                .await
                .map_err(|e| anyhow!("{e}"))?;
            let timeout = Duration::from_millis(timeout_ms);
            if !holon::session::wait_connected(&session, timeout).await {
                return Err(anyhow!("cannot reach the cell at {}", connect.join(", ")));
            }
            let rows = cell::status::collect(&session, &keys, timeout).await?;
            print!("{}", cell::status::render(&cell, &rows));
            let _ = session.close().await;
            Ok(true)
        }
    }
}

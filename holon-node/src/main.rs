//! `holon-node`: runs one resource holon as its own process.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use holon::LogFormat;
use holon_node::config::{HolonConfig, Overrides};

/// Runs one holon: a resource (a robot, an inspection station, a conveyor) that takes
/// Service requests over zenoh and drives its controller over TCP/XML, or a product
/// that answers with its process plan. The config's `kind` says which.
///
/// The holon is ready when its liveliness token holarchy/<cell>/alive/resource/<name>
/// appears. SIGTERM or Ctrl-C stops it cleanly (token withdrawn, components stopped in
/// reverse order, controller connection closed) with exit code 0. It exits 1 when its
/// config is invalid or its components fail more often than the restart intensity allows.
#[derive(Debug, Parser)]
#[command(name = "holon-node", version)]
struct Args {
    /// The holon's config file (TOML); deploy/cells/demo/robot1.toml (resource) and
    /// breaker.toml (product) document every field.
    #[arg(long, value_name = "FILE")]
    config: PathBuf,
    /// The cell, overriding `cell` in the config.
    #[arg(long, value_name = "C")]
    cell: Option<String>,
    /// The holon's name, overriding `name` in the config.
    #[arg(long, value_name = "N")]
    name: Option<String>,
    /// A zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable; replaces
    /// zenoh.connect in the config).
    #[arg(long, value_name = "ENDPOINT")]
    connect: Vec<String>,
    /// The zenoh link lease in ms (replaces zenoh.lease_ms): how long a silent peer
    /// keeps its tokens. Use the same value cell-wide.
    #[arg(long, value_name = "MS")]
    lease_ms: Option<u64>,
    /// A zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7448 (repeatable; replaces
    /// zenoh.listen in the config).
    #[arg(long, value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// The robot controller's HOST:PORT, overriding controller.address in the config.
    #[arg(long, value_name = "HOST:PORT")]
    controller: Option<String>,
    /// The data directory for the holon's journal (overrides journal.dir); without one
    /// the holon's state is not durable.
    #[arg(long, value_name = "DIR")]
    data_dir: Option<PathBuf>,
    /// Terminal log format: text (human-readable) or json (one object per line).
    #[arg(long, default_value = "text", value_name = "text|json")]
    log_format: LogFormat,
    /// Also append JSON log lines to this file.
    #[arg(long, value_name = "PATH")]
    log_file: Option<PathBuf>,
    /// Declare holarchy/<cell>/resource/<name>/debug/crash, which makes a component
    /// panic on request (for tests and demonstrations of supervision; never in production).
    #[arg(long)]
    allow_fault_injection: bool,
    /// Check the config and exit without starting.
    #[arg(long)]
    check: bool,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let (format, log_file) = (args.log_format, args.log_file.clone());
    holon::process_main("holon-node", format, log_file.as_deref(), |shutdown| {
        run(args, shutdown)
    })
}

async fn run(args: Args, shutdown: tokio_util::sync::CancellationToken) -> anyhow::Result<()> {
    let overrides = Overrides {
        common: holon::session::CommandLine {
            cell: args.cell,
            name: args.name,
            connect: args.connect,
            listen: args.listen,
            data_dir: args.data_dir,
            lease_ms: args.lease_ms,
        },
        controller: args.controller,
        allow_fault_injection: args.allow_fault_injection,
    };
    let config = HolonConfig::load(&args.config, overrides)?;
    if args.check {
        println!("{}: ok ({})", args.config.display(), config.holon());
        return Ok(());
    }
    match config {
        HolonConfig::Resource(config) => holon_node::node::run(config, shutdown).await?,
        HolonConfig::Product(config) => holon_node::product::run(config, shutdown).await?,
    }
    Ok(())
}

//! `order-node`: hosts order holons.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use holon::LogFormat;
use order_node::config::{OrderNodeConfig, Overrides};

/// Hosts order holons: each work order becomes one order holon per unit, which fetches
/// its product's plan and gets every step done by the resources alive in the cell.
///
/// Work orders come from --submit and from holarchy/<cell>/orders/submit
/// ({"product": "breaker", "count": 3}; the reply lists the new orders). The node is
/// ready when its token holarchy/<cell>/host/order-node/<name> appears. SIGTERM or
/// Ctrl-C stops it (exit 0); with --data-dir, orders in progress resume where they
/// stood when it starts again.
#[derive(Debug, Parser)]
#[command(name = "order-node", version)]
struct Args {
    /// The node's config file (TOML); deploy/cells/demo/orders1.toml documents every field.
    #[arg(long, value_name = "FILE")]
    config: PathBuf,
    /// The cell, overriding `cell` in the config.
    #[arg(long, value_name = "C")]
    cell: Option<String>,
    /// The node's name, overriding `name` in the config (orders are named <name>-<n>).
    #[arg(long, value_name = "N")]
    name: Option<String>,
    /// A zenoh endpoint to connect to (repeatable; replaces zenoh.connect).
    #[arg(long, value_name = "ENDPOINT")]
    connect: Vec<String>,
    /// The zenoh link lease in ms (replaces zenoh.lease_ms): how long a silent peer
    /// keeps its tokens. Use the same value cell-wide.
    #[arg(long, value_name = "MS")]
    lease_ms: Option<u64>,
    /// A zenoh endpoint to listen on (repeatable; replaces zenoh.listen).
    #[arg(long, value_name = "ENDPOINT")]
    listen: Vec<String>,
    /// The data directory for the node's journal (overrides journal.dir); without one
    /// orders are not durable.
    #[arg(long, value_name = "DIR")]
    data_dir: Option<PathBuf>,
    /// Submit a work order at start: PRODUCT:COUNT (repeatable).
    #[arg(long, value_name = "PRODUCT:COUNT")]
    submit: Vec<String>,
    /// Terminal log format: text or json.
    #[arg(long, default_value = "text", value_name = "text|json")]
    log_format: LogFormat,
    /// Also append JSON log lines to this file.
    #[arg(long, value_name = "PATH")]
    log_file: Option<PathBuf>,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let (format, log_file) = (args.log_format, args.log_file.clone());
    holon::process_main("order-node", format, log_file.as_deref(), |shutdown| {
        run(args, shutdown)
    })
}

async fn run(args: Args, shutdown: tokio_util::sync::CancellationToken) -> anyhow::Result<()> {
    let overrides = Overrides {
        cell: args.cell,
        name: args.name,
        connect: args.connect,
        listen: args.listen,
        data_dir: args.data_dir,
        lease_ms: args.lease_ms,
    };
    let config = OrderNodeConfig::load(&args.config, overrides)?;
    let submits = args
        .submit
        .iter()
        .map(|s| order_node::node::parse_submit(s))
        .collect::<Result<Vec<_>, _>>()?;
    order_node::node::run(config, submits, shutdown).await?;
    Ok(())
}

//! `order-node`: hosts order holons.

use std::process::ExitCode;

use clap::Parser;
use order_node::config::OrderNodeConfig;

/// Hosts order holons: each work order becomes one order holon per unit, which fetches
/// its product's plan and gets every step done by the resources alive in the cell.
///
/// Work orders come from --submit and from holarchy/<cell>/orders/submit
/// ({"product": "breaker", "count": 3, "priority": 0, "due": UNIX_MS}; only product
/// is required; the reply lists the new orders). The node is
/// ready when its token holarchy/<cell>/host/order-node/<name> appears. SIGTERM or
/// Ctrl-C stops it (exit 0); with --data-dir, orders in progress resume where they
/// stood when it starts again.
///
/// With `[journal] etcd = [...]` in the config the orders live in etcd instead (no
/// --data-dir), and order-nodes of one name on several hosts are a primary and
/// standbys: a standby waits, declaring nothing, until it wins the leader key; a
/// deposed primary exits with an error (deposed by epoch N).
#[derive(Debug, Parser)]
#[command(name = "order-node", version, after_help = holon::cli::ENVIRONMENT_HELP)]
struct Args {
    #[command(flatten)]
    common: holon::cli::CommonArgs,
    /// Submit a work order at start: PRODUCT[:COUNT[:PRIORITY]] (repeatable; count 1,
    /// priority 0 when left out; priority -1000 to 1000, higher first).
    #[arg(long, value_name = "PRODUCT[:COUNT[:PRIORITY]]")]
    submit: Vec<String>,
    /// Check the config (and the TLS identity files, if any) and exit without starting.
    #[arg(long)]
    check: bool,
    /// One of a primary and its standbys on other hosts (`cell up` passes it to both
    /// copies of an order-node with `standby_on`). Needs `[journal] etcd` in the config,
    /// and is refused without it: a second order-node of one name on a local journal
    /// would be a twin. With etcd every order-node campaigns for its name; this flag
    /// only says that it is meant so.
    #[arg(long)]
    standby: bool,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let (format, log_file) = (args.common.log_format, args.common.log_file.clone());
    holon::process_main(
        "order-node",
        holon::zenoh_runtime::Pool::OrderNode,
        format,
        log_file.as_deref(),
        |shutdown| run(args, shutdown),
    )
}

async fn run(args: Args, shutdown: tokio_util::sync::CancellationToken) -> anyhow::Result<()> {
    let config = OrderNodeConfig::load(&args.common.config, args.common.overrides())?;
    if args.standby && config.etcd.is_none() {
        anyhow::bail!(
            "{}: --standby needs [journal] etcd: a primary and its standby share their orders through etcd, and without it a second order-node of this name is a twin (docs/reliability.md, \"Order-node standby on etcd\")",
            args.common.config.display()
        );
    }
    let submits = args
        .submit
        .iter()
        .map(|s| order_node::node::parse_submit(s))
        .collect::<Result<Vec<_>, _>>()?;
    if args.check {
        println!(
            "{}: ok (order-node {})",
            args.common.config.display(),
            config.name
        );
        return Ok(());
    }
    order_node::node::run(config, submits, shutdown).await?;
    Ok(())
}

//! `cell demo`: a whole demo cell on this machine ([`cell::demo`]).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Result;

/// `cell demo`: the demo cell's size, pace and what it runs besides.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// The cell's name (all keys live under holarchy/<cell>/).
    #[arg(long, default_value = "demo")]
    pub cell: String,
    /// How many breakers to order.
    #[arg(long, default_value_t = 10)]
    pub orders: u32,
    /// Simulated duration of a robot action in milliseconds (the conveyor and the
    /// inspection station take a third of it).
    #[arg(long, default_value_t = 300)]
    pub delay_ms: u64,
    /// Every Nth inspection fails and the plan reworks the part (0: none fail).
    #[arg(long, default_value_t = 7)]
    pub inspect_fail_every: u64,
    /// Do not hot-add the third robot.
    #[arg(long)]
    pub no_hot_add: bool,
    /// Keep configs and logs in this directory (default: a temporary directory,
    /// removed after a successful run and kept after a failed one).
    #[arg(long, value_name = "DIR")]
    pub dir: Option<PathBuf>,
    /// Run the cell with mutual TLS and access control: a cell CA and one identity
    /// per process are issued into DIR/pki (see docs/security.md).
    #[arg(long)]
    pub secure: bool,
    /// Serve the cell's dashboard (an operator's: it can submit work orders and
    /// acknowledge alarms) while the demo runs; its address is printed.
    #[arg(long)]
    pub dashboard: bool,
    /// Where the dashboard listens (with --dashboard).
    #[arg(long, default_value = "127.0.0.1:8080", value_name = "HOST:PORT")]
    pub listen: std::net::SocketAddr,
    /// Keep the cell up after the summary, until Ctrl-C (to watch it on the
    /// dashboard and submit more orders).
    #[arg(long)]
    pub keep: bool,
    /// Run a staff holon (staff/planner) that advises the orders where to book;
    /// each step booked on its advice is marked, and the summary counts them.
    #[arg(long)]
    pub staff: bool,
    /// Serve the cell over OPC UA (as `cell opcua`, docs/opcua.md) while the demo
    /// runs; its endpoint is printed. Plain: no security, anonymous; with --secure:
    /// SignAndEncrypt, user `operator` with a new password printed.
    #[arg(long)]
    pub opcua: bool,
    /// Where the OPC UA server listens (with --opcua).
    #[arg(long, default_value = cell::opcua::DEFAULT_LISTEN, value_name = "HOST:PORT")]
    pub opcua_listen: std::net::SocketAddr,
}

/// Runs the demo cell until it is done (or, with --keep, until Ctrl-C).
pub async fn run(args: DemoArgs) -> Result<bool> {
    let shutdown = holon::shutdown_on_signals();
    let options = cell::demo::DemoOptions {
        cell: args.cell,
        orders: args.orders,
        action_delay: Duration::from_millis(args.delay_ms),
        inspect_fail_every: args.inspect_fail_every,
        hot_add: !args.no_hot_add,
        dir: args.dir,
        secure: args.secure,
        dashboard: args.dashboard.then_some(args.listen),
        keep: args.keep,
        staff: args.staff,
        opcua: args.opcua.then_some(args.opcua_listen),
    };
    cell::demo::run(options, shutdown).await
}

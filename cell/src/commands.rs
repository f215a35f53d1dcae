//! The command line of `cell`: every subcommand, as `cell --help` shows them; the flags
//! of a command with many are in its handler's file (`cli/`).

use std::path::PathBuf;

use clap::{Parser, Subcommand};

use crate::cli::dashboard::DashboardArgs;
use crate::cli::demo::DemoArgs;
use crate::cli::opcua::OpcuaArgs;
use crate::cli::orders::{OrdersArgs, SubmitArgs};
use crate::cli::packml::PackmlArgs;
use crate::cli::router::RouterArgs;
use crate::cli::up::UpgradeArgs;
use crate::client_args::ClientArgs;

/// The operator's command for a holarchy cell.
#[derive(Debug, Parser)]
#[command(name = "cell", version)]
pub struct Args {
    #[command(subcommand)]
    pub command: Commands,
}

#[derive(Debug, Subcommand)]
pub enum Commands {
    /// Run a complete demo cell on this machine: an embedded zenoh router, two robots,
    /// an inspection station, a conveyor and a transfer robot (each with its controller
    /// in one plant simulator), the
    /// breaker product and an order-node, all as real processes; submit the orders, show
    /// their progress, hot-add a third robot midway, print a summary and stop
    /// everything. Exits 0 only if every order completed (done, or scrapped by its plan).
    Demo(DemoArgs),
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
        /// Check the manifest and the cell's layout, as the resource configs of its
        /// holon-node processes state it together (their `--config`, and `--name` where
        /// given), print the layout (as `cell layout`) and exit without starting
        /// anything: 0 if there is no problem, 1 with each problem named by its config
        /// file and field.
        #[arg(long)]
        check: bool,
        /// Run the cell's plant FACTOR times faster than real time (from 1 to 1000),
        /// overriding the manifest's `time_scale`: every `plant-sim` and `holon-node`
        /// process gets `--time-scale FACTOR` (docs/scheduling.md, "Scaled time"). A
        /// process whose args already give `--time-scale` keeps its own.
        #[arg(long, value_name = "FACTOR")]
        time_scale: Option<schemas::TimeScale>,
    },
    /// Upgrade one process of a running `cell up DIR` (on this host) to a new build or
    /// config while the cell runs: the running holon finishes its step, keeps its
    /// bookings (orders do not rebook) and hands its name and journal to its successor,
    /// which cell up then supervises in its place. The successor's config is checked
    /// first: if it fails, the running process is left alone. Exits 0 when the
    /// successor serves; 1 with the reason (and the successor's last log lines) when
    /// not. See docs/operations.md for rolling out a cell host by host.
    Upgrade(UpgradeArgs),
    /// Run a zenoh router (for hosts without zenohd): from a zenohd config file, or from
    /// the endpoints given here. Prints `router ZID listening on ...` when ready; runs
    /// until SIGTERM or Ctrl-C.
    Router(RouterArgs),
    /// List a cell's orders with their status, step, resource, failed attempts, rebooks
    /// and reworks (from any host): each order-node's running orders, then its newest
    /// finished ones, asked a page at a time. Exits 1 when the listing is incomplete (an
    /// order-node that does not answer, none alive) and says why.
    Orders(OrdersArgs),
    /// Submit work orders to a running cell and print the new orders' ids.
    Submit(SubmitArgs),
    /// Cancel an order (operators only): its bookings are cancelled, a step already
    /// running is let finish, then it ends as `cancelled`.
    Cancel {
        /// The order, e.g. orders1-17.
        order: String,
        #[command(flatten)]
        client: ClientArgs,
    },
    /// Say where an order's lost part is (operators only): a part whose transporter
    /// vanished mid-move, or whose move failed on the way, is lost ("in transit on X,
    /// last seen at Y") until its transporter or an operator says where it is. Name the
    /// lost move's origin (it never left) or its destination (it arrived); the order
    /// records the word with who said it (`cell orders --detail` shows it) and goes on.
    Part {
        /// The order, e.g. orders1-17.
        order: String,
        /// Where the part is, as HOLON.NAME (e.g. robot1.port).
        #[arg(long, value_name = "LOCATION")]
        at: String,
        #[command(flatten)]
        client: ClientArgs,
    },
    /// Take a conveyor's carrier (a pallet or shuttle) out of service, or put it back
    /// (operators only). A part rides its carrier from entry to exit, so the conveyor
    /// lets a part in (grants it a home at its buffers) only while fewer parts are in
    /// the cell than carriers in service: taken out without a word, a missing carrier
    /// can stop the cell. Say it when you take the carrier off the track (the plant
    /// simulator's `retire`) and when you put it back. Prints the carriers in service.
    Carrier {
        /// The conveyor, e.g. conveyor1.
        resource: String,
        /// The carrier as the conveyor numbers them, p1 to p<pallets> (or
        /// conveyor1/p3).
        carrier: String,
        /// Taken out of service.
        #[arg(long, conflicts_with = "back", required_unless_present = "back")]
        out: bool,
        /// Back in service.
        #[arg(long)]
        back: bool,
        #[command(flatten)]
        client: ClientArgs,
    },
    /// Manage the cell's users (one file per cell, read by the dashboard and `cell
    /// opcua`): add, passwd, role, remove, list. Every change is recorded in audit.jsonl
    /// beside the file. See docs/opcua.md, "Users".
    Users(cell::security::users::cli::UsersArgs),
    /// Serve a live web page of a running cell: its holons, orders, alarms, event log
    /// and throughput, pushed to the page as they change; a JSON API (/api/view,
    /// /api/holons, /api/orders, /api/alarms, /api/events) and Prometheus metrics
    /// (/metrics). See docs/operations.md. Stops on Ctrl-C or SIGTERM.
    Dashboard(DashboardArgs),
    /// Serve the cell over OPC UA (docs/opcua.md): every resource as a PackML unit after
    /// OPC 30050 under Objects/PackMLObjects/<resource> (Status, Admin, the methods
    /// Start, Stop, Hold, Unhold, Suspend, Unsuspend, Abort, Clear, Reset and
    /// SetUnitMode), and Objects/Cell (OrdersRunning, OrdersDone, OrdersFailed,
    /// SubmitWorkOrder, Security), live from what the holons publish. Without --pki: no
    /// security, anonymous sessions, loopback only. With --pki: SignAndEncrypt only (no
    /// session on any other channel), user names and passwords from the users file (read
    /// again as it changes; failed logins slowed and locked out as on the dashboard),
    /// unknown client certificates rejected, every login and method call in the audit
    /// trail. Stops on Ctrl-C or SIGTERM.
    Opcua(OpcuaArgs),
    /// Show a resource's PackML state, figures and allowed commands, or command it
    /// (operators only in a secure cell): hold, unhold, stop, reset, start, abort,
    /// clear (or their numbers 1-9), or --mode production|maintenance|manual (only in
    /// Stopped, Idle or Aborted). Prints the new state, or the refusal and exits 1.
    /// What each state does to bookings and orders: docs/packml.md.
    Packml(PackmlArgs),
    /// Show the running cell's layout (docs/material-flow.md): the locations that hold
    /// parts (their role, capacity and where a conveyor reaches them), the transporters,
    /// and what is wrong with them together (a dock on a conveyor or stopper that is not
    /// there, a stopper docked twice, a location nothing reaches, a port no part from an
    /// entry can get to or that leads to no exit), from the parts the serving resources
    /// answer: a station started later is in it, one stopped is not. Exits 0, with the
    /// problems listed (`cell up --check DIR` checks a cell's configs before they run).
    Layout {
        /// Print the layout as JSON (its parts by holon, and its problems).
        #[arg(long)]
        json: bool,
        #[command(flatten)]
        client: ClientArgs,
    },
    /// List the live holons of a cell with their kind, state and agenda length.
    Status {
        #[command(flatten)]
        client: ClientArgs,
    },
    /// Issue the cell's identities for mutual TLS from the manifest DIR/cell.toml: a cell
    /// CA (made once), a certificate and key per process with an `identity`, per router,
    /// per operator, observer and spare of [pki]; the cell's access control
    /// (access_control.json5) and a zenohd config per router (router-<host>.json5), all
    /// in the PKI directory (default DIR/pki). Issues only what is missing, expiring
    /// within 30 days or named by --renew; see docs/security.md.
    Certs {
        /// The directory holding cell.toml.
        dir: PathBuf,
        /// Make a new CA and reissue every identity (the old ones stop working once
        /// every process has the new CA).
        #[arg(long)]
        force: bool,
        /// Reissue this identity, e.g. resource.robot1 (repeatable): rotation.
        #[arg(long, value_name = "IDENTITY")]
        renew: Vec<String>,
    },
}

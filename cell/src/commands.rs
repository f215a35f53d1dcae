//! The command line of `cell`: every subcommand and flag, as `cell --help` shows them.

use std::path::PathBuf;

use clap::{Parser, Subcommand};

use crate::client_args::{parse_due_in, ClientArgs};

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
        /// Run the cell with mutual TLS and access control: a cell CA and one identity
        /// per process are issued into DIR/pki (see docs/security.md).
        #[arg(long)]
        secure: bool,
        /// Serve the cell's dashboard (an operator's: it can submit work orders and
        /// acknowledge alarms) while the demo runs; its address is printed.
        #[arg(long)]
        dashboard: bool,
        /// Where the dashboard listens (with --dashboard).
        #[arg(long, default_value = "127.0.0.1:8080", value_name = "HOST:PORT")]
        listen: std::net::SocketAddr,
        /// Keep the cell up after the summary, until Ctrl-C (to watch it on the
        /// dashboard and submit more orders).
        #[arg(long)]
        keep: bool,
        /// Run a staff holon (staff/planner) that advises the orders where to book;
        /// each step booked on its advice is marked, and the summary counts them.
        #[arg(long)]
        staff: bool,
        /// Serve the cell over OPC UA (as `cell opcua`, docs/opcua.md) while the demo
        /// runs; its endpoint is printed. Plain: no security, anonymous; with --secure:
        /// SignAndEncrypt, user `operator` with a new password printed.
        #[arg(long)]
        opcua: bool,
        /// Where the OPC UA server listens (with --opcua).
        #[arg(long, default_value = cell::opcua::DEFAULT_LISTEN, value_name = "HOST:PORT")]
        opcua_listen: std::net::SocketAddr,
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
        /// Check the manifest and the cell's layout, as the resource configs of its
        /// holon-node processes state it together (their `--config`, and `--name` where
        /// given), print the layout (as `cell layout`) and exit without starting
        /// anything: 0 if there is no problem, 1 with each problem named by its config
        /// file and field.
        #[arg(long)]
        check: bool,
    },
    /// Upgrade one process of a running `cell up DIR` (on this host) to a new build or
    /// config while the cell runs: the running holon finishes its step, keeps its
    /// bookings (orders do not rebook) and hands its name and journal to its successor,
    /// which cell up then supervises in its place. The successor's config is checked
    /// first: if it fails, the running process is left alone. Exits 0 when the
    /// successor serves; 1 with the reason (and the successor's last log lines) when
    /// not. See docs/operations.md for rolling out a cell host by host.
    Upgrade {
        /// The process's name in the manifest (e.g. robot1, orders1, breaker).
        name: String,
        /// The manifest's directory, as given to `cell up`.
        #[arg(long, default_value = ".", value_name = "DIR")]
        dir: PathBuf,
        /// The host `cell up --host` runs (default local).
        #[arg(long, default_value = "local")]
        host: String,
        /// The new program (default: the one running).
        #[arg(long, value_name = "PATH")]
        binary: Option<PathBuf>,
        /// The new config file, replacing the value of the process's --config
        /// (relative paths are relative to DIR, as in the manifest).
        #[arg(long, value_name = "FILE")]
        config: Option<PathBuf>,
        /// How long the running process may take to finish its running step and hand
        /// over; it refuses, and runs on, if it cannot within this.
        #[arg(long, default_value_t = 60_000, value_name = "MS")]
        wait_ms: u64,
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
        /// Without --config: mutual TLS and the cell's access control from this PKI
        /// directory (`cell certs`); endpoints must then be tls/...
        #[arg(long, value_name = "DIR")]
        pki: Option<PathBuf>,
        /// The router's identity with --pki (default router.local).
        #[arg(long, value_name = "ROLE.NAME")]
        identity: Option<String>,
        /// Announce the router in this cell (a liveliness token host/router/NAME that
        /// dashboards show); without it the router is not named in any cell.
        #[arg(long, value_name = "CELL")]
        cell: Option<String>,
        /// The name to announce it by, with --cell (default: this machine's host name).
        #[arg(long, value_name = "NAME", requires = "cell")]
        name: Option<String>,
    },
    /// List a cell's orders with their status, step, resource, failed attempts, rebooks
    /// and reworks (from any host): each order-node's running orders, then its newest
    /// finished ones, asked a page at a time. Exits 1 when the listing is incomplete (an
    /// order-node that does not answer, none alive) and says why.
    Orders {
        /// Also list every ended attempt of each order below it: conversation id, step,
        /// how it ended (done, rejected, failed, lost, no_resource, cancelled) and why.
        #[arg(long)]
        detail: bool,
        /// Which orders: all, running, finished, done, scrapped, failed or cancelled.
        #[arg(long, value_name = "STATUS", default_value = "all", value_parser = schemas::OrderFilter::parse)]
        status: schemas::OrderFilter,
        /// How many finished orders of each order-node to show, newest first.
        #[arg(long, value_name = "N", default_value_t = 20, conflicts_with = "all")]
        finished: usize,
        /// Show every finished order (page by page), not only the newest --finished.
        #[arg(long)]
        all: bool,
        #[command(flatten)]
        client: ClientArgs,
    },
    /// Submit work orders to a running cell and print the new orders' ids.
    Submit {
        /// The product to make, e.g. breaker.
        product: String,
        /// How many.
        #[arg(long, default_value_t = 1)]
        count: u32,
        /// Priority, -1000 to 1000 (higher first, e.g. 100 for a rush order): each
        /// resource serves waiting bookings by it, and passes a waiting booking at
        /// most `agenda.max_overtakes` times.
        #[arg(long, default_value_t = 0, allow_hyphen_values = true)]
        priority: i32,
        /// When the orders are due, from now: a number with a unit, ms, s, m or h
        /// (e.g. 90s, 15m). Kept and shown with each order; a staff holon plans by it.
        #[arg(long, value_name = "DURATION", value_parser = parse_due_in)]
        due_in: Option<std::time::Duration>,
        /// Accept the work order even when no product holon of that name is alive: its
        /// orders wait for the plan (refused `unknown_product` otherwise).
        #[arg(long)]
        queue: bool,
        #[command(flatten)]
        client: ClientArgs,
    },
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
    /// Manage the cell's users (one file per cell, read by the dashboard and `cell
    /// opcua`): add, passwd, role, remove, list. Every change is recorded in audit.jsonl
    /// beside the file. See docs/opcua.md, "Users".
    Users(cell::users::cli::UsersArgs),
    /// Serve a live web page of a running cell: its holons, orders, alarms, event log
    /// and throughput, pushed to the page as they change; a JSON API (/api/view,
    /// /api/holons, /api/orders, /api/alarms, /api/events) and Prometheus metrics
    /// (/metrics). See docs/operations.md. Stops on Ctrl-C or SIGTERM.
    Dashboard {
        /// Where the web server listens (HOST:PORT; port 0 picks one, printed at start).
        #[arg(long, default_value = "127.0.0.1:8080", value_name = "HOST:PORT")]
        listen: std::net::SocketAddr,
        /// Let the page submit work orders and acknowledge alarms. With --pki the
        /// identity's role decides instead: an operator.* identity operates, an
        /// observer.* one only watches (--operator with it is refused); without
        /// --identity, --operator connects as operator.default, else observer.default.
        #[arg(long)]
        operator: bool,
        /// A host name the dashboard answers to besides its IP addresses and localhost
        /// (repeatable), e.g. a name of the plant's DNS: a request naming another host
        /// is refused (a page of another site, rebound to this address).
        #[arg(long = "host-name", value_name = "NAME")]
        host_names: Vec<String>,
        /// The users file people log in with (`cell users`); default <pki>/users.toml
        /// with --pki. Without a users file (and without --pki) nobody logs in, and the
        /// dashboard listens on loopback only.
        #[arg(long, value_name = "FILE")]
        users: Option<PathBuf>,
        /// The audit trail, JSON lines (default: audit.jsonl beside the users file;
        /// without a users file, none unless given).
        #[arg(long, value_name = "FILE")]
        audit: Option<PathBuf>,
        /// A session ends after this many seconds without a request.
        #[arg(long, default_value_t = 900, value_name = "SECONDS")]
        session_idle_s: u64,
        /// A session ends this many seconds after its login, however busy.
        #[arg(long, default_value_t = 28_800, value_name = "SECONDS")]
        session_max_s: u64,
        /// Raise the `part_waits` alarm when a running order's part in the cell stays
        /// where it is longer than this many seconds (a deadlock, a station that never
        /// frees a place, a move nobody ends); cleared once it moves.
        #[arg(long, default_value_t = 300, value_name = "SECONDS", value_parser = clap::value_parser!(u64).range(1..))]
        part_wait_alarm_s: u64,
        /// Serve HTTPS (plain HTTP on the same port then only redirects). On by default
        /// with --pki, with the certificate of the dashboard's identity
        /// (<pki>/<identity>.pem and .key) and client certificates of the cell CA as
        /// logins; without --pki it needs --tls-cert and --tls-key.
        #[arg(long, conflicts_with = "no_tls")]
        tls: bool,
        /// With --pki, serve plain HTTP anyway (loopback only: behind a reverse proxy
        /// on this host that serves HTTPS).
        #[arg(long)]
        no_tls: bool,
        /// The HTTPS certificate chain (PEM), e.g. one the plant's CA issued.
        #[arg(long, value_name = "FILE", requires = "tls_key")]
        tls_cert: Option<PathBuf>,
        /// The HTTPS certificate's key (PEM, readable by its owner only).
        #[arg(long, value_name = "FILE", requires = "tls_cert")]
        tls_key: Option<PathBuf>,
        #[command(flatten)]
        client: ClientArgs,
    },
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
    Opcua {
        /// Where the server listens (HOST:PORT); the endpoint is opc.tcp://HOST:PORT/.
        /// Without --pki only a loopback address is allowed.
        #[arg(long, default_value = cell::opcua::DEFAULT_LISTEN, value_name = "HOST:PORT")]
        listen: std::net::SocketAddr,
        /// The cell's name (the namespace is urn:holarchy:<cell>).
        #[arg(long, default_value = "demo")]
        cell: String,
        /// The endpoint of a zenoh router of the cell, e.g. tcp/127.0.0.1:7447 or
        /// tls/127.0.0.1:7447 (repeatable); the server joins as a client.
        #[arg(long, value_name = "ENDPOINT")]
        connect: Vec<String>,
        /// A secure cell's PKI directory (`cell certs`): the zenoh identity's
        /// certificate, the server's application certificate (opcua-server.der,
        /// opcua-server.key), its store of client certificates (opcua/trusted,
        /// opcua/rejected) and the cell's users file (users.toml, `cell users`).
        #[arg(long, value_name = "DIR")]
        pki: Option<PathBuf>,
        /// The zenoh identity to join with (an operator.* identity; default
        /// operator.opcua). Method calls go to the cell as this identity, with `by`
        /// naming the OPC UA user.
        #[arg(long, value_name = "ROLE.NAME")]
        identity: Option<String>,
        /// The users file (`cell users --file FILE` writes it); default <pki>/users.toml.
        /// Observers may browse, read and subscribe; operators and admins may also call
        /// methods. Only with --pki.
        #[arg(long, value_name = "FILE", requires = "pki")]
        users: Option<PathBuf>,
        /// The audit trail the server appends its logins, failed logins and method calls
        /// to, JSON lines (default: audit.jsonl beside the users file, the dashboard's
        /// and `cell users`' own). Only with --pki.
        #[arg(long, value_name = "FILE", requires = "pki")]
        audit: Option<PathBuf>,
        /// Trust a client application certificate (DER or PEM) of the server in --pki:
        /// copy it into the store's trusted/ (and out of rejected/), print where, and
        /// exit. A running server sees it at the client's next connect.
        #[arg(long, value_name = "CLIENT_CERT", requires = "pki")]
        trust: Option<PathBuf>,
    },
    /// Show a resource's PackML state, figures and allowed commands, or command it
    /// (operators only in a secure cell): hold, unhold, stop, reset, start, abort,
    /// clear (or their numbers 1-9), or --mode production|maintenance|manual (only in
    /// Stopped, Idle or Aborted). Prints the new state, or the refusal and exits 1.
    /// What each state does to bookings and orders: docs/packml.md.
    Packml {
        /// The resource, e.g. robot1.
        resource: String,
        /// The command; none: show the state.
        command: Option<schemas::PackmlCommand>,
        /// Change the unit mode instead.
        #[arg(long, conflicts_with = "command")]
        mode: Option<schemas::UnitMode>,
        /// Run one job of this service type now (Maintenance mode only: the resource
        /// must be in Execute, in Maintenance, with nothing running), and wait for its
        /// end: prints how it ended, exits 1 unless done.
        #[arg(long, value_name = "SERVICE_TYPE", conflicts_with_all = ["command", "mode"])]
        job: Option<String>,
        /// The job's info as JSON, as a booking's would carry it (its poses, program),
        /// e.g. '{"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}}'.
        #[arg(long, value_name = "JSON", requires = "job", default_value = "{}")]
        info: String,
        /// How long to wait for the job's end, in milliseconds.
        #[arg(long, value_name = "MS", requires = "job", default_value_t = 60_000)]
        wait_ms: u64,
        #[command(flatten)]
        client: ClientArgs,
    },
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

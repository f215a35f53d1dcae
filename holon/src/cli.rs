//! The command-line flags every holon binary shares (`holon-node`, `order-node`).

use std::path::PathBuf;

use crate::session::CommandLine;
use crate::LogFormat;

/// The environment a holon binary reads, for its `--help` (`after_help`).
pub const ENVIRONMENT_HELP: &str = "Environment:
  RUST_LOG       log level and filters (default info)
  ZENOH_RUNTIME  zenoh's threads, in zenoh's own syntax; unset, zenoh's work and the
                 holon's run on one pool, of one thread in holon-node and of two in
                 order-node (docs/architecture.md, \"Topology\")";

/// Flattened into each binary's arguments with `#[command(flatten)]`.
#[derive(Debug, Clone, clap::Args)]
pub struct CommonArgs {
    /// The config file (TOML); deploy/cells/demo/ documents every field of each kind.
    #[arg(long, value_name = "FILE")]
    pub config: PathBuf,
    /// The cell, overriding `cell` in the config.
    #[arg(long, value_name = "C")]
    pub cell: Option<String>,
    /// The name, overriding `name` in the config.
    #[arg(long, value_name = "N")]
    pub name: Option<String>,
    /// How this process joins zenoh (replaces zenoh.mode; default client): client
    /// talks through its host's router only, peer links directly to other peers.
    #[arg(long, value_enum, value_name = "client|peer")]
    pub mode: Option<crate::Mode>,
    /// A zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447, the host's router
    /// (repeatable; replaces zenoh.connect in the config).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// A zenoh endpoint to listen on, e.g. tcp/127.0.0.1:0, for a peer (repeatable;
    /// replaces zenoh.listen in the config; a client listens on nothing).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// The zenoh link lease in ms (replaces zenoh.lease_ms): how long a silent peer
    /// keeps its tokens. Use the same value cell-wide.
    #[arg(long, value_name = "MS")]
    pub lease_ms: Option<u64>,
    /// The journal's directory (replaces journal.dir); without one the state is not
    /// durable.
    #[arg(long, value_name = "DIR")]
    pub data_dir: Option<PathBuf>,
    /// Mutual TLS and access control with the identity files `cell certs` wrote into
    /// DIR (replaces [zenoh.tls]); every endpoint must then be tls/...
    #[arg(long, value_name = "DIR")]
    pub pki: Option<PathBuf>,
    /// Take over from the running process of this holon (an upgrade): it finishes its
    /// running step, keeps its bookings and hands over its data dir and name; then this
    /// process serves. The config is checked first: a bad one leaves the running
    /// process untouched. Without a running process, it starts as usual. Exit code 3:
    /// the running process refused (it serves on, nothing changed).
    #[arg(long)]
    pub take_over: bool,
    /// How long the running process may take to finish what it must (its running
    /// step) before it hands over; it refuses, and serves on, if it cannot within this.
    /// It then has 45 s more to stop and close its journal.
    #[arg(long, value_name = "MS", default_value_t = 60_000)]
    pub take_over_wait_ms: u64,
    /// Terminal log format: text (human-readable) or json (one object per line).
    #[arg(long, default_value = "text", value_name = "text|json")]
    pub log_format: LogFormat,
    /// Also append JSON log lines to this file.
    #[arg(long, value_name = "PATH")]
    pub log_file: Option<PathBuf>,
}

impl CommonArgs {
    /// What these flags override in the config file.
    pub fn overrides(&self) -> CommandLine {
        CommandLine {
            cell: self.cell.clone(),
            name: self.name.clone(),
            connect: self.connect.clone(),
            listen: self.listen.clone(),
            data_dir: self.data_dir.clone(),
            lease_ms: self.lease_ms,
            mode: self.mode,
            pki: self.pki.clone(),
            take_over: self
                .take_over
                .then(|| std::time::Duration::from_millis(self.take_over_wait_ms)),
        }
    }
}

//! `cell router`: a zenoh router for a host without zenohd ([`cell::router`]).

use std::path::PathBuf;

use anyhow::Result;

/// `cell router`: the router's config or endpoints, and its name in a cell.
#[derive(Debug, clap::Args)]
pub struct RouterArgs {
    /// A zenohd config file (JSON5), e.g. deploy/routers/router-a.json5.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// An endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable; replaces the file's).
    #[arg(long, value_name = "ENDPOINT")]
    pub listen: Vec<String>,
    /// Another router to connect to (repeatable; replaces the file's).
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// The link lease in ms (how long a silent peer keeps its tokens).
    #[arg(long, value_name = "MS")]
    pub lease_ms: Option<u64>,
    /// Without --config: mutual TLS and the cell's access control from this PKI
    /// directory (`cell certs`); endpoints must then be tls/...
    #[arg(long, value_name = "DIR")]
    pub pki: Option<PathBuf>,
    /// The router's identity with --pki (default router.local).
    #[arg(long, value_name = "ROLE.NAME")]
    pub identity: Option<String>,
    /// Announce the router in this cell (a liveliness token host/router/NAME that
    /// dashboards show); without it the router is not named in any cell.
    #[arg(long, value_name = "CELL")]
    pub cell: Option<String>,
    /// The name to announce it by, with --cell (default: this machine's host name).
    #[arg(long, value_name = "NAME", requires = "cell")]
    pub name: Option<String>,
}

/// Runs the router until SIGTERM or Ctrl-C.
pub async fn run(args: RouterArgs) -> Result<bool> {
    let shutdown = holon::shutdown_on_signals();
    let options = cell::router::RouterOptions {
        config: args.config,
        listen: args.listen,
        connect: args.connect,
        lease_ms: args.lease_ms,
        pki: args.pki,
        identity: args.identity,
        cell: args
            .cell
            .as_deref()
            .map(schemas::CellKeys::new)
            .transpose()?,
        name: args.name,
    };
    cell::router::run(options, shutdown).await?;
    Ok(true)
}

//! `cell dashboard`: the live web page of a running cell ([`cell::dashboard`]).

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Result;

use crate::client_args::ClientArgs;

/// `cell dashboard`: where it listens, who may use it, and how.
#[derive(Debug, clap::Args)]
pub struct DashboardArgs {
    /// Where the web server listens (HOST:PORT; port 0 picks one, printed at start).
    #[arg(long, default_value = "127.0.0.1:8080", value_name = "HOST:PORT")]
    pub listen: std::net::SocketAddr,
    /// Let the page submit work orders and acknowledge alarms. With --pki the
    /// identity's role decides instead: an operator.* identity operates, an
    /// observer.* one only watches (--operator with it is refused); without
    /// --identity, --operator connects as operator.default, else observer.default.
    #[arg(long)]
    pub operator: bool,
    /// A host name the dashboard answers to besides its IP addresses and localhost
    /// (repeatable), e.g. a name of the plant's DNS: a request naming another host
    /// is refused (a page of another site, rebound to this address).
    #[arg(long = "host-name", value_name = "NAME")]
    pub host_names: Vec<String>,
    /// The users file people log in with (`cell users`); default <pki>/users.toml
    /// with --pki. Without a users file (and without --pki) nobody logs in, and the
    /// dashboard listens on loopback only.
    #[arg(long, value_name = "FILE")]
    pub users: Option<PathBuf>,
    /// The audit trail, JSON lines (default: audit.jsonl beside the users file;
    /// without a users file, none unless given).
    #[arg(long, value_name = "FILE")]
    pub audit: Option<PathBuf>,
    /// A session ends after this many seconds without a request.
    #[arg(long, default_value_t = 900, value_name = "SECONDS")]
    pub session_idle_s: u64,
    /// A session ends this many seconds after its login, however busy.
    #[arg(long, default_value_t = 28_800, value_name = "SECONDS")]
    pub session_max_s: u64,
    /// Raise the `part_waits` alarm when a running order's part in the cell stays where
    /// it is longer than this many seconds (a deadlock, a station that never frees a
    /// place, a move nobody ends); cleared once it moves.
    #[arg(long, default_value_t = 300, value_name = "SECONDS", value_parser = clap::value_parser!(u64).range(1..))]
    pub part_wait_alarm_s: u64,
    /// Serve HTTPS (plain HTTP on the same port then only redirects). On by default
    /// with --pki, with the certificate of the dashboard's identity
    /// (<pki>/<identity>.pem and .key) and client certificates of the cell CA as
    /// logins; without --pki it needs --tls-cert and --tls-key.
    #[arg(long, conflicts_with = "no_tls")]
    pub tls: bool,
    /// With --pki, serve plain HTTP anyway (loopback only: behind a reverse proxy
    /// on this host that serves HTTPS).
    #[arg(long)]
    pub no_tls: bool,
    /// The HTTPS certificate chain (PEM), e.g. one the plant's CA issued.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// The HTTPS certificate's key (PEM, readable by its owner only).
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
    #[command(flatten)]
    pub client: ClientArgs,
}

/// Serves the dashboard until Ctrl-C or SIGTERM.
pub async fn run(args: DashboardArgs) -> Result<bool> {
    let client = args.client;
    let (identity, operator) = cell::dashboard::connect_as(
        client.pki.is_some(),
        client.identity.as_deref(),
        args.operator,
    )?;
    let pki = client.pki.as_deref();
    let users = args
        .users
        .or_else(|| pki.map(cell::security::users::default_path));
    let audit = args.audit.or_else(|| {
        users
            .as_deref()
            .and_then(|u| u.parent())
            .map(|dir| dir.join(cell::security::audit::FILE_NAME))
    });
    let tls = cell::dashboard::https_files(
        pki,
        &identity,
        args.tls,
        args.no_tls,
        args.tls_cert.zip(args.tls_key),
        args.listen,
    )?;
    let config = cell::dashboard::DashboardConfig {
        keys: client.keys()?,
        zenoh: client.settings(),
        identity,
        listen: args.listen,
        operator,
        host_names: args.host_names,
        users,
        audit,
        sessions: cell::dashboard::session::SessionLimits {
            idle: Duration::from_secs(args.session_idle_s),
            absolute: Duration::from_secs(args.session_max_s),
        },
        tls,
        part_wait_alarm: Duration::from_secs(args.part_wait_alarm_s),
    };
    cell::dashboard::run(config, holon::shutdown_on_signals()).await?;
    Ok(true)
}

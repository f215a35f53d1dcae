//! `cell opcua`: the cell's OPC UA server ([`cell::opcua`]), or `--trust` of a client's
//! certificate.

use std::path::PathBuf;

use anyhow::{anyhow, Result};

/// `cell opcua`: where it listens, the cell it serves, and its security.
#[derive(Debug, clap::Args)]
pub struct OpcuaArgs {
    /// Where the server listens (HOST:PORT); the endpoint is opc.tcp://HOST:PORT/.
    /// Without --pki only a loopback address is allowed.
    #[arg(long, default_value = cell::opcua::DEFAULT_LISTEN, value_name = "HOST:PORT")]
    pub listen: std::net::SocketAddr,
    /// The cell's name (the namespace is urn:holarchy:<cell>).
    #[arg(long, default_value = "demo")]
    pub cell: String,
    /// The endpoint of a zenoh router of the cell, e.g. tcp/127.0.0.1:7447 or
    /// tls/127.0.0.1:7447 (repeatable); the server joins as a client.
    #[arg(long, value_name = "ENDPOINT")]
    pub connect: Vec<String>,
    /// A secure cell's PKI directory (`cell certs`): the zenoh identity's
    /// certificate, the server's application certificate (opcua-server.der,
    /// opcua-server.key), its store of client certificates (opcua/trusted,
    /// opcua/rejected) and the cell's users file (users.toml, `cell users`).
    #[arg(long, value_name = "DIR")]
    pub pki: Option<PathBuf>,
    /// The zenoh identity to join with (an operator.* identity; default
    /// operator.opcua). Method calls go to the cell as this identity, with `by`
    /// naming the OPC UA user.
    #[arg(long, value_name = "ROLE.NAME")]
    pub identity: Option<String>,
    /// The users file (`cell users --file FILE` writes it); default <pki>/users.toml.
    /// Observers may browse, read and subscribe; operators and admins may also call
    /// methods. Only with --pki.
    #[arg(long, value_name = "FILE", requires = "pki")]
    pub users: Option<PathBuf>,
    /// The audit trail the server appends its logins, failed logins and method calls
    /// to, JSON lines (default: audit.jsonl beside the users file, the dashboard's
    /// and `cell users`' own). Only with --pki.
    #[arg(long, value_name = "FILE", requires = "pki")]
    pub audit: Option<PathBuf>,
    /// Trust a client application certificate (DER or PEM) of the server in --pki:
    /// copy it into the store's trusted/ (and out of rejected/), print where, and
    /// exit. A running server sees it at the client's next connect.
    #[arg(long, value_name = "CLIENT_CERT", requires = "pki")]
    pub trust: Option<PathBuf>,
}

/// Trusts a client's certificate (`--trust`), or serves until Ctrl-C or SIGTERM.
pub async fn run(args: OpcuaArgs) -> Result<bool> {
    if let (Some(client), Some(pki)) = (&args.trust, &args.pki) {
        let path = cell::opcua::security::trust(pki, client)?;
        println!("trusted {} as {}", client.display(), path.display());
        return Ok(true);
    }
    if args.connect.is_empty() {
        return Err(anyhow!("--connect ENDPOINT: a zenoh router of the cell"));
    }
    let identity = args
        .identity
        .unwrap_or_else(|| "operator.opcua".to_string());
    if args.pki.is_some() {
        let (role, _) = cell::security::access::parse_identity(&identity)?;
        if role != cell::security::access::Role::Operator {
            return Err(anyhow!(
                "the OPC UA server joins as an operator.* identity (its methods command resources), not as {identity}"
            ));
        }
    }
    let config = cell::opcua::OpcuaConfig {
        keys: schemas::CellKeys::new(&args.cell)?,
        zenoh: holon::ZenohSettings {
            mode: holon::Mode::Client,
            connect: args.connect,
            tls: args.pki.as_ref().map(|pki| holon::tls::TlsSettings {
                pki: Some(pki.clone()),
                ..holon::tls::TlsSettings::default()
            }),
            ..holon::ZenohSettings::default()
        },
        identity,
        listen: args.listen,
        pki: args.pki,
        users: args.users,
        audit: args.audit,
    };
    cell::opcua::run(config, holon::shutdown_on_signals()).await?;
    Ok(true)
}

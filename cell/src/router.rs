//! `cell router`: a zenoh router from our own binary, for hosts without zenohd. It reads
//! the same JSON5 config files as the stock `zenohd` (same zenoh version), or takes its
//! endpoints from the command line.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use tokio_util::sync::CancellationToken;

#[derive(Debug, Clone, Default)]
pub struct RouterOptions {
    /// A zenohd config file (JSON5); its mode is forced to router.
    pub config: Option<PathBuf>,
    /// Endpoints to listen on (replace the file's, if any).
    pub listen: Vec<String>,
    /// Other routers to connect to (replace the file's, if any).
    pub connect: Vec<String>,
    pub lease_ms: Option<u64>,
    /// Without a config file: mutual TLS and access control from this PKI directory
    /// (`cell certs`), as `identity`.
    pub pki: Option<PathBuf>,
    /// The router's identity (default `router.local`).
    pub identity: Option<String>,
    /// The cell to announce the router in (`host/router/<name>`, for dashboards), if any:
    /// a router may serve several cells, or none by name.
    pub cell: Option<schemas::CellKeys>,
    /// The name it is announced by (default: this machine's host name).
    pub name: Option<String>,
}

fn json(value: &[String]) -> String {
    serde_json::to_string(value).expect("strings serialize")
}

/// The zenoh config of the router these options describe.
pub fn config(options: &RouterOptions) -> Result<zenoh::Config> {
    let mut config = match &options.config {
        Some(path) => zenoh::Config::from_file(path)
            .map_err(|e| anyhow!("{e}"))
            .with_context(|| format!("cannot load {}", path.display()))?,
        None => {
            let settings = holon::ZenohSettings {
                mode: holon::Mode::Router,
                multicast_scouting: false,
                listen: options.listen.clone(),
                connect: options.connect.clone(),
                tls: options.pki.as_ref().map(|pki| holon::tls::TlsSettings {
                    pki: Some(pki.clone()),
                    ..holon::tls::TlsSettings::default()
                }),
                ..holon::ZenohSettings::default()
            };
            let identity = options
                .identity
                .clone()
                .unwrap_or_else(|| holon::role::identity(holon::role::Role::Router, "local"));
            settings.to_config(&identity).map_err(|e| anyhow!("{e}"))?
        }
    };
    let mut set = |key: &str, value: String| {
        config
            .insert_json5(key, &value)
            .map_err(|e| anyhow!("{key}: {e}"))
    };
    set("mode", "\"router\"".into())?;
    if !options.listen.is_empty() {
        set("listen/endpoints", json(&options.listen))?;
    }
    if !options.connect.is_empty() {
        set("connect/endpoints", json(&options.connect))?;
    }
    if let Some(lease) = options.lease_ms {
        set("transport/link/tx/lease", lease.to_string())?;
    }
    Ok(config)
}

/// Announces a router in a cell: a liveliness token `host/router/<name>` that
/// dashboards show (live or gone) and launchers may wait on. It lasts as long as the
/// token is held.
pub async fn announce(
    session: &zenoh::Session,
    keys: &schemas::CellKeys,
    name: &str,
) -> Result<zenoh::liveliness::LivelinessToken> {
    schemas::validate_name("router name", name)?;
    session
        .liveliness()
        .declare_token(keys.host("router", name))
        .await
        .map_err(|e| {
            anyhow!(
                "cannot announce the router in cell {}: {}",
                keys.cell(),
                holon::zenoh_error::describe(&e)
            )
        })
}

/// Runs the router until `shutdown` is cancelled.
pub async fn run(options: RouterOptions, shutdown: CancellationToken) -> Result<()> {
    let config = config(&options)?;
    let endpoints = config
        .get_json("listen/endpoints")
        .unwrap_or_else(|_| "zenoh's default endpoints".into());
    let session = tokio::time::timeout(Duration::from_secs(10), zenoh::open(config))
        .await
        .map_err(|_| anyhow!("the router did not start within 10 s"))?
        .map_err(|e| {
            anyhow!(
                "cannot start the router: {}",
                holon::zenoh_error::describe(&e)
            )
        })?;
    println!("router {} listening on {endpoints}", session.zid());
    let _announced = match &options.cell {
        Some(keys) => {
            let name = options
                .name
                .clone()
                .unwrap_or_else(holon::presence::host_name);
            Some(announce(&session, keys, &name).await?)
        }
        None => None,
    };
    shutdown.cancelled().await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    println!("router stopped");
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_router_configs_load() {
        let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/routers");
        let mut loaded = 0;
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "json5") {
                let options = RouterOptions {
                    config: Some(path.clone()),
                    ..RouterOptions::default()
                };
                config(&options).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
                loaded += 1;
            }
        }
        assert!(loaded >= 3, "{loaded} router configs");
    }

    #[test]
    fn command_line_endpoints_replace_the_files() {
        let options = RouterOptions {
            listen: vec!["tcp/127.0.0.1:17447".into()],
            connect: vec!["tcp/127.0.0.1:17448".into()],
            lease_ms: Some(3000),
            ..RouterOptions::default()
        };
        let text = format!("{}", config(&options).unwrap());
        assert!(text.contains("17447") && text.contains("17448"), "{text}");
    }
}

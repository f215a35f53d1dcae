//! The zenoh session of a holon process, from the `[zenoh]` section of its config and
//! the command line. A holon is by default a client of its host's router (one link per
//! process; the routers link the hosts); `mode = "peer"` links holons directly, one
//! link per pair (see docs/architecture.md, "Topology"). Multicast scouting is off
//! unless the config turns it on. With
//! `[zenoh.tls]` every link is mutual TLS and, on holons and routers, the cell's access
//! control is enforced (see `crate::tls` and docs/security.md).

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::{Deserialize, Serialize};

use crate::tls::{IdentityFiles, TlsError, TlsSettings};

/// How a process takes part in the zenoh network.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Talks only through the router it connects to: one link per process, whatever
    /// the size of the cell; the router forwards every message (one hop more than a
    /// direct link). The default for holons.
    #[default]
    Client,
    /// Links directly to every other peer it learns of (a full mesh): the shortest
    /// path between two holons, one link per pair (memory and sockets grow with the
    /// cell). Each peer must listen on an address the others reach.
    Peer,
    /// Routes for the clients and peers that connect to it, and links to other routers
    /// (`cell router`, `cell up`; not a holon's mode).
    #[value(skip)]
    Router,
}

impl Mode {
    /// The name zenoh's configuration uses.
    pub fn as_str(self) -> &'static str {
        match self {
            Mode::Client => "client",
            Mode::Peer => "peer",
            Mode::Router => "router",
        }
    }
}

impl std::fmt::Display for Mode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How a holon joins the zenoh network (`[zenoh]` in every holon config).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    /// `client` (default: talks only through the router it connects to), `peer` (links
    /// directly to the other peers) or `router`. See [`Mode`].
    #[serde(default)]
    pub mode: Mode,
    /// Endpoints to connect to, e.g. `tcp/127.0.0.1:7447`: the host's router (a client
    /// takes the first that answers, and the next when it goes), or routers and
    /// other peers (a peer).
    #[serde(default)]
    pub connect: Vec<String>,
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7448` (peers and routers; a client
    /// listens on nothing). Empty lets a peer's zenoh choose.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Discover peers by UDP multicast on the local network (off by default: explicit
    /// endpoints are predictable on a factory network).
    #[serde(default)]
    pub multicast_scouting: bool,
    /// The link lease in ms: how long a silent peer (a frozen process, a cut network)
    /// keeps its tokens before the others consider it gone. Short detects failures fast;
    /// too short raises false alarms on a loaded host. Default: zenoh's 10000.
    #[serde(default)]
    pub lease_ms: Option<u64>,
    /// A standard zenoh JSON5 config file loaded first; the fields above (and `tls`)
    /// override what it says. For settings holarchy does not expose. Relative to the
    /// config file's directory.
    #[serde(default)]
    pub config_file: Option<PathBuf>,
    /// Mutual TLS and access control (`[zenoh.tls]`); off when absent.
    #[serde(default)]
    pub tls: Option<TlsSettings>,
}

#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("invalid zenoh setting {key}: {message}")]
    Config { key: &'static str, message: String },
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
    #[error("opening the zenoh session took longer than {0:?}")]
    Timeout(Duration),
    #[error("TLS identity {identity}: {source}")]
    Tls { identity: String, source: TlsError },
    #[error("cannot load the zenoh config file {path}: {message}")]
    ConfigFile { path: String, message: String },
}

impl ZenohSettings {
    /// Checks the settings without opening anything (with TLS: reads and checks the
    /// identity files of `identity`).
    pub fn validate(&self, identity: &str) -> Result<(), SessionError> {
        self.to_config(identity).map(|_| ())
    }

    /// Makes the relative paths of `config_file` and `[zenoh.tls]` relative to `base`,
    /// the directory of the config file they were read from.
    pub fn resolve_paths(&mut self, base: &Path) {
        if let Some(path) = self.config_file.as_mut().filter(|p| p.is_relative()) {
            *path = base.join(&*path);
        }
        if let Some(tls) = self.tls.as_mut() {
            tls.resolve_paths(base);
        }
    }

    /// The checked identity files when TLS is on; a client (`mode = "client"`) links
    /// only to routers and does not load the access control.
    pub fn identity_files(&self, identity: &str) -> Result<Option<IdentityFiles>, SessionError> {
        let Some(tls) = &self.tls else {
            return Ok(None);
        };
        tls.identity_files(identity, self.mode != Mode::Client)
            .map(Some)
            .map_err(|source| SessionError::Tls {
                identity: identity.to_string(),
                source,
            })
    }

    /// The zenoh configuration these settings describe, for the process whose TLS
    /// identity is `identity` (`<role>.<name>`; unused without TLS).
    pub fn to_config(&self, identity: &str) -> Result<zenoh::Config, SessionError> {
        let tls = self.identity_files(identity)?;
        let mut config = match &self.config_file {
            Some(path) => load_file(path)?,
            None => zenoh::Config::default(),
        };
        if let Some(path) = tls.as_ref().and_then(|f| f.access_control.as_ref()) {
            let invalid = |e: zenoh::Error| SessionError::ConfigFile {
                path: path.display().to_string(),
                message: e.to_string(),
            };
            let access = load_file(path)?
                .get_json("access_control")
                .map_err(invalid)?;
            config
                .insert_json5("access_control", &access)
                .map_err(invalid)?;
        }
        let mut set = |key: &'static str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| SessionError::Config {
                    key,
                    message: e.to_string(),
                })
        };
        self.check_client()?;
        let json = |v: &serde_json::Value| v.to_string();
        set("mode", json(&self.mode.as_str().into()))?;
        set("connect/endpoints", json(&self.connect.clone().into()))?;
        set("listen/endpoints", json(&self.listen.clone().into()))?;
        set(
            "scouting/multicast/enabled",
            self.multicast_scouting.to_string(),
        )?;
        if let Some(lease) = self.lease_ms {
            if lease < 100 {
                return Err(SessionError::Config {
                    key: "lease_ms",
                    message: "must be at least 100".into(),
                });
            }
            set("transport/link/tx/lease", lease.to_string())?;
        }
        // A peer keeps retrying its connect endpoints rather than failing to start.
        set("connect/timeout_ms", "-1".into())?;
        set("connect/exit_on_failure", "false".into())?;
        if let Some(files) = &tls {
            for endpoint in self.connect.iter().chain(&self.listen) {
                if !endpoint.starts_with("tls/") {
                    return Err(SessionError::Config {
                        key: "tls",
                        message: format!(
                            "with [zenoh.tls] every endpoint must be tls/..., not {endpoint}"
                        ),
                    });
                }
            }
            let path = |p: &Path| json(&p.display().to_string().into());
            set("transport/link/tls/root_ca_certificate", path(&files.ca))?;
            set(
                "transport/link/tls/listen_certificate",
                path(&files.certificate),
            )?;
            set("transport/link/tls/listen_private_key", path(&files.key))?;
            set(
                "transport/link/tls/connect_certificate",
                path(&files.certificate),
            )?;
            set("transport/link/tls/connect_private_key", path(&files.key))?;
            set("transport/link/tls/enable_mtls", "true".into())?;
            set("transport/link/tls/verify_name_on_connect", "true".into())?;
            set("transport/link/tls/close_link_on_expiration", "true".into())?;
        }
        Ok(config)
    }

    /// A client needs a router to connect to and listens on nothing.
    fn check_client(&self) -> Result<(), SessionError> {
        if self.mode != Mode::Client {
            return Ok(());
        }
        if self.connect.is_empty() && !self.multicast_scouting {
            return Err(SessionError::Config {
                key: "connect",
                message: "a client needs its host's router to connect to: set zenoh.connect \
                          or --connect (or mode = \"peer\" to link to other peers directly)"
                    .into(),
            });
        }
        if let Some(endpoint) = self.listen.first() {
            return Err(SessionError::Config {
                key: "listen",
                message: format!(
                    "a client listens on nothing (it links only to its router), so {endpoint} \
                     would be an open port that serves no one: remove zenoh.listen and \
                     --listen, or set mode = \"peer\" for a holon others link to"
                ),
            });
        }
        Ok(())
    }

    /// Opens the session of `identity` (see `to_config`), bounded by `timeout`. A
    /// client gives up when its router does not answer within `timeout` (zenoh's open
    /// would retry for ever); once open, it reconnects by itself when the link drops.
    pub async fn open(
        &self,
        identity: &str,
        timeout: Duration,
    ) -> Result<zenoh::Session, SessionError> {
        let mut config = self.to_config(identity)?;
        if self.mode == Mode::Client {
            // zenoh's open does not return while it retries its connect endpoints.
            for (key, value) in [
                ("connect/timeout_ms", timeout.as_millis().max(1).to_string()),
                ("connect/exit_on_failure", "true".to_string()),
            ] {
                config
                    .insert_json5(key, &value)
                    .map_err(|e| SessionError::Config {
                        key: "connect",
                        message: e.to_string(),
                    })?;
            }
        }
        match tokio::time::timeout(timeout, zenoh::open(config)).await {
            Ok(Ok(session)) => Ok(session),
            Ok(Err(e)) => Err(SessionError::Open(crate::zenoh_error::describe(&e))),
            Err(_) => Err(SessionError::Timeout(timeout)),
        }
    }
}

fn load_file(path: &Path) -> Result<zenoh::Config, SessionError> {
    zenoh::Config::from_file(path).map_err(|e| SessionError::ConfigFile {
        path: path.display().to_string(),
        message: e.to_string(),
    })
}

/// Waits until the session is connected to at least one router or peer; false if it
/// is still alone after `timeout` (e.g. nothing listens on its connect endpoints).
pub async fn wait_connected(session: &zenoh::Session, timeout: Duration) -> bool {
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        let info = session.info();
        if info.routers_zid().await.next().is_some() || info.peers_zid().await.next().is_some() {
            return true;
        }
        if tokio::time::Instant::now() >= deadline {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}

/// What the command line of every holon binary may override in its config file.
#[derive(Debug, Clone, Default)]
pub struct CommandLine {
    pub cell: Option<String>,
    pub name: Option<String>,
    /// Replaces `zenoh.connect` when not empty.
    pub connect: Vec<String>,
    /// Replaces `zenoh.listen` when not empty.
    pub listen: Vec<String>,
    pub data_dir: Option<std::path::PathBuf>,
    /// Replaces `zenoh.lease_ms`.
    pub lease_ms: Option<u64>,
    /// Replaces `zenoh.mode`.
    pub mode: Option<Mode>,
    /// Turns on mutual TLS with the identity files in this PKI directory (replaces
    /// `[zenoh.tls]`).
    pub pki: Option<PathBuf>,
    /// Start as the successor of the running process of the same name (an upgrade),
    /// waiting at most this long for it to hand over (see [`crate::takeover`]).
    pub take_over: Option<std::time::Duration>,
}

impl CommandLine {
    /// Applies the overrides to the fields read from a config file.
    pub fn apply(
        &self,
        cell: &mut String,
        name: &mut String,
        zenoh: &mut ZenohSettings,
        data_dir: &mut Option<std::path::PathBuf>,
    ) {
        if let Some(c) = &self.cell {
            *cell = c.clone();
        }
        if let Some(n) = &self.name {
            *name = n.clone();
        }
        if !self.connect.is_empty() {
            zenoh.connect = self.connect.clone();
        }
        if !self.listen.is_empty() {
            zenoh.listen = self.listen.clone();
        }
        if let Some(dir) = &self.data_dir {
            *data_dir = Some(dir.clone());
        }
        if self.lease_ms.is_some() {
            zenoh.lease_ms = self.lease_ms;
        }
        if let Some(mode) = self.mode {
            zenoh.mode = mode;
        }
        if let Some(pki) = &self.pki {
            zenoh.tls = Some(TlsSettings {
                pki: Some(pki.clone()),
                ..TlsSettings::default()
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builds_a_config_with_multicast_off() {
        let settings = ZenohSettings {
            connect: vec!["tcp/127.0.0.1:7447".into()],
            ..ZenohSettings::default()
        };
        settings.validate("resource.robot1").unwrap();
        let config = settings.to_config("resource.robot1").unwrap();
        let text = format!("{config}");
        assert!(text.contains("tcp/127.0.0.1:7447"), "{text}");
    }

    #[test]
    fn tls_refuses_to_start_without_its_files() {
        let settings = ZenohSettings {
            tls: Some(TlsSettings {
                pki: Some("/nonexistent/pki".into()),
                ..TlsSettings::default()
            }),
            ..ZenohSettings::default()
        };
        let err = settings
            .validate("resource.robot1")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("resource.robot1") && err.contains("/nonexistent/pki"),
            "{err}"
        );
    }

    #[test]
    fn rejects_bad_settings() {
        let bad_mode =
            serde_json::from_str::<ZenohSettings>(r#"{"mode": "router-ish"}"#).unwrap_err();
        assert!(bad_mode.to_string().contains("client"), "{bad_mode}");
        let alone = ZenohSettings::default()
            .validate("x")
            .unwrap_err()
            .to_string();
        assert!(alone.contains("router to connect to"), "{alone}");
        let listening_client = ZenohSettings {
            connect: vec!["tcp/127.0.0.1:7447".into()],
            listen: vec!["tcp/127.0.0.1:0".into()],
            ..ZenohSettings::default()
        };
        let err = listening_client.validate("x").unwrap_err().to_string();
        assert!(err.contains("listens on nothing"), "{err}");
        let listening_peer = ZenohSettings {
            mode: Mode::Peer,
            ..listening_client
        };
        listening_peer.validate("x").unwrap();
        let bad_endpoint = ZenohSettings {
            connect: vec!["nonsense".into()],
            ..ZenohSettings::default()
        };
        assert!(bad_endpoint.validate("x").is_err());
    }
}

//! The zenoh session of a holon process, from the `[zenoh]` section of its config and
//! the command line. Multicast scouting is off unless the config turns it on.

use std::time::Duration;

use serde::{Deserialize, Serialize};

/// How a holon joins the zenoh network (`[zenoh]` in every holon config).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    /// `peer` (default), `client` (talks only through the routers it connects to) or
    /// `router` (also routes for the peers and clients that connect to it).
    #[serde(default = "default_mode")]
    pub mode: String,
    /// Endpoints to connect to, e.g. `tcp/127.0.0.1:7447` (a router or another peer).
    #[serde(default)]
    pub connect: Vec<String>,
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7448`; empty lets zenoh choose.
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
}

fn default_mode() -> String {
    "peer".into()
}

impl Default for ZenohSettings {
    fn default() -> Self {
        ZenohSettings {
            mode: default_mode(),
            connect: Vec::new(),
            listen: Vec::new(),
            multicast_scouting: false,
            lease_ms: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    #[error("invalid zenoh setting {key}: {message}")]
    Config { key: &'static str, message: String },
    #[error("cannot open the zenoh session: {0}")]
    Open(String),
    #[error("opening the zenoh session took longer than {0:?}")]
    Timeout(Duration),
}

impl ZenohSettings {
    /// Checks the settings without opening anything.
    pub fn validate(&self) -> Result<(), SessionError> {
        self.to_config().map(|_| ())
    }

    /// The zenoh configuration these settings describe.
    pub fn to_config(&self) -> Result<zenoh::Config, SessionError> {
        let mut config = zenoh::Config::default();
        let mut set = |key: &'static str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| SessionError::Config {
                    key,
                    message: e.to_string(),
                })
        };
        if !matches!(self.mode.as_str(), "peer" | "client" | "router") {
            return Err(SessionError::Config {
                key: "mode",
                message: format!("{:?} is not peer, client or router", self.mode),
            });
        }
        let json = |v: &serde_json::Value| v.to_string();
        set("mode", json(&self.mode.clone().into()))?;
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
        Ok(config)
    }

    /// Opens the session, bounded by `timeout`.
    pub async fn open(&self, timeout: Duration) -> Result<zenoh::Session, SessionError> {
        let config = self.to_config()?;
        match tokio::time::timeout(timeout, zenoh::open(config)).await {
            Ok(Ok(session)) => Ok(session),
            Ok(Err(e)) => Err(SessionError::Open(e.to_string())),
            Err(_) => Err(SessionError::Timeout(timeout)),
        }
    }
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
        settings.validate().unwrap();
        let config = settings.to_config().unwrap();
        let text = format!("{config}");
        assert!(text.contains("tcp/127.0.0.1:7447"), "{text}");
    }

    #[test]
    fn rejects_bad_settings() {
        let bad_mode = ZenohSettings {
            mode: "router-ish".into(),
            ..ZenohSettings::default()
        };
        assert!(bad_mode.validate().is_err());
        let bad_endpoint = ZenohSettings {
            connect: vec!["nonsense".into()],
            ..ZenohSettings::default()
        };
        assert!(bad_endpoint.validate().is_err());
    }
}

//! What the `cell` commands that join a running cell share on their command line: how
//! they reach it, as whom, and how long they wait; and the parsing of `--due-in`.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Result};

/// How an operator's command reaches a cell.
#[derive(Debug, clap::Args)]
pub struct ClientArgs {
    /// The cell's name.
    #[arg(long, default_value = "demo")]
    pub cell: String,
    /// The endpoint of a zenoh router of the cell, e.g. tcp/127.0.0.1:7447 or
    /// tls/127.0.0.1:7447 (repeatable); the command joins as a client.
    #[arg(long, value_name = "ENDPOINT", required = true)]
    pub connect: Vec<String>,
    /// How long to wait for answers, in milliseconds.
    #[arg(long, default_value_t = 5000)]
    pub timeout_ms: u64,
    /// A secure cell's PKI directory (written by `cell certs`): connect with mutual
    /// TLS as --identity.
    #[arg(long, value_name = "DIR")]
    pub pki: Option<PathBuf>,
    /// The identity to use with --pki (default operator.default for submit and
    /// cancel, observer.default for status and orders).
    #[arg(long, value_name = "ROLE.NAME")]
    pub identity: Option<String>,
}

impl ClientArgs {
    pub fn keys(&self) -> Result<schemas::CellKeys> {
        Ok(schemas::CellKeys::new(&self.cell)?)
    }

    /// Who asks, for the holons' logs: `cell operator.default on host1 (user kim)`.
    pub fn who_asks(&self) -> String {
        let user = std::env::var("USER").unwrap_or_else(|_| nix::unistd::getuid().to_string());
        format!(
            "cell {} on {} (user {user})",
            self.identity.as_deref().unwrap_or(OPERATOR),
            holon::presence::host_name()
        )
    }

    pub fn timeout(&self) -> Duration {
        Duration::from_millis(self.timeout_ms)
    }

    /// The settings of a zenoh client of the cell.
    pub fn settings(&self) -> holon::ZenohSettings {
        holon::ZenohSettings {
            mode: holon::Mode::Client,
            connect: self.connect.clone(),
            tls: self.pki.as_ref().map(|pki| holon::tls::TlsSettings {
                pki: Some(pki.clone()),
                ..holon::tls::TlsSettings::default()
            }),
            ..holon::ZenohSettings::default()
        }
    }

    /// A zenoh client of the cell: everything it asks is routed by the router it
    /// connects to.
    pub async fn session(&self, default_identity: &str) -> Result<zenoh::Session> {
        if self.pki.is_none() {
            if let Some(tls) = self.connect.iter().find(|e| e.starts_with("tls/")) {
                return Err(anyhow!(
                    "{tls} is a secure cell's endpoint (mutual TLS): give --pki DIR (its PKI directory, written by cell certs) and, if not the default, --identity ROLE.NAME"
                ));
            }
        }
        let settings = self.settings();
        let identity = self.identity.as_deref().unwrap_or(default_identity);
        let session = settings
            .open(identity, self.timeout().max(Duration::from_secs(1)))
            .await
            .map_err(|e| anyhow!("cannot reach the cell at {}: {e}", self.connect.join(", ")))?;
        if !holon::session::wait_connected(&session, self.timeout()).await {
            return Err(anyhow!(
                "cannot reach the cell at {}",
                self.connect.join(", ")
            ));
        }
        Ok(session)
    }
}

pub const OPERATOR: &str = "operator.default";
pub const OBSERVER: &str = "observer.default";

pub async fn close(session: zenoh::Session) {
    if let Err(e) = session.close().await {
        tracing::debug!(error = %e, "closing the client session");
    }
}

/// `--due-in`: a whole number with a unit (`500ms`, `90s`, `15m`, `2h`).
pub fn parse_due_in(text: &str) -> Result<std::time::Duration, String> {
    let split = text
        .find(|c: char| !c.is_ascii_digit())
        .ok_or_else(|| format!("{text:?} has no unit (ms, s, m or h)"))?;
    let (number, unit) = text.split_at(split);
    let number: u64 = number
        .parse()
        .map_err(|_| format!("{text:?} does not start with a whole number"))?;
    let millis = match unit {
        "ms" => Some(number),
        "s" => number.checked_mul(1_000),
        "m" => number.checked_mul(60_000),
        "h" => number.checked_mul(3_600_000),
        _ => return Err(format!("{text:?}: the unit must be ms, s, m or h")),
    }
    .filter(|ms| *ms <= 366 * 24 * 3_600_000)
    .ok_or_else(|| format!("{text:?} is more than a year"))?;
    Ok(std::time::Duration::from_millis(millis))
}

#[cfg(test)]
mod due_in_tests {
    use super::parse_due_in;
    use std::time::Duration;

    #[test]
    pub fn durations_have_a_unit() {
        assert_eq!(parse_due_in("90s"), Ok(Duration::from_secs(90)));
        assert_eq!(parse_due_in("15m"), Ok(Duration::from_secs(900)));
        assert_eq!(parse_due_in("2h"), Ok(Duration::from_secs(7200)));
        assert_eq!(parse_due_in("500ms"), Ok(Duration::from_millis(500)));
        for bad in ["90", "s", "1.5m", "-1s", "3d", "9999h", ""] {
            assert!(parse_due_in(bad).is_err(), "{bad:?} was accepted");
        }
    }
}

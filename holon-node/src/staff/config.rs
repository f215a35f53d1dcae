//! The staff holon's config file (`deploy/cells/demo/planner.toml` documents it).

use std::time::Duration;

use holon::ZenohSettings;
use schemas::HolonKind;
use serde::Deserialize;

use holon::config_file::ConfigError;

use crate::identity::{Header, Identity, Overrides};

/// The file as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct StaffFile {
    cell: String,
    name: String,
    kind: String,
    #[serde(default)]
    zenoh: ZenohSettings,
    #[serde(default)]
    advice: AdviceSection,
}

/// `[advice]`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct AdviceSection {
    /// How long after its forecast end an advised step that was never booked still
    /// counts as the order's intention.
    #[serde(default = "default_intention_ttl_ms")]
    intention_ttl_ms: u64,
    /// How often, at most, the staff republishes its state when it changed.
    #[serde(default = "default_state_interval_ms")]
    state_interval_ms: u64,
}

fn default_intention_ttl_ms() -> u64 {
    5000
}

fn default_state_interval_ms() -> u64 {
    1000
}

impl Default for AdviceSection {
    fn default() -> Self {
        AdviceSection {
            intention_ttl_ms: default_intention_ttl_ms(),
            state_interval_ms: default_state_interval_ms(),
        }
    }
}

/// A validated staff config.
#[derive(Debug, Clone)]
pub struct StaffConfig {
    /// Its cell, id (`staff/<name>`) and zenoh settings.
    pub identity: Identity,
    /// How long an advised step never booked stays an intention after its forecast end.
    pub intention_ttl: Duration,
    /// How often, at most, the state is republished.
    pub state_interval: Duration,
}

impl StaffConfig {
    pub fn parse(text: &str, path: &str, overrides: Overrides) -> Result<StaffConfig, ConfigError> {
        let invalid = holon::config_file::invalid(path);
        let file: StaffFile = holon::config_file::parse(text, path)?;
        // A staff holon keeps no state of its own: what it knows, it learns again.
        let header = Header {
            cell: file.cell,
            name: file.name,
            zenoh: file.zenoh,
        };
        let identity =
            Identity::from_header(header, &file.kind, HolonKind::Staff, path, &overrides)?;
        if !(100..=600_000).contains(&file.advice.intention_ttl_ms) {
            return Err(invalid(
                "advice.intention_ttl_ms must be 100 to 600000".into(),
            ));
        }
        if !(10..=60_000).contains(&file.advice.state_interval_ms) {
            return Err(invalid(
                "advice.state_interval_ms must be 10 to 60000".into(),
            ));
        }
        Ok(StaffConfig {
            identity,
            intention_ttl: Duration::from_millis(file.advice.intention_ttl_ms),
            state_interval: Duration::from_millis(file.advice.state_interval_ms),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DEMO: &str = include_str!("../../../deploy/cells/demo/planner.toml");

    #[test]
    fn the_demo_staff_loads_and_bad_files_are_refused() {
        let config = StaffConfig::parse(DEMO, "planner.toml", Overrides::default()).unwrap();
        assert_eq!(config.identity.holon.to_string(), "staff/planner");
        assert_eq!(config.intention_ttl, Duration::from_secs(5));
        for (from, to, names) in [
            ("kind = \"staff\"", "kind = \"staf\"", "kind"),
            (
                "intention_ttl_ms = 5000",
                "intention_ttl_ms = 5",
                "intention_ttl_ms",
            ),
            (
                "state_interval_ms = 1000",
                "state_interval_ms = 0",
                "state_interval_ms",
            ),
            ("[advice]", "[advice]\nspeed = 3", "speed"),
        ] {
            assert!(DEMO.contains(from), "{from}");
            let error = StaffConfig::parse(&DEMO.replace(from, to), "x.toml", Overrides::default())
                .unwrap_err()
                .to_string();
            assert!(error.contains(names), "{from} -> {to}: {error}");
        }
    }
}

//! Who a holon without hardware or journal (a product, a staff holon) is in the cell:
//! the `cell`, `name`, `kind` and `[zenoh]` of its config with the command line applied
//! and checked, and its session opened as that identity with its name claimed; and what
//! holon-node's command line overrides, for every kind of holon.

use std::time::Duration;

use holon::config_file::ConfigError;
use holon::ZenohSettings;
use schemas::{CellKeys, HolonId, HolonKind};

/// A plain holon's identity, from its config file.
#[derive(Debug, Clone)]
pub struct Identity {
    /// Its cell's keys.
    pub keys: CellKeys,
    /// `<kind>/<name>`.
    pub holon: HolonId,
    /// How it joins the cell.
    pub zenoh: ZenohSettings,
    /// Start as the successor of the running process (`--take-over`), waiting this
    /// long at most for it to hand over.
    pub take_over: Option<std::time::Duration>,
}

pub use holon::config_file::Header;

/// How long a holon waits for zenoh to open and for its components to come up.
pub const STARTUP_TIMEOUT: Duration = Duration::from_secs(10);

/// What holon-node's command line may override, for every kind of holon (the
/// controller, fault injection and standby only apply to a resource).
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    /// Cell, name, zenoh endpoints, data directory.
    pub common: holon::session::CommandLine,
    /// `--controller`: the controller's HOST:PORT, instead of `controller.address`.
    pub controller: Option<String>,
    /// `--allow-fault-injection`: declare the crash queryable.
    pub allow_fault_injection: bool,
    /// `--standby`: fenced, whatever the file says.
    pub standby: bool,
    /// `--time-scale`: the plant runs this many times faster than real time (a
    /// resource's nominal durations and travel follow it).
    pub time_scale: schemas::TimeScale,
}

impl Identity {
    /// Checks `header` (of the file at `path`, whose `kind` field says `written_kind`)
    /// for a holon of `kind`, with the command line's `overrides` applied. Such a holon
    /// keeps no state: a data directory, if given, is not used.
    pub fn from_header(
        header: Header,
        written_kind: &str,
        kind: HolonKind,
        path: &str,
        overrides: &Overrides,
    ) -> Result<Identity, ConfigError> {
        let invalid = holon::config_file::invalid(path);
        if written_kind != kind.to_string() {
            return Err(invalid(format!("kind: {written_kind:?} is not {kind}")));
        }
        let header = header
            .check(
                path,
                &overrides.common,
                &mut None,
                holon::role::Role::of_holon(kind),
            )
            .map_err(&invalid)?;
        let holon = HolonId::new(kind, &header.name).map_err(|e| invalid(format!("name: {e}")))?;
        Ok(Identity {
            keys: header.keys,
            holon,
            zenoh: header.zenoh,
            take_over: overrides.common.take_over,
        })
    }

    /// Who the holon is, for the life cycle every holon shares.
    pub fn life(&self) -> holon::life::Life {
        holon::life::Life {
            presence_key: self.keys.alive(&self.holon),
            holder: self.holon.to_string(),
            version: crate::VERSION,
            take_over: self.take_over,
            data_dir: None,
            startup_timeout: STARTUP_TIMEOUT,
        }
    }

    /// How the holon's process opens its session: as `<kind>.<name>` for TLS.
    pub fn process(&self) -> holon::life::Process<'_> {
        let holon = &self.holon;
        holon::life::Process {
            life: self.life(),
            zenoh: &self.zenoh,
            tls_identity: holon::role::identity(
                holon::role::Role::of_holon(holon.kind()),
                holon.name(),
            ),
        }
    }

    /// The stand-in of a plain holon (it has nothing to finish) on `key`, its one
    /// queryable: `unavailable` with a retry hint. Until its own queryable there goes,
    /// both answer, and a requester takes the answer that is not `unavailable`, so no
    /// request in the switch goes unanswered.
    pub fn stand_in(&self, key: String) -> holon::life::StandInSpec {
        let holon = &self.holon;
        holon::life::StandInSpec {
            keys: vec![(key, false)],
            answer: holon::life::unavailable_answer(
                &holon.to_string(),
                format!(
                    "{holon} is being handed over to its successor (an upgrade); ask again shortly"
                ),
            ),
        }
    }
}

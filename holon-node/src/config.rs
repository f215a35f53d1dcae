//! The resource holon's config file (TOML). `deploy/cells/demo/robot1.toml` documents
//! every field. Unknown fields are errors, so a typo cannot silently change behaviour.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use holon::{Intensity, Strategy, ZenohSettings};
use schemas::{validate_name, CellKeys, HolonId};
use serde::Deserialize;

use crate::catalog::{ServiceCatalog, ServiceDefinition, Step};
use crate::identity::Overrides;

pub use holon::config_file::ConfigError;

/// The file as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConfigFile {
    pub cell: String,
    pub name: String,
    #[serde(default = "default_kind")]
    pub kind: String,
    #[serde(default)]
    pub zenoh: ZenohSettings,
    pub controller: ControllerSection,
    #[serde(default)]
    pub supervisor: SupervisorSection,
    #[serde(default)]
    pub agenda: AgendaSection,
    #[serde(default)]
    pub delivery: DeliverySection,
    #[serde(default)]
    pub shutdown: ShutdownSection,
    #[serde(default)]
    pub journal: JournalSection,
    #[serde(default)]
    pub packml: PackmlSection,
    pub services: BTreeMap<String, ServiceSection>,
    /// `[layout]`: the resource's own part of the cell's layout (docs/material-flow.md).
    #[serde(default)]
    pub layout: schemas::layout::LayoutSection,
}

/// `[packml]`: how the resource's PackML unit starts, and how long a held resource
/// keeps its bookings (docs/packml.md).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PackmlSection {
    /// The state of a resource that has never run (no PackML state in its journal):
    /// `execute` (default: it takes work at once), `idle` (until Start) or `stopped`
    /// (until Reset and Start). A journalled state always wins.
    #[serde(default = "default_initial_state")]
    pub initial_state: String,
    /// Its unit mode then: `production` (default), `maintenance` or `manual`.
    #[serde(default = "default_initial_mode")]
    pub initial_mode: String,
    /// How long bookings wait on a Held resource before they are handed back, so that
    /// their orders rebook elsewhere (default 30000).
    #[serde(default = "default_held_bookings_ms")]
    pub held_bookings_ms: u64,
}

fn default_initial_state() -> String {
    "execute".into()
}
fn default_initial_mode() -> String {
    "production".into()
}
fn default_held_bookings_ms() -> u64 {
    30_000
}

impl Default for PackmlSection {
    fn default() -> Self {
        PackmlSection {
            initial_state: default_initial_state(),
            initial_mode: default_initial_mode(),
            held_bookings_ms: default_held_bookings_ms(),
        }
    }
}

impl PackmlSection {
    fn settings(&self) -> Result<crate::machine::agenda::PackmlSettings, String> {
        use schemas::PackmlState;
        let initial_state = match self.initial_state.to_ascii_lowercase().as_str() {
            "execute" => PackmlState::Execute,
            "idle" => PackmlState::Idle,
            "stopped" => PackmlState::Stopped,
            other => {
                return Err(format!(
                    "packml.initial_state: {other:?} is not one of execute, idle, stopped"
                ))
            }
        };
        let initial_mode = self
            .initial_mode
            .parse::<schemas::UnitMode>()
            .map_err(|e| format!("packml.initial_mode: {e}"))?;
        Ok(crate::machine::agenda::PackmlSettings {
            initial_state,
            initial_mode,
            held_bookings_ms: self.held_bookings_ms,
        })
    }
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JournalSection {
    /// The data directory; `--data-dir` overrides it. None: no journal.
    #[serde(default)]
    pub dir: Option<std::path::PathBuf>,
    #[serde(default)]
    pub durability: holon::journal::Durability,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShutdownSection {
    #[serde(default = "default_grace_ms")]
    pub grace_ms: u64,
}

fn default_grace_ms() -> u64 {
    30_000
}

impl Default for ShutdownSection {
    fn default() -> Self {
        ShutdownSection {
            grace_ms: default_grace_ms(),
        }
    }
}

fn default_kind() -> String {
    "resource".into()
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ControllerSection {
    pub address: String,
    /// The first pause before reconnecting, and the pause after a connection that
    /// served (docs/dialects.md section 4.6).
    #[serde(default = "default_reconnect_ms")]
    pub reconnect_interval_ms: u64,
    /// The longest pause before reconnecting: the pause doubles from
    /// `reconnect_interval_ms` up to it while connections fail or end without serving.
    #[serde(default = "default_reconnect_max_ms")]
    pub reconnect_max_ms: u64,
    #[serde(default = "default_command_timeout_ms")]
    pub command_timeout_ms: u64,
    #[serde(default = "default_connect_timeout_ms")]
    pub connect_timeout_ms: u64,
    /// The controller's protocol: a shipped dialect's name or a dialect file (relative
    /// to the config file). Default holarchy-xml.
    #[serde(default = "default_dialect")]
    pub dialect: String,
    /// Claim the controller before serving (a standby resource, docs/reliability.md,
    /// "Standby resources"); `--standby` sets it too. The dialect must fence.
    #[serde(default)]
    pub fenced: bool,
    /// How many jobs the controller runs at once: 1 (a robot), or a transporter's moves
    /// at once (a conveyor moving several pallets). More than 1 needs a dialect whose
    /// replies carry the command's id (`correlation = "id"`).
    #[serde(default = "default_jobs_at_once")]
    pub jobs_at_once: usize,
}

fn default_jobs_at_once() -> usize {
    1
}

fn default_dialect() -> String {
    robot_bridge::dialect::DEFAULT.to_string()
}

fn default_reconnect_ms() -> u64 {
    1000
}
fn default_reconnect_max_ms() -> u64 {
    10_000
}
fn default_command_timeout_ms() -> u64 {
    30_000
}
fn default_connect_timeout_ms() -> u64 {
    2000
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SupervisorSection {
    #[serde(default)]
    pub strategy: Strategy,
    #[serde(default = "default_max_restarts")]
    pub max_restarts: u32,
    #[serde(default = "default_period_ms")]
    pub period_ms: u64,
}

fn default_max_restarts() -> u32 {
    5
}
fn default_period_ms() -> u64 {
    10_000
}

impl Default for SupervisorSection {
    fn default() -> Self {
        SupervisorSection {
            strategy: Strategy::default(),
            max_restarts: default_max_restarts(),
            period_ms: default_period_ms(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AgendaSection {
    #[serde(default = "default_capacity")]
    pub capacity: usize,
    /// How long a requester may be absent from the cell (no liveliness token) before
    /// its bookings are released.
    #[serde(default = "default_requester_grace_ms")]
    pub requester_grace_ms: u64,
    /// How many later bookings of higher priority may go ahead of a waiting booking
    /// (0: first come, first served whatever the priority).
    #[serde(default = "default_max_overtakes")]
    pub max_overtakes: u32,
}

fn default_max_overtakes() -> u32 {
    crate::machine::agenda::DEFAULT_MAX_OVERTAKES
}

fn default_requester_grace_ms() -> u64 {
    60_000
}

fn default_capacity() -> usize {
    64
}

impl Default for AgendaSection {
    fn default() -> Self {
        AgendaSection {
            capacity: default_capacity(),
            requester_grace_ms: default_requester_grace_ms(),
            max_overtakes: default_max_overtakes(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeliverySection {
    #[serde(default = "default_retry_initial_ms")]
    pub retry_initial_ms: u64,
    #[serde(default = "default_retry_max_ms")]
    pub retry_max_ms: u64,
    #[serde(default = "default_attempt_timeout_ms")]
    pub attempt_timeout_ms: u64,
}

fn default_retry_initial_ms() -> u64 {
    200
}
fn default_retry_max_ms() -> u64 {
    5000
}
fn default_attempt_timeout_ms() -> u64 {
    2000
}

impl Default for DeliverySection {
    fn default() -> Self {
        DeliverySection {
            retry_initial_ms: default_retry_initial_ms(),
            retry_max_ms: default_retry_max_ms(),
            attempt_timeout_ms: default_attempt_timeout_ms(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ServiceSection {
    #[serde(default = "default_nominal_ms")]
    pub nominal_duration_ms: u64,
    pub steps: Vec<StepSection>,
}

fn default_nominal_ms() -> u64 {
    1000
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StepSection {
    pub action: String,
    pub until: Vec<String>,
    #[serde(default)]
    pub position: Option<String>,
}

/// How results are delivered to `reply_to`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct DeliverySettings {
    pub retry_initial: Duration,
    pub retry_max: Duration,
    pub attempt_timeout: Duration,
}

/// The validated config of one resource holon, command-line overrides applied.
#[derive(Debug, Clone)]
pub struct ResourceConfig {
    pub keys: CellKeys,
    pub holon: HolonId,
    pub zenoh: ZenohSettings,
    pub controller: robot_bridge::client::ClientConfig,
    /// The longest pause before reconnecting to the controller (the backoff's cap; its
    /// first pause is `controller.reconnect_interval`).
    pub reconnect_max: Duration,
    pub strategy: Strategy,
    pub intensity: Intensity,
    pub agenda_capacity: usize,
    /// How many later bookings of higher priority may go ahead of a waiting one.
    pub agenda_max_overtakes: u32,
    /// How the PackML unit starts, and how long a held resource keeps its bookings.
    pub packml: crate::machine::agenda::PackmlSettings,
    /// How long a requester may be absent before its bookings are released.
    pub requester_grace: Duration,
    pub delivery: DeliverySettings,
    pub catalog: Arc<ServiceCatalog>,
    /// On SIGTERM, how long to wait for the running job and the hand-back of bookings.
    pub shutdown_grace: Duration,
    /// Where the journal lives (`<dir>/resource-<name>.sqlite`); None: not durable.
    pub data_dir: Option<std::path::PathBuf>,
    pub durability: holon::journal::Durability,
    /// Declare `resource/<name>/debug/crash` (tests and demonstrations only).
    pub allow_fault_injection: bool,
    /// Start as the successor of the running process (`--take-over`), waiting this
    /// long at most for it to hand over.
    pub take_over: Option<Duration>,
    /// Claim the controller before serving, wait as a standby while another session
    /// holds it, step down when deposed (`[controller] fenced`, `--standby`).
    pub fenced: bool,
    /// How many jobs its controller runs at once (`[controller] jobs_at_once`).
    pub jobs_at_once: usize,
    /// How many times faster than real time its plant runs (`--time-scale`); the
    /// catalog's nominal durations and the layout are already in its wall time.
    pub time_scale: schemas::TimeScale,
    /// Its part of the cell's layout (`[layout]`), answered on `resource/<name>/layout`;
    /// None: it takes no part in the cell's material flow.
    pub layout: Option<schemas::layout::LayoutPart>,
}

impl ResourceConfig {
    pub fn load(path: &Path, overrides: Overrides) -> Result<ResourceConfig, ConfigError> {
        let (text, display) = holon::config_file::read(path)?;
        Self::parse(&text, &display, overrides)
    }

    pub fn parse(
        text: &str,
        path: &str,
        overrides: Overrides,
    ) -> Result<ResourceConfig, ConfigError> {
        let invalid = holon::config_file::invalid(path);
        let mut file: ConfigFile = holon::config_file::parse(text, path)?;
        if let Some(base) = Path::new(path).parent() {
            let dialect = &mut file.controller.dialect;
            let is_file = dialect.contains('/') || dialect.ends_with(".toml");
            if is_file && Path::new(dialect.as_str()).is_relative() {
                *dialect = base.join(dialect.as_str()).display().to_string();
            }
        }
        let header = holon::config_file::Header {
            cell: file.cell.clone(),
            name: file.name.clone(),
            zenoh: file.zenoh.clone(),
        }
        .check(
            path,
            &overrides.common,
            &mut file.journal.dir,
            holon::role::Role::Resource,
        )
        .map_err(&invalid)?;
        if let Some(controller) = overrides.controller {
            file.controller.address = controller;
        }
        file.controller.fenced |= overrides.standby;
        let mut config =
            Self::validate(file, header, overrides.allow_fault_injection).map_err(&invalid)?;
        config.take_over = overrides.common.take_over;
        config.scale_plant_time(overrides.time_scale);
        if config.fenced && config.take_over.is_some() {
            return Err(ConfigError::Invalid {
                path: path.to_string(),
                message: "--take-over with a fenced resource (--standby, controller.fenced): the controller's claim decides who serves; start it as a standby instead".into(),
            });
        }
        Ok(config)
    }

    /// Counts the durations the config gives in plant time in the wall time of a plant
    /// run at `scale`: each service's nominal duration, its part of the layout's travel
    /// (`holon-node --time-scale`).
    fn scale_plant_time(&mut self, scale: schemas::TimeScale) {
        self.time_scale = scale;
        if scale.is_real() {
            return;
        }
        let mut services = self.catalog.definitions().clone();
        for definition in services.values_mut() {
            definition.nominal_duration = scale.wall(definition.nominal_duration);
        }
        self.catalog = Arc::new(ServiceCatalog::new(services));
        self.layout = self.layout.take().map(|part| part.at_scale(scale));
    }

    /// Checks the file section by section (the first problem is the one reported) and
    /// makes the resource's config of it.
    fn validate(
        file: ConfigFile,
        header: holon::config_file::CheckedHeader,
        allow_fault_injection: bool,
    ) -> Result<ResourceConfig, String> {
        if file.kind != "resource" {
            return Err(format!(
                "kind: {:?} is not supported by this holon-node (resource)",
                file.kind
            ));
        }
        let holon = HolonId::resource(&header.name).map_err(|e| format!("name: {e}"))?;
        let c = &file.controller;
        check_address(&c.address)?;
        check_periods(&file)?;
        check_limits(&file)?;
        let services = services(file.services)?;
        let dialect = dialect(c)?;
        let packml = file.packml.settings()?;
        let layout = (!file.layout.is_empty())
            .then(|| file.layout.part(holon.name()))
            .transpose()
            .map_err(|e| e.to_string())?;
        check_actions(&services, &dialect)?;
        Ok(ResourceConfig {
            keys: header.keys,
            holon,
            zenoh: header.zenoh,
            controller: robot_bridge::client::ClientConfig {
                address: c.address.clone(),
                reconnect_interval: Duration::from_millis(c.reconnect_interval_ms),
                command_timeout: Duration::from_millis(c.command_timeout_ms),
                connect_timeout: Duration::from_millis(c.connect_timeout_ms),
                dialect,
            },
            reconnect_max: Duration::from_millis(c.reconnect_max_ms),
            strategy: file.supervisor.strategy,
            intensity: Intensity {
                max_restarts: file.supervisor.max_restarts,
                period: Duration::from_millis(file.supervisor.period_ms),
            },
            agenda_capacity: file.agenda.capacity,
            agenda_max_overtakes: file.agenda.max_overtakes,
            packml,
            requester_grace: Duration::from_millis(file.agenda.requester_grace_ms),
            delivery: DeliverySettings {
                retry_initial: Duration::from_millis(file.delivery.retry_initial_ms),
                retry_max: Duration::from_millis(file.delivery.retry_max_ms),
                attempt_timeout: Duration::from_millis(file.delivery.attempt_timeout_ms),
            },
            catalog: Arc::new(ServiceCatalog::new(services)),
            shutdown_grace: Duration::from_millis(file.shutdown.grace_ms),
            data_dir: file.journal.dir.clone(),
            durability: file.journal.durability,
            allow_fault_injection,
            take_over: None,
            fenced: c.fenced,
            jobs_at_once: c.jobs_at_once,
            time_scale: schemas::TimeScale::REAL,
            layout,
        })
    }
}

/// `controller.address`: HOST:PORT, the port from 1 to 65535.
fn check_address(address: &str) -> Result<(), String> {
    let port = address
        .rsplit_once(':')
        .filter(|(host, _)| !host.trim().is_empty())
        .map(|(_, port)| port);
    match port.map(str::parse::<u16>) {
        Some(Ok(port)) if port > 0 => Ok(()),
        Some(_) => Err(format!(
            "controller.address: {address:?}: the port must be a number from 1 to 65535"
        )),
        None => Err(format!("controller.address: {address:?} is not HOST:PORT")),
    }
}

/// The periods and timeouts: none is 0, and no maximum is below its minimum.
fn check_periods(file: &ConfigFile) -> Result<(), String> {
    let c = &file.controller;
    for (field, value) in [
        ("controller.reconnect_interval_ms", c.reconnect_interval_ms),
        ("controller.reconnect_max_ms", c.reconnect_max_ms),
        ("controller.command_timeout_ms", c.command_timeout_ms),
        ("controller.connect_timeout_ms", c.connect_timeout_ms),
        ("supervisor.period_ms", file.supervisor.period_ms),
        ("delivery.retry_initial_ms", file.delivery.retry_initial_ms),
        ("delivery.retry_max_ms", file.delivery.retry_max_ms),
        (
            "delivery.attempt_timeout_ms",
            file.delivery.attempt_timeout_ms,
        ),
    ] {
        if value == 0 {
            return Err(format!("{field} must be greater than 0"));
        }
    }
    if c.reconnect_max_ms < c.reconnect_interval_ms {
        return Err(format!(
            "controller.reconnect_max_ms ({}) must be at least controller.reconnect_interval_ms ({})",
            c.reconnect_max_ms, c.reconnect_interval_ms
        ));
    }
    if file.delivery.retry_max_ms < file.delivery.retry_initial_ms {
        return Err("delivery.retry_max_ms must be at least retry_initial_ms".into());
    }
    Ok(())
}

/// The agenda's limits, and at least one service.
fn check_limits(file: &ConfigFile) -> Result<(), String> {
    if file.agenda.capacity == 0 {
        return Err("agenda.capacity must be greater than 0".into());
    }
    if file.agenda.requester_grace_ms < 1000 {
        return Err("agenda.requester_grace_ms must be at least 1000".into());
    }
    if file.services.is_empty() {
        return Err("services: a resource must offer at least one service type".into());
    }
    Ok(())
}

/// `[services]`: each service type's steps, their actions, results and positions named.
fn services(
    sections: BTreeMap<String, ServiceSection>,
) -> Result<BTreeMap<String, ServiceDefinition>, String> {
    let mut services = BTreeMap::new();
    for (service_type, section) in sections {
        validate_name("service type", &service_type)
            .map_err(|e| format!("services.{service_type}: {e}"))?;
        if section.steps.is_empty() {
            return Err(format!("services.{service_type}.steps: at least one step"));
        }
        let mut steps = Vec::new();
        for (i, step) in section.steps.into_iter().enumerate() {
            steps.push(service_step(
                &format!("services.{service_type}.steps[{i}]"),
                step,
            )?);
        }
        services.insert(
            service_type,
            ServiceDefinition {
                steps,
                nominal_duration: Duration::from_millis(section.nominal_duration_ms),
            },
        );
    }
    Ok(services)
}

/// One step of a service (`at` names it): an action until one of its results.
fn service_step(at: &str, step: StepSection) -> Result<Step, String> {
    validate_name("action", &step.action).map_err(|e| format!("{at}.action: {e}"))?;
    if step.until.is_empty() {
        return Err(format!("{at}.until: at least one result"));
    }
    for result in &step.until {
        validate_name("result", result).map_err(|e| format!("{at}.until: {e}"))?;
        if result == schemas::robot::RESULT_ERROR {
            return Err(format!("{at}.until: \"error\" always fails a step"));
        }
    }
    if let Some(position) = &step.position {
        validate_name("position", position).map_err(|e| format!("{at}.position: {e}"))?;
    }
    Ok(Step {
        action: step.action,
        until: step.until,
        position: step.position,
    })
}

/// `controller.dialect`, loaded; a fenced resource's dialect must have a fence.
fn dialect(c: &ControllerSection) -> Result<Arc<robot_bridge::dialect::Dialect>, String> {
    let dialect = robot_bridge::dialect::Dialect::load(&c.dialect, None)
        .map_err(|e| format!("controller.dialect: {e}"))?;
    if c.fenced && !dialect.fencing_supported() {
        return Err(format!(
            "controller.fenced (--standby): the dialect {} has no fence (claim, epochs, step ids): standby is refused",
            dialect.name
        ));
    }
    if c.jobs_at_once == 0 {
        return Err("controller.jobs_at_once must be at least 1".into());
    }
    if c.jobs_at_once > 1 && dialect.correlation != robot_bridge::dialect::Correlation::Id {
        return Err(format!(
            "controller.jobs_at_once = {}: the dialect {} has one request in flight at a time (its replies carry no id), so its controller runs one job at a time",
            c.jobs_at_once, dialect.name
        ));
    }
    Ok(dialect)
}

/// Every step's action can be sent in the dialect.
fn check_actions(
    services: &BTreeMap<String, ServiceDefinition>,
    dialect: &robot_bridge::dialect::Dialect,
) -> Result<(), String> {
    for (service_type, definition) in services {
        for step in &definition.steps {
            dialect.check_action(&step.action).map_err(|e| {
                format!(
                    "services.{service_type}: the action {:?} cannot be sent in the dialect {}: {e}",
                    step.action, dialect.name
                )
            })?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;

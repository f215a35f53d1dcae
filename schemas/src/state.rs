//! State snapshots published on `<kind>/<name>/state`.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::id::HolonId;
use crate::robot::ControllerState;

/// A resource's execution status, as its agenda manager sees it (the seed's Figure 4,
/// plus `init`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ResourceState {
    /// The controller is not ready (not connected yet, in fault or estop): no new work.
    Init,
    /// Ready, and a job may begin: nothing runs (or, on a resource that runs several
    /// jobs at once, fewer than it can).
    Free,
    /// A job is running, and no other can begin beside it (on a resource that runs
    /// several at once: all it can run are running).
    Busy,
}

impl ResourceState {
    pub fn as_str(self) -> &'static str {
        match self {
            ResourceState::Init => "init",
            ResourceState::Free => "free",
            ResourceState::Busy => "busy",
        }
    }
}

impl std::fmt::Display for ResourceState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The controller as a resource holon sees it: the last `ROBOT_STATUS` of a connected
/// controller, or `disconnected`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ControllerStatus {
    /// No connection (yet, or any more).
    Disconnected,
    Ready,
    Fault,
    Estop,
}

impl ControllerStatus {
    pub fn is_ready(self) -> bool {
        self == ControllerStatus::Ready
    }

    pub fn as_str(self) -> &'static str {
        match self {
            ControllerStatus::Disconnected => "disconnected",
            ControllerStatus::Ready => "ready",
            ControllerStatus::Fault => "fault",
            ControllerStatus::Estop => "estop",
        }
    }
}

impl From<ControllerState> for ControllerStatus {
    fn from(state: ControllerState) -> ControllerStatus {
        match state {
            ControllerState::Ready => ControllerStatus::Ready,
            ControllerState::Fault => ControllerStatus::Fault,
            ControllerState::Estop => ControllerStatus::Estop,
        }
    }
}

impl std::fmt::Display for ControllerStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One booking on a resource's agenda, as it appears in a snapshot.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct BookingView {
    pub requester: HolonId,
    pub conversation_id: String,
    pub service_type: String,
    /// Set while the requester is absent from the cell (no liveliness token): since
    /// when, in Unix milliseconds. The booking ends when the absence outlasts the
    /// resource's `agenda.requester_grace_ms`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub requester_absent_since: Option<u64>,
    /// The booking's priority ([`crate::info_key::PRIORITY`]; 0 unless given).
    #[serde(default)]
    pub priority: i32,
    /// When its order is due, in Unix milliseconds, if it said.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub due: Option<u64>,
    /// How many later bookings of higher priority went ahead of it (at most the
    /// resource's `agenda.max_overtakes`).
    #[serde(default)]
    pub overtaken: u32,
    /// The job's program (product variant), from its `info.program`, if it names one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
}

impl BookingView {
    /// A booking of `requester`'s that waits on the agenda: its requester present, of
    /// priority 0, not due, never overtaken, no program; set over it what differs.
    pub fn waiting(requester: HolonId, conversation_id: &str, service_type: &str) -> BookingView {
        BookingView {
            requester,
            conversation_id: conversation_id.to_string(),
            service_type: service_type.to_string(),
            requester_absent_since: None,
            priority: 0,
            due: None,
            overtaken: 0,
            program: None,
        }
    }
}

/// A resource holon's state after a change.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ResourceSnapshot {
    /// e.g. `resource/robot1`.
    pub holon: HolonId,
    /// The agenda manager's execution status: `init` (controller not ready), `free`, `busy`.
    pub state: ResourceState,
    /// The controller: `disconnected`, `ready`, `fault`, `estop`.
    pub controller: ControllerStatus,
    /// Bookings in the order they will be served (by priority, then as they came).
    pub agenda: Vec<BookingView>,
    /// The job being executed, if any, and its step.
    pub current: Option<CurrentJobView>,
    /// The other jobs being executed at the same time, on a resource whose controller
    /// runs several at once (a conveyor moving several pallets, `[controller]
    /// jobs_at_once`), in the order they began; `current` is the first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub more_running: Vec<CurrentJobView>,
    /// Results (`done` / `failed`) sent but not yet acknowledged.
    pub undelivered: usize,
    /// Service types offered.
    pub services: Vec<String>,
    /// Each offered service type's nominal duration in ms (its config's
    /// `nominal_duration_ms`): what proposals count with, and a staff holon's first
    /// guess before it has measured the resource.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub nominal_ms: std::collections::BTreeMap<String, u64>,
    /// Set while the resource's journal cannot be written (e.g. a full disk): why. It
    /// takes no new work and holds its results until a write succeeds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub journal_fault: Option<String>,
    /// How many times a result went out again because an attempt was not acknowledged,
    /// since the process started (a requester away, slow or refusing).
    #[serde(default)]
    pub delivery_retries: u64,
    /// Set while the resource is handed over to its successor (a planned upgrade,
    /// `cell upgrade`): it takes no new work and starts nothing, keeps its bookings for
    /// the successor, and finishes its running step. Orders booked here keep their
    /// bookings while it is away, for at most their node's `orders.handover_grace_ms`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub handing_over: bool,
    /// Its PackML state, unit mode and figures (docs/packml.md); absent from holons
    /// built before PackML. A resource takes orders' work only in Execute and
    /// Production.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub packml: Option<crate::packml::PackmlStatus>,
    /// The places held at its locations (docs/material-flow.md, "Reservations"): each
    /// location's parts, in the order they were reserved.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub places: std::collections::BTreeMap<String, Vec<String>>,
    /// A conveyor's carriers taken out of service by an operator (`cell carrier`), by
    /// name (`p3`); it grants homes only while fewer are held than carriers are in
    /// service (docs/material-flow.md, "Carriers out of service").
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub carriers_out: Vec<String>,
    /// The machine the holon's process runs on (its hostname).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host: Option<String>,
    /// The epoch of the controller's claim this process holds, for a fenced resource
    /// (docs/reliability.md, "Standby resources"); absent when not fenced. Watchers
    /// tell two processes of one name apart by it: a state from a lower epoch than one
    /// already seen is a deposed holder's, and is not read.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub epoch: Option<u64>,
    /// The release of the holon's program (its package version, e.g. `0.1.0`); absent
    /// from holons built before versions were published.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<String>,
    /// The plant's time scale the resource runs at (`holon-node --time-scale`), when
    /// it is not real time: the dashboard draws its schedule in plant time by it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_scale: Option<f64>,
    /// The Service message version the holon speaks ([`crate::SERVICE_VERSION`]); 0
    /// from holons built before it was published.
    #[serde(default)]
    pub v: u32,
    /// Unix time in milliseconds.
    pub at: u64,
}

impl ResourceSnapshot {
    /// The state of `holon` before it knows anything: initialising, no controller
    /// connection, nothing booked, running or offered, at time 0. Whoever publishes or
    /// builds a state sets what it knows over it (`..ResourceSnapshot::blank(holon)`).
    pub fn blank(holon: HolonId) -> ResourceSnapshot {
        ResourceSnapshot {
            holon,
            state: ResourceState::Init,
            controller: ControllerStatus::Disconnected,
            agenda: Vec::new(),
            current: None,
            more_running: Vec::new(),
            undelivered: 0,
            services: Vec::new(),
            nominal_ms: Default::default(),
            journal_fault: None,
            delivery_retries: 0,
            handing_over: false,
            packml: None,
            places: Default::default(),
            carriers_out: Vec::new(),
            host: None,
            epoch: None,
            version: None,
            time_scale: None,
            v: 0,
            at: 0,
        }
    }
}

/// The highest epoch seen of each fenced resource: a state published by a process of a
/// lower epoch is a deposed holder's (frozen or cut off, then thawed), and whoever reads
/// the resources' states ignores it rather than read the cell backwards.
#[derive(Debug, Clone, Default)]
pub struct Epochs {
    /// By resource, the highest epoch its states carried.
    highest: std::collections::HashMap<HolonId, u64>,
}

impl Epochs {
    /// Whether `snapshot` is from the resource's current holder (or from a resource that
    /// is not fenced), remembering its epoch: false for a deposed holder's.
    pub fn current(&mut self, snapshot: &ResourceSnapshot) -> bool {
        let Some(epoch) = snapshot.epoch else {
            return true;
        };
        let highest = self.highest.entry(snapshot.holon.clone()).or_insert(epoch);
        if epoch < *highest {
            return false;
        }
        *highest = epoch;
        true
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct CurrentJobView {
    pub requester: HolonId,
    pub conversation_id: String,
    pub service_type: String,
    /// The action of the step in progress, e.g. `pick`.
    pub step: Option<String>,
    /// The job's program (product variant), from its `info.program`, if it names one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
    /// When the job began executing (Unix ms), once the execution has it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub started_at: Option<u64>,
}

/// Milliseconds since the Unix epoch, for `at` fields.
pub fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

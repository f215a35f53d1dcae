//! State snapshots published on `<kind>/<name>/state`.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::id::HolonId;

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
}

/// A resource holon's state after a change.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct ResourceSnapshot {
    /// e.g. `resource/robot1`.
    pub holon: HolonId,
    /// The agenda manager's execution status: `init` (controller not ready), `free`, `busy`.
    pub state: String,
    /// The controller: `disconnected`, `ready`, `fault`, `estop`.
    pub controller: String,
    /// Bookings in the order they were made.
    pub agenda: Vec<BookingView>,
    /// The job being executed, if any, and its step.
    pub current: Option<CurrentJobView>,
    /// Results (`done` / `failed`) sent but not yet acknowledged.
    pub undelivered: usize,
    /// Service types offered.
    pub services: Vec<String>,
    /// Set while the resource's journal cannot be written (e.g. a full disk): why. It
    /// takes no new work and holds its results until a write succeeds.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub journal_fault: Option<String>,
    /// Unix time in milliseconds.
    pub at: u64,
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct CurrentJobView {
    pub requester: HolonId,
    pub conversation_id: String,
    pub service_type: String,
    /// The action of the step in progress, e.g. `pick`.
    pub step: Option<String>,
}

/// Milliseconds since the Unix epoch, for `at` fields.
pub fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

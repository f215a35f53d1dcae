//! What the model tells of: alarms (raised, cleared, acknowledged) and the event log's
//! entries, each about a [`Source`].

use schemas::HolonId;
use serde::Serialize;

use super::ProcessId;

/// What an alarm or an event is about: a holon or an order, or a router or order-node.
/// Shown as `kind/name` either way.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(untagged)]
pub enum Source {
    Holon(HolonId),
    Process(ProcessId),
}

impl From<&HolonId> for Source {
    fn from(holon: &HolonId) -> Source {
        Source::Holon(holon.clone())
    }
}

impl From<&ProcessId> for Source {
    fn from(process: &ProcessId) -> Source {
        Source::Process(process.clone())
    }
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Source::Holon(holon) => holon.fmt(f),
            Source::Process(process) => process.fmt(f),
        }
    }
}

/// What an alarm is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AlarmKind {
    /// A resource's controller is in fault or estop.
    Controller,
    /// A resource's token vanished.
    Vanished,
    /// A resource's journal cannot be written.
    Journal,
    /// Results pile up on a resource, not acknowledged.
    Undelivered,
    /// A holon's token keeps appearing: its process restarts repeatedly.
    Restarting,
    /// An order failed.
    OrderFailed,
    /// An order's part was scrapped.
    OrderScrapped,
    /// An order's part is lost: its move ended without its transporter saying where
    /// the part is (docs/material-flow.md, "Parts and carriers"); raised while it is.
    PartLost,
    /// An order's part in the cell has stayed where it is beyond the dashboard's bound
    /// (`--part-wait-alarm-s`): it waits for something that does not come; cleared
    /// once it moves or leaves.
    PartWaits,
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Alarm {
    pub id: u64,
    pub kind: AlarmKind,
    /// The holon, order or process it is about.
    pub source: Source,
    /// For people: what is wrong.
    pub message: String,
    /// When it was raised (Unix ms).
    pub raised: u64,
    /// When its condition ended, if it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub cleared: Option<u64>,
    /// When an operator acknowledged it, if one did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub acknowledged: Option<u64>,
}

impl Alarm {
    pub fn active(&self) -> bool {
        self.cleared.is_none()
    }
}

/// One entry of the event log.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Event {
    pub at: u64,
    /// The holon, order or process it is about.
    pub source: Source,
    pub text: String,
}

//! What the dashboard's model hears: every input its one owner applies.

use std::collections::BTreeMap;

use schemas::{HolonId, OrderSnapshot, ResourceSnapshot};

use super::ProcessId;

/// What the model hears.
#[derive(Debug, Clone, PartialEq)]
pub enum Input {
    /// A holon's liveliness token appeared.
    Appeared { holon: HolonId, at: u64 },
    /// A holon's liveliness token vanished.
    Vanished { holon: HolonId, at: u64 },
    /// A resource's state (boxed: a snapshot is large beside the other inputs).
    Resource {
        snapshot: Box<ResourceSnapshot>,
        at: u64,
    },
    /// An order's state (boxed, as a resource's).
    Order {
        snapshot: Box<OrderSnapshot>,
        at: u64,
    },
    /// A process that serves the cell without being a holon (a router, an
    /// order-node) announced itself.
    ProcessAppeared { process: ProcessId, at: u64 },
    /// Its token vanished.
    ProcessVanished { process: ProcessId, at: u64 },
    /// `by` (a user) acknowledged alarm `id`.
    Acknowledge { id: u64, by: String, at: u64 },
    /// The fenced resources' processes that answered, as of now (docs/reliability.md,
    /// "Standby resources"): they replace the previous list.
    Fences {
        reports: Vec<schemas::FenceReport>,
        at: u64,
    },
    /// The processes of the order-nodes on etcd that answered, as of now
    /// (docs/reliability.md, "Order-node standby on etcd"): they replace the previous
    /// list.
    NodeFences {
        /// Each process's report: holder or standby, epoch, lag.
        reports: Vec<schemas::fence::NodeFenceReport>,
    },
    /// The order-nodes' counts of their orders by status, as each answered a listing
    /// (a page of none, [`schemas::listing`]): they replace the previous ones.
    NodeCounts {
        counts: BTreeMap<String, schemas::OrderCounts>,
    },
    /// The cell's layout, as the serving resources answered it (docs/material-flow.md):
    /// it replaces the previous one.
    Layout(Box<schemas::layout::CellLayout>),
    /// Time passes (every few seconds): what waits too long is alarmed.
    Tick { at: u64 },
}

//! What a fenced resource's process says of its place at the controller (a standby
//! resource, docs/reliability.md): `holarchy/<cell>/resource/<name>/fence/<zid>`, one
//! key per process, so a holder and its standbys are listed side by side (`cell
//! status`).

use serde::{Deserialize, Serialize};

use crate::HolonId;

/// A process's place in its resource's fence.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FenceRole {
    /// It holds the controller's claim and serves the resource.
    Holder,
    /// It waits for the claim, serving nothing.
    Standby,
}

/// One process's report.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FenceReport {
    /// The resource.
    pub holon: HolonId,
    /// Holder or standby.
    pub role: FenceRole,
    /// The epoch it holds, while a holder.
    pub epoch: Option<u64>,
    /// The holder's epoch as the controller last said, while a standby (none before it
    /// has heard).
    pub holder_epoch: Option<u64>,
    /// The machine the process runs on.
    pub host: String,
    /// Its zenoh session id.
    pub zid: String,
    /// Unix ms of the last change.
    pub at: u64,
}

/// One order-node process's report, for an order-node whose journal is on etcd (a
/// primary and its standbys, docs/reliability.md): `holarchy/<cell>/host/order-node/
/// <name>/fence/<zid>` ([`crate::CellKeys::node_fence`]), one key per process.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct NodeFenceReport {
    /// The order-node's name.
    pub node: String,
    /// Holder (it holds the leader key on etcd and serves) or standby.
    pub role: FenceRole,
    /// The epoch it holds, while a holder.
    #[serde(default)]
    pub epoch: Option<u64>,
    /// The holder's epoch as etcd last said, while a standby (none while nobody holds
    /// the key or before it has asked).
    #[serde(default)]
    pub holder_epoch: Option<u64>,
    /// The etcd revisions of the cluster it has not read yet, while a standby following
    /// the journal (0: caught up; none before its first read).
    #[serde(default)]
    pub lag: Option<u64>,
    /// True while it cannot reach etcd (its last read failed): its lag is then as of
    /// its last read, and it cannot take over.
    #[serde(default)]
    pub store_lost: bool,
    /// The machine the process runs on.
    pub host: String,
    /// Its zenoh session id.
    pub zid: String,
    /// Unix ms of the last change.
    pub at: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_node_report_without_the_later_fields_still_reads() {
        let report: NodeFenceReport = serde_json::from_str(
            r#"{"node":"orders","role":"standby","host":"b","zid":"z","at":1}"#,
        )
        .unwrap();
        assert_eq!(report.role, FenceRole::Standby);
        assert_eq!((report.lag, report.store_lost), (None, false));
    }
}

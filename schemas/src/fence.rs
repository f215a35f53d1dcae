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

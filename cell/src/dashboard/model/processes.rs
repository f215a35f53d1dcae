//! The processes that serve the cell without being holons (routers and order-nodes),
//! as their tokens (`host/<program>/<name>`) name them and the page lists them.

use serde::Serialize;

/// A process that serves the cell without being a holon, as its token names it:
/// `router/<host>`, `order-node/<name>`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ProcessId {
    /// `router` or `order-node`.
    pub program: String,
    pub name: String,
}

impl std::fmt::Display for ProcessId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.program, self.name)
    }
}

impl Serialize for ProcessId {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

/// One router or order-node as the page shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ProcessView {
    pub process: ProcessId,
    /// Its token is visible.
    pub live: bool,
    /// Since when it is live or gone (Unix ms).
    pub since: u64,
}

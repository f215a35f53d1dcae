//! Why an order-node stops with an error (its exit code and message).

use crate::journal::OrderJournalError;

/// Why the order-node could not start, or stopped serving.
#[derive(Debug, thiserror::Error)]
pub enum OrderNodeError {
    /// A step of the holon's life cycle: its session, its name, a take-over, a
    /// hand-over.
    #[error(transparent)]
    Life(#[from] holon::life::LifeError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("invalid work order: {0}")]
    WorkOrder(String),
    #[error(transparent)]
    Journal(#[from] holon::journal::JournalError),
    /// The order journal could not be read at start (SQLite or etcd).
    #[error(transparent)]
    OrderJournal(#[from] OrderJournalError),
    /// etcd could not be used for the election.
    #[error("etcd: {0}")]
    Etcd(#[from] holon::etcd::EtcdError),
    /// Another process of this name holds the leader key now: this one stopped serving
    /// (its supervisor starts it again, a standby).
    #[error("deposed by {by}: this order-node held epoch {epoch} ({why}); it stopped serving and exits, to start again as a standby")]
    Deposed {
        /// The epoch this node held.
        epoch: i64,
        /// Who holds the key now (`epoch N (holder)`), as etcd said.
        by: String,
        /// How the node learned it was deposed.
        why: String,
    },
}

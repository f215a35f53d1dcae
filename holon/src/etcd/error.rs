//! What can go wrong between a holon and etcd.

/// An error of the etcd client, election or store.
#[derive(Debug, Clone, thiserror::Error)]
pub enum EtcdError {
    /// The client was given nothing usable to connect to.
    #[error("etcd client configuration: {0}")]
    Config(String),
    /// No member answered: each was tried once, in turn. Nothing was written.
    #[error("no etcd member answered (tried {tried}): {last}")]
    Unreachable {
        /// The endpoints tried, in order.
        tried: String,
        /// Why the last one failed.
        last: String,
    },
    /// A write reached a member, but no reply told whether etcd committed it (the member
    /// died, or the reply did not come in time): it may or may not be in the store.
    #[error(
        "etcd member {endpoint} did not say whether the write committed ({why}): it may or \
         may not be in the store"
    )]
    Uncertain {
        /// The member the write went to.
        endpoint: String,
        /// What happened instead of a reply.
        why: String,
    },
    /// etcd answered with an error.
    #[error("etcd member {endpoint} refused {path}: {message} (code {code})")]
    Refused {
        /// The member that answered.
        endpoint: String,
        /// The gateway's path, e.g. `/v3/kv/txn`.
        path: String,
        /// etcd's message, e.g. `etcdserver: requested lease not found`.
        message: String,
        /// The gRPC status code (5: not found, 14: unavailable, ...).
        code: i32,
    },
    /// A reply that is not the JSON the gateway writes.
    #[error("etcd member {endpoint} answered {path} with a malformed reply: {why}")]
    Malformed {
        /// The member that answered.
        endpoint: String,
        /// The gateway's path.
        path: String,
        /// What did not parse.
        why: String,
    },
    /// The write was refused because this process no longer holds the leader key it was
    /// fenced on (its lease expired or was revoked, and maybe another holder won since).
    /// Nothing of the write was stored.
    #[error("deposed: {key} is no longer held at epoch {epoch} ({holder}); nothing was written")]
    Deposed {
        /// The leader key.
        key: String,
        /// The epoch this process held (the leader key's create_revision when it won).
        epoch: i64,
        /// Who holds the key now, as etcd said (or "nobody", or "stepped down" when this
        /// process found itself deposed before asking etcd).
        holder: String,
    },
    /// A write with more operations than etcd takes in one txn (its `--max-txn-ops`,
    /// 128 by default): refused before it was sent.
    #[error("a write of {count} records is more than the {max} etcd takes in one commit")]
    TooLarge {
        /// The records in the write.
        count: usize,
        /// The most one write may hold.
        max: usize,
    },
    /// A kind or id that cannot be a key of the store.
    #[error("{what} {name:?} cannot be part of a journal key: {why}")]
    BadName {
        /// `kind` or `id`.
        what: &'static str,
        /// The name given.
        name: String,
        /// Why not.
        why: &'static str,
    },
    /// A record whose JSON does not decode to the type asked for.
    #[error("etcd record {key} cannot be read: {why}")]
    Decode {
        /// The record's key.
        key: String,
        /// serde's message.
        why: String,
    },
}

impl EtcdError {
    /// Whether trying again later may succeed: etcd was unreachable, a write's outcome
    /// is unknown, or etcd was busy (no raft leader, a timeout). A deposed holder, a bad
    /// request or a malformed reply stays so.
    pub fn is_transient(&self) -> bool {
        match self {
            EtcdError::Unreachable { .. } | EtcdError::Uncertain { .. } => true,
            // gRPC's UNAVAILABLE and DEADLINE_EXCEEDED: no leader, leader changed, timed out.
            EtcdError::Refused { code, .. } => matches!(code, 4 | 14),
            _ => false,
        }
    }
}

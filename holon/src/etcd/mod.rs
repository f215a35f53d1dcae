//! A holon's state on etcd, for a standby on another host (issue 31, order-nodes): a
//! client of etcd's v3 JSON gateway with failover between members ([`Client`]), the
//! election of one holder by a leased key whose create_revision is its epoch
//! ([`Candidate`], [`Leader`]), and a record store whose every write is fenced on that
//! epoch ([`FencedStore`]).
//!
//! Keys, under a holon's prefix (e.g. `holarchy/<cell>/order-node/<name>`):
//! - `<prefix>/leader`: the holder's name, under its lease;
//! - `<prefix>/journal/<kind>/<id>`: a record's JSON.
//!
//! SQLite ([`crate::journal::Journal`]) stays the journal of a single-host cell; this
//! store is for a holon with a standby. docs/reliability.md, "The order-node's store on
//! etcd", says what is built and what is not yet.

#![warn(missing_docs)]

mod client;
mod endpoint;
mod error;
mod leadership;
mod store;
mod wire;

pub use client::{Client, ClientConfig, MemberStatus};
pub use endpoint::{common_scheme, Endpoint, Scheme, TlsFiles};
pub use error::EtcdError;
pub use leadership::{Candidate, ElectionConfig, Holder, Leader, Leadership};
pub use store::{journal_since, FencedStore, JournalRead, MAX_RECORDS_PER_WRITE};

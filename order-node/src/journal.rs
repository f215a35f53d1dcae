//! The order-node's record store, on one of two backends: the SQLite journal on this
//! host's disk (the default, [`holon::journal::Journal`]), or etcd (`journal.etcd`: a
//! [`FencedStore`] of the epoch this node won, for an order-node with a standby on
//! another host; docs/reliability.md, "The order-node's store on etcd").
//!
//! Both are used the same way, synchronously, from the order tasks and the node's
//! loop: a write returns only once it is committed (SQLite: on this disk; etcd: on a
//! majority of the members' disks). On etcd every write is fenced on the epoch: one by
//! a deposed holder writes nothing and fails [`OrderJournalError::is_deposed`], which the
//! order-node treats as any journal fault (the order waits, nothing is acknowledged)
//! while its loop stops it ([`OrderJournal::deposed`]).

use holon::etcd::{EtcdError, FencedStore, MAX_RECORDS_PER_WRITE};
use holon::journal::{Journal, JournalError};
use serde::de::DeserializeOwned;
use serde::Serialize;
use tokio_util::sync::CancellationToken;

/// Why the order-node's store could not read or write.
#[derive(Debug, thiserror::Error)]
pub enum OrderJournalError {
    /// The SQLite journal failed.
    #[error(transparent)]
    Local(#[from] JournalError),
    /// etcd failed, or refused a write of a deposed holder ([`EtcdError::Deposed`]).
    #[error("the order journal on etcd: {0}")]
    Replicated(#[from] EtcdError),
}

impl OrderJournalError {
    /// Whether the write was refused because this node no longer holds its leader key.
    pub fn is_deposed(&self) -> bool {
        matches!(
            self,
            OrderJournalError::Replicated(EtcdError::Deposed { .. })
        )
    }
}

/// The order-node's records: `(kind, id)` → JSON, on SQLite or etcd.
pub enum OrderJournal {
    /// The SQLite journal in the node's data directory.
    Local(Journal),
    /// The node's records in etcd, written only at its epoch.
    Replicated(Replicated),
}

/// The etcd backend: a fenced store, and the runtime its calls run on.
pub struct Replicated {
    /// The store, fenced on the epoch this node won.
    pub store: FencedStore,
    /// The runtime the async calls run on: a multi-thread one, whose other workers run
    /// it while a caller blocks on etcd.
    pub handle: tokio::runtime::Handle,
    /// Cancelled when etcd refused a write because this node was deposed: the node's
    /// loop stops at once, even before its keep-alive hears it.
    pub deposed: CancellationToken,
}

impl Replicated {
    /// Runs an etcd call to its end from synchronous code: on the multi-thread runtime
    /// the worker hands its other tasks over while it waits
    /// ([`holon::journal::blocking`]), then blocks on the call.
    fn run<R>(
        &self,
        call: impl std::future::Future<Output = Result<R, EtcdError>>,
    ) -> Result<R, OrderJournalError> {
        let outcome = holon::journal::blocking(|| self.handle.block_on(call));
        if let Err(e @ EtcdError::Deposed { .. }) = &outcome {
            if !self.deposed.is_cancelled() {
                tracing::error!(error = %e, "etcd refused a journal write: this order-node is deposed");
            }
            self.deposed.cancel();
        }
        outcome.map_err(OrderJournalError::from)
    }
}

impl std::fmt::Debug for OrderJournal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            OrderJournal::Local(journal) => f.debug_tuple("Local").field(journal).finish(),
            OrderJournal::Replicated(r) => f
                .debug_struct("Replicated")
                .field("epoch", &r.store.epoch())
                .finish(),
        }
    }
}

impl OrderJournal {
    /// The epoch the writes are fenced on (etcd), `None` on SQLite.
    pub fn epoch(&self) -> Option<i64> {
        match self {
            OrderJournal::Local(_) => None,
            OrderJournal::Replicated(r) => Some(r.store.epoch()),
        }
    }

    /// Cancelled once etcd refused a write because this node is deposed (never on
    /// SQLite).
    pub fn deposed(&self) -> Option<CancellationToken> {
        match self {
            OrderJournal::Local(_) => None,
            OrderJournal::Replicated(r) => Some(r.deposed.clone()),
        }
    }

    /// Writes one record; committed when this returns.
    pub fn put<T: Serialize>(
        &self,
        kind: &str,
        id: &str,
        value: &T,
    ) -> Result<(), OrderJournalError> {
        match self {
            OrderJournal::Local(journal) => Ok(journal.put(kind, id, value)?),
            OrderJournal::Replicated(r) => r.run(r.store.put(kind, id, value)),
        }
    }

    /// Writes several records in one commit: all or none. On etcd at most
    /// [`MAX_RECORDS_PER_WRITE`] (more is refused whole; the config keeps a work order
    /// below it).
    pub fn put_all<'a, T, I>(&self, records: I) -> Result<(), OrderJournalError>
    where
        T: Serialize + 'a,
        I: IntoIterator<Item = (&'a str, &'a str, &'a T)>,
    {
        match self {
            OrderJournal::Local(journal) => Ok(journal.put_all(records)?),
            OrderJournal::Replicated(r) => {
                let records: Vec<_> = records.into_iter().collect();
                r.run(r.store.put_all(records))
            }
        }
    }

    /// Removes records of `kind` (absent ones are no error). SQLite: in one commit. etcd:
    /// in commits of at most [`MAX_RECORDS_PER_WRITE`], so a failure may leave some
    /// removed (the retention sweep removes the rest next time).
    pub fn delete<I, S>(&self, kind: &str, ids: I) -> Result<(), OrderJournalError>
    where
        I: IntoIterator<Item = S>,
        S: AsRef<str>,
    {
        match self {
            OrderJournal::Local(journal) => Ok(journal.delete(kind, ids)?),
            OrderJournal::Replicated(r) => {
                let ids: Vec<String> = ids.into_iter().map(|i| i.as_ref().to_string()).collect();
                for chunk in ids.chunks(MAX_RECORDS_PER_WRITE) {
                    r.run(r.store.delete(kind, chunk))?;
                }
                Ok(())
            }
        }
    }

    /// Reads one record.
    pub fn get<T: DeserializeOwned>(
        &self,
        kind: &str,
        id: &str,
    ) -> Result<Option<T>, OrderJournalError> {
        match self {
            OrderJournal::Local(journal) => Ok(journal.get(kind, id)?),
            OrderJournal::Replicated(r) => r.run(r.store.get(kind, id)),
        }
    }

    /// Reads the records of `kind` with these ids, in the order asked; absent ones are
    /// left out.
    pub fn get_many<T, I, S>(
        &self,
        kind: &str,
        ids: I,
    ) -> Result<Vec<(String, T)>, OrderJournalError>
    where
        T: DeserializeOwned,
        I: IntoIterator<Item = S>,
        S: AsRef<str>,
    {
        match self {
            OrderJournal::Local(journal) => Ok(journal.get_many(kind, ids)?),
            OrderJournal::Replicated(r) => {
                let ids: Vec<String> = ids.into_iter().map(|i| i.as_ref().to_string()).collect();
                r.run(r.store.get_many(kind, ids))
            }
        }
    }

    /// Every record of `kind`, by id, handed to `visit` one at a time. (On etcd they are
    /// read whole first, at one revision.)
    pub fn for_each<T: DeserializeOwned>(
        &self,
        kind: &str,
        mut visit: impl FnMut(String, T),
    ) -> Result<(), OrderJournalError> {
        match self {
            OrderJournal::Local(journal) => Ok(journal.for_each(kind, visit)?),
            OrderJournal::Replicated(r) => {
                for (id, value) in r.run(r.store.list::<T>(kind))? {
                    visit(id, value);
                }
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_write_of_a_deposed_holder_is_told_apart() {
        let deposed = OrderJournalError::from(EtcdError::Deposed {
            key: "holarchy/t/order-node/n1/leader".into(),
            epoch: 7,
            holder: "held by host-b at epoch 9".into(),
        });
        assert!(deposed.is_deposed());
        assert!(deposed.to_string().contains("epoch 7"), "{deposed}");
        let unreachable = OrderJournalError::from(EtcdError::Unreachable {
            tried: "http://127.0.0.1:1".into(),
            last: "refused".into(),
        });
        assert!(!unreachable.is_deposed());
    }
}

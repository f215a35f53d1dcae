//! What an order-node's journal holds, as a node that starts serving on it needs it:
//! the orders to host, the finished orders that stay in the journal, the named work
//! orders it made ([`crate::submits`]), and the number of the next order
//! ([`Recovered`]).
//!
//! A node on SQLite, or one that won its leader key on etcd without a copy, reads its
//! journal once ([`recover`]). A standby on etcd keeps a [`Recovery`] hot instead: it
//! applies every record its holder writes as it reads it ([`Recovery::apply`]), so
//! that when it wins it reads only what changed since its last read (docs/reliability.md,
//! "Order-node standby on etcd"). Both sort a record the same way: of a finished order
//! only its number and end are kept, so a day of finished orders is never all in
//! memory.

use std::collections::BTreeMap;

use crate::context::ORDER_RECORD;
use crate::host::{order_number, Ended, Finished, NEXT_RECORD};
use crate::journal::{OrderJournal, OrderJournalError};
use crate::progress::OrderProgress;
use crate::submits::{Submits, Submitted, SUBMIT_RECORD};

/// What the journal holds at start-up.
#[derive(Debug, Default)]
pub struct Recovered {
    /// The orders to host: the unfinished ones, and finished ones whose end was not
    /// recorded.
    pub hosted: Vec<(String, OrderProgress)>,
    /// The finished orders that stay in the journal.
    pub finished: Finished,
    /// The named work orders it made.
    pub submits: Submits,
    /// The number of the next order.
    pub next: u64,
}

/// The journal of node `node` as a starting node needs it, built one record at a time.
#[derive(Debug, Default)]
pub struct Recovery {
    /// The node whose orders these are (order names are `<node>-<number>`).
    node: String,
    /// The orders a starting node hosts, by name: the unfinished ones, and finished
    /// ones whose end was not recorded (an older journal).
    hosted: BTreeMap<String, OrderProgress>,
    /// The finished orders left in the journal: number → when it finished (Unix ms).
    finished: Finished,
    /// The named work orders it made.
    submits: Submits,
    /// The number of the next order, once the journal recorded one.
    next: Option<u64>,
    /// The first record that could not be read, with why: a node that wins with it
    /// reads its journal whole instead, and fails there with the journal's own error.
    unreadable: Option<String>,
}

impl Recovery {
    /// Nothing read yet.
    pub fn new(node: &str) -> Recovery {
        Recovery {
            node: node.to_string(),
            ..Recovery::default()
        }
    }

    /// Sorts one order's progress: a finished order with its end recorded keeps only
    /// its number and end; any other is hosted, replacing what was read of it before.
    pub fn order(&mut self, name: String, progress: OrderProgress) {
        match (
            progress.status.is_final(),
            progress.finished_at,
            order_number(&self.node, &name),
        ) {
            (true, Some(at), Some(number)) => {
                self.hosted.remove(&name);
                let status = progress.status;
                self.finished.insert(number, Ended { at, status });
            }
            _ => {
                self.hosted.insert(name, progress);
            }
        }
    }

    /// Applies records read from the journal on etcd, oldest change first: `key` is
    /// `<kind>/<id>` under the journal, the value its JSON. Records of other kinds are
    /// not the node's state and are passed over.
    pub fn apply(&mut self, records: &[(String, Vec<u8>)]) {
        for (key, value) in records {
            let Some((kind, id)) = key.split_once('/') else {
                continue;
            };
            if kind == ORDER_RECORD {
                match serde_json::from_slice::<OrderProgress>(value) {
                    Ok(progress) => self.order(id.to_string(), progress),
                    Err(e) => self.unreadable(key, e),
                }
            } else if kind == SUBMIT_RECORD {
                match serde_json::from_slice::<Submitted>(value) {
                    Ok(made) => self.submits.insert(id.to_string(), made),
                    Err(e) => self.unreadable(key, e),
                }
            } else if (kind, id) == NEXT_RECORD {
                match serde_json::from_slice::<u64>(value) {
                    Ok(next) => self.next = Some(next),
                    Err(e) => self.unreadable(key, e),
                }
            }
        }
    }

    fn unreadable(&mut self, key: &str, e: serde_json::Error) {
        if self.unreadable.is_none() {
            self.unreadable = Some(format!("{key}: {e}"));
        }
    }

    /// Forgets the finished orders that ended before `before` (Unix ms): the holder's
    /// retention sweep removes them from the journal, and a range of changes does not
    /// show removals, so a standby forgets them by the same rule.
    pub fn forget_finished_before(&mut self, before: u64) {
        self.finished.retain(|_, ended| ended.at >= before);
        self.submits.forget_before(before);
    }

    /// The first record that could not be read, if any.
    pub fn unreadable_record(&self) -> Option<&str> {
        self.unreadable.as_deref()
    }

    /// How many orders it holds: hosted, and finished.
    pub fn counts(&self) -> (usize, usize) {
        (self.hosted.len(), self.finished.len())
    }

    /// What a node starts serving with.
    pub fn into_recovered(self) -> Recovered {
        Recovered {
            hosted: self.hosted.into_iter().collect(),
            finished: self.finished,
            submits: self.submits,
            next: self.next.unwrap_or(1),
        }
    }
}

/// Reads node `node`'s journal whole, one record at a time.
pub fn recover(journal: &OrderJournal, node: &str) -> Result<Recovered, OrderJournalError> {
    let mut recovery = Recovery::new(node);
    journal.for_each::<OrderProgress>(ORDER_RECORD, |name, progress| {
        recovery.order(name, progress)
    })?;
    journal.for_each::<Submitted>(SUBMIT_RECORD, |id, made| recovery.submits.insert(id, made))?;
    let next = journal.get::<u64>(NEXT_RECORD.0, NEXT_RECORD.1)?;
    recovery.next = next;
    Ok(recovery.into_recovered())
}

#[cfg(test)]
mod tests {
    use schemas::HolonId;

    use super::*;

    fn progress(name: &str) -> OrderProgress {
        OrderProgress::new(HolonId::order(name).unwrap(), "breaker", 3)
    }

    fn record(key: &str, value: &impl serde::Serialize) -> (String, Vec<u8>) {
        (key.to_string(), serde_json::to_vec(value).unwrap())
    }

    #[test]
    fn a_followed_journal_keeps_unfinished_orders_whole_and_of_finished_ones_their_end() {
        let mut recovery = Recovery::new("n1");
        let mut ended = progress("n1-1");
        recovery.apply(&[
            record("meta/next_order", &3u64),
            record("order/n1-1", &ended),
            record("order/n1-2", &progress("n1-2")),
            // Not the node's state: passed over.
            record("lease/whatever", &1u64),
        ]);
        assert_eq!(recovery.counts(), (2, 0));
        // n1-1 ends: of it only its number and end are kept from then on.
        ended.fail("no plan".into());
        let at = 1_700_000_000_000;
        ended.finished_at = Some(at);
        recovery.apply(&[record("order/n1-1", &ended)]);
        assert_eq!(recovery.counts(), (1, 1));
        assert_eq!(recovery.unreadable_record(), None);
        // Forgotten by the holder's retention rule.
        recovery.forget_finished_before(at);
        assert_eq!(recovery.counts(), (1, 1));
        recovery.forget_finished_before(at + 1);
        assert_eq!(recovery.counts(), (1, 0));
        let recovered = recovery.into_recovered();
        assert_eq!(recovered.hosted.len(), 1);
        assert_eq!(recovered.hosted[0].0, "n1-2");
        assert!(recovered.finished.is_empty());
        assert_eq!(recovered.next, 3);
    }

    #[test]
    fn a_record_that_cannot_be_read_is_named_and_the_rest_is_applied() {
        let mut recovery = Recovery::new("n1");
        recovery.apply(&[
            ("order/n1-1".to_string(), b"{not json".to_vec()),
            record("order/n1-2", &progress("n1-2")),
        ]);
        assert!(
            recovery
                .unreadable_record()
                .is_some_and(|why| why.starts_with("order/n1-1: ")),
            "{:?}",
            recovery.unreadable_record()
        );
        assert_eq!(recovery.counts(), (1, 0));
        // No next number recorded yet: the first order is 1.
        assert_eq!(recovery.into_recovered().next, 1);
    }

    #[test]
    fn a_finished_order_without_a_recorded_end_is_hosted() {
        // An older journal: ended, but not stamped; or a name not of this node.
        let mut old = progress("n1-1");
        old.fail("no plan".into());
        old.finished_at = None;
        let mut other = progress("n2-1");
        other.fail("no plan".into());
        other.finished_at = Some(1_700_000_000_000);
        let mut recovery = Recovery::new("n1");
        recovery.order("n1-1".into(), old);
        recovery.order("n2-1".into(), other);
        assert_eq!(recovery.counts(), (2, 0));
    }

    #[test]
    fn a_followed_journal_keeps_the_named_work_orders_as_long_as_finished_orders() {
        let made = |at: u64| Submitted {
            product: "breaker".into(),
            count: 2,
            first: 1,
            at,
        };
        let mut recovery = Recovery::new("n1");
        recovery.apply(&[
            record("submit/mes-1", &made(1_000)),
            record("submit/mes-2", &made(2_000)),
        ]);
        recovery.forget_finished_before(1_500);
        let recovered = recovery.into_recovered();
        assert!(recovered.submits.get("mes-1").is_none());
        assert_eq!(recovered.submits.get("mes-2"), Some(&made(2_000)));
    }
}

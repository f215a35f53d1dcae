//! The work orders a node made under a name their submitter gave them (`submit_id`),
//! so that a submitter that asks again (an answer that came too late, an MES that
//! retries) gets the orders made the first time, and no more are made.
//!
//! Each is journalled with its orders, in the same commit: a node that takes over the
//! journal (a restart, a standby) knows it too. It is remembered as long as finished
//! orders are (`keep_finished`): the retention sweep forgets it with the orders of its
//! age.

use std::collections::BTreeMap;

use schemas::WorkOrder;
use serde::{Deserialize, Serialize};

/// The journal records' kind: one record per named work order, by its `submit_id`.
pub const SUBMIT_RECORD: &str = "submit";

/// What a named work order made.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Submitted {
    /// Its product.
    pub product: String,
    /// How many orders it made.
    pub count: u32,
    /// The number of its first order; the others follow it.
    pub first: u64,
    /// When it was made (Unix ms).
    pub at: u64,
}

impl Submitted {
    /// The names of the orders it made on node `node`.
    pub fn orders(&self, node: &str) -> Vec<String> {
        (self.first..self.first + u64::from(self.count))
            .map(|n| crate::host::order_name_of(node, n))
            .collect()
    }

    /// Whether `work` asks for what it made (a submitter's repeat), rather than for
    /// something else under the same name (refused: names are not reused).
    pub fn is_repeated_by(&self, work: &WorkOrder) -> bool {
        self.product == work.product && self.count == work.count
    }
}

/// The named work orders a node remembers, by name.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Submits(BTreeMap<String, Submitted>);

impl Submits {
    /// What the work order named `id` made, if the node remembers it.
    pub fn get(&self, id: &str) -> Option<&Submitted> {
        self.0.get(id)
    }

    /// Remembers what the work order named `id` made.
    pub fn insert(&mut self, id: String, made: Submitted) {
        self.0.insert(id, made);
    }

    /// The names of the work orders made before `before` (Unix ms), at most `at_most`.
    pub fn made_before(&self, before: u64, at_most: usize) -> Vec<String> {
        self.0
            .iter()
            .filter(|(_, made)| made.at < before)
            .map(|(id, _)| id.clone())
            .take(at_most)
            .collect()
    }

    /// Forgets the work orders named `ids`.
    pub fn forget(&mut self, ids: &[String]) {
        for id in ids {
            self.0.remove(id);
        }
    }

    /// Forgets every work order made before `before` (Unix ms).
    pub fn forget_before(&mut self, before: u64) {
        self.0.retain(|_, made| made.at >= before);
    }

    /// How many it remembers.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether it remembers none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn made(at: u64) -> Submitted {
        Submitted {
            product: "part".into(),
            count: 3,
            first: 17,
            at,
        }
    }

    #[test]
    fn a_named_work_order_gives_its_orders_and_knows_its_repeat() {
        let made = made(1000);
        assert_eq!(made.orders("n1"), ["n1-17", "n1-18", "n1-19"]);
        let mut work: WorkOrder =
            serde_json::from_str(r#"{"product": "part", "count": 3}"#).unwrap();
        assert!(made.is_repeated_by(&work));
        work.count = 4;
        assert!(!made.is_repeated_by(&work));
        work.count = 3;
        work.product = "other".into();
        assert!(!made.is_repeated_by(&work));
    }

    #[test]
    fn the_oldest_are_forgotten() {
        let mut submits = Submits::default();
        submits.insert("a".into(), made(1000));
        submits.insert("b".into(), made(2000));
        submits.insert("c".into(), made(3000));
        assert_eq!(submits.made_before(2500, 10), ["a", "b"]);
        assert_eq!(submits.made_before(2500, 1), ["a"]);
        submits.forget(&["a".to_string()]);
        assert!(submits.get("a").is_none());
        submits.forget_before(3000);
        assert_eq!(submits.len(), 1);
        assert!(submits.get("c").is_some());
    }
}

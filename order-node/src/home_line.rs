//! Who waits outside the cell for a home (docs/material-flow.md, "Reservations"): the
//! parts of a node's orders that have no buffer place yet, with their orders'
//! priorities. A part does not take a freed home while a part of a higher priority
//! waits for one: a rush order's part enters before the older parts of lower priority
//! that waited outside. Among parts of one priority nothing changes: whoever looks
//! first takes the place, at the spaced pace of the idle orders (a thousand parts
//! waiting outside cost next to nothing).
//!
//! A part of a higher priority than another waiting one looks whenever a place frees
//! up (every part skipping the place for it would otherwise leave it empty until its
//! own spaced look).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use schemas::HolonId;

/// The parts waiting for a home, shared by a node's orders.
#[derive(Debug, Clone, Default)]
pub struct HomeLine {
    /// Each waiting part's order and its priority.
    waiting: Arc<Mutex<HashMap<HolonId, i32>>>,
}

impl HomeLine {
    /// `order`'s part waits for a home with its order's `priority`, until the ticket
    /// is dropped.
    pub fn wait(&self, order: &HolonId, priority: i32) -> HomeTicket {
        self.lock().insert(order.clone(), priority);
        HomeTicket {
            line: self.clone(),
            order: order.clone(),
            priority,
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<HolonId, i32>> {
        // A panic while holding the map leaves it whole (inserts and removes only).
        self.waiting.lock().unwrap_or_else(|e| e.into_inner())
    }
}

/// A part's place among those waiting for a home.
#[derive(Debug)]
pub struct HomeTicket {
    line: HomeLine,
    order: HolonId,
    priority: i32,
}

impl HomeTicket {
    /// Whether a part of a higher priority waits for a home: this one leaves a freed
    /// place to it.
    pub fn outranked(&self) -> bool {
        self.line.lock().values().any(|p| *p > self.priority)
    }

    /// Whether a part of a lower priority waits too: this one looks whenever a place
    /// frees up, since they leave it the place.
    pub fn ahead_of_others(&self) -> bool {
        self.line.lock().values().any(|p| *p < self.priority)
    }
}

impl Drop for HomeTicket {
    fn drop(&mut self) {
        self.line.lock().remove(&self.order);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn order(n: u32) -> HolonId {
        HolonId::order(&format!("orders1-{n}")).unwrap()
    }

    #[test]
    fn a_part_leaves_a_home_to_a_part_of_a_higher_priority_and_only_to_it() {
        let line = HomeLine::default();
        let normal = line.wait(&order(1), 0);
        let other = line.wait(&order(2), 0);
        assert!(!normal.outranked() && !normal.ahead_of_others());
        let rush = line.wait(&order(3), 10);
        assert!(normal.outranked() && other.outranked());
        assert!(!rush.outranked() && rush.ahead_of_others());
        // The rush part has its home: the others look as before.
        drop(rush);
        assert!(!normal.outranked());
        drop(other);
        drop(normal);
        assert!(line.lock().is_empty());
    }
}

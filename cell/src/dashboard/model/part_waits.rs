//! How long each running order's part has stayed where it is, for the `part_waits`
//! alarm: a part in the cell that has not changed place for longer than the bound
//! (`cell dashboard --part-wait-alarm-s`) waits for something that does not come (a
//! deadlock, a station that never frees a place, a move nobody ends). Pure: the times
//! come with the inputs.

use std::collections::BTreeMap;

use schemas::{HolonId, OrderSnapshot, PartPlace};

/// The bound unless the dashboard is told otherwise: 5 minutes.
pub const DEFAULT_BOUND_MS: u64 = 300_000;

/// Where each running order's part is and since when.
#[derive(Debug, Clone)]
pub struct PartWaits {
    /// Beyond this a part waits too long (ms).
    bound_ms: u64,
    /// Each running order whose part is in the cell: where its part is, since when
    /// (Unix ms). An order leaves it when it ends or its part leaves the cell.
    since: BTreeMap<HolonId, (PartPlace, u64)>,
}

impl Default for PartWaits {
    fn default() -> Self {
        PartWaits::new(DEFAULT_BOUND_MS)
    }
}

impl PartWaits {
    pub fn new(bound_ms: u64) -> PartWaits {
        PartWaits {
            bound_ms,
            since: BTreeMap::new(),
        }
    }

    /// An order's snapshot at `at`: true when its part is no longer where it waited
    /// (moved, left the cell, or its order ended), so that its alarm clears.
    pub fn seen(&mut self, snapshot: &OrderSnapshot, at: u64) -> bool {
        let in_cell = snapshot.part.as_ref().filter(|p| {
            !snapshot.status.is_final()
                && !matches!(p, PartPlace::Outside | PartPlace::Shipped { .. })
        });
        let Some(place) = in_cell else {
            return self.since.remove(&snapshot.holon).is_some();
        };
        match self.since.get(&snapshot.holon) {
            Some((held, _)) if held == place => false,
            Some(_) => {
                self.since
                    .insert(snapshot.holon.clone(), (place.clone(), at));
                true
            }
            None => {
                self.since
                    .insert(snapshot.holon.clone(), (place.clone(), at));
                false
            }
        }
    }

    /// The parts that have waited beyond the bound as of `now`: each order, and what
    /// its alarm says.
    pub fn overdue(&self, now: u64) -> Vec<(HolonId, String)> {
        self.since
            .iter()
            .filter(|(_, (_, since))| now.saturating_sub(*since) > self.bound_ms)
            .map(|(order, (place, since))| {
                let message = format!(
                    "{order}'s part has been {place} for {} s (the bound is {} s): it waits for something that does not come",
                    now.saturating_sub(*since) / 1000,
                    self.bound_ms / 1000
                );
                (order.clone(), message)
            })
            .collect()
    }
}

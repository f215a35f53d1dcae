//! What the model counts for `/metrics`: totals since the dashboard started, and how long
//! each service type's jobs took on each resource.

use std::collections::BTreeMap;

/// The upper bounds of the step-duration histograms' buckets, in seconds.
pub const STEP_BUCKETS: [f64; 10] = [0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0];

/// How long the jobs of one service type took on one resource.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct StepHistogram {
    /// Jobs per bucket of [`STEP_BUCKETS`] (not cumulative), and one more for longer.
    pub buckets: [u64; STEP_BUCKETS.len() + 1],
    pub sum_seconds: f64,
    pub count: u64,
}

impl StepHistogram {
    pub(super) fn observe(&mut self, seconds: f64) {
        let bucket = STEP_BUCKETS
            .iter()
            .position(|bound| seconds <= *bound)
            .unwrap_or(STEP_BUCKETS.len());
        self.buckets[bucket] += 1;
        self.sum_seconds += seconds;
        self.count += 1;
    }
}

/// Totals since the dashboard started, for `/metrics`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Counters {
    pub orders_done: u64,
    pub orders_failed: u64,
    pub orders_scrapped: u64,
    /// Entries into fault or estop, per resource.
    pub controller_faults: BTreeMap<String, u64>,
    /// Bookings seen appear on agendas, per resource.
    pub bookings: BTreeMap<String, u64>,
    /// How long jobs took, per (service type, resource): from the snapshot that showed
    /// the job running to the one that showed it ended (jobs seen starting only).
    pub steps: BTreeMap<(String, String), StepHistogram>,
}

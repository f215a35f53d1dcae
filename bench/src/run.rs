//! What every section shares: the run (its directory, cell, floors, simulator and
//! `robot1`), our figures set beside the Erlang peer's, and the table of figures.

use std::path::PathBuf;
use std::process::Child;
use std::time::Duration;

use holarchy_tests::{Cell, Process, Sim};
use serde_json::Value;

use crate::stats::Latency;

/// The table of figures: each row printed as it is added, and kept as JSON.
pub struct Table {
    pub rows: Vec<(String, String, String)>,
    pub json: serde_json::Map<String, Value>,
}

impl Table {
    pub fn add(&mut self, name: &str, figure: String, baseline: String, data: Value) {
        println!("{name:<46} {figure:<40} {baseline}");
        self.rows.push((name.into(), figure, baseline));
        self.json.insert(name.into(), data);
    }
}

/// What every section shares: the run's directory, the cell (this process is its
/// router), the floors measured first, a controller simulator and `robot1`.
pub struct Run {
    pub dir: PathBuf,
    pub cell: Cell,
    pub table: Table,
    pub floor: Latency,
    pub journal_floor: (Latency, Latency),
    pub sim: Sim,
    pub robot1: Process,
    pub robot1_ready: Duration,
    pub samples: usize,
    pub echo: Child,
    /// Our figures the Erlang peer's are set beside.
    pub ours: Ours,
}

/// Our booking (`process_crash`) and cycle, p50 and p99 in µs, once measured.
#[derive(Default)]
pub struct Ours {
    pub booking: Option<(f64, f64)>,
    /// Booking starting on its turn (what orders do by default).
    pub cycle: Option<(f64, f64)>,
    /// Booking, then a separate `start`.
    pub cycle_by_request: Option<(f64, f64)>,
}

impl Drop for Run {
    fn drop(&mut self) {
        let _ = self.echo.kill();
        let _ = self.echo.wait();
    }
}

impl Run {
    pub fn ratio(&self, latency: &Latency) -> f64 {
        latency.pct(0.5) / self.floor.pct(0.5)
    }
}

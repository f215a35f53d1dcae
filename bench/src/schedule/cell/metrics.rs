//! A cell run's figures, from the plant's trace (every action its controllers ran, in
//! plant time) and the bench's releases: makespan, flow times, tardiness, each
//! station's and the shuttles' utilisation.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{Context, Result};
use robot_bridge::plant::trace::TraceRecord;

/// An order the bench released.
#[derive(Debug, Clone, serde::Serialize)]
pub struct Released {
    /// The order's name (its part's name in the plant).
    pub order: String,
    pub product: String,
    /// When, in plant ms.
    pub at_ms: u64,
    /// When it is due, in plant ms, if it is.
    pub due_ms: Option<u64>,
    pub rush: bool,
}

/// How the released orders ended: each status's count (`done`, `scrapped`, ...), and
/// how often their parts were sent back (reworked or recovered), from the orders'
/// snapshots.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct Endings {
    pub by_status: BTreeMap<String, usize>,
    pub reworks: u32,
}

impl Endings {
    /// The endings of the `released` orders among `orders`, if every one has ended.
    pub fn of(orders: &[schemas::OrderSnapshot], released: &[Released]) -> Option<Endings> {
        let mut endings = Endings::default();
        let mut ended = 0;
        for order in orders {
            if order.status.is_final() && released.iter().any(|r| r.order == order.holon.name()) {
                ended += 1;
                *endings
                    .by_status
                    .entry(order.status.as_str().to_string())
                    .or_default() += 1;
                endings.reworks += order.reworks;
            }
        }
        (ended == released.len()).then_some(endings)
    }

    /// As the bench prints it: `13 done, 1 scrapped; 3 sent back`.
    pub fn summary(&self) -> String {
        let statuses: Vec<String> = self
            .by_status
            .iter()
            .map(|(status, n)| format!("{n} {status}"))
            .collect();
        format!("{}; {} sent back", statuses.join(", "), self.reworks)
    }
}

/// What one run of a cell scenario measured, in plant time.
#[derive(Debug, Clone, serde::Serialize)]
pub struct CellFigures {
    /// From the first release to the last part's exit.
    pub makespan_ms: u64,
    /// Release to exit, mean over the orders whose part left.
    pub mean_flow_ms: u64,
    /// The rush orders' mean flow, if there were any.
    pub rush_mean_flow_ms: Option<u64>,
    /// Mean of max(0, exit - due) over the orders with a due time, and how many were
    /// late.
    pub mean_tardiness_ms: u64,
    pub late: usize,
    /// Per station: its busy time over the makespan.
    pub utilisation: BTreeMap<String, f64>,
    /// The transporter's moves' time over the makespan times its shuttles.
    pub shuttle_utilisation: f64,
    /// Orders whose part left the cell, of those released.
    pub finished: usize,
    pub released: usize,
}

/// Reads the plant's trace file.
pub fn read_trace(path: &Path) -> Result<Vec<TraceRecord>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| serde_json::from_str(l).with_context(|| format!("{}: {l}", path.display())))
        .collect()
}

/// The figures of a run: `transporter` is the resource whose moves are the shuttles'
/// (with `shuttles` of them), the others are stations.
pub fn figures(
    trace: &[TraceRecord],
    released: &[Released],
    transporter: &str,
    shuttles: u32,
) -> CellFigures {
    let start = released.iter().map(|r| r.at_ms).min().unwrap_or(0);
    // A part's exit: the end of its last action (its move to the exit).
    let mut exit: BTreeMap<&str, u64> = BTreeMap::new();
    for record in trace {
        if let Some(part) = &record.part {
            let at = exit.entry(part.as_str()).or_default();
            *at = (*at).max(record.end_ms);
        }
    }
    let end = released
        .iter()
        .filter_map(|r| exit.get(r.order.as_str()))
        .copied()
        .max()
        .unwrap_or(start);
    let makespan_ms = end.saturating_sub(start);
    let flows: Vec<(u64, &Released)> = released
        .iter()
        .filter_map(|r| {
            exit.get(r.order.as_str())
                .map(|e| (e.saturating_sub(r.at_ms), r))
        })
        .collect();
    let mean = |values: Vec<u64>| {
        let n = values.len() as u64;
        (n > 0).then(|| values.iter().sum::<u64>() / n)
    };
    let tardy: Vec<u64> = released
        .iter()
        .filter_map(|r| {
            let due = r.due_ms?;
            let done = exit.get(r.order.as_str()).copied().unwrap_or(end);
            Some(done.saturating_sub(due))
        })
        .collect();
    let mut busy: BTreeMap<String, u64> = BTreeMap::new();
    for record in trace.iter().filter(|r| r.begin_ms >= start) {
        *busy.entry(record.resource.clone()).or_default() +=
            record.end_ms.saturating_sub(record.begin_ms);
    }
    let span = makespan_ms.max(1) as f64;
    let moved = busy.remove(transporter).unwrap_or(0);
    CellFigures {
        makespan_ms,
        mean_flow_ms: mean(flows.iter().map(|(f, _)| *f).collect()).unwrap_or(0),
        rush_mean_flow_ms: mean(
            flows
                .iter()
                .filter(|(_, r)| r.rush)
                .map(|(f, _)| *f)
                .collect(),
        ),
        mean_tardiness_ms: mean(tardy.clone()).unwrap_or(0),
        late: tardy.iter().filter(|t| **t > 0).count(),
        utilisation: busy
            .into_iter()
            .map(|(station, ms)| (station, ms as f64 / span))
            .collect(),
        shuttle_utilisation: moved as f64 / (span * f64::from(shuttles.max(1))),
        finished: flows.len(),
        released: released.len(),
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A trace record of `part` at `resource` (tests of the figures read from traces).
    pub(crate) fn record(resource: &str, part: &str, begin_ms: u64, end_ms: u64) -> TraceRecord {
        TraceRecord {
            resource: resource.into(),
            action: "x".into(),
            part: Some(part.into()),
            carrier: None,
            begin_ms,
            end_ms,
            done: true,
        }
    }

    #[test]
    fn figures_count_from_the_first_release_to_the_last_exit() {
        let released = vec![
            Released {
                order: "o-1".into(),
                product: "b".into(),
                at_ms: 1_000,
                due_ms: Some(5_000),
                rush: false,
            },
            Released {
                order: "o-2".into(),
                product: "b".into(),
                at_ms: 2_000,
                due_ms: Some(20_000),
                rush: true,
            },
        ];
        let trace = vec![
            record("belt", "o-1", 1_000, 2_000),
            record("m1", "o-1", 2_000, 4_000),
            record("belt", "o-1", 4_000, 7_000),
            record("belt", "o-2", 2_000, 3_000),
            record("m1", "o-2", 4_000, 6_000),
            record("belt", "o-2", 6_000, 11_000),
        ];
        let f = figures(&trace, &released, "belt", 2);
        assert_eq!(f.makespan_ms, 10_000);
        assert_eq!(f.mean_flow_ms, (6_000 + 9_000) / 2);
        assert_eq!(f.rush_mean_flow_ms, Some(9_000));
        // o-1 left 2 s late, o-2 in time.
        assert_eq!((f.mean_tardiness_ms, f.late), (1_000, 1));
        assert_eq!(f.utilisation["m1"], 0.4);
        // 10 s of moves over 10 s times 2 shuttles.
        assert_eq!(f.shuttle_utilisation, 0.5);
        assert_eq!((f.finished, f.released), (2, 2));
    }
}

//! The running schedule, as the page draws it (a Gantt chart): per resource, the jobs
//! it ran and runs, each with its order, service and product, from when it began to
//! when it ended, and the bookings waiting on its agenda.
//!
//! It is read from the resources' snapshots alone: a job that appears among a
//! snapshot's running ones (`current`, `more_running`) opens a bar at its start (the
//! execution's `started_at`, or the snapshot's time when the job was running before
//! the dashboard saw it); a job gone from them closes its bar at the snapshot's time. A
//! resource that vanishes closes its open bars then and there (cut short).
//!
//! | input | what changes |
//! |---|---|
//! | a resource's snapshot with a job not yet drawn running | a bar opens at the job's start |
//! | a resource's snapshot without a job drawn running | its bar ends at the snapshot's time |
//! | a resource vanishes | its running bars end, marked cut |
//!
//! Each resource keeps its last [`BARS_KEPT`] bars, so the model stays bounded however
//! long the cell runs; the view sends the bars of the last [`WINDOW_PLANT_MS`] of plant
//! time.

use std::collections::{BTreeMap, VecDeque};

use schemas::{CurrentJobView, HolonId, ResourceSnapshot};
use serde::Serialize;

/// How many bars each resource keeps (its newest).
pub const BARS_KEPT: usize = 200;

/// How much plant time the page's chart spans, back from now: fifteen minutes of the
/// plant (fifteen minutes of wall time at real time, 45 s at 20x).
pub const WINDOW_PLANT_MS: u64 = 15 * 60 * 1000;

/// One job on one resource.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Bar {
    /// The order (its holon's name) the job is for.
    pub order: String,
    pub conversation_id: String,
    pub service_type: String,
    /// The job's program (product variant), if it names one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
    /// When it began, Unix ms (wall time).
    pub start: u64,
    /// When it ended, Unix ms; None while it runs.
    pub end: Option<u64>,
    /// Ended because its resource vanished, not seen finishing.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub cut: bool,
}

/// One resource's row.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Row {
    /// Its bars, oldest first.
    pub bars: VecDeque<Bar>,
    /// Bookings waiting on its agenda.
    pub waiting: usize,
    /// The plant's time scale the resource runs at (1: real time).
    pub time_scale: f64,
}

/// The running schedule as the page draws it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ScheduleView {
    /// How much plant time the chart spans back from now ([`WINDOW_PLANT_MS`]).
    pub window_plant_ms: u64,
    /// Each resource's name and row, its bars within the window.
    pub rows: Vec<(String, Row)>,
}

/// Every resource's row.
#[derive(Debug, Clone, Default)]
pub struct Schedule {
    rows: BTreeMap<HolonId, Row>,
}

impl Schedule {
    /// Reads a resource's snapshot taken at `at`: whether a row changed.
    pub fn resource(&mut self, snapshot: &ResourceSnapshot, at: u64) -> bool {
        let row = self.rows.entry(snapshot.holon.clone()).or_default();
        let before = row.clone();
        let running: Vec<&CurrentJobView> = snapshot
            .current
            .iter()
            .chain(&snapshot.more_running)
            .collect();
        for bar in row.bars.iter_mut().filter(|b| b.end.is_none()) {
            if !running
                .iter()
                .any(|job| job.conversation_id == bar.conversation_id)
            {
                bar.end = Some(at.max(bar.start));
            }
        }
        for job in running {
            let drawn = row
                .bars
                .iter()
                .any(|b| b.end.is_none() && b.conversation_id == job.conversation_id);
            if !drawn {
                row.bars.push_back(Bar {
                    order: job.requester.name().to_string(),
                    conversation_id: job.conversation_id.clone(),
                    service_type: job.service_type.clone(),
                    program: job.program.clone(),
                    start: job.started_at.unwrap_or(at).min(at),
                    end: None,
                    cut: false,
                });
            }
        }
        while row.bars.len() > BARS_KEPT {
            row.bars.pop_front();
        }
        row.waiting = snapshot.agenda.len();
        row.time_scale = snapshot.time_scale.unwrap_or(1.0);
        *row != before
    }

    /// A resource vanished at `at`: its running bars end there, cut.
    pub fn vanished(&mut self, holon: &HolonId, at: u64) -> bool {
        let Some(row) = self.rows.get_mut(holon) else {
            return false;
        };
        let mut changed = false;
        for bar in row.bars.iter_mut().filter(|b| b.end.is_none()) {
            bar.end = Some(at.max(bar.start));
            bar.cut = true;
            changed = true;
        }
        changed
    }

    /// The rows as the page draws them at `now`: each resource's bars that end within
    /// the window (its plant time span counted in wall time at the resource's scale).
    pub fn view(&self, now: u64) -> ScheduleView {
        let rows = self
            .rows
            .iter()
            .map(|(holon, row)| {
                let window = (WINDOW_PLANT_MS as f64 / row.time_scale.max(1.0)) as u64;
                let since = now.saturating_sub(window);
                let bars = row
                    .bars
                    .iter()
                    .filter(|b| b.end.is_none_or(|end| end >= since))
                    .cloned()
                    .collect();
                (
                    holon.name().to_string(),
                    Row {
                        bars,
                        waiting: row.waiting,
                        time_scale: row.time_scale,
                    },
                )
            })
            .collect();
        ScheduleView {
            window_plant_ms: WINDOW_PLANT_MS,
            rows,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn robot() -> HolonId {
        HolonId::resource("robot1").unwrap()
    }

    fn job(order: &str, conversation: &str, started_at: Option<u64>) -> CurrentJobView {
        CurrentJobView {
            requester: HolonId::order(order).unwrap(),
            conversation_id: conversation.into(),
            service_type: "pick_n_place".into(),
            step: None,
            program: Some("b".into()),
            started_at,
        }
    }

    fn snapshot(running: Vec<CurrentJobView>, scale: Option<f64>) -> ResourceSnapshot {
        let mut running = running.into_iter();
        ResourceSnapshot {
            state: schemas::ResourceState::Free,
            controller: schemas::ControllerStatus::Ready,
            current: running.next(),
            more_running: running.collect(),
            time_scale: scale,
            ..ResourceSnapshot::blank(robot())
        }
    }

    #[test]
    fn a_job_is_a_bar_from_its_start_to_the_snapshot_without_it() {
        let mut s = Schedule::default();
        assert!(s.resource(&snapshot(vec![job("o-1", "c1", Some(900))], None), 1_000));
        // The same job again: nothing new.
        assert!(!s.resource(&snapshot(vec![job("o-1", "c1", Some(900))], None), 1_500));
        // Another beside it (a conveyor's second pallet), then the first ends.
        s.resource(
            &snapshot(
                vec![job("o-1", "c1", Some(900)), job("o-2", "c2", None)],
                None,
            ),
            2_000,
        );
        assert!(s.resource(&snapshot(vec![job("o-2", "c2", None)], None), 3_000));
        let rows = s.view(3_000).rows;
        let bars: Vec<(&str, u64, Option<u64>)> = rows[0]
            .1
            .bars
            .iter()
            .map(|b| (b.order.as_str(), b.start, b.end))
            .collect();
        assert_eq!(bars, vec![("o-1", 900, Some(3_000)), ("o-2", 2_000, None)]);
    }

    #[test]
    fn a_vanished_resource_cuts_its_running_bars() {
        let mut s = Schedule::default();
        s.resource(&snapshot(vec![job("o-1", "c1", Some(100))], None), 200);
        assert!(s.vanished(&robot(), 700));
        assert!(!s.vanished(&robot(), 800));
        let bar = &s.view(800).rows[0].1.bars[0];
        assert_eq!((bar.end, bar.cut), (Some(700), true));
    }

    #[test]
    fn each_row_keeps_its_newest_bars_and_the_view_its_window_in_plant_time() {
        let mut s = Schedule::default();
        for i in 0..(BARS_KEPT as u64 + 10) {
            let c = format!("c{i}");
            s.resource(
                &snapshot(vec![job("o-1", &c, Some(i * 1_000))], Some(20.0)),
                i * 1_000,
            );
        }
        s.resource(&snapshot(vec![], Some(20.0)), 1_000_000);
        assert_eq!(s.rows[&robot()].bars.len(), BARS_KEPT);
        // At 20x, fifteen minutes of plant time are 45 s of wall time.
        let rows = s.view(1_000_000 + 45_000).rows;
        assert_eq!(rows[0].1.bars.len(), 1);
        assert_eq!(rows[0].1.time_scale, 20.0);
        assert!(s.view(1_000_000 + 46_000).rows[0].1.bars.is_empty());
    }
}

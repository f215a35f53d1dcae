//! A run's critical path, read back from the plant's trace, and the plant time on it
//! that no plant action accounts for: the control's.
//!
//! An action can begin only once what it needs has ended:
//! - the part's action before it (a part is in one place, doing one thing);
//! - at a station, the station's action before it (a station works one part at a time);
//! - a part's move to a station's port, the departure of the part that was there
//!   before it (a port holds one part, and its place frees when that part's move away
//!   begins).
//!
//! Walking back from the action that ended last, each time to whichever of those ended
//! last, gives the chain of actions that set the makespan. Where a link of the chain
//! began later than what it waited for ended (and from the first release to the
//! chain's first action), the plant waited on the control: its decisions (a part
//! waiting at its port for a place, then riding home) and its latency (a result's
//! message, a proposal round, a booking). A control that takes a fixed wall time
//! to answer takes N times as much plant time at N x: that share of the critical path
//! is the systematic part of a scaled run's drift (docs/scheduling.md, "Drift").

use std::collections::BTreeMap;

use robot_bridge::plant::trace::TraceRecord;

/// A wait on the critical path shorter than this much wall time is the control's
/// latency (messages, rounds, bookings: a few ms each); a longer one is the control's
/// choice (a part waiting at its port, bounded by its move home's plant time) or a
/// timer of its own.
pub const LATENCY_WALL_MS: u64 = 250;

/// The critical path of a run.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CriticalPath {
    /// The actions on it.
    pub actions: usize,
    /// Its plant time between the links, and before the first: the control's.
    pub idle_ms: u64,
    /// The part of `idle_ms` in waits shorter than [`LATENCY_WALL_MS`] of wall time:
    /// the control's latency, which grows with the time scale.
    pub latency_ms: u64,
    /// The longest of those waits.
    pub longest: Option<Wait>,
}

/// One wait on the critical path.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Wait {
    /// How long, in plant ms.
    pub ms: u64,
    /// The action that waited: its resource, its action and its part.
    pub resource: String,
    pub action: String,
    pub part: String,
    /// When it began, plant ms since the first release.
    pub began_ms: u64,
}

/// The critical path of `trace` from `start_ms` (the first release), run at `scale`;
/// `transporter` is the resource whose actions are moves. None for a trace without a
/// part's action.
pub fn critical_path(
    trace: &[TraceRecord],
    start_ms: u64,
    transporter: &str,
    scale: u32,
) -> Option<CriticalPath> {
    let latency_below = LATENCY_WALL_MS * u64::from(scale.max(1));
    let actions: Vec<&TraceRecord> = trace
        .iter()
        .filter(|r| r.part.is_some() && r.begin_ms >= start_ms)
        .collect();
    let needs = needs(&actions, transporter);
    let last = (0..actions.len()).max_by_key(|&i| (actions[i].end_ms, i))?;
    let mut path = CriticalPath {
        actions: 0,
        idle_ms: 0,
        latency_ms: 0,
        longest: None,
    };
    let mut at = last;
    loop {
        path.actions += 1;
        let action = actions[at];
        // What it waited for last, of what had ended (or departed) by its begin.
        let waited = needs[at]
            .iter()
            .filter(|(ready, _)| *ready <= action.begin_ms)
            .max_by_key(|(ready, _)| *ready)
            .copied();
        let ready = waited.map_or(start_ms, |(ready, _)| ready);
        let idle = action.begin_ms.saturating_sub(ready);
        path.idle_ms += idle;
        if idle < latency_below {
            path.latency_ms += idle;
        }
        if idle > 0 && path.longest.as_ref().is_none_or(|w| idle > w.ms) {
            path.longest = Some(Wait {
                ms: idle,
                resource: action.resource.clone(),
                action: action.action.clone(),
                part: action.part.clone().unwrap_or_default(),
                began_ms: action.begin_ms - start_ms,
            });
        }
        match waited {
            Some((_, before)) => at = before,
            None => return Some(path),
        }
    }
}

/// A part's visit to a station, by the indices of its actions: its first action there,
/// its last, its move in and its move away.
type Visit = (usize, usize, Option<usize>, Option<usize>);

/// For each action (by index), what it needs: (when that is ready, plant ms; the
/// action it is).
fn needs(actions: &[&TraceRecord], transporter: &str) -> Vec<Vec<(u64, usize)>> {
    let mut needs = vec![Vec::new(); actions.len()];
    let mut of_part: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, action) in actions.iter().enumerate() {
        of_part
            .entry(action.part.as_deref().unwrap_or_default())
            .or_default()
            .push(i);
    }
    let mut visits: BTreeMap<&str, Vec<Visit>> = BTreeMap::new();
    for own in of_part.values_mut() {
        own.sort_by_key(|&i| (actions[i].begin_ms, actions[i].end_ms));
        for pair in own.windows(2) {
            needs[pair[1]].push((actions[pair[0]].end_ms, pair[0]));
        }
        let mut k = 0;
        while k < own.len() {
            let station = actions[own[k]].resource.as_str();
            if station == transporter {
                k += 1;
                continue;
            }
            let first = k;
            while k + 1 < own.len() && actions[own[k + 1]].resource == station {
                k += 1;
            }
            let move_in = first
                .checked_sub(1)
                .map(|m| own[m])
                .filter(|&m| actions[m].resource == transporter);
            let move_away = own
                .get(k + 1)
                .copied()
                .filter(|&m| actions[m].resource == transporter);
            visits
                .entry(station)
                .or_default()
                .push((own[first], own[k], move_in, move_away));
            k += 1;
        }
    }
    for at_station in visits.values_mut() {
        at_station.sort_by_key(|(first, ..)| actions[*first].begin_ms);
        for pair in at_station.windows(2) {
            let (_, last, _, move_away) = pair[0];
            let (first, _, move_in, _) = pair[1];
            needs[first].push((actions[last].end_ms, last));
            if let (Some(away), Some(into)) = (move_away, move_in) {
                needs[into].push((actions[away].begin_ms, away));
            }
        }
    }
    needs
}

#[cfg(test)]
mod tests {
    use super::super::metrics::tests::record;
    use super::*;

    #[test]
    fn the_path_follows_what_each_action_waited_for_and_counts_the_control_between() {
        let trace = vec![
            // a: in at 100 (released at 0), worked at m1, away at 3_050.
            record("belt", "a", 100, 1_000),
            record("m1", "a", 1_020, 3_000),
            record("belt", "a", 3_050, 4_000),
            // b: rides towards m1 while a is there; its move in begins once a's move
            // away has begun (the port frees as a departs), 30 ms later.
            record("belt", "b", 200, 900),
            record("belt", "b", 3_080, 3_500),
            record("m1", "b", 3_510, 6_000),
            record("belt", "b", 6_040, 7_000),
        ];
        let path = critical_path(&trace, 0, "belt", 1).unwrap();
        // b's exit, b at m1, b's move in (after a's departure), a's move away, a at m1,
        // a's move in.
        assert_eq!(path.actions, 6);
        // 40 + 10 + 30 + 50 + 20 + 100 from the release, each a latency at 1x (under
        // 250 ms of wall time).
        assert_eq!((path.idle_ms, path.latency_ms), (250, 250));
        let longest = path.longest.unwrap();
        assert_eq!((longest.ms, longest.part.as_str()), (100, "a"));
    }

    #[test]
    fn a_station_waits_for_its_work_before() {
        // Two parts at a station with two places: the second's work waits for the
        // first's, not for its own move in.
        let trace = vec![
            record("belt", "a", 0, 100),
            record("belt", "b", 0, 200),
            record("m1", "a", 100, 1_100),
            record("m1", "b", 1_150, 2_150),
        ];
        let path = critical_path(&trace, 0, "belt", 1).unwrap();
        assert_eq!(path.actions, 3);
        assert_eq!(path.idle_ms, 50);
    }

    #[test]
    fn a_wait_is_latency_below_a_quarter_second_of_wall_time() {
        let trace = vec![record("belt", "a", 0, 100), record("m1", "a", 3_100, 4_000)];
        // 3 s of plant time before m1: a choice at 1x, latency at 20x (150 ms of wall).
        let real = critical_path(&trace, 0, "belt", 1).unwrap();
        assert_eq!((real.idle_ms, real.latency_ms), (3_000, 0));
        let scaled = critical_path(&trace, 0, "belt", 20).unwrap();
        assert_eq!((scaled.idle_ms, scaled.latency_ms), (3_000, 3_000));
    }

    #[test]
    fn no_part_no_path() {
        assert_eq!(critical_path(&[], 0, "belt", 1), None);
    }
}

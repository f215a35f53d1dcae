//! The reconnect backoff, checked from the controller's side: robot-sim's log of the
//! connections it accepted and of the commands begun on each, against the rule of
//! docs/dialects.md section 4.6 (the holon-node's `component::interfacing`): the first
//! pause `reconnect_interval_ms`; after an attempt that failed or a connection that did
//! not serve, twice the last, up to `reconnect_max_ms`; after a connection that served
//! (a step answered on it, or up at least `reconnect_max_ms`), back to the first.
//!
//! What robot-sim cannot see (attempts refused while it was down between two runs) only
//! lengthens the holon's pauses, and a connection is taken as served when a command
//! began on it (more generous than the holon, which wants it answered): the pauses
//! checked are the least the rule allows, so a gap shorter than that is a holon that
//! reconnected too soon.

use std::time::Duration;

use serde::Serialize;

/// One connection robot-sim accepted.
#[derive(Debug, Clone)]
pub struct Connection {
    /// Seconds (of the day, UTC) it was accepted.
    pub start: f64,
    /// Seconds it ended (None: still up when robot-sim stopped).
    pub end: Option<f64>,
    /// Commands begun on it.
    pub commands: u64,
    peer: String,
}

/// The seconds of the day of a tracing line's timestamp (`2026-11-26T12:22:12.768431Z`).
fn seconds_of(line: &str) -> Option<f64> {
    let stamp = line.split_whitespace().next()?;
    let time = stamp.split_once('T')?.1.strip_suffix('Z')?;
    let mut parts = time.split(':');
    let (h, m, s) = (parts.next()?, parts.next()?, parts.next()?);
    Some(h.parse::<f64>().ok()? * 3600.0 + m.parse::<f64>().ok()? * 60.0 + s.parse::<f64>().ok()?)
}

/// The connections of one robot-sim run, from its stderr.
pub fn connections(log: &str) -> Vec<Connection> {
    let mut found: Vec<Connection> = Vec::new();
    let mut day = 0.0;
    let mut last = 0.0;
    for line in log.lines() {
        let Some(mut t) = seconds_of(line) else {
            continue;
        };
        t += day;
        if t + 3600.0 < last {
            // Past midnight.
            day += 86_400.0;
            t += 86_400.0;
        }
        last = t;
        let peer = line
            .split_whitespace()
            .find_map(|w| w.strip_prefix("peer="))
            .unwrap_or("")
            .to_string();
        if line.contains("bridge connected") {
            found.push(Connection {
                start: t,
                end: None,
                commands: 0,
                peer,
            });
        } else if line.contains("bridge disconnected") || line.contains("connection ended with") {
            if let Some(c) = found
                .iter_mut()
                .rev()
                .find(|c| c.peer == peer && c.end.is_none())
            {
                c.end = Some(t);
            }
        } else if line.contains("robot_bridge::sim::session: command ") {
            if let Some(c) = found.iter_mut().rev().find(|c| c.end.is_none()) {
                c.commands += 1;
            }
        }
    }
    found
}

/// The rule's parameters, and how much earlier than its pause a connection may be seen
/// (robot-sim logs a connection's end once the action under way completes).
#[derive(Debug, Clone, Copy)]
pub struct Rule {
    pub interval: Duration,
    pub max: Duration,
    pub tolerance: Duration,
}

/// One run's connections judged.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Judged {
    pub connections: u64,
    /// Connections that served (a command began on it, or it was up `max`).
    pub served: u64,
    /// The most connections the rule allows in the run's time with that many served.
    pub allowed: u64,
    /// Reconnections sooner than the rule's least pause: (gap ms, least pause ms).
    pub too_soon: Vec<(u64, u64)>,
    /// The longest pause seen between two connections, in ms.
    pub longest_pause_ms: u64,
}

impl Rule {
    fn served(&self, c: &Connection) -> bool {
        let lasted = c.end.map_or(0.0, |end| end - c.start);
        c.commands > 0 || lasted + self.tolerance.as_secs_f64() >= self.max.as_secs_f64()
    }

    /// Judges one run's connections (`lasted`: how long robot-sim ran).
    pub fn judge(&self, connections: &[Connection], lasted: Duration) -> Judged {
        let mut judged = Judged {
            connections: connections.len() as u64,
            ..Judged::default()
        };
        let mut backoff = holon::Backoff::new(self.interval, self.max);
        for pair in connections.windows(2) {
            let (before, next) = (&pair[0], &pair[1]);
            if self.served(before) {
                backoff.reset();
            }
            let least = backoff.next_pause();
            let Some(end) = before.end else { continue };
            let gap = (next.start - end).max(0.0);
            judged.longest_pause_ms = judged.longest_pause_ms.max((gap * 1000.0).round() as u64);
            if gap + self.tolerance.as_secs_f64() < least.as_secs_f64() {
                judged
                    .too_soon
                    .push(((gap * 1000.0).round() as u64, least.as_millis() as u64));
            }
        }
        judged.served = connections.iter().filter(|c| self.served(c)).count() as u64;
        judged.allowed = self.allowed(lasted, judged.served);
        judged
    }

    /// The most connections the rule allows within `time` when `served` of them served:
    /// after each served one the pause is `interval`; the others' pauses grow along a
    /// chain that each served connection starts again (the first chain from `interval`,
    /// the others from twice it, as after a reset the first unserved pause is doubled).
    pub fn allowed(&self, time: Duration, served: u64) -> u64 {
        let mut left = time.as_secs_f64() - served as f64 * self.interval.as_secs_f64();
        let mut unserved = 0u64;
        if left < 0.0 {
            // As many served as the time holds, at `interval` apart.
            return 1 + (time.as_secs_f64() / self.interval.as_secs_f64()) as u64;
        }
        // Cheapest pauses first: one `interval`, then `served + 1` of each doubling.
        let mut pause = self.interval;
        let mut count = 1u64;
        loop {
            let each = pause.as_secs_f64();
            let fits = (left / each).floor() as u64;
            let take = if pause >= self.max {
                fits
            } else {
                fits.min(count)
            };
            unserved += take;
            left -= take as f64 * each;
            if pause >= self.max || take < count {
                break;
            }
            pause = (pause * 2).min(self.max);
            count = served + 1;
        }
        1 + served + unserved
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rule() -> Rule {
        Rule {
            interval: Duration::from_millis(200),
            max: Duration::from_millis(1600),
            tolerance: Duration::from_millis(30),
        }
    }

    #[test]
    fn a_log_gives_each_connection_its_times_and_commands() {
        let log = "\
2026-11-26T12:22:12.768431Z  INFO robot_bridge::sim: bridge connected peer=127.0.0.1:1
2026-11-26T12:22:12.769463Z  INFO robot_bridge::sim::session: command id=1 action=pick n=1
2026-11-26T12:22:12.968621Z  WARN robot_bridge::sim: connection ended with an error peer=127.0.0.1:1 error=x
2026-11-26T12:22:13.068621Z  INFO robot_bridge::sim: bridge connected peer=127.0.0.1:2
2026-11-26T12:22:13.168621Z  INFO robot_bridge::sim: bridge disconnected peer=127.0.0.1:2
";
        let found = connections(log);
        assert_eq!(found.len(), 2);
        assert_eq!(found[0].commands, 1);
        assert_eq!(found[1].commands, 0);
        assert!((found[0].end.unwrap() - found[0].start - 0.2).abs() < 1e-3);
    }

    fn at(start: f64, lasted: f64, commands: u64) -> Connection {
        Connection {
            start,
            end: Some(start + lasted),
            commands,
            peer: String::new(),
        }
    }

    #[test]
    fn unserved_connections_must_back_off_and_a_served_one_starts_over() {
        // Unserved: pauses of 200, 400, 800 ms at least.
        let backed_off = [
            at(0.0, 0.01, 0),
            at(0.21, 0.01, 0),
            at(0.62, 0.01, 0),
            at(1.43, 0.01, 1),
            at(1.64, 0.01, 0),
        ];
        let judged = rule().judge(&backed_off, Duration::from_secs(2));
        assert!(judged.too_soon.is_empty(), "{judged:?}");
        assert_eq!(judged.served, 1);
        // The third came 200 ms after the second: 400 was due.
        let hasty = [at(0.0, 0.01, 0), at(0.21, 0.01, 0), at(0.42, 0.01, 0)];
        let judged = rule().judge(&hasty, Duration::from_secs(1));
        assert_eq!(judged.too_soon, vec![(200, 400)]);
    }

    #[test]
    fn the_allowed_count_grows_with_the_served_connections() {
        // None served, 3.1 s: pauses 200, 400, 800, 1600 fit in 3.0 s: 5 connections.
        assert_eq!(rule().allowed(Duration::from_millis(3100), 0), 5);
        // Served ones each allow a pause of 200 ms more.
        assert!(
            rule().allowed(Duration::from_secs(10), 20)
                > rule().allowed(Duration::from_secs(10), 0)
        );
        assert_eq!(rule().allowed(Duration::from_millis(100), 5), 1);
    }
}

//! The one restart policy of the project, after Erlang/OTP's supervisor: a restart type
//! per child, and a restart intensity over a sliding window.
//!
//! Held by the one supervision machine ([`crate::supervisor::machine`]), which decides
//! for the holons' components ([`crate::Supervisor`]), the order-node's order tasks and
//! `cell up`'s processes; the pause before a restart, where there is one, is a
//! [`crate::Backoff`].
//!
//! | restart type | ends normally | fails (error, panic, crash) |
//! |---|---|---|
//! | `permanent` | restarted (it should run as long as its supervisor) | restarted |
//! | `transient` | not restarted: its work is done | restarted |
//! | `temporary` | not restarted | not restarted |
//!
//! Every restart counts against the intensity: more than `max_restarts` within any
//! `period` and the supervisor gives up (stops everything it supervises, or, for an
//! order, fails it).

use std::collections::VecDeque;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::time::Instant;

/// When a child that ended is started again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RestartType {
    /// Always: it should run as long as its supervisor.
    #[default]
    Permanent,
    /// Only when it failed; ending normally means its work is done.
    Transient,
    /// Never.
    Temporary,
}

impl RestartType {
    /// Whether a child that ended so is restarted.
    pub fn restarts(self, ended_normally: bool) -> bool {
        match self {
            RestartType::Permanent => true,
            RestartType::Transient => !ended_normally,
            RestartType::Temporary => false,
        }
    }
}

impl std::fmt::Display for RestartType {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            RestartType::Permanent => "permanent",
            RestartType::Transient => "transient",
            RestartType::Temporary => "temporary",
        })
    }
}

/// At most `max_restarts` restarts within any `period`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Intensity {
    /// The most restarts allowed within `period`.
    pub max_restarts: u32,
    /// The sliding window restarts are counted over.
    pub period: Duration,
}

impl Default for Intensity {
    /// OTP's default: 1 restart in 5 s is strict; a holon's components get 5 in 10 s.
    fn default() -> Self {
        Intensity {
            max_restarts: 5,
            period: Duration::from_secs(10),
        }
    }
}

/// The restarts made within the last `period`, held against an [`Intensity`].
#[derive(Debug, Clone)]
pub struct RestartWindow {
    intensity: Intensity,
    /// When each restart within the window happened, oldest first.
    restarts: VecDeque<Instant>,
}

impl RestartWindow {
    pub fn new(intensity: Intensity) -> RestartWindow {
        RestartWindow {
            intensity,
            restarts: VecDeque::new(),
        }
    }

    pub fn intensity(&self) -> Intensity {
        self.intensity
    }

    /// Records a restart at `now`: true while within the intensity, false when this one
    /// makes more than `max_restarts` within `period` (give up).
    pub fn allow(&mut self, now: Instant) -> bool {
        self.restarts.push_back(now);
        while self
            .restarts
            .front()
            .is_some_and(|t| now.duration_since(*t) > self.intensity.period)
        {
            self.restarts.pop_front();
        }
        self.restarts.len() <= self.intensity.max_restarts as usize
    }

    /// Restarts within the window as of the last [`RestartWindow::allow`].
    pub fn recent(&self) -> usize {
        self.restarts.len()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn restart_types_follow_otp() {
        assert!(RestartType::Permanent.restarts(true));
        assert!(RestartType::Permanent.restarts(false));
        assert!(!RestartType::Transient.restarts(true));
        assert!(RestartType::Transient.restarts(false));
        assert!(!RestartType::Temporary.restarts(true));
        assert!(!RestartType::Temporary.restarts(false));
    }

    #[test]
    fn more_than_max_restarts_within_the_period_is_refused_and_old_ones_expire() {
        let mut window = RestartWindow::new(Intensity {
            max_restarts: 2,
            period: Duration::from_secs(10),
        });
        let start = Instant::now();
        let at = |s: u64| start + Duration::from_secs(s);
        assert!(window.allow(at(0)));
        assert!(window.allow(at(1)));
        assert!(!window.allow(at(2)), "a third within the period");
        assert!(window.allow(at(13)), "the earlier ones left the window");
        assert_eq!(window.recent(), 1);
    }
}

//! A simulated plant run faster than real time (docs/scheduling.md, "Scaled time"):
//! `plant-sim --time-scale N` runs the plant's processing and travel in 1/N of their
//! durations, and the resource holons of the same cell, started with the same factor,
//! count the plant's durations (their services' nominal durations, their part of the
//! layout's travel) in the same wall time. What the cell reports in plant time is wall
//! time multiplied by N. Network timers (leases, bid windows, timeouts) are not plant
//! time and do not follow it.

use std::fmt;
use std::str::FromStr;
use std::time::Duration;

/// How many times faster than real time the plant runs: 1 is real time.
#[derive(Debug, Clone, Copy, PartialEq, PartialOrd)]
pub struct TimeScale(f64);

/// The largest factor accepted: beyond it a plant's milliseconds round to nothing.
pub const MAX_TIME_SCALE: f64 = 1000.0;

impl TimeScale {
    /// Real time.
    pub const REAL: TimeScale = TimeScale(1.0);

    /// A factor from 1 to [`MAX_TIME_SCALE`] (a plant slower than real time is not a
    /// thing anyone needs from a simulator here).
    pub fn new(factor: f64) -> Result<TimeScale, String> {
        if !factor.is_finite() || !(1.0..=MAX_TIME_SCALE).contains(&factor) {
            return Err(format!(
                "time scale {factor}: must be a number from 1 (real time) to {MAX_TIME_SCALE}"
            ));
        }
        Ok(TimeScale(factor))
    }

    /// The factor.
    pub fn factor(self) -> f64 {
        self.0
    }

    /// Whether it is real time.
    pub fn is_real(self) -> bool {
        self.0 == 1.0
    }

    /// The wall time `plant_ms` of plant time takes, rounded to the ms.
    pub fn wall_ms(self, plant_ms: u64) -> u64 {
        (plant_ms as f64 / self.0).round() as u64
    }

    /// The wall time a plant duration takes (to the microsecond).
    pub fn wall(self, plant: Duration) -> Duration {
        Duration::from_micros((plant.as_micros() as f64 / self.0).round() as u64)
    }

    /// The plant time `wall_ms` of wall time is, rounded to the ms.
    pub fn plant_ms(self, wall_ms: u64) -> u64 {
        (wall_ms as f64 * self.0).round() as u64
    }
}

impl Default for TimeScale {
    fn default() -> Self {
        TimeScale::REAL
    }
}

impl fmt::Display for TimeScale {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)
    }
}

impl FromStr for TimeScale {
    type Err = String;

    fn from_str(text: &str) -> Result<TimeScale, String> {
        let factor: f64 = text
            .trim()
            .parse()
            .map_err(|_| format!("time scale {text:?}: not a number"))?;
        TimeScale::new(factor)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_factor_turns_plant_time_into_wall_time_and_back() {
        let twenty: TimeScale = "20".parse().unwrap();
        assert_eq!(twenty.wall_ms(20_000), 1_000);
        assert_eq!(twenty.plant_ms(1_000), 20_000);
        assert_eq!(
            twenty.wall(Duration::from_millis(150)),
            Duration::from_micros(7_500)
        );
        assert!(TimeScale::REAL.is_real());
        assert_eq!(TimeScale::REAL.wall_ms(123), 123);
        assert_eq!("2.5".parse::<TimeScale>().unwrap().wall_ms(100), 40);
    }

    #[test]
    fn a_factor_out_of_range_is_refused_with_why() {
        for bad in ["0", "0.5", "-3", "1001", "inf", "NaN", "fast", ""] {
            let err = bad.parse::<TimeScale>().unwrap_err();
            assert!(err.contains("time scale"), "{bad}: {err}");
        }
    }
}

//! The statistics of a series of round trips: percentiles, rate, their JSON.

use std::time::Duration;

use serde_json::{json, Value};

/// Latency distribution of a series of round trips.
#[derive(Debug, Clone)]
pub struct Latency {
    pub samples: Vec<Duration>,
    total: Duration,
}

impl Latency {
    pub fn new(mut samples: Vec<Duration>, total: Duration) -> Self {
        samples.sort();
        Latency { samples, total }
    }

    pub fn pct(&self, p: f64) -> f64 {
        if self.samples.is_empty() {
            return f64::NAN;
        }
        let i = ((self.samples.len() as f64 - 1.0) * p).round() as usize;
        self.samples[i].as_secs_f64() * 1e6
    }

    pub fn rate(&self) -> f64 {
        self.samples.len() as f64 / self.total.as_secs_f64()
    }

    /// Its p50 and p99, as the table shows them: `p50 N us, p99 M us`.
    pub fn p50_p99(&self) -> String {
        format!("p50 {:.0} us, p99 {:.0} us", self.pct(0.5), self.pct(0.99))
    }

    pub fn json(&self) -> Value {
        json!({"n": self.samples.len(), "p50_us": self.pct(0.5), "p99_us": self.pct(0.99), "rate_per_s": self.rate()})
    }
}

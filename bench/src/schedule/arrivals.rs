//! A scenario's stream of orders for a seed: the same orders, at the same moments, in
//! every mode.

use std::time::Duration;

use super::Scenario;

/// One order of the stream.
#[derive(Debug, Clone)]
pub(super) struct Arrival {
    /// When it is submitted, from the start of the stream.
    pub(super) at: Duration,
    /// The product ordered.
    pub(super) product: String,
    /// A rush order (the scenario's rush priority).
    pub(super) rush: bool,
}

/// SplitMix64: the orders of a seed, the same in both modes.
struct Random(u64);

impl Random {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// The stream of `seed`: exponential gaps of the scenario's mean interval, products
/// drawn by their weights, every `rush_every`th order a rush.
pub(super) fn arrivals(scenario: &Scenario, seed: u64) -> Vec<Arrival> {
    let mut random = Random(seed);
    let total: u32 = scenario.products.iter().map(|p| p.weight).sum();
    let mut at = Duration::ZERO;
    (0..scenario.orders.count)
        .map(|n| {
            let gap = -(1.0 - random.unit()).ln() * scenario.orders.mean_interval_ms as f64;
            if n > 0 {
                at += Duration::from_secs_f64(gap / 1000.0);
            }
            let mut pick = (random.unit() * total as f64) as u32;
            let product = scenario
                .products
                .iter()
                .find(|p| {
                    if pick < p.weight {
                        true
                    } else {
                        pick -= p.weight;
                        false
                    }
                })
                .unwrap_or(&scenario.products[0]);
            let rush_every = scenario.orders.rush_every;
            Arrival {
                at,
                product: product.name.clone(),
                rush: rush_every > 0 && (n + 1) % rush_every == 0,
            }
        })
        .collect()
}

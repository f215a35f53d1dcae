//! The service cycle of an order whose step needs moves, against the same step without
//! them: one order at a time through the real order-node, from its submission to its
//! end as the node publishes it, alternating the two products order by order.
//!
//! - `moved` (`moves_parts = true`): the order reserves its part's home and a place at
//!   the station's port, books the conveyor to bring the part from the load to the
//!   port, works the step there, then books the conveyor to take it back to the load
//!   (the exit) and releases its places; two moves.
//! - `still`: the same step (a pick and a place, the same controller time) on a station
//!   outside the material flow, with no part to move.

use std::collections::HashSet;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use holarchy_tests::Cell;
use schemas::{OrderSnapshot, OrderStatus};

use crate::stats::Latency;

/// The two series, cycle by cycle.
pub struct Cycles {
    /// Orders whose part moves in and out.
    pub moved: Latency,
    /// Orders of the same step without a part.
    pub still: Latency,
}

/// Submits one order of `product` and waits for the node to publish its end (`done`;
/// anything else fails the run): how long it took.
async fn one_order(
    cell: &Cell,
    states: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    product: &str,
) -> Result<Duration> {
    let t = Instant::now();
    let names: HashSet<String> = cell.submit(product, 1).await?.into_iter().collect();
    loop {
        let sample = tokio::time::timeout(Duration::from_secs(60), states.recv_async())
            .await
            .map_err(|_| anyhow!("an order of {product} did not end within 60 s"))?
            .map_err(|e| anyhow!("{e}"))?;
        let snapshot: OrderSnapshot = serde_json::from_slice(&sample.payload().to_bytes())?;
        if !names.contains(snapshot.holon.name()) {
            continue;
        }
        match snapshot.status {
            OrderStatus::Done => return Ok(t.elapsed()),
            OrderStatus::Running => {}
            other => bail!("{} ended {other:?}: {:?}", snapshot.holon, snapshot.reason),
        }
    }
}

/// `cycles` orders of each product (after 5 of each to warm up), alternating which goes
/// first.
pub async fn cycles(cell: &Cell, moved: &str, still: &str, cycles: usize) -> Result<Cycles> {
    let states = cell
        .session
        .declare_subscriber(cell.keys.order_states())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let (mut with_moves, mut without) = (Vec::new(), Vec::new());
    let (mut moved_total, mut still_total) = (Duration::ZERO, Duration::ZERO);
    for i in 0..cycles + 5 {
        let order = if i % 2 == 0 {
            [moved, still]
        } else {
            [still, moved]
        };
        for product in order {
            let took = one_order(cell, &states, product).await?;
            if i < 5 {
                continue;
            }
            if product == moved {
                with_moves.push(took);
                moved_total += took;
            } else {
                without.push(took);
                still_total += took;
            }
        }
    }
    Ok(Cycles {
        moved: Latency::new(with_moves, moved_total),
        still: Latency::new(without, still_total),
    })
}

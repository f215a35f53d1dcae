//! A move asks no more than it must (docs/material-flow.md, "A move's conversations"):
//! a move that one transporter alone can make is booked on it without a proposal
//! round, and a step whose station proposed when the part was found at its port is
//! booked there without a second round. Real binaries: plant-sim, the conveyor and two
//! stations as holon processes over their own controller connections, an order-node.
//! The test listens to the cell's proposal requests as one more resource would, and
//! answers none.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use holarchy_tests::{FlowCell, CONVEYOR};

/// Counts the proposal requests for each of `services` that reach a listener of the
/// cell's offers (one more offerer that never answers: a round does not wait for it).
struct RoundCounter {
    seen: Arc<Mutex<BTreeMap<String, usize>>>,
    _listeners: Vec<zenoh::query::Queryable<()>>,
}

impl RoundCounter {
    async fn listen(flow: &FlowCell, services: &[&str]) -> RoundCounter {
        let seen = Arc::new(Mutex::new(BTreeMap::new()));
        let mut listeners = Vec::new();
        for &service in services {
            let key = flow.cell.keys.offer(service, "listener");
            let seen = seen.clone();
            let service = service.to_string();
            let listener = flow
                .cell
                .session
                .declare_queryable(&key)
                .callback(move |_query| {
                    // Dropped unanswered: the round's get ends without a reply from it.
                    *seen.lock().unwrap().entry(service.clone()).or_default() += 1;
                })
                .await
                .unwrap();
            listeners.push(listener);
        }
        RoundCounter {
            seen,
            _listeners: listeners,
        }
    }

    fn count(&self, service: &str) -> usize {
        self.seen.lock().unwrap().get(service).copied().unwrap_or(0)
    }
}

/// Three orders of `ab` (drill on station_a, mill on station_b), one after another, on
/// the cell whose only transporter is conveyor1: each order's three moves (in to
/// station_a, on to station_b, out) are booked without one transport round, and each
/// step takes two station rounds (where to go, and once there whether the station
/// still proposes), not three. Every order ends done, each step once, the plant empty.
/// On the build before, the listener saw a transport round for every move and three
/// station rounds a step.
#[tokio::test(flavor = "multi_thread")]
async fn a_move_with_one_transporter_is_booked_without_a_round() {
    let flow = FlowCell::start("t-move-rounds", CONVEYOR).await;
    let rounds = RoundCounter::listen(&flow, &["transport", "drill", "mill"]).await;
    let mut all = Vec::new();
    for _ in 0..3 {
        let orders = flow.cell.submit("ab", 1).await.unwrap();
        flow.wait_ended(&orders, Duration::from_secs(60)).await;
        all.extend(orders);
    }
    flow.assert_all_done_and_plant_empty(&all).await;
    let (transport, drill, mill) = (
        rounds.count("transport"),
        rounds.count("drill"),
        rounds.count("mill"),
    );
    eprintln!("proposal rounds seen: transport {transport}, drill {drill}, mill {mill}");
    assert_eq!(
        transport, 0,
        "a move that only conveyor1 can make was asked of the cell in a round"
    );
    assert_eq!(
        (drill, mill),
        (2 * all.len(), 2 * all.len()),
        "each step's station rounds: two (where to go, and whether it still proposes once there)"
    );
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
}

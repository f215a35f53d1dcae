//! A step asks no more than it must (docs/material-flow.md, "A move's conversations"):
//! a step whose station proposed in the round that found the part at its port is
//! booked there without a second round, while every move still has its round (the
//! proof that its transporter answers). Real binaries: plant-sim, the conveyor and two
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

/// Three orders of `ab` (drill on station_a, mill on station_b), one after another:
/// each order's three moves (in to station_a, on to station_b, out) take one transport
/// round each, and each step two station rounds (where to go, and once there whether
/// the station still proposes), not three. Every order ends done, each step once, the
/// plant empty. On the build before, the listener saw three station rounds a step.
#[tokio::test(flavor = "multi_thread")]
async fn a_step_at_the_port_it_was_found_at_takes_no_second_round() {
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
        transport,
        3 * all.len(),
        "each move has its round: its transporter answered just before it is booked"
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

/// A held transporter holds the moves: with conveyor1 held (PackML Held: its bookings
/// kept, no new work), an order's move is asked of the cell in a round that finds no
/// transporter, and waits; once conveyor1 is unheld the order goes on and finishes,
/// each step once, the plant empty.
#[tokio::test(flavor = "multi_thread")]
async fn a_held_transporter_is_asked_in_a_round_and_the_move_waits_for_it() {
    let flow = FlowCell::start("t-move-held", CONVEYOR).await;
    let rounds = RoundCounter::listen(&flow, &["transport"]).await;
    flow.cell.packml("conveyor1", "hold").await.unwrap();
    flow.cell.wait_packml("conveyor1", 11).await.unwrap();
    let orders = flow.cell.submit("ab", 1).await.unwrap();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
    while rounds.count("transport") == 0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "no transport round while conveyor1 was held: {:#}",
            flow.cell.order_state(&orders[0]).await.unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let state = flow.cell.order_state(&orders[0]).await.unwrap();
    assert_eq!(state["status"], "running", "{state:#}");
    assert_eq!(
        state["completed"].as_array().map_or(0, Vec::len),
        0,
        "{state:#}"
    );
    flow.cell.packml("conveyor1", "unhold").await.unwrap();
    flow.wait_ended(&orders, Duration::from_secs(60)).await;
    flow.assert_all_done_and_plant_empty(&orders).await;
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
}

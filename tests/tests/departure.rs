//! A station's port is freed when the pallet leaving it has departed, not when it has
//! arrived (docs/material-flow.md, "Departure"): the conveyor's controller says
//! `departed` once the pallet has left the port, the conveyor holon tells the order,
//! and the order releases the port's place then, so the next part rides in while the
//! last one still rides away. Real binaries: plant-sim, the conveyor and a station as
//! holon processes over their own controller connections, an order-node.

use std::collections::BTreeMap;
use std::time::Duration;

use holarchy_tests::{moving_at_once, slow_loop, FlowCell};

/// One ended action of the plant's trace.
#[derive(Debug, Clone)]
struct Record {
    resource: String,
    part: String,
    begin_ms: u64,
    end_ms: u64,
}

fn trace(flow: &FlowCell) -> Vec<Record> {
    let text = std::fs::read_to_string(flow.dir.path().join("plant-trace.jsonl")).unwrap();
    text.lines()
        .map(|line| serde_json::from_str::<serde_json::Value>(line).unwrap())
        .filter(|r| r["done"] == true && r["part"].is_string())
        .map(|r| Record {
            resource: r["resource"].as_str().unwrap().to_string(),
            part: r["part"].as_str().unwrap().to_string(),
            begin_ms: r["begin_ms"].as_u64().unwrap(),
            end_ms: r["end_ms"].as_u64().unwrap(),
        })
        .collect()
}

/// For each two parts worked one after the other at `station`: whether the second's
/// move in began before the first's move away had ended (plant ms, from the trace),
/// with both moves' times.
fn hand_overs(records: &[Record], station: &str) -> Vec<(bool, String)> {
    // A part's visit: from its first action at the station to its last (a pick and a
    // place).
    let mut visits: BTreeMap<&str, Record> = BTreeMap::new();
    for r in records.iter().filter(|r| r.resource == station) {
        let visit = visits.entry(r.part.as_str()).or_insert_with(|| r.clone());
        visit.begin_ms = visit.begin_ms.min(r.begin_ms);
        visit.end_ms = visit.end_ms.max(r.end_ms);
    }
    let mut works: Vec<&Record> = visits.values().collect();
    works.sort_by_key(|r| r.begin_ms);
    let moves: Vec<&Record> = records
        .iter()
        .filter(|r| r.resource == "conveyor1")
        .collect();
    let mut found = Vec::new();
    for pair in works.windows(2) {
        let (first, second) = (pair[0], pair[1]);
        let away = moves
            .iter()
            .filter(|m| m.part == first.part && m.begin_ms >= first.end_ms)
            .min_by_key(|m| m.begin_ms);
        let into = moves
            .iter()
            .filter(|m| m.part == second.part && m.end_ms <= second.begin_ms)
            .max_by_key(|m| m.end_ms);
        if let (Some(away), Some(into)) = (away, into) {
            found.push((
                into.begin_ms < away.end_ms,
                format!(
                    "{} away {}..{} ms, {} in {}..{} ms",
                    first.part, away.begin_ms, away.end_ms, second.part, into.begin_ms, into.end_ms
                ),
            ));
        }
    }
    found
}

/// Four parts, each drilled on station_a (one port), then milled on station_b, then
/// out. A slow loop: the way from station_a's stopper to station_b's takes 2 s, from
/// the buffer to station_a 1 s; the conveyor runs three moves at once. The next part's
/// move in to station_a begins while the last part still rides away from it; each
/// order still finishes with each step done once, and the plant ends empty. Were the port released at the move's end, as before,
/// no move in could begin before the move away had ended.
#[tokio::test(flavor = "multi_thread")]
async fn the_next_part_rides_in_while_the_last_rides_away() {
    let (conveyor, plant) = moving_at_once(&slow_loop(), 3);
    let flow = FlowCell::start_on("t-departure", &conveyor, &plant).await;
    let orders = flow.cell.submit("ab", 4).await.unwrap();
    flow.wait_ended(&orders, Duration::from_secs(120)).await;
    flow.assert_all_done_and_plant_empty(&orders).await;

    let records = trace(&flow);
    let worked: BTreeMap<&str, usize> =
        records
            .iter()
            .filter(|r| r.resource == "station_a")
            .fold(BTreeMap::new(), |mut n, r| {
                *n.entry(r.part.as_str()).or_default() += 1;
                n
            });
    assert_eq!(worked.len(), 4, "station_a's work by part: {worked:?}");
    // Each part's one step: a pick and a place, once each.
    assert!(
        worked.values().all(|&n| n == 2),
        "a part worked twice: {worked:?}"
    );
    let hand_overs = hand_overs(&records, "station_a");
    eprintln!("station_a's hand-overs: {hand_overs:#?}");
    assert_eq!(hand_overs.len(), 3, "{records:#?}");
    assert!(
        hand_overs.iter().any(|(early, _)| *early),
        "no part rode in to station_a before the last had arrived where it went: {hand_overs:#?}"
    );
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
}

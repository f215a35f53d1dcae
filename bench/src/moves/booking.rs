//! A transport booking's round trip: `booking_req` for `transport` with the part and
//! its move (`{"part", "from", "to"}`) to the conveyor, a resource holon on the plant;
//! interleaved sample by sample with a raw zenoh `get` (the floor) and the booking of a
//! plain step on a station of the same plant, so that all three see the same machine.

use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Result};
use holarchy_tests::Cell;
use schemas::{info_key, HolonId, MessageType, Service};
use serde_json::{json, Map, Value};

use crate::cells::get_once;
use crate::echo::ECHO_KEY;
use crate::stats::Latency;

/// The three series, sample by sample.
pub struct TransportSeries {
    /// `transport` booked on the conveyor.
    pub transport: Latency,
    /// A plain step booked on a station.
    pub step: Latency,
    /// A raw zenoh `get` to the echo helper, just before each pair.
    pub floor: Latency,
}

/// A request of `service` with `info`, from the bench's order, its inbox the reply-to.
fn request(
    cell: &Cell,
    kind: MessageType,
    service: &str,
    conversation: &str,
    info: &Map<String, Value>,
) -> Service {
    Service::request(
        kind,
        service,
        conversation,
        HolonId::order("bench").expect("a valid name"),
    )
    .with_reply_to(cell.keys.inbox("bench"))
    .with_info(info.clone())
}

/// A move's info: the part `part` from the load to `to`.
pub fn move_info(part: &str, to: &str) -> Map<String, Value> {
    let mut info = Map::new();
    info.insert(info_key::PART.into(), Value::from(part));
    info.insert(info_key::FROM.into(), Value::from("conveyor1.load"));
    info.insert(info_key::TO.into(), Value::from(to));
    info
}

/// A step's info: a pick and a place.
fn step_info() -> Map<String, Value> {
    json!({
        "pick": {"x": 100.0, "y": 20.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 0.0},
        "place": {"x": 300.0, "y": 40.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 90.0}
    })
    .as_object()
    .expect("an object")
    .clone()
}

/// Books `service` on `resource` and cancels it: how long the booking took.
async fn book_and_cancel(
    cell: &Cell,
    resource: &str,
    service: &str,
    conversation: &str,
    info: &Map<String, Value>,
) -> Result<Duration> {
    let key = cell.keys.service(resource);
    let book = request(cell, MessageType::BookingReq, service, conversation, info);
    let cancel = request(
        cell,
        MessageType::BookingCancel,
        service,
        conversation,
        info,
    );
    let t = Instant::now();
    let answer = Service::from_json(&get_once(cell, &key, book.to_json()).await?)?;
    let booked = t.elapsed();
    if answer.result != Some(true) {
        bail!("{service} refused by {resource}: {answer:?}");
    }
    get_once(cell, &key, cancel.to_json()).await?;
    Ok(booked)
}

/// Until the conveyor books a move to `to` (it must have heard the cell's layout, which
/// it asks of the serving resources when it starts): at most 20 s.
pub async fn wait_transport_bookable(cell: &Cell, to: &str) -> Result<()> {
    let deadline = Instant::now() + Duration::from_secs(20);
    let info = move_info("bench-ready", to);
    let mut last = String::new();
    while Instant::now() < deadline {
        match book_and_cancel(cell, "conveyor1", "transport", "ready/0/1", &info).await {
            Ok(_) => return Ok(()),
            Err(e) => last = e.to_string(),
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Err(anyhow!("conveyor1 never booked a move to {to}: {last}"))
}

/// `samples` rounds (after 100 warm-up ones) of: the floor, a step booked on `station`
/// (`service`), a move to `to` booked on conveyor1; each booking cancelled at once.
pub async fn series(
    cell: &Cell,
    station: &str,
    service: &str,
    to: &str,
    samples: usize,
) -> Result<TransportSeries> {
    let echo = vec![
        b'x';
        request(
            cell,
            MessageType::BookingReq,
            "transport",
            "bench/1/1",
            &move_info("p-1", to)
        )
        .to_json()
        .len()
    ];
    let step = step_info();
    let (mut transport, mut plain, mut floor) = (Vec::new(), Vec::new(), Vec::new());
    let started = Instant::now();
    for i in 0..samples + 100 {
        let t = Instant::now();
        get_once(cell, ECHO_KEY, echo.clone()).await?;
        let floor_took = t.elapsed();
        let step_took =
            book_and_cancel(cell, station, service, &format!("step/{i}/1"), &step).await?;
        let info = move_info(&format!("p-{i}"), to);
        let move_took = book_and_cancel(
            cell,
            "conveyor1",
            "transport",
            &format!("move/{i}/1"),
            &info,
        )
        .await?;
        if i >= 100 {
            floor.push(floor_took);
            plain.push(step_took);
            transport.push(move_took);
        }
    }
    let total = started.elapsed();
    Ok(TransportSeries {
        transport: Latency::new(transport, total),
        step: Latency::new(plain, total),
        floor: Latency::new(floor, total),
    })
}

//! The booking section: booking round trips against the interleaved zenoh floor and the
//! journal commit, eight orders booking at once, both journal durabilities.

use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use holarchy_tests::{pick_n_place, resource_config, Cell, Process, Sim};
use schemas::{MessageType, Service};
use serde_json::json;

use crate::cells::get_once;
use crate::echo::ECHO_KEY;
use crate::run::Run;
use crate::stats::Latency;

/// What a booking series measured.
pub struct BookingSeries {
    pub booking: Latency,
    book_and_cancel: Latency,
    /// A raw zenoh `get` to the echo helper just before each booking: the floor under
    /// the same load at the same moment, so the ratio survives a noisy machine.
    pub floor: Latency,
}

impl BookingSeries {
    fn ratio(&self) -> f64 {
        self.booking.pct(0.5) / self.floor.pct(0.5)
    }
}

/// One `booking_req` then its `booking_cancel`: how long the booking took, and the pair.
pub async fn book_and_cancel(
    cell: &Cell,
    resource: &str,
    conversation: &str,
) -> Result<(Duration, Duration)> {
    let key = cell.keys.service(resource);
    let book = pick_n_place(&cell.keys, MessageType::BookingReq, "bench", conversation);
    let cancel = pick_n_place(
        &cell.keys,
        MessageType::BookingCancel,
        "bench",
        conversation,
    );
    let t = Instant::now();
    let answer = Service::from_json(&get_once(cell, &key, book.to_json()).await?)?;
    let booked = t.elapsed();
    if answer.result != Some(true) {
        bail!("booking refused by {resource}: {answer:?}");
    }
    get_once(cell, &key, cancel.to_json()).await?;
    Ok((booked, t.elapsed()))
}

/// Eight orders booking `resource` at the same moment (their bookings share a journal
/// write), against the same eight one after another: until all eight are booked,
/// `rounds` times each, after 5 warm-up rounds; each round's bookings are cancelled.
async fn eight_at_once(cell: &Cell, resource: &str, rounds: usize) -> Result<(Latency, Latency)> {
    let key = cell.keys.service(resource);
    let (mut together, mut in_turn) = (Vec::new(), Vec::new());
    let started = Instant::now();
    for round in 0..rounds + 5 {
        let requests = |how: &str, kind: MessageType| -> Vec<Vec<u8>> {
            (0..8)
                .map(|i| {
                    let order = format!("eight{i}");
                    pick_n_place(&cell.keys, kind, &order, &format!("{order}/{how}{round}/1"))
                        .to_json()
                })
                .collect()
        };
        let t = Instant::now();
        let answers = futures_util::future::try_join_all(
            requests("a", MessageType::BookingReq)
                .into_iter()
                .map(|book| get_once(cell, &key, book)),
        )
        .await?;
        let at_once = t.elapsed();
        let t = Instant::now();
        for book in requests("b", MessageType::BookingReq) {
            get_once(cell, &key, book).await?;
        }
        let one_by_one = t.elapsed();
        for answer in answers {
            if Service::from_json(&answer)?.result != Some(true) {
                bail!(
                    "a booking of 8 at once was refused: {}",
                    String::from_utf8_lossy(&answer)
                );
            }
        }
        for how in ["a", "b"] {
            for cancel in requests(how, MessageType::BookingCancel) {
                get_once(cell, &key, cancel).await?;
            }
        }
        if round >= 5 {
            together.push(at_once);
            in_turn.push(one_by_one);
        }
    }
    let total = started.elapsed();
    Ok((Latency::new(together, total), Latency::new(in_turn, total)))
}

/// `booking_req` then `booking_cancel` to `resource`, `samples` times after 100 warm-up
/// pairs, each after a raw `get` to the echo helper (the interleaved floor).
pub async fn booking_series(cell: &Cell, resource: &str, samples: usize) -> Result<BookingSeries> {
    let echo = vec![
        b'x';
        pick_n_place(&cell.keys, MessageType::BookingReq, "bench", "bench/1/1")
            .to_json()
            .len()
    ];
    let (mut book_times, mut pair_times, mut floor_times) = (Vec::new(), Vec::new(), Vec::new());
    let started = Instant::now();
    for i in 0..samples + 100 {
        let t = Instant::now();
        get_once(cell, ECHO_KEY, echo.clone()).await?;
        let floor = t.elapsed();
        let (booked, pair) = book_and_cancel(cell, resource, &format!("{resource}/{i}/1")).await?;
        if i >= 100 {
            book_times.push(booked);
            pair_times.push(pair);
            floor_times.push(floor);
        }
    }
    let total = started.elapsed();
    Ok(BookingSeries {
        booking: Latency::new(book_times, total),
        book_and_cancel: Latency::new(pair_times, total),
        floor: Latency::new(floor_times, total),
    })
}

/// Booking round trips to `robot1` (journal `power_loss`) and to a second holon with
/// `process_crash`.
pub async fn section(run: &mut Run) -> Result<()> {
    let series = booking_series(&run.cell, "robot1", run.samples).await?;
    booking_row(
        run,
        "booking round trip (booking_req, journal power_loss)",
        &series,
        0,
    );
    let (together, in_turn) = eight_at_once(&run.cell, "robot1", run.samples / 20).await?;
    run.table.add(
        "8 orders booking at once (power_loss)",
        format!(
            "all 8 booked in p50 {:.0} us, p99 {:.0} us",
            together.pct(0.5),
            together.pct(0.99)
        ),
        format!(
            "the same 8 one after another: p50 {:.0} us ({:.1}x)",
            in_turn.pct(0.5),
            in_turn.pct(0.5) / together.pct(0.5)
        ),
        json!({"at_once": together.json(), "one_after_another": in_turn.json()}),
    );

    // The same with the journal's `process_crash` durability (no fsync per commit): the
    // difference is what the fsyncs of `power_loss` cost.
    let mut fast = start_process_crash_robot(run, "robot9").await?;
    let series = booking_series(&run.cell, "robot9", run.samples).await?;
    fast.kill();
    run.ours.booking = Some((series.booking.pct(0.5), series.booking.pct(0.99)));
    booking_row(
        run,
        "booking round trip (journal process_crash)",
        &series,
        1,
    );

    // What a standby costs a booking: the same on a fenced resource holding its
    // controller's claim, which confirms the claim with the controller before it books
    // (docs/reliability.md, "Standby resources").
    let (_sim, mut fenced) = start_fenced_robot(run, "robot10").await?;
    let fenced_series = booking_series(&run.cell, "robot10", run.samples).await?;
    fenced.kill();
    run.table.add(
        "booking round trip, fenced resource (standby-capable, process_crash)",
        fenced_series.booking.p50_p99(),
        format!(
            "{:.2}x the unfenced booking's p50 ({:.0} us); {:.2}x its interleaved zenoh floor",
            fenced_series.booking.pct(0.5) / series.booking.pct(0.5),
            series.booking.pct(0.5),
            fenced_series.ratio()
        ),
        json!({
            "booking": fenced_series.booking.json(),
            "interleaved_floor": fenced_series.floor.json(),
            "unfenced_booking": series.booking.json(),
        }),
    );
    Ok(())
}

/// A fenced resource holon `name` (`--standby`, `process_crash`) on a controller
/// simulator of its own that fences (`robot-sim --fenced`), holding the claim and free.
async fn start_fenced_robot(run: &Run, name: &str) -> Result<(Sim, Process)> {
    let sim = Sim::start(
        &run.dir,
        &format!("{name}-sim"),
        "127.0.0.1:0",
        &["--fenced", "--lease-ms", "1000"],
    )?;
    let data = run.dir.join(format!("data-{name}"));
    let data = data.to_str().unwrap();
    let robot =
        start_process_crash_robot_on(run, name, &sim.address, &["--data-dir", data, "--standby"])
            .await?;
    Ok((sim, robot))
}

/// A resource holon `name` on the run's controller with the journal's
/// `process_crash` durability (no fsync per commit), free.
pub async fn start_process_crash_robot(run: &Run, name: &str) -> Result<Process> {
    let data = run.dir.join("data");
    start_process_crash_robot_on(
        run,
        name,
        &run.sim.address,
        &["--data-dir", data.to_str().unwrap()],
    )
    .await
}

/// A resource holon `name` with the journal's `process_crash` durability, on the
/// controller at `controller` with `flags`, free.
async fn start_process_crash_robot_on(
    run: &Run,
    name: &str,
    controller: &str,
    flags: &[&str],
) -> Result<Process> {
    let config = resource_config(&run.dir, name, 5000)?;
    let text = std::fs::read_to_string(&config)?;
    std::fs::write(
        &config,
        format!("{text}\n[journal]\ndurability = \"process_crash\"\n"),
    )?;
    let robot = holarchy_tests::start_node(
        &run.dir,
        &config,
        "bench",
        &run.cell.endpoint,
        controller,
        flags,
    )?;
    run.cell
        .wait_state(name, "free", |s| s["state"] == "free")
        .await?;
    Ok(robot)
}

/// A booking figure against the floors: `journal` 0 for power_loss, 1 for process_crash.
fn booking_row(run: &mut Run, name: &str, series: &BookingSeries, journal: usize) {
    let journal_floor = if journal == 0 {
        &run.journal_floor.0
    } else {
        &run.journal_floor.1
    };
    let above = series.booking.pct(0.5) - series.floor.pct(0.5) - journal_floor.pct(0.5);
    run.table.add(
        name,
        format!(
            "p50 {:.0} us, p99 {:.0} us, {:.0} book+cancel/s",
            series.booking.pct(0.5),
            series.booking.pct(0.99),
            series.book_and_cancel.rate()
        ),
        format!(
            "{:.2}x interleaved zenoh floor (p50 {:.0} us); {above:.0} us above it + journal commit",
            series.ratio(),
            series.floor.pct(0.5)
        ),
        json!({
            "booking": series.booking.json(),
            "book_and_cancel": series.book_and_cancel.json(),
            "interleaved_floor": series.floor.json(),
            "ratio_to_floor_p50": series.ratio(),
            "above_floors_us": above,
        }),
    );
}

//! The cycle section: service cycles (book, two controller steps, `done`), starting on
//! their turn and by a separate `start`, and where their time goes.

use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use holarchy_tests::{pick_n_place, Cell};
use schemas::{MessageType, Service};
use serde_json::json;

use crate::booking::start_process_crash_robot;
use crate::cells::get_once;
use crate::run::Run;
use crate::stats::Latency;

/// Service cycles: book (starting on its turn, as orders do by default), two controller
/// steps, `done` acknowledged; beside it, interleaved cycle by cycle so that both see the
/// same machine, the same with a separate `start`.
pub async fn section(run: &mut Run) -> Result<()> {
    // `process_crash` (the target's), both ways; then `power_loss` (robot1) beside it.
    let mut fast = start_process_crash_robot(run, "robot8").await?;
    cycle_on(
        run,
        "robot8",
        "process_crash",
        &[Starting::OnTurn, Starting::ByRequest],
    )
    .await?;
    fast.kill();
    cycle_on(run, "robot1", "power_loss", &[Starting::OnTurn]).await
}

/// How a cycle's job is started.
#[derive(Clone, Copy, PartialEq)]
enum Starting {
    /// The `booking_req` asks to start on its turn: one request books and starts.
    OnTurn,
    /// `booking_req`, then `start`: two requests.
    ByRequest,
}

/// Where one cycle's time went: until booked, until started, until `done` arrived.
struct CycleTimes {
    booked: Duration,
    started: Duration,
    done: Duration,
}

/// One cycle of `conversation` on the resource at `key`, started the `starting` way.
async fn one_cycle(
    cell: &Cell,
    key: &str,
    inbox: &mut holarchy_tests::Inbox,
    conversation: &str,
    starting: Starting,
) -> Result<CycleTimes> {
    let t = Instant::now();
    let mut book = pick_n_place(&cell.keys, MessageType::BookingReq, "bench", conversation);
    if starting == Starting::OnTurn {
        book = book.with_start_on_turn();
    }
    let answer = Service::from_json(&get_once(cell, key, book.to_json()).await?)?;
    let booked = t.elapsed();
    match starting {
        Starting::OnTurn if !answer.started() => bail!("not started on its turn: {answer:?}"),
        Starting::OnTurn => {}
        Starting::ByRequest => {
            let start = pick_n_place(&cell.keys, MessageType::Start, "bench", conversation);
            let answer = Service::from_json(&get_once(cell, key, start.to_json()).await?)?;
            if answer.result != Some(true) {
                bail!("start refused: {answer:?}");
            }
        }
    }
    let started = t.elapsed();
    while inbox.next().await?.conversation_id != conversation {}
    Ok(CycleTimes {
        booked,
        started,
        done: t.elapsed(),
    })
}

/// Service cycles on `robot`, whose journal has `durability`: for each cycle, one of
/// each way in `ways`, one after the other; a row (and where its time goes) per way.
async fn cycle_on(run: &mut Run, robot: &str, durability: &str, ways: &[Starting]) -> Result<()> {
    let cell = &run.cell;
    let key = cell.keys.service(robot);
    let mut inbox = cell.inbox("bench", 0).await?;
    let cycles = run.samples / 4;
    let mut measured: Vec<Vec<CycleTimes>> = ways.iter().map(|_| Vec::new()).collect();
    for i in 0..cycles + 20 {
        for (way, starting) in ways.iter().enumerate() {
            let conversation = format!("cycle-{durability}-{way}/{i}/1");
            let times = one_cycle(cell, &key, &mut inbox, &conversation, *starting).await?;
            if i >= 20 {
                measured[way].push(times);
            }
        }
    }
    for (starting, times) in ways.iter().zip(measured) {
        // Its rate: cycles of this way back to back, the time of each its own.
        let own: Duration = times.iter().map(|t| t.done).sum();
        let cycle = Latency::new(times.iter().map(|t| t.done).collect(), own);
        let part = |f: fn(&CycleTimes) -> Duration| {
            Latency::new(times.iter().map(f).collect(), Duration::from_secs(1))
        };
        let (book, start, until_done) = (
            part(|t| t.booked),
            part(|t| t.started - t.booked),
            part(|t| t.done - t.started),
        );
        let ratio = run.ratio(&cycle);
        if durability == "process_crash" {
            let figure = Some((cycle.pct(0.5), cycle.pct(0.99)));
            match starting {
                Starting::OnTurn => run.ours.cycle = figure,
                Starting::ByRequest => run.ours.cycle_by_request = figure,
            }
        }
        let (how, gets, parts, split) = match starting {
            Starting::OnTurn => (
                "book starting on its turn",
                2,
                "book and start | until done",
                format!("p50 {:.0} | {:.0} us", book.pct(0.5), until_done.pct(0.5)),
            ),
            Starting::ByRequest => (
                "book, start",
                3,
                "book | start | until done",
                format!(
                    "p50 {:.0} | {:.0} | {:.0} us",
                    book.pct(0.5),
                    start.pct(0.5),
                    until_done.pct(0.5)
                ),
            ),
        };
        let interleaved = if ways.len() > 1 {
            ", interleaved with the other way"
        } else {
            ""
        };
        run.table.add(
            &format!("service cycle, {durability} ({how}, 2 TCP/XML steps, done acked)"),
            format!(
                "p50 {:.0} us, p99 {:.0} us, {:.0} cycles/s",
                cycle.pct(0.5),
                cycle.pct(0.99),
                cycle.rate()
            ),
            format!(
                "{ratio:.1}x zenoh floor p50 ({gets} gets + 2 controller commands){interleaved}"
            ),
            cycle.json(),
        );
        run.table.add(
            // The row names its durability: it is the JSON key too, one per way.
            &format!("  where it goes, {durability}: {parts}"),
            split,
            "the last: 2 controller steps + result delivery".into(),
            json!({"book": book.json(), "start": start.json(), "until_done": until_done.json()}),
        );
    }
    Ok(())
}

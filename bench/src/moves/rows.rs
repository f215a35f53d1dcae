//! The moves section's rows of the table, each with its baseline from the same run.

use serde_json::json;

use super::booking::TransportSeries;
use super::cycle::Cycles;
use super::load::{Load, Memory, ProcessLoad};
use super::Sizes;
use crate::run::Run;

/// The coordination a move may add, in transport bookings' p50 (issue 42's target).
const TARGET_BOOKINGS: f64 = 2.0;

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

/// The transport booking beside the floor and the plain step's booking.
pub fn bookings(run: &mut Run, series: &TransportSeries) {
    let floor = series.floor.pct(0.5);
    run.table.add(
        "moves: transport booking round trip (conveyor on plant-sim, process_crash)",
        series.transport.p50_p99(),
        format!(
            "{:.2}x interleaved zenoh floor (p50 {floor:.0} us); {:.2}x the step booking",
            series.transport.pct(0.5) / floor,
            series.transport.pct(0.5) / series.step.pct(0.5),
        ),
        json!({
            "transport": series.transport.json(),
            "interleaved_floor": series.floor.json(),
            "ratio_to_floor_p50": series.transport.pct(0.5) / floor,
            "ratio_to_step_p50": series.transport.pct(0.5) / series.step.pct(0.5),
        }),
    );
    run.table.add(
        "moves: plain step booking, a station on the same plant",
        series.step.p50_p99(),
        format!(
            "{:.2}x interleaved zenoh floor",
            series.step.pct(0.5) / floor
        ),
        json!({"step": series.step.json()}),
    );
}

/// The order's cycle with moves against without, and what the moves add.
/// `journal`: the order-node's journal durability in these cycles.
pub fn cycles(
    run: &mut Run,
    series: &TransportSeries,
    cycles: &Cycles,
    travel_ms: f64,
    journal: &str,
) {
    let (moved, still) = (cycles.moved.pct(0.5) / 1e3, cycles.still.pct(0.5) / 1e3);
    run.table.add(
        &format!("moves: order cycle, its part moved in and out (2 moves), order-node {journal}"),
        format!(
            "p50 {moved:.1} ms, p99 {:.1} ms",
            cycles.moved.pct(0.99) / 1e3
        ),
        format!(
            "the same step, no part: p50 {still:.1} ms, p99 {:.1} ms; simulated travel {travel_ms:.0} ms",
            cycles.still.pct(0.99) / 1e3
        ),
        json!({"moved": cycles.moved.json(), "still": cycles.still.json(), "travel_ms": travel_ms}),
    );
    let added = moved - still - travel_ms;
    let per_move_us = added * 1e3 / 2.0;
    let booking = series.transport.pct(0.5);
    let ratio = per_move_us / booking;
    run.table.add(
        &format!("moves: coordination a move adds (beyond travel), order-node {journal}"),
        format!("{:.2} ms per move at p50 ({added:.2} ms for 2)", per_move_us / 1e3),
        format!(
            "{ratio:.1}x a transport booking's p50 ({booking:.0} us); target <= {TARGET_BOOKINGS:.0}x: {}",
            if ratio <= TARGET_BOOKINGS { "met" } else { "missed" }
        ),
        json!({
            "added_ms": added,
            "per_move_us": per_move_us,
            "transport_booking_p50_us": booking,
            "ratio_to_booking": ratio,
            "target_ratio": TARGET_BOOKINGS,
        }),
    );
}

/// A kind of process's figures: the median and the largest over its processes.
fn spread(values: &mut [f64]) -> (f64, f64) {
    values.sort_by(f64::total_cmp);
    let median = values.get(values.len() / 2).copied().unwrap_or(f64::NAN);
    (median, values.last().copied().unwrap_or(f64::NAN))
}

/// The figures of a kind of process (a name, or the names starting with a prefix).
fn kind_row(run: &mut Run, sizes: &Sizes, label: &str, figures: &[&ProcessLoad]) {
    let last = |m: &Vec<Memory>| m.last().copied().unwrap_or_default();
    let mut cpu: Vec<f64> = figures
        .iter()
        .map(|f| f.cpu_share.iter().sum::<f64>() / f.cpu_share.len().max(1) as f64)
        .collect();
    let mut peak: Vec<f64> = figures
        .iter()
        .map(|f| {
            mib(f
                .peak_in_flight
                .iter()
                .map(|m| m.rss_kib)
                .max()
                .unwrap_or(0))
        })
        .collect();
    let mut anon_flight: Vec<f64> = figures
        .iter()
        .map(|f| {
            mib(f
                .peak_in_flight
                .iter()
                .map(|m| m.anon_kib)
                .max()
                .unwrap_or(0))
        })
        .collect();
    let mut anon_idle: Vec<f64> = figures.iter().map(|f| mib(f.idle.anon_kib)).collect();
    let mut anon_done: Vec<f64> = figures
        .iter()
        .map(|f| mib(last(&f.after_done).anon_kib))
        .collect();
    let (cpu, cpu_max) = spread(&mut cpu);
    let (peak, peak_max) = spread(&mut peak);
    let (anon_flight, _) = spread(&mut anon_flight);
    let (anon_idle, _) = spread(&mut anon_idle);
    let (anon_done, _) = spread(&mut anon_done);
    let each = if figures.len() > 1 {
        " (median; max)"
    } else {
        ""
    };
    let max = |m: f64, suffix: &str| {
        if figures.len() > 1 {
            format!("; {m:.1}{suffix}")
        } else {
            String::new()
        }
    };
    run.table.add(
        &format!(
            "moves: {} transporters, {} parts in flight: {label}{each}",
            sizes.transporters, sizes.in_flight
        ),
        format!(
            "{:.0}%{} of a core, {peak:.1}{} MiB resident",
            cpu * 100.0,
            max(cpu_max * 100.0, "%"),
            max(peak_max, "")
        ),
        format!("own memory (anon) idle {anon_idle:.1}, in flight {anon_flight:.1}, all done {anon_done:.1} MiB"),
        json!({"processes": figures.len(), "cpu_share_median": cpu, "cpu_share_max": cpu_max, "rss_peak_mib_median": peak, "rss_peak_mib_max": peak_max, "anon_idle_mib": anon_idle, "anon_in_flight_mib": anon_flight, "anon_done_mib": anon_done}),
    );
}

/// Every process's CPU and memory under the waves; the order-node's memory wave by wave.
pub fn load(run: &mut Run, sizes: &Sizes, load: &Load) {
    let named = |prefix: &str| -> Vec<&ProcessLoad> {
        load.processes
            .iter()
            .filter(|(name, _)| {
                name.starts_with(prefix) && name[prefix.len()..].chars().all(|c| c.is_ascii_digit())
            })
            .map(|(_, f)| f)
            .collect()
    };
    for (label, prefix) in [
        ("order-node", "orders1"),
        ("plant-sim", "plant-sim"),
        ("product", "flow"),
        ("conveyor (entry, homes)", "conveyor1"),
        ("stations", "st"),
        ("transfers", "tr"),
    ] {
        let figures = named(prefix);
        if !figures.is_empty() {
            kind_row(run, sizes, label, &figures);
        }
    }
    let Some(node) = load.processes.get("orders1") else {
        return;
    };
    let done: Vec<String> = node
        .after_done
        .iter()
        .map(|m| format!("{:.1}", mib(m.anon_kib)))
        .collect();
    let flight: Vec<String> = node
        .peak_in_flight
        .iter()
        .map(|m| format!("{:.1}", mib(m.anon_kib)))
        .collect();
    let first = node.after_done.first().map_or(0, |m| m.anon_kib) as f64;
    let final_ = node.after_done.last().map_or(0, |m| m.anon_kib) as f64;
    let parts_after_first = f64::from(load.orders) * (node.after_done.len().max(1) - 1) as f64;
    let growth_per_100 = if parts_after_first > 0.0 {
        (final_ - first) / parts_after_first * 100.0
    } else {
        f64::NAN
    };
    let waves: Vec<String> = load.wave_s.iter().map(|s| format!("{s:.1}")).collect();
    run.table.add(
        "moves: order-node's own memory, wave by wave",
        format!(
            "after each {} done: {} MiB",
            load.orders,
            done.join(" / ")
        ),
        format!(
            "in flight: {} MiB; {growth_per_100:.0} KiB per 100 parts done after the first wave; waves took {} s",
            flight.join(" / "),
            waves.join(" / ")
        ),
        json!({"load": load, "growth_kib_per_100_done": growth_per_100}),
    );
}

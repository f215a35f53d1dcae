//! The moves section: what material flow costs (issue 42, item 8), each figure beside
//! a baseline from the same run, on real holons over the plant simulator.
//!
//! 1. A transport booking's round trip (`transport` with `{"part", "from", "to"}` to the
//!    conveyor) beside the interleaved zenoh floor and a plain step's booking on a
//!    station of the same plant.
//! 2. The cycle of an order whose step needs its part moved in and out, against the
//!    same step without a part; what the moves add beyond the simulated travel (known
//!    from the layout: the plant moves a pallet in exactly that time, unobstructed),
//!    per move, against the transport booking's p50 (the target: at most 2x).
//! 3. Many transporters and many parts in flight: one transfer per station between the
//!    cell's load and the station's port (a conveyor moves one part at a time, so 20
//!    transporters are 20 transfers, beside the conveyor that holds the entry and the
//!    homes); every process's CPU and memory while the parts are in flight, and the
//!    memory after each wave is done.

mod booking;
mod cell;
mod cycle;
mod load;
mod rows;

use anyhow::{anyhow, Context, Result};

use crate::echo::{spawn_helper, ECHO_KEY};
use crate::run::Run;
use cell::{MoveCell, Spec, Station, DOCK_MS, SPEED_MM_S, STATION_STOPPER_MM};

/// How the section is sized (`bench all --transporters N --in-flight N --waves N`).
#[derive(Debug, Clone)]
pub struct Sizes {
    /// Transporters (transfers) and stations of the load figure.
    pub transporters: usize,
    /// Parts (orders) in flight at once, per wave.
    pub in_flight: u32,
    /// Waves of them, one after the other.
    pub waves: usize,
}

/// The simulated travel of the cycle's two moves: load to the station's stopper, then
/// back to the load, each the distance at the conveyor's speed plus docking out and in.
fn cycle_travel_ms() -> f64 {
    let one_way = f64::from(STATION_STOPPER_MM) * 1000.0 / f64::from(SPEED_MM_S);
    2.0 * (one_way + 2.0 * DOCK_MS as f64)
}

pub async fn section(run: &mut Run, sizes: &Sizes) -> Result<()> {
    // 1 and 2: a conveyor, a station docked on it, a station outside the flow.
    let spec = Spec {
        cell: "bench-moves".into(),
        stations: vec![
            Station {
                name: "st0".into(),
                service: "work".into(),
                dock: Some("s1".into()),
                has_port: true,
            },
            Station {
                name: "still0".into(),
                service: "work_still".into(),
                dock: None,
                has_port: false,
            },
        ],
        action_ms: 10,
        transfer_ms: 40,
        buffer: 2,
        products: vec![
            ("moved".into(), "work".into(), true),
            ("still".into(), "work_still".into(), false),
        ],
    };
    let mut flow = MoveCell::start(&run.dir.join("moves"), &spec)
        .await
        .context("starting the cycle's cell")?;
    let (mut echo, _) = spawn_helper(&[
        "echo-zenoh",
        "--connect",
        &flow.cell.endpoint,
        "--key",
        ECHO_KEY,
    ])
    .context("starting the echo helper")?;
    let measured = async {
        flow.cell.wait_token(&format!("{ECHO_KEY}/alive")).await?;
        booking::wait_transport_bookable(&flow.cell, "st0.port").await?;
        let series = booking::series(&flow.cell, "st0", "work", "st0.port", run.samples)
            .await
            .context("the booking series")?;
        let n = (run.samples / 50).max(10);
        let cycles = cycle::cycles(&flow.cell, "moved", "still", n)
            .await
            .context("the order cycles")?;
        // The same with the order-node's journal on `process_crash`: what its fsyncs
        // (one per recorded change of the order and its part) cost the moves.
        flow.restart_orders("process_crash").await?;
        let unsynced = cycle::cycles(&flow.cell, "moved", "still", n)
            .await
            .context("the order cycles, process_crash")?;
        Ok::<_, anyhow::Error>((series, cycles, unsynced))
    }
    .await;
    let _ = echo.kill();
    let _ = echo.wait();
    let (series, cycles, unsynced) = measured?;
    rows::bookings(run, &series);
    rows::cycles(run, &series, &cycles, cycle_travel_ms(), "power_loss");
    rows::cycles(run, &series, &unsynced, cycle_travel_ms(), "process_crash");
    drop(flow);

    // 3: one transfer per station, the parts in waves.
    let stations = (0..sizes.transporters)
        .map(|i| Station {
            name: format!("st{i}"),
            service: "work".into(),
            dock: None,
            has_port: true,
        })
        .collect();
    let spec = Spec {
        cell: "bench-flow".into(),
        stations,
        action_ms: 20,
        transfer_ms: 40,
        buffer: sizes.in_flight,
        products: vec![("flow".into(), "work".into(), true)],
    };
    let flow = MoveCell::start(&run.dir.join("flow"), &spec)
        .await
        .context("starting the parts-in-flight cell")?;
    let processes = flow.processes();
    let load = load::waves(&flow.cell, &processes, "flow", sizes.in_flight, sizes.waves)
        .await
        .map_err(|e| anyhow!("{e} (the cell's logs: {})", flow.dir.display()))?;
    rows::load(run, sizes, &load);
    Ok(())
}

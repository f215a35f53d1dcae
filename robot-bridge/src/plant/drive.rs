//! The task that drives the plant's time: it advances the pure model
//! ([`Plant::advance`]) when the next thing is due (a pallet at its stopper, a docking
//! over, a transfer's arrival) or when a controller or the control port changed the
//! plant, logs what happened and writes the state file.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tracing::warn;

use super::controller::{log_happenings, OnChange};
use super::model::Plant;
use super::Clock;

/// The longest the plant goes unlooked at: then, while pallets wait, the state file is
/// written again (their waits grow longer).
const HEARTBEAT: Duration = Duration::from_secs(1);

/// Advances `plant` on `clock` until `shutdown`: woken by `wake` (a change from
/// outside) or when the next thing is due; `write` writes the state file.
pub async fn drive(
    plant: Arc<Mutex<Plant>>,
    clock: Clock,
    write: OnChange,
    wake: Arc<Notify>,
    shutdown: CancellationToken,
) {
    let mut deadlocked = false;
    loop {
        let next = {
            let mut plant = plant.lock().unwrap_or_else(|e| e.into_inner());
            let happened = plant.advance(clock.now_ms());
            log_happenings(&happened);
            let waits = plant.waits();
            if !happened.is_empty() || !waits.is_empty() {
                write(&plant);
            }
            let deadlock = plant.deadlock();
            if !deadlock.is_empty() && !deadlocked {
                warn!(pallets = ?deadlock, ?waits, "the plant is deadlocked: these pallets wait only on one another");
            }
            deadlocked = !deadlock.is_empty();
            plant.next_due()
        };
        let heartbeat = tokio::time::Instant::now() + HEARTBEAT;
        let until = next.map_or(heartbeat, |due| heartbeat.min(clock.at(due).into()));
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = wake.notified() => {}
            _ = tokio::time::sleep_until(until) => {}
        }
    }
}

//! The plant's control port (`plant-sim --control HOST:PORT`): tests and operators ask
//! where everything is and play the plant's faults, one command a line, one answer a
//! line.
//!
//! | command | answer |
//! |---|---|
//! | `where` | where everything is: the state file's JSON, on one line |
//! | `waits` | what waits: `{"now_ms", "deadlocked", "deadlock", "longest_wait_ms", "waits": [{"pallet", "waits", "since_ms", "for_ms"}]}`, on one line |
//! | `jam CONVEYOR.STOPPER` | `ok`: the track that ends at that stopper is jammed: no pallet enters it or leaves it (it holds its pallets, as a full queue) |
//! | `clear CONVEYOR.STOPPER` | `ok`: it is not any more; the pallets held up go on |
//! | `silence PALLET` | `ok`: the pallet (`conveyor1/p2`) stops reporting: a move it carries ends in the plant without its controller saying so |
//! | `report PALLET` | `ok`: it reports again |
//! | `estop RESOURCE MS` | `ok`: the resource's controller is e-stopped for MS ms (it says `estop`, refuses every command meanwhile, and a transporter's pallets stand still), then ready again |
//! | `counts` | what each controller did, as robot-sim's count file says it: `{"robot1": {"executed", "received", "aborted", "connections", "by_action", ...; fenced: "epoch", "by_step"}, ...}`, on one line |
//! | `retire PALLET` | `ok`: the pallet (`conveyor1/p2`) is taken out of service: at once if it is free, else once the part it carries has left it; a move that finds no free pallet waits for one (its part at its `from`) |
//! | `restore PALLET` | `ok`: it is back in service, free |
//! | `fail RESOURCE N` | `ok`: the resource's controller answers its next N inspections `inspect_fail` (a fault of the part, as an inspection finds it; the plant's `inspect_fail_every` goes on counting beside it) |
//! | `cut RESOURCE` | `ok`: every connection to the resource's controller is closed at once, as a failed network between it and its holon; what the controller was doing goes on (a move ends in the plant), and it takes connections again at once |
//!
//! Anything else is answered `error ` and why; nothing changes. The plant is advanced to
//! now before every command.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::layout::Dock;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::controller::{log_happenings, OnChange};
use super::model::{Plant, WaitView};
use super::Clock;
use crate::sim::SimStats;

/// What a command asks of the plant besides its state.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Effect {
    None,
    /// The plant's state changed.
    Changed,
    /// Press `resource`'s e-stop for `time`.
    Estop {
        resource: String,
        time: Duration,
    },
    /// Cut every link to `resource`'s controller.
    Cut {
        resource: String,
    },
    /// Fail `resource`'s next `count` inspections.
    FailInspections {
        resource: String,
        count: u64,
    },
}

/// The longest command line read.
const MAX_LINE: usize = 256;

/// What waits in the plant, as `waits` answers.
#[derive(Debug, serde::Serialize)]
struct Waits {
    /// The plant's time: ms since it started.
    now_ms: u64,
    /// Whether some pallets wait only on one another.
    deadlocked: bool,
    /// The pallets that do.
    deadlock: Vec<String>,
    /// The longest any pallet has waited, or waits now, in ms.
    longest_wait_ms: u64,
    /// Every pallet that waits.
    waits: Vec<WaitView>,
}

/// Carries out one command line on `plant` (whose controllers are `resources`): the
/// answer, and what else it asks for.
pub fn command(plant: &mut Plant, resources: &[String], line: &str) -> (String, Effect) {
    let words: Vec<&str> = line.split_whitespace().collect();
    let done = |result: Result<(), String>| match result {
        Ok(()) => ("ok".to_string(), Effect::Changed),
        Err(why) => (format!("error {why}"), Effect::None),
    };
    let dock = |text: &str| Dock::try_from(text.to_string());
    match words.as_slice() {
        ["where"] => (
            serde_json::to_string(&plant.view()).expect("a plant view serializes"),
            Effect::None,
        ),
        ["waits"] => {
            let view = plant.view();
            let waits = Waits {
                now_ms: view.now_ms,
                deadlocked: view.deadlocked,
                deadlock: view.deadlock,
                longest_wait_ms: view.longest_wait_ms,
                waits: plant.waits(),
            };
            (
                serde_json::to_string(&waits).expect("waits serialize"),
                Effect::None,
            )
        }
        ["estop", resource, ms] => match resource_and_count(resources, resource, ms) {
            Ok(ms) => (
                "ok".into(),
                Effect::Estop {
                    resource: resource.to_string(),
                    time: Duration::from_millis(ms),
                },
            ),
            Err(why) => (format!("error {why}"), Effect::None),
        },
        ["cut", resource] if resources.iter().any(|r| r == resource) => (
            "ok".into(),
            Effect::Cut {
                resource: resource.to_string(),
            },
        ),
        ["cut", resource] => (
            format!("error {resource}: no controller of that resource in the plant"),
            Effect::None,
        ),
        ["fail", resource, count] => match resource_and_count(resources, resource, count) {
            Ok(count) => (
                "ok".into(),
                Effect::FailInspections {
                    resource: resource.to_string(),
                    count,
                },
            ),
            Err(why) => (format!("error {why}"), Effect::None),
        },
        ["jam", at] => done(dock(at).and_then(|at| plant.jam(at, true))),
        ["clear", at] => done(dock(at).and_then(|at| plant.jam(at, false))),
        ["silence", pallet] => done(plant.silence(pallet, true)),
        ["report", pallet] => done(plant.silence(pallet, false)),
        ["retire", pallet] => done(plant.retire(pallet, true)),
        ["restore", pallet] => done(plant.retire(pallet, false)),
        _ => (
            format!(
                "error {line:?}: not a command (where, waits, counts, jam, clear, silence, report, retire, restore, estop, cut, fail)"
            ),
            Effect::None,
        ),
    }
}

/// A command's resource, which must have a controller in the plant, and its count
/// (milliseconds, inspections), a number above 0: the count, or why not.
fn resource_and_count(resources: &[String], resource: &str, count: &str) -> Result<u64, String> {
    if !resources.iter().any(|r| r == resource) {
        return Err(format!(
            "{resource}: no controller of that resource in the plant"
        ));
    }
    match count.parse::<u64>() {
        Ok(n) if n > 0 => Ok(n),
        _ => Err(format!("{count:?}: not a number above 0")),
    }
}

/// Serves the control port until `shutdown`.
pub async fn serve(
    listener: TcpListener,
    plant: Arc<Mutex<Plant>>,
    clock: Clock,
    controllers: BTreeMap<String, Arc<SimStats>>,
    on_change: OnChange,
    shutdown: CancellationToken,
) {
    let controllers = Arc::new(controllers);
    loop {
        let (stream, peer) = tokio::select! {
            _ = shutdown.cancelled() => return,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    warn!(error = %e, "the control port cannot accept a connection");
                    continue;
                }
            },
        };
        let (plant, on_change, shutdown) = (plant.clone(), on_change.clone(), shutdown.clone());
        let controllers = controllers.clone();
        tokio::spawn(async move {
            let (read, mut write) = stream.into_split();
            // A connection reads at most 1 MiB in all: a bounded window, not a stream.
            let mut lines = BufReader::new(read.take(1 << 20)).lines();
            loop {
                let line = tokio::select! {
                    _ = shutdown.cancelled() => return,
                    line = lines.next_line() => match line {
                        Ok(Some(line)) if line.len() <= MAX_LINE => line,
                        Ok(Some(_)) => "(a line too long)".to_string(),
                        _ => return,
                    },
                };
                if line.trim() == "counts" {
                    let counts: Vec<String> = controllers
                        .iter()
                        .map(|(resource, stats)| format!("\"{resource}\":{}", stats.to_json()))
                        .collect();
                    let answer = format!("{{{}}}\n", counts.join(","));
                    if let Err(e) = write.write_all(answer.as_bytes()).await {
                        warn!(%peer, error = %e, "cannot answer on the control port: the connection is gone");
                        return;
                    }
                    continue;
                }
                let answer = {
                    let resources: Vec<String> = controllers.keys().cloned().collect();
                    let mut locked = plant.lock().unwrap_or_else(|e| e.into_inner());
                    log_happenings(&locked.advance(clock.now_ms()));
                    let (answer, effect) = command(&mut locked, &resources, line.trim());
                    if effect != Effect::None {
                        info!(%peer, command = %line.trim(), "the plant changed by its control port");
                    }
                    if let Effect::Estop { resource, time } = &effect {
                        // MS is plant time; the controller and the release wait wall time.
                        let time = clock.wall(*time);
                        locked.estop(resource, true);
                        controllers[resource].stop(schemas::ControllerState::Estop, time);
                        let release = Release {
                            plant: plant.clone(),
                            clock,
                            resource: resource.clone(),
                            on_change: on_change.clone(),
                        };
                        release.after(time);
                    }
                    if let Effect::Cut { resource } = &effect {
                        controllers[resource].cut_links();
                    }
                    if let Effect::FailInspections { resource, count } = &effect {
                        controllers[resource].fail_inspections(*count);
                    }
                    if effect != Effect::None {
                        on_change(&locked);
                    }
                    answer
                };
                if let Err(e) = write.write_all(format!("{answer}\n").as_bytes()).await {
                    warn!(%peer, error = %e, "cannot answer on the control port: the connection is gone");
                    return;
                }
            }
        });
    }
}

/// A resource's e-stop to release.
struct Release {
    /// The plant.
    plant: Arc<Mutex<Plant>>,
    /// The plant's time.
    clock: Clock,
    /// The resource whose e-stop it is.
    resource: String,
    /// Told once it is released.
    on_change: OnChange,
}

impl Release {
    /// Releases the e-stop after `time` (its controller says `ready` again by itself
    /// then): the pallets go on.
    fn after(self, time: Duration) {
        tokio::spawn(async move {
            tokio::time::sleep(time).await;
            let mut plant = self.plant.lock().unwrap_or_else(|e| e.into_inner());
            log_happenings(&plant.advance(self.clock.now_ms()));
            plant.estop(&self.resource, false);
            info!(resource = %self.resource, "e-stop released");
            (self.on_change)(&plant);
        });
    }
}

//! A plant simulator killed and started again goes on from where it was
//! (docs/material-flow.md, "When the plant simulator dies").
//!
//! The state file holds, beside where everything is, the plant's **memory**: its whole
//! physical state ([`PlantMemory`]) and each fenced controller's fence ([`FenceMemory`]:
//! its last epoch and its latest steps' states). It is rewritten (a new file renamed
//! over the old) after every change of the plant, after a fenced station's action
//! ends, before its reply goes out, so that a step told done is remembered done, and
//! when a fence grants an epoch, before the grant is sent, so that no epoch is granted
//! twice.
//!
//! Started again on the same state file, the plant resumes from the memory: its clock
//! goes on from the plant time it had (the world stood still while it was dead), every
//! pallet is where it was and goes on where it was bound. What each controller was
//! doing when it died:
//!
//! | remembered | the step, fenced | what the plant does |
//! |---|---|---|
//! | a move under way | running, until the part is there | the move goes on; at its end it is traced and counted, its step done (`arrived`), as a controller ends a motion whose connection is gone |
//! | a move ended in the plant, its end not yet told | done (`arrived`) | |
//! | a move stopped on the way (aborted) | failed (`aborted`) | the part stays where it stopped |
//! | a station's action under way, or a command that had not begun | failed: the controller restarted before it ended | the action did not happen: nothing changes |
//!
//! Faults played on the control port: jams, silent and retired pallets stay as they
//! were; an e-stop is released (its timer died with the plant, and every controller
//! comes back ready); inspections told to fail (`fail`) and the count behind
//! `inspect_fail_every` start again from nothing.
//!
//! Every connection is gone: each holon sees its controller go and come back, and a
//! fenced one asks what became of its steps (`STEP_STATUS`). `plant-sim --fresh` forgets
//! the memory and starts an empty plant.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::controller::{log_happenings, OnChange};
use super::model::{Plant, PlantMemory, PlantView, ResumedMove};
use super::trace::{Trace, TraceRecord};
use super::{Clock, PlantError};
use crate::sim::fence::{FenceBook, FenceMemory, StepRecord};
use crate::sim::SimStats;

/// How many of each fenced controller's latest steps the memory keeps (a holon asks
/// only after its own steps under way).
const STEPS_REMEMBERED: usize = 512;

/// How often a resumed move is looked at until it ends in the plant.
const RESUMED_MOVE_CHECK: Duration = Duration::from_millis(50);

/// What the state file remembers besides where everything is.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Memory {
    /// The plant's physical state.
    pub plant: PlantMemory,
    /// Each fenced controller's fence, by resource.
    #[serde(default)]
    pub fences: BTreeMap<String, FenceMemory>,
}

/// The state file: where everything is, and the plant's memory.
#[derive(Serialize)]
struct StateFile {
    #[serde(flatten)]
    view: PlantView,
    memory: Memory,
}

/// The state file as read back: only its memory matters.
#[derive(Deserialize)]
struct Remembered {
    memory: Option<Memory>,
}

/// Each controller's resource and counts (their fences), known once the controllers
/// are bound; the state file's writer reads their fences.
pub type Fences = Arc<OnceLock<Vec<(String, Arc<SimStats>)>>>;

/// The memory in the state file at `path`, if the file is there. Err: a file that is
/// not a plant's memory (the plant would start from a state it cannot trust).
pub fn read_memory(path: &Path) -> Result<Option<Memory>, PlantError> {
    let bytes = match std::fs::read(path) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => {
            return Err(PlantError::Read {
                path: path.display().to_string(),
                why: e.to_string(),
            })
        }
    };
    let invalid = |why: String| {
        PlantError::Invalid {
        path: path.display().to_string(),
        why: format!("{why}; the plant cannot resume from it: remove the file or start plant-sim with --fresh"),
    }
    };
    let remembered: Remembered = serde_json::from_slice(&bytes)
        .map_err(|e| invalid(format!("not a plant's state file: {e}")))?;
    remembered
        .memory
        .map(Some)
        .ok_or_else(|| invalid("the state file has no memory (an older plant-sim wrote it)".into()))
}

/// Writes the state file at `path` (None: nowhere) after every change: where
/// everything is and the memory, a new file renamed over the old (a reader never sees
/// half of it; a kill of the process loses nothing written).
pub fn state_writer(path: Option<PathBuf>, fences: Fences) -> OnChange {
    Arc::new(move |plant: &Plant| {
        let Some(path) = &path else { return };
        let fences = fences
            .get()
            .map(|controllers| {
                controllers
                    .iter()
                    .filter_map(|(resource, stats)| {
                        let fence = stats.fence();
                        Some((resource.clone(), fence.as_ref()?.memory(STEPS_REMEMBERED)))
                    })
                    .collect()
            })
            .unwrap_or_default();
        let file = StateFile {
            view: plant.view(),
            memory: Memory {
                plant: plant.memory(),
                fences,
            },
        };
        let json = serde_json::to_vec_pretty(&file).expect("a plant's state serializes");
        let next = path.with_extension("json.next");
        if let Err(e) = std::fs::write(&next, json).and_then(|()| std::fs::rename(&next, path)) {
            warn!(path = %path.display(), error = %e, "cannot write the plant's state file: readers see an older state, and a plant started again would resume from it");
        }
    })
}

/// Each fenced controller's fence as `fences` remembers it, its steps under way settled
/// by what the plant remembers (the module's table). Returns the moves that go on, each
/// to be ended by [`end_resumed_move`].
pub fn resume_controllers(
    plant: &mut Plant,
    controllers: &[(String, Arc<SimStats>)],
    mut fences: BTreeMap<String, FenceMemory>,
) -> Vec<ResumedMove> {
    let moves = plant.moves_under_way();
    for (resource, stats) in controllers {
        let mut guard = stats.fence();
        let (Some(book), Some(memory)) = (guard.as_mut(), fences.remove(resource)) else {
            continue;
        };
        let mut resumed = FenceBook::resume(book.lease, memory);
        for step in resumed.running() {
            let under_way = moves.iter().find(|m| {
                &m.transporter == resource
                    && m.command.as_ref().and_then(|c| c.step.as_deref()) == Some(step.as_str())
            });
            let record = match under_way {
                Some(m) if !m.stopped => continue,
                Some(_) => StepRecord::Failed("aborted".into()),
                None if plant.arrived_untold(resource, &step) => {
                    plant.end_told(resource, &step);
                    StepRecord::Done("arrived".into())
                }
                None => StepRecord::Failed(
                    "the controller restarted before the action ended: not done".into(),
                ),
            };
            info!(
                resource,
                step,
                ?record,
                "a step under way when the plant died"
            );
            resumed.settle(&step, record);
        }
        info!(
            resource,
            epoch = resumed.epoch(),
            "the fence resumed from the plant's memory"
        );
        *book = resumed;
    }
    for (resource, _) in fences {
        warn!(
            resource,
            "the memory has a fence for a controller that is not fenced now: forgotten"
        );
    }
    // Every ended move untold is settled above, or its controller is not fenced now.
    plant.forget_untold();
    // An e-stop played on the control port is released when its time is up, by a
    // timer that died with the plant; every controller comes back ready.
    for resource in plant.view().estopped {
        plant.estop(&resource, false);
        info!(resource, "an e-stop pressed when the plant died: released");
    }
    moves.into_iter().filter(|m| !m.stopped).collect()
}

/// A move under way when the plant died goes on: once its part is there in the plant,
/// it ends as its controller would end a motion whose connection is gone (traced,
/// counted as executed, its step done).
pub async fn end_resumed_move(
    resumed: ResumedMove,
    plant: Arc<Mutex<Plant>>,
    clock: Clock,
    stats: Arc<SimStats>,
    trace: Trace,
    on_change: OnChange,
    shutdown: CancellationToken,
) {
    let ResumedMove {
        part,
        transporter,
        carrier,
        began_ms,
        command,
        ..
    } = resumed;
    info!(
        part,
        transporter, "a move under way when the plant died goes on"
    );
    loop {
        {
            let mut plant = plant.lock().unwrap_or_else(|e| e.into_inner());
            log_happenings(&plant.advance(clock.now_ms()));
            if plant.on_its_way(&part, &transporter).is_none() {
                break;
            }
        }
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = tokio::time::sleep(RESUMED_MOVE_CHECK) => {}
        }
    }
    let action = command.as_ref().map_or("move", |c| c.action.as_str());
    let step = command.as_ref().and_then(|c| c.step.clone());
    // Traced first: a kill before the memory is written leaves the move traced once
    // and its step done on the next start (it ended in the plant, untold).
    trace.record(&TraceRecord {
        resource: transporter.clone(),
        action: action.to_string(),
        part: Some(part.clone()),
        carrier,
        begin_ms: began_ms,
        end_ms: clock.now_ms(),
        done: true,
    });
    if let Some(step) = &step {
        if let Some(book) = stats.fence().as_mut() {
            book.settle(step, StepRecord::Done("arrived".into()));
        }
    }
    stats.count_executed(action);
    let mut plant = plant.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(step) = &step {
        plant.end_told(&transporter, step);
    }
    info!(part, transporter, where_it_is = %plant.where_is(&part), "a move under way when the plant died ended");
    on_change(&plant);
}

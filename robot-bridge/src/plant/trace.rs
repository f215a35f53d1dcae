//! The plant's trace (`plant-sim --trace FILE`, or the plant file's `trace_file`):
//! every action its controllers ran, one JSON line each when it ends, in plant time.
//! A benchmark reads it for makespan, flow times, utilisation and its Gantt chart;
//! an operator reads what each station did when.
//!
//! ```json
//! {"resource":"m2","action":"place","part":"orders1-3","carrier":null,"begin_ms":41200,"end_ms":61200,"done":true}
//! {"resource":"monorail","action":"move","part":"orders1-3","carrier":"monorail/p4","begin_ms":61210,"end_ms":67950,"done":true}
//! ```

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;
use std::sync::{Arc, Mutex};

use serde::{Deserialize, Serialize};
use tracing::warn;

/// One line of the trace: an action one controller ran, from its command's arrival to
/// its end.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TraceRecord {
    /// The resource whose controller ran it.
    pub resource: String,
    /// The action (`place`, `inspect`, `move`, ...).
    pub action: String,
    /// The part it worked or moved (None: a command in no material flow, at an empty
    /// station).
    pub part: Option<String>,
    /// The pallet (shuttle) a move carried its part on, when it began.
    pub carrier: Option<String>,
    /// When it began and ended, plant ms since the plant started.
    pub begin_ms: u64,
    pub end_ms: u64,
    /// Whether it ran to its end (false: aborted, stopped short).
    pub done: bool,
}

/// Where the trace goes (shared by every controller of the plant): a file written a
/// line at a time, or nowhere.
#[derive(Clone, Default)]
pub struct Trace {
    /// The open file; None: no trace asked for. A lock is the right tool: a
    /// controller's session writes one line from its own task, never across an await.
    file: Option<Arc<Mutex<BufWriter<File>>>>,
}

impl Trace {
    /// A trace written to `path` (created, or emptied).
    pub fn create(path: &Path) -> std::io::Result<Trace> {
        let file = File::create(path)?;
        Ok(Trace {
            file: Some(Arc::new(Mutex::new(BufWriter::new(file)))),
        })
    }

    /// A trace written on at the end of `path` (created if it is not there): a plant
    /// that resumes after its death adds to the trace of its life before.
    pub fn append(path: &Path) -> std::io::Result<Trace> {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(path)?;
        Ok(Trace {
            file: Some(Arc::new(Mutex::new(BufWriter::new(file)))),
        })
    }

    /// No trace.
    pub fn none() -> Trace {
        Trace::default()
    }

    /// Writes `record` as one line, flushed: a reader sees every ended action.
    pub fn record(&self, record: &TraceRecord) {
        let Some(file) = &self.file else { return };
        let line = serde_json::to_string(record).expect("a trace record serializes");
        let mut file = file.lock().unwrap_or_else(|e| e.into_inner());
        if let Err(e) = writeln!(file, "{line}").and_then(|()| file.flush()) {
            warn!(error = %e, resource = %record.resource, "cannot write the plant's trace: this action is missing from it");
        }
    }
}

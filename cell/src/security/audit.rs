//! The cell's audit trail: who did what to the cell, from where, and how it ended.
//!
//! One JSON object per line ([`AuditRecord`]) in an append-only file, `audit.jsonl`
//! beside the cell's users file (docs/security.md). The dashboard appends every
//! operator action (logins and logouts, failed logins, submits, cancels, where a lost
//! part is, alarm acknowledgements, PackML commands, user changes), the OPC UA server its logins,
//! failed logins and every method call (accepted or refused), and `cell users` the
//! changes made from the command line; each record says through which door
//! ([`AuditDoor`]). Each line is written with one `write` on a file
//! opened for appending, and synced before the call returns: two writers never tear
//! each other's lines, and a recorded action survives a crash or a power cut.
//!
//! The file is created readable by its owner only, and refused when others can read it
//! (it names people and what they did).

use std::fs::File;
use std::io::{Read, Seek, SeekFrom, Write};
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

/// The file name of the audit trail, beside the users file.
pub const FILE_NAME: &str = "audit.jsonl";

/// What was done.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AuditAction {
    /// A user logged in (a password, or a client certificate's first request).
    Login,
    /// A login was refused (wrong password, unknown user, locked out).
    LoginFailed,
    /// A user logged out.
    Logout,
    /// A work order was submitted.
    Submit,
    /// An order was cancelled.
    Cancel,
    /// An operator said where an order's lost part is (`{"at": LOCATION}`).
    PartFound,
    /// An alarm was acknowledged.
    AcknowledgeAlarm,
    /// A resource was sent a PackML command, unit mode or operator job.
    Packml,
    /// A user was added to the users file.
    UserAdd,
    /// A user's password was changed.
    UserPassword,
    /// A user's role was changed.
    UserRole,
    /// A user was removed from the users file.
    UserRemove,
}

/// Through which door of the cell an action came.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AuditDoor {
    /// The web dashboard.
    Dashboard,
    /// The OPC UA server (`cell opcua`).
    Opcua,
    /// The command line (`cell users`).
    Cli,
}

/// How an action ended.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "outcome", content = "why", rename_all = "snake_case")]
pub enum AuditOutcome {
    /// It was done.
    Done,
    /// It was refused (a role without the right, a state that does not allow it, a
    /// wrong password): the cell did not change.
    Refused(String),
    /// It was tried and failed (the cell could not be reached, ...).
    Failed(String),
}

/// One line of the trail.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct AuditRecord {
    /// When (Unix ms).
    pub at: u64,
    /// Who: `anna` (a user of the users file), `cert:operator.anna` (a client
    /// certificate), `local` (a dashboard without login), `cli:<os user>`.
    pub who: String,
    /// From where: the client's address, or `cell users on <host>`.
    pub from: String,
    /// Through which door (absent in records written before doors were recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub door: Option<AuditDoor>,
    /// What.
    pub action: AuditAction,
    /// What it was done to: an order, an alarm's id, a resource, a user.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target: Option<String>,
    /// The request's particulars (a work order, a PackML command), as given.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detail: Option<serde_json::Value>,
    /// How it ended.
    #[serde(flatten)]
    pub outcome: AuditOutcome,
}

impl AuditRecord {
    /// A record stamped now.
    pub fn now(who: &str, from: &str, action: AuditAction, outcome: AuditOutcome) -> AuditRecord {
        AuditRecord {
            at: schemas::unix_ms(),
            who: who.to_string(),
            from: from.to_string(),
            door: None,
            action,
            target: None,
            detail: None,
            outcome,
        }
    }

    /// The same, about `target`.
    pub fn on(mut self, target: impl Into<String>) -> AuditRecord {
        self.target = Some(target.into());
        self
    }

    /// The same, as done through `door`.
    pub fn through(mut self, door: AuditDoor) -> AuditRecord {
        self.door = Some(door);
        self
    }

    /// The same, with the request's particulars.
    pub fn with(mut self, detail: serde_json::Value) -> AuditRecord {
        self.detail = Some(detail);
        self
    }
}

/// The trail's problems.
#[derive(Debug, thiserror::Error)]
pub enum AuditError {
    #[error("cannot open the audit trail {path}: {source}")]
    Open {
        path: String,
        source: std::io::Error,
    },
    #[error("the audit trail {path} is readable by other users (mode {mode:o}); it names people and what they did: chmod 600 {path}")]
    OpenToOthers { path: String, mode: u32 },
    #[error("cannot record in the audit trail {path}: {source}")]
    Write {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot read the audit trail {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
}

/// An audit trail open for appending.
#[derive(Debug)]
pub struct AuditTrail {
    /// Where it is.
    path: PathBuf,
    /// The file, opened for appending (one writer in this process at a time).
    file: Mutex<File>,
}

impl AuditTrail {
    /// Opens (or creates, 0600) the trail at `path`; refuses a trail others can read.
    pub fn open(path: &Path) -> Result<AuditTrail, AuditError> {
        let shown = path.display().to_string();
        let file = std::fs::OpenOptions::new()
            .append(true)
            .create(true)
            .mode(0o600)
            .open(path)
            .map_err(|source| AuditError::Open {
                path: shown.clone(),
                source,
            })?;
        if let Some(mode) = crate::security::private_file::open_to_others(path) {
            return Err(AuditError::OpenToOthers { path: shown, mode });
        }
        Ok(AuditTrail {
            path: path.to_path_buf(),
            file: Mutex::new(file),
        })
    }

    /// Where the trail is.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Appends `record` and syncs it to disk before returning.
    pub fn append(&self, record: &AuditRecord) -> Result<(), AuditError> {
        let mut line = serde_json::to_string(record).expect("an audit record encodes");
        line.push('\n');
        let failed = |source| AuditError::Write {
            path: self.path.display().to_string(),
            source,
        };
        let file = self
            .file
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner());
        (&*file).write_all(line.as_bytes()).map_err(failed)?;
        file.sync_data().map_err(failed)
    }

    /// Appends `record`; a failure is logged as an error (the action itself happened).
    pub fn record(&self, record: &AuditRecord) {
        if let Err(e) = self.append(record) {
            tracing::error!(error = %e, action = ?record.action, who = %record.who, "an action is missing from the audit trail");
        }
    }
}

/// The last `count` records of the trail at `path`, the newest first (reads at most
/// the last 4 MiB; a line that is not a record, such as a torn last line after a
/// crash, is skipped).
pub fn newest(path: &Path, count: usize) -> Result<Vec<AuditRecord>, AuditError> {
    const TAIL: u64 = 4 << 20;
    let failed = |source| AuditError::Read {
        path: path.display().to_string(),
        source,
    };
    let mut file = match File::open(path) {
        Ok(file) => file,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(failed(e)),
    };
    let length = file.metadata().map_err(failed)?.len();
    let start = length.saturating_sub(TAIL);
    file.seek(SeekFrom::Start(start)).map_err(failed)?;
    let mut bytes = Vec::new();
    file.read_to_end(&mut bytes).map_err(failed)?;
    let text = String::from_utf8_lossy(&bytes);
    let mut lines = text.lines();
    if start > 0 {
        lines.next(); // begun mid-line
    }
    let mut records: Vec<AuditRecord> = lines
        .filter_map(|line| serde_json::from_str(line).ok())
        .collect();
    records.reverse();
    records.truncate(count);
    Ok(records)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_survive_reopening_and_come_back_newest_first() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE_NAME);
        let trail = AuditTrail::open(&path).unwrap();
        let submit = AuditRecord::now(
            "anna",
            "10.0.0.9:5123",
            AuditAction::Submit,
            AuditOutcome::Done,
        )
        .with(serde_json::json!({"product": "breaker", "count": 1}));
        trail.append(&submit).unwrap();
        drop(trail);
        let trail = AuditTrail::open(&path).unwrap();
        let refused = AuditRecord::now(
            "bert",
            "10.0.0.9:5124",
            AuditAction::Cancel,
            AuditOutcome::Refused("observers change nothing".into()),
        )
        .on("orders1-3");
        trail.append(&refused).unwrap();
        // A torn line (a crash mid-write) is skipped, not fatal.
        std::fs::OpenOptions::new()
            .append(true)
            .open(&path)
            .unwrap()
            .write_all(b"{\"at\":1,\"who\"")
            .unwrap();
        assert_eq!(newest(&path, 10).unwrap(), vec![refused.clone(), submit]);
        assert_eq!(newest(&path, 1).unwrap(), vec![refused]);
        let line = std::fs::read_to_string(&path).unwrap();
        assert!(
            line.contains(r#""outcome":"refused","why":"observers change nothing""#),
            "{line}"
        );
    }

    #[test]
    fn a_trail_others_can_read_is_refused() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE_NAME);
        drop(AuditTrail::open(&path).unwrap());
        let mode = std::fs::metadata(&path).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode, 0o600);
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
        let refused = AuditTrail::open(&path).unwrap_err().to_string();
        assert!(refused.contains("chmod 600"), "{refused}");
    }
}

//! The journal: a holon's durable state, in an embedded SQLite database (rusqlite with
//! the bundled library) in WAL mode, one file per holon under `--data-dir`.
//!
//! The store is deliberately small: records of JSON, addressed by a kind and an id.
//! Holons write the record that changed *before* they acknowledge anything that depends
//! on it.
//!
//! Group commit: writers that call [`Journal::put`] at the same time (an order-node's
//! orders, each in its own task) share one transaction and so one fsync. Each queues its
//! record and takes the connection; whoever gets it commits every record queued so far,
//! and the writers whose records went in that commit return with its outcome, without
//! a commit of their own. A lone writer commits alone, as before.
//!
//! Durability ([`Durability`]):
//! - `process_crash`: `synchronous = NORMAL`. A commit survives the process being killed
//!   at any instant (the WAL is in the OS's page cache); a power loss or kernel crash may
//!   lose the last commits (never corrupts the database).
//! - `power_loss` (default): `synchronous = FULL`. Every commit is fsynced before it
//!   returns; it survives a power loss too, at the cost of one fsync per commit.
//!
//! The file is opened with an exclusive lock, so a second process pointed at the same
//! data directory fails at start with a clear error instead of corrupting the state.

use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::Mutex;

use rusqlite::{params, Connection, OptionalExtension};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};

/// What a commit survives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Durability {
    /// Survives the process being killed (SQLite `synchronous = NORMAL` in WAL mode).
    ProcessCrash,
    /// Survives a power loss as well (`synchronous = FULL`: an fsync per commit).
    #[default]
    PowerLoss,
}

impl FromStr for Durability {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "process_crash" => Ok(Durability::ProcessCrash),
            "power_loss" => Ok(Durability::PowerLoss),
            other => Err(format!(
                "unknown durability {other:?} (process_crash or power_loss)"
            )),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum JournalError {
    #[error("cannot create the data directory {path}: {source}")]
    Directory {
        path: String,
        source: std::io::Error,
    },
    #[error("the data directory {path} is not writable ({source}): the journal lives there")]
    NotWritable {
        path: String,
        source: std::io::Error,
    },
    #[error("journal {path}: {message}")]
    Sqlite { path: String, message: String },
    #[error("journal {path} is in use by another process (one holon per data file)")]
    InUse { path: String },
    #[error(
        "journal {path} exists but cannot be read: {why}. It was not replaced by an empty \
         one (that would lose what it holds). Restore it from a backup, or move it (and \
         its -wal file) aside to start with an empty state: see \"A damaged journal\" in \
         docs/reliability.md"
    )]
    Damaged { path: String, why: String },
    #[error("journal {path}: record {kind}/{id} cannot be read: {message}")]
    Decode {
        path: String,
        kind: String,
        id: String,
        message: String,
    },
}

/// SQLite's WAL magic numbers (big- and little-endian checksums).
const WAL_MAGIC: [u32; 2] = [0x377f_0682, 0x377f_0683];

/// Refuses a write-ahead log that exists but does not start with a WAL header: SQLite
/// would ignore it, and the commits in it would be lost without a word. (An empty WAL
/// or none is normal; a torn last frame after a crash is normal too and is handled by
/// SQLite: only the header is checked here.)
fn check_wal_header(wal: &Path) -> Result<(), String> {
    use std::io::Read;
    let mut file = match std::fs::File::open(wal) {
        Ok(file) => file,
        Err(_) => return Ok(()),
    };
    let mut header = Vec::with_capacity(32);
    if let Err(e) = (&mut file).take(32).read_to_end(&mut header) {
        return Err(format!(
            "its write-ahead log {} cannot be read: {e}",
            wal.display()
        ));
    }
    if header.is_empty() {
        return Ok(());
    }
    let magic = header
        .get(..4)
        .map(|b| u32::from_be_bytes([b[0], b[1], b[2], b[3]]));
    if header.len() < 32 || !magic.is_some_and(|m| WAL_MAGIC.contains(&m)) {
        return Err(format!(
            "its write-ahead log {} is not a SQLite WAL (damaged: it may hold the last commits)",
            wal.display()
        ));
    }
    Ok(())
}

/// Runs journal work that may block (an fsync, waiting for the file lock): on the
/// multi-thread runtime the worker hands its other tasks over while it waits (with
/// thousands of orders writing at once, nothing else, SIGTERM or queries, would run
/// otherwise); elsewhere it just runs.
pub fn blocking<R>(work: impl FnOnce() -> R) -> R {
    let multi_thread = tokio::runtime::Handle::try_current()
        .is_ok_and(|h| h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread);
    if multi_thread {
        tokio::task::block_in_place(work)
    } else {
        work()
    }
}

/// A holon's journal.
pub struct Journal {
    path: PathBuf,
    /// What a commit survives; a `power_loss` commit waits for its fsync in
    /// [`blocking`].
    durability: Durability,
    connection: Mutex<Connection>,
    /// Records queued for the next commit, and how the last commits ended.
    queue: Mutex<Queue>,
}

/// The group commit's queue (see the module's doc).
#[derive(Default)]
struct Queue {
    /// Records waiting for a commit: (sequence number, kind, id, body).
    records: Vec<(u64, String, String, String)>,
    /// The sequence number of the next record queued.
    next: u64,
    /// Every record numbered below this went through a commit (or a failed one).
    done_below: u64,
    /// Commits that failed and still have writers to tell: the records' numbers
    /// (first, end), the error's text, and how many writers have yet to read it.
    failed: Vec<(u64, u64, String, usize)>,
    /// Commits made by [`Journal::put`] so far.
    commits: u64,
}

impl std::fmt::Debug for Journal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Journal").field("path", &self.path).finish()
    }
}

/// Narrows the journal's files (`path` and its `-wal` and `-shm`) to their owner: a
/// journal of an older release was created 0644, and a process whose umask is open
/// creates them so.
fn owner_only(path: &Path) -> std::io::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
    let name = name.unwrap_or_default();
    for file in [
        path.to_path_buf(),
        path.with_file_name(format!("{name}-wal")),
        path.with_file_name(format!("{name}-shm")),
    ] {
        let mode = match std::fs::metadata(&file) {
            Ok(meta) => meta.permissions().mode(),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e),
        };
        if mode & 0o077 != 0 {
            std::fs::set_permissions(&file, std::fs::Permissions::from_mode(mode & 0o700))?;
        }
    }
    Ok(())
}

impl Journal {
    /// Opens (creating if needed) `dir/file`, readable by its owner only.
    pub fn open(dir: &Path, file: &str, durability: Durability) -> Result<Journal, JournalError> {
        std::fs::create_dir_all(dir).map_err(|source| JournalError::Directory {
            path: dir.display().to_string(),
            source,
        })?;
        // A read-only directory would surface as SQLite's "disk I/O error": say it.
        let probe = dir.join(format!(".{file}.write-test"));
        if let Err(e) = std::fs::write(&probe, b"") {
            return Err(JournalError::NotWritable {
                path: dir.display().to_string(),
                source: e,
            });
        }
        if let Err(e) = std::fs::remove_file(&probe) {
            tracing::debug!(error = %e, "cannot remove the write test file");
        }
        let path = dir.join(file);
        let display = path.display().to_string();
        let damaged = |why: String| JournalError::Damaged {
            path: display.clone(),
            why,
        };
        // A journal that existed must come back as it was, never as an empty one: SQLite
        // would take a zero-length file for a new database and ignore a WAL whose header
        // is garbage (with the commits in it).
        let existed = match std::fs::metadata(&path) {
            Ok(meta) if meta.len() == 0 => {
                return Err(damaged("the file is empty (zero length)".into()))
            }
            Ok(_) => true,
            Err(_) => false,
        };
        check_wal_header(&path.with_file_name(format!("{file}-wal"))).map_err(&damaged)?;

        let sqlite = |e: rusqlite::Error| match e.sqlite_error_code() {
            Some(rusqlite::ErrorCode::DatabaseBusy | rusqlite::ErrorCode::DatabaseLocked) => {
                JournalError::InUse {
                    path: display.clone(),
                }
            }
            Some(rusqlite::ErrorCode::DatabaseCorrupt | rusqlite::ErrorCode::NotADatabase) => {
                JournalError::Damaged {
                    path: display.clone(),
                    why: e.to_string(),
                }
            }
            _ => JournalError::Sqlite {
                path: display.clone(),
                message: e.to_string(),
            },
        };
        let connection = Connection::open(&path).map_err(sqlite)?;
        connection
            .busy_timeout(std::time::Duration::from_millis(200))
            .map_err(sqlite)?;
        let synchronous = match durability {
            Durability::ProcessCrash => "NORMAL",
            Durability::PowerLoss => "FULL",
        };
        let setup = format!(
            "PRAGMA locking_mode = EXCLUSIVE;
             PRAGMA journal_mode = WAL;
             PRAGMA synchronous = {synchronous};"
        );
        connection.execute_batch(&setup).map_err(sqlite)?;
        // Orders, bookings and results are the plant's business: the journal is its
        // owner's alone (the holon binaries also create every file so, umask 077).
        owner_only(&path).map_err(|source| JournalError::NotWritable {
            path: display.clone(),
            source,
        })?;
        if existed {
            // Every page read once: damage shows now, not in the middle of a job.
            let verdict: String = connection
                .query_row("PRAGMA quick_check", [], |row| row.get(0))
                .map_err(sqlite)?;
            if verdict != "ok" {
                return Err(damaged(format!("SQLite's quick_check says: {verdict}")));
            }
            let has_records: bool = connection
                .query_row(
                    "SELECT count(*) > 0 FROM sqlite_master WHERE type = 'table' AND name = 'records'",
                    [],
                    |row| row.get(0),
                )
                .map_err(sqlite)?;
            if !has_records {
                return Err(damaged(
                    "it is not a holarchy journal (no records table)".into(),
                ));
            }
        }
        connection
            .execute_batch(
                "CREATE TABLE IF NOT EXISTS records (
                     kind TEXT NOT NULL,
                     id   TEXT NOT NULL,
                     body TEXT NOT NULL,
                     PRIMARY KEY (kind, id)
                 );",
            )
            .map_err(sqlite)?;
        // Take the exclusive lock now, so a second process fails at start.
        connection
            .execute_batch("BEGIN IMMEDIATE; COMMIT;")
            .map_err(sqlite)?;
        Ok(Journal {
            path,
            durability,
            connection: Mutex::new(connection),
            queue: Mutex::new(Queue::default()),
        })
    }

    /// Opens `dir/file` like [`Journal::open`], but waits up to `patience` for another
    /// process to let go of it: a successor taking over a holon opens the journal its
    /// predecessor is closing. Any other error returns at once. The wait does not hold
    /// a runtime worker (see [`blocking`]).
    pub fn open_when_free(
        dir: &Path,
        file: &str,
        durability: Durability,
        patience: std::time::Duration,
    ) -> Result<Journal, JournalError> {
        if patience.is_zero() {
            return Journal::open(dir, file, durability);
        }
        blocking(|| Journal::open_waiting(dir, file, durability, patience))
    }

    /// [`Journal::open_when_free`]'s wait, on the calling thread.
    fn open_waiting(
        dir: &Path,
        file: &str,
        durability: Durability,
        patience: std::time::Duration,
    ) -> Result<Journal, JournalError> {
        let deadline = std::time::Instant::now() + patience;
        loop {
            match Journal::open(dir, file, durability) {
                Err(JournalError::InUse { path }) => {
                    if std::time::Instant::now() >= deadline {
                        return Err(JournalError::InUse { path });
                    }
                    tracing::debug!(%path, "the journal is still in use; waiting for its holder to close it");
                    std::thread::sleep(std::time::Duration::from_millis(20));
                }
                opened => return opened,
            }
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    fn error(&self, e: rusqlite::Error) -> JournalError {
        JournalError::Sqlite {
            path: self.path.display().to_string(),
            message: e.to_string(),
        }
    }

    fn connection(&self) -> std::sync::MutexGuard<'_, Connection> {
        self.connection.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// How many commits [`Journal::put`] made so far (fewer than its records when
    /// writers shared them).
    pub fn commits(&self) -> u64 {
        self.queue().commits
    }

    fn queue(&self) -> std::sync::MutexGuard<'_, Queue> {
        self.queue.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Writes one record, committed (durable as configured) when this returns; writers
    /// at the same time share the commit (see the module's doc).
    pub fn put<T: Serialize>(&self, kind: &str, id: &str, value: &T) -> Result<(), JournalError> {
        let body = serde_json::to_string(value).expect("journal records serialize");
        let mine = {
            let mut queue = self.queue();
            let mine = queue.next;
            queue.next += 1;
            queue
                .records
                .push((mine, kind.to_string(), id.to_string(), body));
            mine
        };
        let mut connection = self.connection();
        let (batch, first) = {
            let mut queue = self.queue();
            if mine < queue.done_below {
                // Committed by the writer that had the connection before: its outcome.
                return match queue.failed.iter_mut().find(|f| f.0 <= mine && mine < f.1) {
                    Some(failed) => {
                        failed.3 -= 1;
                        let message = failed.2.clone();
                        queue.failed.retain(|f| f.3 > 0);
                        Err(JournalError::Sqlite {
                            path: self.path.display().to_string(),
                            message,
                        })
                    }
                    None => Ok(()),
                };
            }
            let batch = std::mem::take(&mut queue.records);
            let first = batch.first().map_or(mine, |r| r.0);
            (batch, first)
        };
        let end = batch.last().map_or(mine + 1, |r| r.0 + 1);
        let written = self.committing(|| self.commit(&mut connection, &batch));
        // Told while the connection is still held: the next writer to take it must see
        // whether its record went in this commit.
        let mut queue = self.queue();
        queue.done_below = end;
        if let Err(e) = &written {
            let others = batch.len() - 1;
            if others > 0 {
                let message = match e {
                    JournalError::Sqlite { message, .. } => message.clone(),
                    other => other.to_string(),
                };
                queue.failed.push((first, end, message, others));
            }
        }
        queue.commits += 1;
        drop(queue);
        drop(connection);
        written
    }

    /// Writes `batch` in one transaction (a single record in its own statement); the
    /// sequence numbers are the group commit's, not written.
    fn commit(
        &self,
        connection: &mut Connection,
        batch: &[(u64, String, String, String)],
    ) -> Result<(), JournalError> {
        // Statements are prepared once per connection and cached: parsing the SQL
        // again cost about as much as executing it (profiled on the booking path).
        const UPSERT: &str = "INSERT INTO records (kind, id, body) VALUES (?1, ?2, ?3)
             ON CONFLICT (kind, id) DO UPDATE SET body = excluded.body";
        if let [(_, kind, id, body)] = batch {
            return connection
                .prepare_cached(UPSERT)
                .and_then(|mut statement| statement.execute(params![kind, id, body]))
                .map(|_| ())
                .map_err(|e| self.error(e));
        }
        let transaction = connection.transaction().map_err(|e| self.error(e))?;
        {
            let mut statement = transaction
                .prepare_cached(UPSERT)
                .map_err(|e| self.error(e))?;
            for (_, kind, id, body) in batch {
                statement
                    .execute(params![kind, id, body])
                    .map_err(|e| self.error(e))?;
            }
        }
        transaction.commit().map_err(|e| self.error(e))
    }

    /// Writes several records (`(kind, id, value)`) in one commit: either all are
    /// written or none, and they share one sync (a batch of new orders costs one
    /// fsync with `power_loss`, not one each).
    pub fn put_all<'a, T, I>(&self, records: I) -> Result<(), JournalError>
    where
        T: Serialize + 'a,
        I: IntoIterator<Item = (&'a str, &'a str, &'a T)>,
    {
        let batch: Vec<(u64, String, String, String)> = records
            .into_iter()
            .map(|(kind, id, value)| {
                let body = serde_json::to_string(value).expect("journal records serialize");
                (0, kind.to_string(), id.to_string(), body)
            })
            .collect();
        self.committing(|| self.commit(&mut self.connection(), &batch))
    }

    /// Runs a commit: a `power_loss` one in [`blocking`], since its fsync may take long
    /// on a slow or failing disk and a holon-node's pool has one thread (its links'
    /// keep-alives and its other components go on meanwhile). A `process_crash` commit
    /// only writes to the OS's page cache and runs where it is.
    fn committing<R>(&self, commit: impl FnOnce() -> R) -> R {
        match self.durability {
            Durability::PowerLoss => blocking(commit),
            Durability::ProcessCrash => commit(),
        }
    }

    /// Removes records of `kind` (no error for one that is absent), all in one commit:
    /// either every one is gone or none is. Their pages are reused by later records
    /// (the file does not shrink).
    pub fn delete<I, S>(&self, kind: &str, ids: I) -> Result<(), JournalError>
    where
        I: IntoIterator<Item = S>,
        S: AsRef<str>,
    {
        let mut connection = self.connection();
        let transaction = connection.transaction().map_err(|e| self.error(e))?;
        {
            let mut statement = transaction
                .prepare_cached("DELETE FROM records WHERE kind = ?1 AND id = ?2")
                .map_err(|e| self.error(e))?;
            for id in ids {
                statement
                    .execute(params![kind, id.as_ref()])
                    .map_err(|e| self.error(e))?;
            }
        }
        self.committing(|| transaction.commit().map_err(|e| self.error(e)))
    }

    /// Reads one record.
    pub fn get<T: DeserializeOwned>(
        &self,
        kind: &str,
        id: &str,
    ) -> Result<Option<T>, JournalError> {
        let body: Option<String> = self
            .connection()
            .query_row(
                "SELECT body FROM records WHERE kind = ?1 AND id = ?2",
                params![kind, id],
                |row| row.get(0),
            )
            .optional()
            .map_err(|e| self.error(e))?;
        body.map(|b| self.decode(kind, id, &b)).transpose()
    }

    /// Reads the records of `kind` with these ids, in the order asked, with one hold of
    /// the connection; absent ones are left out.
    pub fn get_many<T, I, S>(&self, kind: &str, ids: I) -> Result<Vec<(String, T)>, JournalError>
    where
        T: DeserializeOwned,
        I: IntoIterator<Item = S>,
        S: AsRef<str>,
    {
        let rows: Vec<(String, String)> = {
            let connection = self.connection();
            let mut statement = connection
                .prepare_cached("SELECT body FROM records WHERE kind = ?1 AND id = ?2")
                .map_err(|e| self.error(e))?;
            let mut rows = Vec::new();
            for id in ids {
                let id = id.as_ref();
                let body: Option<String> = statement
                    .query_row(params![kind, id], |row| row.get(0))
                    .optional()
                    .map_err(|e| self.error(e))?;
                if let Some(body) = body {
                    rows.push((id.to_string(), body));
                }
            }
            rows
        };
        rows.into_iter()
            .map(|(id, body)| {
                let value = self.decode(kind, &id, &body)?;
                Ok((id, value))
            })
            .collect()
    }

    /// Every record of a kind, by id, handed to `visit` one at a time as it is decoded
    /// (a caller that keeps a few of many records never holds them all). The
    /// connection is held until the last is visited.
    pub fn for_each<T: DeserializeOwned>(
        &self,
        kind: &str,
        mut visit: impl FnMut(String, T),
    ) -> Result<(), JournalError> {
        let connection = self.connection();
        let mut statement = connection
            .prepare("SELECT id, body FROM records WHERE kind = ?1 ORDER BY id")
            .map_err(|e| self.error(e))?;
        let mut rows = statement.query(params![kind]).map_err(|e| self.error(e))?;
        while let Some(row) = rows.next().map_err(|e| self.error(e))? {
            let id: String = row.get(0).map_err(|e| self.error(e))?;
            let body: String = row.get(1).map_err(|e| self.error(e))?;
            let value = self.decode(kind, &id, &body)?;
            visit(id, value);
        }
        Ok(())
    }

    /// Every record of a kind, by id.
    pub fn list<T: DeserializeOwned>(&self, kind: &str) -> Result<Vec<(String, T)>, JournalError> {
        let rows: Vec<(String, String)> = {
            let connection = self.connection();
            let mut statement = connection
                .prepare("SELECT id, body FROM records WHERE kind = ?1 ORDER BY id")
                .map_err(|e| self.error(e))?;
            let rows = statement
                .query_map(params![kind], |row| Ok((row.get(0)?, row.get(1)?)))
                .map_err(|e| self.error(e))?;
            rows.collect::<Result<_, _>>().map_err(|e| self.error(e))?
        };
        rows.into_iter()
            .map(|(id, body)| {
                let value = self.decode(kind, &id, &body)?;
                Ok((id, value))
            })
            .collect()
    }

    fn decode<T: DeserializeOwned>(
        &self,
        kind: &str,
        id: &str,
        body: &str,
    ) -> Result<T, JournalError> {
        serde_json::from_str(body).map_err(|e| JournalError::Decode {
            path: self.path.display().to_string(),
            kind: kind.to_string(),
            id: id.to_string(),
            message: e.to_string(),
        })
    }
}

#[cfg(test)]
mod tests;

//! Reading the users file, and changing it: under an exclusive lock, written whole to a
//! temporary file beside it (0600), synced, renamed over it, the directory synced; a
//! crash leaves the old file or the new one, and two `cell users` never lose each
//! other's change.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

use nix::fcntl::{Flock, FlockArg};
use serde::{Deserialize, Serialize};

use super::{password, valid_name, User, Users, UsersError};

/// The users file as written.
#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct UsersFile {
    /// One entry per user.
    #[serde(default)]
    user: Vec<User>,
}

/// What the file starts with when `cell users` writes it.
const HEADER: &str = "# The cell's users (docs/opcua.md, \"Users\"): written by `cell users`; keep it 0600.\n# role: observer | operator | admin; password: an argon2id hash, never the password.\n\n";

/// Reads the users file at `path`; refuses one that others may read or write, unknown
/// fields, bad names, names given twice and hashes that are not argon2id PHC strings.
pub fn load(path: &Path) -> Result<Users, UsersError> {
    read(path)?.ok_or_else(|| UsersError::Read {
        path: path.display().to_string(),
        source: std::io::ErrorKind::NotFound.into(),
    })
}

/// [`load`], with `None` for a file that does not exist.
fn read(path: &Path) -> Result<Option<Users>, UsersError> {
    let shown = path.display().to_string();
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(source) => {
            return Err(UsersError::Read {
                path: shown,
                source,
            })
        }
    };
    if let Some(mode) = crate::security::private_file::open_to_others(path) {
        return Err(UsersError::Open { path: shown, mode });
    }
    let invalid = |message: String| UsersError::Invalid {
        path: shown.clone(),
        message,
    };
    let file: UsersFile = toml::from_str(&text).map_err(|e| invalid(e.to_string()))?;
    let mut users = Users::default();
    for user in file.user {
        if !valid_name(&user.name) {
            return Err(invalid(UsersError::BadName(user.name).to_string()));
        }
        if users.get(&user.name).is_some() {
            return Err(invalid(format!("user {} appears twice", user.name)));
        }
        password::check(&user.password).map_err(|e| invalid(format!("user {}: {e}", user.name)))?;
        users.users.push(user);
    }
    Ok(Some(users))
}

/// Changes the users file at `path`: takes an exclusive lock (`<path>.lock`, 0600),
/// reads the file (a missing one is empty), applies `f`, and writes the result
/// atomically, readable by its owner only. Nothing is written when `f` fails.
pub fn change<T>(
    path: &Path,
    f: impl FnOnce(&mut Users) -> Result<T, UsersError>,
) -> Result<T, UsersError> {
    let _lock = lock(path)?;
    let mut users = read(path)?.unwrap_or_default();
    let out = f(&mut users)?;
    write(path, &users)?;
    tracing::debug!(file = %path.display(), users = users.len(), "users file written");
    Ok(out)
}

/// The lock file of the users file `path`.
fn lock_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".lock");
    PathBuf::from(name)
}

/// Holds the exclusive lock of the users file `path` until dropped.
fn lock(path: &Path) -> Result<Flock<File>, UsersError> {
    let lock_path = lock_path(path);
    let failed = |source| UsersError::Lock {
        path: lock_path.display().to_string(),
        source,
    };
    let file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .mode(0o600)
        .open(&lock_path)
        .map_err(failed)?;
    Flock::lock(file, FlockArg::LockExclusive).map_err(|(_, errno)| failed(errno.into()))
}

/// Writes `users` to `path` atomically (temporary file, fsync, rename, fsync of the
/// directory).
fn write(path: &Path, users: &Users) -> Result<(), UsersError> {
    let failed = |source| UsersError::Write {
        path: path.display().to_string(),
        source,
    };
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let file_name = path
        .file_name()
        .ok_or_else(|| failed(std::io::ErrorKind::InvalidInput.into()))?;
    let temp = dir.join(format!(
        ".{}.{}.tmp",
        file_name.to_string_lossy(),
        std::process::id()
    ));
    let text = toml::to_string(&UsersFile {
        user: users.users.clone(),
    })
    .map_err(|e| failed(std::io::Error::other(e)))?;
    // A leftover of a crash of this very pid is ours to replace (we hold the lock).
    let _ = std::fs::remove_file(&temp);
    let written = (|| {
        let mut file = OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(0o600)
            .open(&temp)?;
        file.write_all(HEADER.as_bytes())?;
        file.write_all(text.as_bytes())?;
        file.sync_all()?;
        std::fs::rename(&temp, path)?;
        File::open(dir)?.sync_all()
    })();
    if written.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    written.map_err(failed)
}

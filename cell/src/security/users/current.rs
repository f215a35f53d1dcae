//! The users file as it is now: every door (the dashboard's login, the OPC UA server)
//! reads the cell's people through one [`CurrentUsers`], which reads the file again
//! when its modification time or length changed, so that `cell users` (or the
//! dashboard's admin page) changing it is seen by the next login, and by the next
//! check of a live session.

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::SystemTime;

use tracing::{error, info};

use super::{User, Users};

/// The users file as last read.
#[derive(Debug, Default)]
struct Cache {
    /// The file's modification time, length and inode when read (`cell users` replaces
    /// the file by a rename: a new inode even within the clock's resolution).
    stamp: Option<(SystemTime, u64, u64)>,
    /// Its users (empty when it could not be read).
    users: Arc<Users>,
}

/// A users file, read again when it changes; or a fixed set of users (none: a door
/// without passwords).
#[derive(Debug)]
pub struct CurrentUsers {
    /// The file (`None`: the users are fixed).
    path: Option<PathBuf>,
    /// What was read last.
    cache: Mutex<Cache>,
}

impl CurrentUsers {
    /// The users of the file at `path`, as it changes.
    pub fn file(path: PathBuf) -> CurrentUsers {
        CurrentUsers {
            path: Some(path),
            cache: Mutex::new(Cache::default()),
        }
    }

    /// These users, for good (none: nobody logs in with a password).
    pub fn fixed(users: Users) -> CurrentUsers {
        CurrentUsers {
            path: None,
            cache: Mutex::new(Cache {
                stamp: None,
                users: Arc::new(users),
            }),
        }
    }

    /// The file, if the users come from one.
    pub fn path(&self) -> Option<&Path> {
        self.path.as_deref()
    }

    /// The users now: the file is read again if it changed since it was last read. A
    /// file that cannot be read (a typo of an edit by hand) lets nobody in, with an
    /// error in the log, until it is fixed.
    pub fn get(&self) -> Arc<Users> {
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        let Some(path) = &self.path else {
            return cache.users.clone();
        };
        let stamp = std::fs::metadata(path)
            .ok()
            .and_then(|m| Some((m.modified().ok()?, m.len(), m.ino())));
        if cache.stamp.is_some() && cache.stamp == stamp {
            return cache.users.clone();
        }
        cache.stamp = stamp;
        cache.users = match super::load(path) {
            Ok(users) => {
                info!(users = users.len(), file = %path.display(), "users file read");
                Arc::new(users)
            }
            Err(e) => {
                error!(error = %e, "nobody can log in with a password until the users file is fixed");
                Arc::new(Users::default())
            }
        };
        cache.users.clone()
    }
}

/// What a live session remembers of its user: a user whose role or password changed
/// (or who was removed) has another fingerprint, or none, and their sessions end. A
/// short digest: it names neither the role nor the hash.
pub fn fingerprint(user: &User) -> String {
    use std::hash::{Hash, Hasher};
    let mut hasher = std::collections::hash_map::DefaultHasher::new();
    user.role.as_str().hash(&mut hasher);
    user.password.hash(&mut hasher);
    format!("{:016x}", hasher.finish())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::security::users::Role;

    #[test]
    fn a_changed_file_is_read_again_and_a_changed_user_has_another_fingerprint() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("users.toml");
        crate::security::users::change(&path, |users| {
            users.add("anna", Role::Operator, "anna-password-1")
        })
        .unwrap();
        let current = CurrentUsers::file(path.clone());
        let before = fingerprint(current.get().get("anna").unwrap());
        crate::security::users::change(&path, |users| {
            users.set_role("anna", Role::Observer).map(|_| ())
        })
        .unwrap();
        let after = current.get();
        assert_eq!(after.get("anna").unwrap().role, Role::Observer);
        assert_ne!(fingerprint(after.get("anna").unwrap()), before);
        crate::security::users::change(&path, |users| users.remove("anna").map(|_| ())).unwrap();
        assert!(current.get().get("anna").is_none());
    }
}

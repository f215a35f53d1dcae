//! The people of a cell: one users file per cell, read by the web dashboard's login and
//! by `cell opcua`, changed with `cell users` (docs/opcua.md, "Users").
//!
//! The file is TOML, `<pki>/users.toml` by default ([`default_path`]), its owner's
//! alone (0600; one that others may read or write is refused):
//!
//! ```toml
//! [[user]]
//! name = "anna"
//! role = "operator"   # observer | operator | admin
//! password = "$argon2id$v=19$m=19456,t=2,p=1$..."   # PHC string, written by `cell users`
//! ```
//!
//! Passwords are stored as argon2id hashes ([`password`]); neither a password nor a
//! hash is ever logged or printed. [`Users::verify`] costs tens of milliseconds of CPU:
//! callers in async code run it in `tokio::task::spawn_blocking`. [`change`] changes
//! the file under a lock, atomically.

pub mod cli;
mod current;
mod file;
pub mod password;
#[cfg(test)]
mod tests;

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::{Deserialize, Serialize};

pub use current::{fingerprint, CurrentUsers};
pub use file::{change, load};

/// The users file's name in a cell's PKI directory.
pub const FILE_NAME: &str = "users.toml";

/// The longest user name, in bytes (`opcua:<name>` fits a PackML request's `by`).
pub const MAX_NAME: usize = 64;

/// The users file of the cell whose PKI directory is `pki`.
pub fn default_path(pki: &Path) -> PathBuf {
    pki.join(FILE_NAME)
}

/// What a user may do; ordered by what they may do (Observer < Operator < Admin).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Watches: browse, read, subscribe; changes nothing.
    Observer,
    /// Operates the cell: submits and cancels orders, commands resources, acknowledges
    /// alarms.
    Operator,
    /// Operates the cell and manages its users.
    Admin,
}

impl Role {
    /// Whether the role may operate the cell (operator, admin).
    pub fn may_operate(self) -> bool {
        self >= Role::Operator
    }

    /// Whether the role may add, change and remove users (admin).
    pub fn may_manage_users(self) -> bool {
        self == Role::Admin
    }

    /// The role as written in the users file: `observer`, `operator`, `admin`.
    pub fn as_str(self) -> &'static str {
        match self {
            Role::Observer => "observer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }
}

impl fmt::Display for Role {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for Role {
    type Err = UsersError;

    fn from_str(text: &str) -> Result<Role, UsersError> {
        match text {
            "observer" => Ok(Role::Observer),
            "operator" => Ok(Role::Operator),
            "admin" => Ok(Role::Admin),
            _ => Err(UsersError::BadRole(text.to_string())),
        }
    }
}

/// One person of the cell, as the users file holds them.
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct User {
    /// The name they log in with: 1 to [`MAX_NAME`] bytes of `[A-Za-z0-9._-]`.
    pub name: String,
    /// What they may do.
    pub role: Role,
    /// Their password's argon2id hash, a PHC string ([`password::hash`]).
    pub password: String,
}

/// Without the hash: a `{:?}` in a log line never shows it.
impl fmt::Debug for User {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("User")
            .field("name", &self.name)
            .field("role", &self.role)
            .finish_non_exhaustive()
    }
}

/// The users file's problems, and the changes it refuses.
#[derive(Debug, thiserror::Error)]
pub enum UsersError {
    #[error("cannot read the users file {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot write the users file {path}: {source}")]
    Write {
        path: String,
        source: std::io::Error,
    },
    #[error("cannot lock the users file {path}: {source}")]
    Lock {
        path: String,
        source: std::io::Error,
    },
    #[error("the users file {path} is not valid: {message}")]
    Invalid { path: String, message: String },
    #[error("the users file {path} is open to other users (mode {mode:o}); it holds password hashes: chmod 600 {path}")]
    Open { path: String, mode: u32 },
    #[error("bad user name {0:?}: 1 to 64 bytes of letters, digits, '.', '_' and '-'")]
    BadName(String),
    #[error("unknown role {0:?}: observer, operator or admin")]
    BadRole(String),
    #[error("a password of at least {} characters", password::MIN_LENGTH)]
    ShortPassword,
    #[error("there is already a user {0}")]
    Exists(String),
    #[error("there is no user {0}")]
    Unknown(String),
    #[error("{0} is the last admin: add another admin first")]
    LastAdmin(String),
}

impl UsersError {
    /// Whether this is a change refused (a bad name, an existing user...), not a
    /// problem of the file or the system.
    pub fn is_refusal(&self) -> bool {
        matches!(
            self,
            UsersError::BadName(_)
                | UsersError::BadRole(_)
                | UsersError::ShortPassword
                | UsersError::Exists(_)
                | UsersError::Unknown(_)
                | UsersError::LastAdmin(_)
        )
    }
}

/// Whether `name` is a valid user name: 1 to [`MAX_NAME`] bytes of `[A-Za-z0-9._-]`.
pub fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= MAX_NAME
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'-'))
}

/// The users of a cell, in the file's order.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Users {
    /// One per name.
    users: Vec<User>,
}

impl Users {
    /// The user called `name`.
    pub fn get(&self, name: &str) -> Option<&User> {
        self.users.iter().find(|u| u.name == name)
    }

    /// Every user, in the file's order.
    pub fn iter(&self) -> impl Iterator<Item = &User> {
        self.users.iter()
    }

    /// Whether there is no user at all.
    pub fn is_empty(&self) -> bool {
        self.users.is_empty()
    }

    /// How many users there are.
    pub fn len(&self) -> usize {
        self.users.len()
    }

    /// The user called `name` if `password` is theirs. When no user has that name, a
    /// fixed hash is verified anyway, so that the time taken does not tell which names
    /// exist. Costs tens of milliseconds of CPU: in async code, call it in
    /// `tokio::task::spawn_blocking`.
    pub fn verify(&self, name: &str, password: &str) -> Option<&User> {
        self.verify_in(name, password, &mut password::Memory::default())
    }

    /// [`Users::verify`], in `memory` kept from one check to the next (a server's
    /// logins, [`crate::security::logins`]).
    pub fn verify_in(
        &self,
        name: &str,
        password: &str,
        memory: &mut password::Memory,
    ) -> Option<&User> {
        match self.get(name) {
            Some(user) => password::verify_in(&user.password, password, memory).then_some(user),
            None => {
                password::verify_dummy_in(password, memory);
                None
            }
        }
    }

    /// Adds a user with a new password (hashed here); refuses a bad name, a name
    /// taken, a password shorter than [`password::MIN_LENGTH`] characters.
    pub fn add(&mut self, name: &str, role: Role, password: &str) -> Result<(), UsersError> {
        if !valid_name(name) {
            return Err(UsersError::BadName(name.to_string()));
        }
        if self.get(name).is_some() {
            return Err(UsersError::Exists(name.to_string()));
        }
        if !password::long_enough(password) {
            return Err(UsersError::ShortPassword);
        }
        self.users.push(User {
            name: name.to_string(),
            role,
            password: password::hash(password),
        });
        Ok(())
    }

    /// Gives `name` a new password.
    pub fn set_password(&mut self, name: &str, password: &str) -> Result<(), UsersError> {
        if !password::long_enough(password) {
            return Err(UsersError::ShortPassword);
        }
        let user = self.get_mut(name)?;
        user.password = password::hash(password);
        Ok(())
    }

    /// Gives `name` another role and returns the one they had; refuses to demote the
    /// last admin.
    pub fn set_role(&mut self, name: &str, role: Role) -> Result<Role, UsersError> {
        let was = self.get_mut(name)?.role;
        if was == Role::Admin && role != Role::Admin {
            self.keep_an_admin(name)?;
        }
        self.get_mut(name)?.role = role;
        Ok(was)
    }

    /// Removes `name` and returns them; refuses to remove the last admin.
    pub fn remove(&mut self, name: &str) -> Result<User, UsersError> {
        let at = self
            .users
            .iter()
            .position(|u| u.name == name)
            .ok_or_else(|| UsersError::Unknown(name.to_string()))?;
        if self.users[at].role == Role::Admin {
            self.keep_an_admin(name)?;
        }
        Ok(self.users.remove(at))
    }

    fn get_mut(&mut self, name: &str) -> Result<&mut User, UsersError> {
        self.users
            .iter_mut()
            .find(|u| u.name == name)
            .ok_or_else(|| UsersError::Unknown(name.to_string()))
    }

    /// Refuses when the admin `name` is the only one (a file with admins keeps one; a
    /// file without any is allowed).
    fn keep_an_admin(&self, name: &str) -> Result<(), UsersError> {
        let admins = self.users.iter().filter(|u| u.role == Role::Admin).count();
        if admins <= 1 {
            return Err(UsersError::LastAdmin(name.to_string()));
        }
        Ok(())
    }
}

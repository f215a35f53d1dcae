//! What every holon's config file shares, read and checked in one place: the file read
//! and parsed with errors that name it, and its header (`cell`, `name`, `[zenoh]`) with
//! the command line applied, paths resolved beside the file, and the name and session
//! settings checked for the holon's identity. Resources, products, staff holons and
//! order-nodes each add their own sections.

use std::path::{Path, PathBuf};

use schemas::CellKeys;
use serde::de::DeserializeOwned;

use crate::role::Role;
use crate::session::{CommandLine, ZenohSettings};

/// A config file that cannot be used, naming the file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    /// Not TOML, or a field unknown, missing or of the wrong type.
    #[error("{path}: {message}")]
    Parse { path: String, message: String },
    /// Well-formed, but a value is not allowed.
    #[error("{path}: {message}")]
    Invalid { path: String, message: String },
}

/// Reads the file at `path`: its text and its name for messages.
pub fn read(path: &Path) -> Result<(String, String), ConfigError> {
    let display = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: display.clone(),
        source,
    })?;
    Ok((text, display))
}

/// Parses `text` (of the file named `path`) as `T`.
pub fn parse<T: DeserializeOwned>(text: &str, path: &str) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| ConfigError::Parse {
        path: path.to_string(),
        message: e.to_string(),
    })
}

/// The fields every holon's file begins with, as read.
#[derive(Debug, Clone)]
pub struct Header {
    /// The cell's name: the root of every key.
    pub cell: String,
    /// The holon's name (an order-node's: the prefix of its orders' names).
    pub name: String,
    /// How it joins the cell.
    pub zenoh: ZenohSettings,
}

/// A header checked: what the holon is in the cell.
#[derive(Debug, Clone)]
pub struct CheckedHeader {
    /// The cell's keys.
    pub keys: CellKeys,
    /// The holon's name, valid as a key segment and a TLS identity.
    pub name: String,
    /// The session settings, checked for the holon's identity (its TLS files exist).
    pub zenoh: ZenohSettings,
}

impl Header {
    /// Checks the header of the file at `path` for a holon of `role`: its `[zenoh]`
    /// paths are resolved beside the file, the command line's `overrides` applied
    /// (`data_dir` is the file's data directory, which `--data-dir` replaces), then the
    /// cell, the name and the session settings checked. The error is the message, for
    /// [`ConfigError::Invalid`].
    pub fn check(
        mut self,
        path: &str,
        overrides: &CommandLine,
        data_dir: &mut Option<PathBuf>,
        role: Role,
    ) -> Result<CheckedHeader, String> {
        if let Some(base) = Path::new(path).parent() {
            self.zenoh.resolve_paths(base);
        }
        overrides.apply(&mut self.cell, &mut self.name, &mut self.zenoh, data_dir);
        let keys = CellKeys::new(&self.cell).map_err(|e| format!("cell: {e}"))?;
        let what = match role {
            Role::OrderNode => "order-node name",
            _ => "holon name",
        };
        schemas::validate_name(what, &self.name).map_err(|e| format!("name: {e}"))?;
        self.zenoh
            .validate(&crate::role::identity(role, &self.name))
            .map_err(|e| format!("zenoh: {e}"))?;
        Ok(CheckedHeader {
            keys,
            name: self.name,
            zenoh: self.zenoh,
        })
    }
}

/// The error for a value that is not allowed in the file named `path`.
pub fn invalid(path: &str) -> impl Fn(String) -> ConfigError + '_ {
    move |message| ConfigError::Invalid {
        path: path.to_string(),
        message,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(cell: &str, name: &str) -> Header {
        Header {
            cell: cell.into(),
            name: name.into(),
            zenoh: ZenohSettings {
                connect: vec!["tcp/127.0.0.1:7447".into()],
                ..ZenohSettings::default()
            },
        }
    }

    #[test]
    fn the_command_line_wins_and_the_result_is_checked() {
        let overrides = CommandLine {
            name: Some("robot2".into()),
            data_dir: Some("/var/lib/holarchy".into()),
            ..CommandLine::default()
        };
        let mut data_dir = None;
        let checked = header("demo", "robot1")
            .check(
                "/etc/holarchy/robot1.toml",
                &overrides,
                &mut data_dir,
                Role::Resource,
            )
            .unwrap();
        assert_eq!(checked.name, "robot2");
        assert_eq!(checked.keys.cell(), "demo");
        assert_eq!(data_dir, Some(PathBuf::from("/var/lib/holarchy")));
    }

    #[test]
    fn a_bad_header_says_which_field() {
        let none = CommandLine::default();
        let check = |h: Header| h.check("x.toml", &none, &mut None, Role::Resource);
        assert!(check(header("De mo", "robot1"))
            .unwrap_err()
            .starts_with("cell:"));
        assert!(check(header("demo", "Robot 1"))
            .unwrap_err()
            .starts_with("name:"));
        let alone = Header {
            zenoh: ZenohSettings::default(),
            ..header("demo", "robot1")
        };
        assert!(check(alone).unwrap_err().starts_with("zenoh:"));
    }

    #[test]
    fn a_file_that_is_not_there_or_not_toml_is_named() {
        let missing = read(Path::new("/nonexistent/robot1.toml")).unwrap_err();
        assert!(
            missing.to_string().contains("/nonexistent/robot1.toml"),
            "{missing}"
        );
        let bad = parse::<toml::Table>("cell = ", "robot1.toml").unwrap_err();
        assert!(bad.to_string().starts_with("robot1.toml:"), "{bad}");
    }
}

//! `cell users`: add, change, remove and list the people of a cell. Every change is
//! appended to the audit trail beside the users file (`audit.jsonl`).

use std::io::{BufRead, IsTerminal, Write};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use clap::{ArgGroup, Args, Subcommand};

use super::{Role, Users, UsersError};
use crate::security::audit::{self, AuditAction, AuditDoor, AuditOutcome, AuditRecord, AuditTrail};

/// `cell users`: which users file, and what to do with it.
#[derive(Debug, Args)]
#[command(group(ArgGroup::new("where").required(true).args(["pki", "file"])))]
pub struct UsersArgs {
    /// The cell's PKI directory: the users file is DIR/users.toml (what `cell opcua
    /// --pki DIR` and the dashboard read).
    #[arg(long, value_name = "DIR")]
    pub pki: Option<PathBuf>,
    /// The users file itself (instead of --pki).
    #[arg(long, value_name = "FILE")]
    pub file: Option<PathBuf>,
    /// What to do.
    #[command(subcommand)]
    pub command: UsersCommand,
}

/// What `cell users` does.
#[derive(Debug, Subcommand)]
pub enum UsersCommand {
    /// Add a user. The password is asked twice on a terminal, else read as one line
    /// from standard input; at least 8 characters.
    Add {
        /// The user's name: 1 to 64 bytes of letters, digits, '.', '_' and '-'.
        name: String,
        /// What the user may do: observer (watch), operator (operate the cell) or admin
        /// (operate and manage users).
        #[arg(long, value_name = "ROLE")]
        role: Role,
    },
    /// Give a user a new password (asked as for `add`).
    Passwd {
        /// The user's name.
        name: String,
    },
    /// Give a user another role (the last admin cannot be demoted: add another admin
    /// first).
    Role {
        /// The user's name.
        name: String,
        /// The new role: observer, operator or admin.
        role: Role,
    },
    /// Remove a user (the last admin cannot be removed: add another admin first).
    Remove {
        /// The user's name.
        name: String,
    },
    /// List the users: name and role (never a password or its hash).
    List,
}

/// A change `cell users` makes to one user.
#[derive(Debug, Clone, Copy)]
enum Change {
    /// Add them with this role.
    Add(Role),
    /// Give them a new password.
    Passwd,
    /// Give them this role.
    Role(Role),
    /// Remove them.
    Remove,
}

impl Change {
    /// How the audit trail calls it.
    fn action(self) -> AuditAction {
        match self {
            Change::Add(_) => AuditAction::UserAdd,
            Change::Passwd => AuditAction::UserPassword,
            Change::Role(_) => AuditAction::UserRole,
            Change::Remove => AuditAction::UserRemove,
        }
    }
}

/// Runs `cell users`.
pub fn run(args: UsersArgs) -> Result<()> {
    let path = match (args.pki, args.file) {
        (Some(pki), None) => super::default_path(&pki),
        (None, Some(file)) => file,
        _ => bail!("exactly one of --pki DIR and --file FILE"),
    };
    let (name, change) = match args.command {
        UsersCommand::List => return list(&path),
        UsersCommand::Add { name, role } => (name, Change::Add(role)),
        UsersCommand::Passwd { name } => (name, Change::Passwd),
        UsersCommand::Role { name, role } => (name, Change::Role(role)),
        UsersCommand::Remove { name } => (name, Change::Remove),
    };
    apply(&path, &name, change)
}

/// Prints the users of the file at `path`: name and role.
fn list(path: &Path) -> Result<()> {
    let users = match read(path)? {
        Some(users) => users,
        None => {
            eprintln!(
                "no users file at {} yet: `cell users add` makes it",
                path.display()
            );
            return Ok(());
        }
    };
    let width = users.iter().map(|u| u.name.len()).max().unwrap_or(0);
    let mut out = std::io::stdout().lock();
    for user in users.iter() {
        writeln!(out, "{:width$}  {}", user.name, user.role)?;
    }
    Ok(())
}

/// The users file at `path`; `None` when there is none yet.
fn read(path: &Path) -> Result<Option<Users>, UsersError> {
    match super::load(path) {
        Ok(users) => Ok(Some(users)),
        Err(UsersError::Read { source, .. }) if source.kind() == std::io::ErrorKind::NotFound => {
            Ok(None)
        }
        Err(e) => Err(e),
    }
}

/// Makes `change` to the user `name` in the file at `path`, and records it (or its
/// refusal) in the audit trail beside the file.
fn apply(path: &Path, name: &str, change: Change) -> Result<()> {
    let action = change.action();
    // The trail first: a change that could not be recorded is not made.
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let trail = AuditTrail::open(&dir.join(audit::FILE_NAME))?;
    let password = match change {
        Change::Add(_) | Change::Passwd => {
            // Known before asking: a bad name, a name taken or an unknown user fails
            // before the password is typed.
            let known = read(path)?.is_some_and(|users| users.get(name).is_some());
            let refusal = match change {
                Change::Add(_) if !super::valid_name(name) => {
                    Some(UsersError::BadName(name.to_string()))
                }
                Change::Add(_) if known => Some(UsersError::Exists(name.to_string())),
                Change::Passwd if !known => Some(UsersError::Unknown(name.to_string())),
                _ => None,
            };
            if let Some(refusal) = refusal {
                refused(&trail, name, action, &refusal);
                return Err(refusal.into());
            }
            read_password(name)?
        }
        Change::Role(_) | Change::Remove => String::new(),
    };
    let changed = super::change(path, |users| match change {
        Change::Add(role) => {
            users.add(name, role, &password)?;
            Ok((
                Some(serde_json::json!({ "role": role.as_str() })),
                format!("added {name} ({role})"),
            ))
        }
        Change::Passwd => {
            users.set_password(name, &password)?;
            Ok((None, format!("changed the password of {name}")))
        }
        Change::Role(role) => {
            let was = users.set_role(name, role)?;
            Ok((
                Some(serde_json::json!({ "role": role.as_str(), "was": was.as_str() })),
                format!("{name} is now {role} (was {was})"),
            ))
        }
        Change::Remove => {
            let user = users.remove(name)?;
            Ok((
                Some(serde_json::json!({ "role": user.role.as_str() })),
                format!("removed {name} ({})", user.role),
            ))
        }
    });
    match changed {
        Ok((detail, said)) => {
            let mut record = AuditRecord::now(&who(), &from(), action, AuditOutcome::Done)
                .on(name)
                .through(AuditDoor::Cli);
            if let Some(detail) = detail {
                record = record.with(detail);
            }
            trail.append(&record).context(
                "the users file was changed, but the change is missing from the audit trail",
            )?;
            println!("{said} in {}", path.display());
            Ok(())
        }
        Err(e) if e.is_refusal() => {
            refused(&trail, name, action, &e);
            Err(e.into())
        }
        Err(e) => {
            trail.record(
                &AuditRecord::now(&who(), &from(), action, AuditOutcome::Failed(e.to_string()))
                    .on(name)
                    .through(AuditDoor::Cli),
            );
            Err(e.into())
        }
    }
}

/// Records a refused change.
fn refused(trail: &AuditTrail, name: &str, action: AuditAction, why: &UsersError) {
    trail.record(
        &AuditRecord::now(
            &who(),
            &from(),
            action,
            AuditOutcome::Refused(why.to_string()),
        )
        .on(name)
        .through(AuditDoor::Cli),
    );
}

/// Who runs the command: `cli:<$USER>`, or `cli:<uid>`.
fn who() -> String {
    match std::env::var("USER") {
        Ok(user) if !user.is_empty() => format!("cli:{user}"),
        _ => format!("cli:{}", nix::unistd::getuid()),
    }
}

/// Where from: `cell users on <hostname>`.
fn from() -> String {
    let host = nix::unistd::gethostname()
        .ok()
        .and_then(|h| h.into_string().ok())
        .unwrap_or_else(|| "?".to_string());
    format!("cell users on {host}")
}

/// The new password: asked twice without echo on a terminal, else one line of
/// standard input.
fn read_password(name: &str) -> Result<String> {
    let stdin = std::io::stdin();
    if !stdin.is_terminal() {
        let mut line = String::new();
        stdin
            .lock()
            .read_line(&mut line)
            .context("cannot read the password from standard input")?;
        let password = line.trim_end_matches(['\r', '\n']).to_string();
        if password.is_empty() {
            bail!("no password on standard input: one line");
        }
        return Ok(password);
    }
    let first = prompt(&format!("password for {name}: "))?;
    let second = prompt("again: ")?;
    if first != second {
        bail!("the two passwords differ; nothing changed");
    }
    Ok(first)
}

/// Reads one line from the terminal with its echo off, restored even on an error.
fn prompt(question: &str) -> Result<String> {
    use nix::sys::termios::{tcgetattr, tcsetattr, LocalFlags, SetArg};
    let stdin = std::io::stdin();
    let saved = tcgetattr(&stdin).context("cannot read the terminal's settings")?;
    let mut quiet = saved.clone();
    quiet.local_flags.remove(LocalFlags::ECHO);
    quiet.local_flags.insert(LocalFlags::ECHONL);
    /// Puts the terminal's settings back when dropped.
    struct Restore<'a> {
        /// The terminal.
        stdin: &'a std::io::Stdin,
        /// Its settings before.
        saved: nix::sys::termios::Termios,
    }
    impl Drop for Restore<'_> {
        fn drop(&mut self) {
            let _ = tcsetattr(self.stdin, SetArg::TCSANOW, &self.saved);
        }
    }
    eprint!("{question}");
    std::io::stderr().flush()?;
    tcsetattr(&stdin, SetArg::TCSAFLUSH, &quiet).context("cannot turn the terminal's echo off")?;
    let _restore = Restore {
        stdin: &stdin,
        saved,
    };
    let mut line = String::new();
    let read = stdin.lock().read_line(&mut line)?;
    if read == 0 {
        return Err(anyhow!("no password typed"));
    }
    Ok(line.trim_end_matches(['\r', '\n']).to_string())
}

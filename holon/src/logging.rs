//! Logging set-up, as the seed used OTP's error_logger: every message received and sent,
//! every state transition, every failure and restart, with `holon`, `conversation_id`
//! and `message_type` as structured fields.
//!
//! The terminal (stderr) gets human-readable text, or JSON lines with `--log-format json`;
//! `--log-file PATH` additionally appends JSON lines to PATH. One event is one line:
//! control characters in what is logged (a client's product name with a newline) are
//! written escaped (`log_writer`), so that no client can split or forge a line. The level comes from
//! `RUST_LOG` (default `info`; set but blank counts as unset).
//!
//! Lines are written by a thread of their own per destination (the `log-writer` crate),
//! not by the task that logs: a request's path formats its lines and hands them over,
//! it makes no write call (at `info` a service cycle logs about a dozen lines). Nothing
//! is dropped: when a writer falls [`LINES_IN_FLIGHT`] lines behind, logging waits for
//! it. The [`LogGuard`] that [`init`] returns writes out what is left
//! when it is dropped, at the end of `main`.

use std::fs::OpenOptions;
use std::io::IsTerminal;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::str::FromStr;

use tracing_subscriber::filter::filter_fn;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::{EnvFilter, Layer, Registry};

/// The target of a fatal error's log line (see [`init`]).
pub const FATAL: &str = "holon::fatal";

/// How log lines look on the terminal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum LogFormat {
    #[default]
    Text,
    Json,
}

impl FromStr for LogFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "text" => Ok(LogFormat::Text),
            "json" => Ok(LogFormat::Json),
            other => Err(format!("unknown log format {other:?} (text or json)")),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum LoggingError {
    #[error("cannot open log file {path}: {source}")]
    File {
        path: String,
        source: std::io::Error,
    },
    #[error("logging is already set up: {0}")]
    AlreadySet(String),
    #[error("cannot start a log writer thread: {0}")]
    Thread(std::io::Error),
}

type BoxedLayer = Box<dyn Layer<Registry> + Send + Sync>;

/// Keeps the log writers' threads: dropping it writes out the lines still queued. Hold
/// it for as long as the program runs.
#[must_use = "dropping the guard stops the log writers"]
pub struct LogGuard {
    _writers: Vec<log_writer::WriterGuard>,
}

pub use log_writer::LINES_IN_FLIGHT;

/// A writer on its own thread that never drops a line.
fn off_the_path<W: std::io::Write + Send + 'static>(
    destination: W,
    name: &str,
    guards: &mut Vec<log_writer::WriterGuard>,
) -> Result<log_writer::LineWriter, LoggingError> {
    let (writer, guard) = log_writer::spawn(destination, name).map_err(LoggingError::Thread)?;
    guards.push(guard);
    Ok(writer)
}

/// Installs the global subscriber. Call once, at the start of `main`, and keep the guard.
pub fn init(
    format: LogFormat,
    file: Option<&Path>,
    default: &str,
) -> Result<LogGuard, LoggingError> {
    // `RUST_LOG` unset or blank: the default (a blank filter would mean errors only).
    let filter = match std::env::var("RUST_LOG") {
        Ok(value) if !value.trim().is_empty() => {
            EnvFilter::try_new(&value).unwrap_or_else(|_| EnvFilter::new(default))
        }
        _ => EnvFilter::new(default),
    };
    // A fatal error is printed once on stderr by the binary's edge (as `program: error`);
    // the terminal layer leaves it out, the log file keeps it.
    let not_fatal = filter_fn(|meta| meta.target() != FATAL);
    let mut guards = Vec::new();
    let stderr = off_the_path(std::io::stderr(), "log-stderr", &mut guards)?;
    let terminal: BoxedLayer = match format {
        LogFormat::Text => tracing_subscriber::fmt::layer()
            .with_writer(stderr.keeping_esc(std::io::stderr().is_terminal()))
            .with_ansi(std::io::stderr().is_terminal())
            .with_target(false)
            .with_filter(not_fatal)
            .boxed(),
        LogFormat::Json => tracing_subscriber::fmt::layer()
            .json()
            .flatten_event(true)
            .with_writer(stderr)
            .with_filter(not_fatal)
            .boxed(),
    };
    let mut layers = vec![terminal];
    if let Some(path) = file {
        // Logs name orders, products and identities: their owner's alone.
        let file = OpenOptions::new()
            .create(true)
            .append(true)
            .mode(0o600)
            .open(path)
            .map_err(|source| LoggingError::File {
                path: path.display().to_string(),
                source,
            })?;
        layers.push(
            tracing_subscriber::fmt::layer()
                .json()
                .flatten_event(true)
                .with_ansi(false)
                .with_writer(off_the_path(file, "log-file", &mut guards)?)
                .boxed(),
        );
    }
    tracing_subscriber::registry()
        .with(layers)
        .with(filter)
        .try_init()
        .map_err(|e| LoggingError::AlreadySet(e.to_string()))?;
    Ok(LogGuard { _writers: guards })
}

//! What every holarchy holon process shares: the zenoh session from its config, presence
//! (liveliness), the supervisor of its components, logging and shutdown signals.

pub mod backoff;
pub mod cli;
pub mod config_file;
pub mod etcd;
pub mod journal;
pub mod layout;
pub mod life;
pub mod logging;
pub mod malloc;
pub mod presence;
pub mod query;
pub mod restart;
pub mod role;
pub mod session;
pub mod supervisor;
pub mod takeover;
pub mod tls;
pub mod zenoh_error;
pub mod zenoh_runtime;

pub use backoff::Backoff;
pub use logging::LogFormat;
pub use restart::{Intensity, RestartType, RestartWindow};
pub use session::{Mode, ZenohSettings};
pub use supervisor::{ChildError, ChildSpec, Strategy, Supervisor};

use tokio_util::sync::CancellationToken;

/// A token cancelled on SIGTERM or SIGINT (Ctrl-C): a holon's `shutdown`.
pub fn shutdown_on_signals() -> CancellationToken {
    let token = CancellationToken::new();
    let cancel = token.clone();
    tokio::spawn(async move {
        let mut term =
            match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
                Ok(term) => term,
                Err(e) => {
                    tracing::error!(error = %e, "cannot listen for SIGTERM");
                    return;
                }
            };
        tokio::select! {
            _ = term.recv() => tracing::info!("SIGTERM received; shutting down"),
            _ = tokio::signal::ctrl_c() => tracing::info!("interrupt received; shutting down"),
        }
        cancel.cancel();
    });
    token
}

/// Sets the process umask to 077: the files it creates from now on are readable and
/// writable by their owner only. For a binary's `main`, before any file is made.
pub fn owner_only_files() {
    nix::sys::stat::umask(nix::sys::stat::Mode::from_bits_truncate(0o077));
}

/// The edge of a holon binary: sets up logging, runs `run` on zenoh's `app` runtime
/// ([`zenoh_runtime::runtime`], multi-thread) with a shutdown token cancelled by
/// SIGTERM / Ctrl-C, and turns its result into the exit code (errors are logged and
/// printed as `program: error`): 0 on success,
/// [`takeover::EXIT_REFUSED`] when the process was a successor whose predecessor
/// refused to hand over (nothing changed), 1 on any other error.
pub fn process_main<F, Fut, E>(
    program: &str,
    pool: zenoh_runtime::Pool,
    format: LogFormat,
    log_file: Option<&std::path::Path>,
    run: F,
) -> std::process::ExitCode
where
    F: FnOnce(CancellationToken) -> Fut,
    Fut: std::future::Future<Output = Result<(), E>>,
    E: Into<anyhow::Error>,
{
    // Journals, logs and keys name the plant's orders and identities: every file the
    // process creates is its owner's alone.
    owner_only_files();
    // Before any thread: a bounded number of allocator arenas (see the module).
    malloc::limit_arenas();
    // Before any thread: zenoh's work and the holon's on one pool (see the module).
    zenoh_runtime::configure(pool);
    // Dropped at the end: every line logged until then is written out (zenoh's pool,
    // which the holon runs on, is a static and never dropped).
    let _logs = match logging::init(format, log_file, "info") {
        Ok(guard) => guard,
        Err(e) => {
            eprintln!("{program}: {e}");
            return std::process::ExitCode::FAILURE;
        }
    };
    // The holon's tasks share zenoh's pool (see `zenoh_runtime`).
    let result = zenoh_runtime::runtime().block_on(async { run(shutdown_on_signals()).await });
    match result {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            let e: anyhow::Error = e.into();
            tracing::error!(target: logging::FATAL, error = %e, "{program} failed");
            eprintln!("{program}: {e}");
            let refused = e.chain().any(|cause| {
                matches!(
                    cause.downcast_ref::<takeover::TakeoverError>(),
                    Some(takeover::TakeoverError::Refused { .. })
                )
            });
            match refused {
                true => std::process::ExitCode::from(takeover::EXIT_REFUSED),
                false => std::process::ExitCode::FAILURE,
            }
        }
    }
}

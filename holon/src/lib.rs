//! What every holarchy holon process shares: the zenoh session from its config, presence
//! (liveliness), the supervisor of its components, logging and shutdown signals.

pub mod journal;
pub mod logging;
pub mod presence;
pub mod session;
pub mod supervisor;

pub use logging::LogFormat;
pub use session::ZenohSettings;
pub use supervisor::{ChildError, ChildSpec, Intensity, Strategy, Supervisor};

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

//! What the simulators' binaries (`robot-sim`, `plant-sim`) share as processes: where
//! their log goes, and how they are stopped.

use std::io::IsTerminal;

use tokio_util::sync::CancellationToken;

/// Logs to stderr (`RUST_LOG`, default `info`) through a thread of its own, off the
/// command path, as the holons write theirs: none is dropped, the thread neither spins
/// nor is woken per line, and the rest are written out when the guard drops (keep it
/// to the end of `main`).
pub fn log_to_stderr() -> std::io::Result<log_writer::WriterGuard> {
    let (stderr, guard) = log_writer::spawn(std::io::stderr(), "log-stderr")?;
    tracing_subscriber::fmt()
        .with_writer(stderr)
        // Colour codes only on a terminal, never in a redirected log file.
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    Ok(guard)
}

/// Cancelled on SIGTERM or Ctrl-C.
pub fn stop_on_signals() -> CancellationToken {
    let shutdown = CancellationToken::new();
    let stop = shutdown.clone();
    tokio::spawn(async move {
        let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            .expect("SIGTERM handler");
        tokio::select! {
            _ = term.recv() => {}
            _ = tokio::signal::ctrl_c() => {}
        }
        stop.cancel();
    });
    shutdown
}

//! `cell up DIR`: launches the processes of a cell from the manifest `DIR/cell.toml` and
//! supervises them like an OTP supervisor (one_for_one), with the project's one restart
//! policy ([`holon::restart`]): each process has a restart type (`permanent` unless its
//! `restart` says otherwise); a process to restart is started again after a backoff
//! that doubles while it keeps dying ([`holon::Backoff`]); more than
//! `restart.max_restarts` restarts within `restart.period_ms` (all processes together)
//! stops everything and exits non-zero. Ctrl-C or SIGTERM stops the processes in
//! reverse order (SIGTERM, then SIGKILL after `restart.stop_timeout_ms`). It runs the
//! cell's zenoh router in its own process when the manifest has a `[router]`.
//!
//! The manifest format is documented in `deploy/cells/demo/cell.toml`.
//!
//! It also listens on `DIR/run/<host>.sock` for `cell upgrade` ([`crate::up::upgrade`]):
//! one process at a time is replaced by its successor through a planned hand-over,
//! and the successor is supervised in its place.

//! Its parts: [`manifest`] (the file it runs), [`supervision`] (the processes and their
//! restarts, and the upgrades the supervisor carries out), [`control`] (the control
//! socket `cell upgrade` talks to) and [`upgrade`] (what `cell upgrade` asks and is
//! answered).

mod control;
pub mod manifest;
mod supervision;
pub mod upgrade;

use std::path::Path;
use std::time::Duration;

use anyhow::{anyhow, Result};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::up::manifest::{Manifest, RouterSection};
use control::Control;
use supervision::{Clock, Processes};

/// Runs the cell until `shutdown`; Ok(false) when the restart intensity was exceeded.
pub async fn run(dir: &Path, host: &str, shutdown: CancellationToken) -> Result<bool> {
    run_scaled(dir, host, None, shutdown).await
}

/// [`run`], the plant at `time_scale` when given (overriding the manifest's).
pub async fn run_scaled(
    dir: &Path,
    host: &str,
    time_scale: Option<schemas::TimeScale>,
    shutdown: CancellationToken,
) -> Result<bool> {
    let mut manifest = Manifest::load(dir)?;
    if let Some(scale) = time_scale {
        manifest.time_scale = Some(scale.factor());
    }
    let (manifest, router) = manifest.for_host(host)?;
    let clock = Clock(Instant::now());
    let logs = dir.join("logs");
    std::fs::create_dir_all(&logs)?;
    let _router = match &router {
        Some(router) => Some(start_router(dir, host, &manifest, router, clock).await?),
        None => None,
    };
    let (control, upgrades) = Control::listen(dir, host)?;
    let mut processes = Processes::new(dir, logs, &manifest, clock);
    processes.start_all()?;
    let healthy = processes.supervise(shutdown, upgrades).await;
    clock.say("stopping the cell, in reverse order");
    processes.stop_all().await;
    drop(control);
    clock.say("cell stopped");
    Ok(healthy)
}

/// The cell's zenoh router, inside this process: it lives as long as the session.
async fn start_router(
    dir: &Path,
    host: &str,
    manifest: &Manifest,
    router: &RouterSection,
    clock: Clock,
) -> Result<Router> {
    let settings = router.settings(&crate::security::certs::pki_dir(dir, manifest));
    let session = settings
        .open(
            &holon::role::identity(holon::role::Role::Router, host),
            Duration::from_secs(10),
        )
        .await
        .map_err(|e| anyhow!("router: {e}"))?;
    clock.say(format!(
        "zenoh router of cell {} listening on {}",
        manifest.cell,
        router.listen.join(", ")
    ));
    let keys = schemas::CellKeys::new(&manifest.cell)?;
    let token = crate::router::announce(&session, &keys, host).await?;
    Ok(Router {
        _announced: token,
        _session: session,
    })
}

/// The cell's router in this process, announced as `host/router/<host>`.
struct Router {
    /// Its announcement, withdrawn when the router stops (dropped first).
    _announced: zenoh::liveliness::LivelinessToken,
    /// The router itself: it lives as long as the session.
    _session: zenoh::Session,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(flavor = "multi_thread")]
    async fn a_host_with_nothing_to_run_names_the_hosts() {
        let dir = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../deploy/cells/factory"
        ));
        let err = run(dir, "local", CancellationToken::new())
            .await
            .unwrap_err()
            .to_string();
        assert!(err.contains("its hosts are a, b, c"), "{err}");
    }
}

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

use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use holon::{Backoff, RestartWindow};
use tokio::process::Command;
use tokio::task::JoinSet;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::manifest::{Manifest, ProcessSection, RouterSection};

/// A program named in a manifest: a binary next to `cell` if there is one, else as given.
fn resolve(program: &str) -> PathBuf {
    if !program.contains('/') {
        if let Some(dir) = std::env::current_exe()
            .ok()
            .and_then(|e| e.parent().map(Path::to_path_buf))
        {
            let sibling = dir.join(program);
            if sibling.exists() {
                return sibling;
            }
        }
    }
    PathBuf::from(program)
}

/// Prints one line of the cell's story, stamped with the seconds since `cell up` began.
#[derive(Clone, Copy)]
struct Clock(Instant);

impl Clock {
    fn say(self, text: impl std::fmt::Display) {
        println!("[{:8.2}s] {text}", self.0.elapsed().as_secs_f64());
    }
}

/// Runs the cell until `shutdown`; Ok(false) when the restart intensity was exceeded.
pub async fn run(dir: &Path, host: &str, shutdown: CancellationToken) -> Result<bool> {
    let (manifest, router) = Manifest::load(dir)?.for_host(host)?;
    let clock = Clock(Instant::now());
    let logs = dir.join("logs");
    std::fs::create_dir_all(&logs)?;
    let _router = match &router {
        Some(router) => Some(start_router(dir, host, &manifest, router, clock).await?),
        None => None,
    };
    let mut processes = Processes::new(dir, logs, &manifest, clock);
    processes.start_all()?;
    let healthy = processes.supervise(shutdown).await;
    clock.say("stopping the cell, in reverse order");
    processes.stop_all().await;
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
    let settings = router.settings(&crate::certs::pki_dir(dir, manifest));
    let session = settings
        .open(
            &holon::tls::identity("router", host),
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

/// One process of the manifest, as `cell up` tracks it.
struct Slot {
    /// While it runs.
    pid: Option<u32>,
    /// How many times it was started: an exit of an older generation is stale.
    generation: u64,
    /// The pause before its next restart.
    backoff: Backoff,
    /// When it was last started.
    started_at: Instant,
    /// When it is due to start again, after it exited.
    restart_at: Option<Instant>,
}

/// How one process ended: its index, generation and exit status.
type Ended = (usize, u64, std::io::Result<ExitStatus>);

/// The processes of the manifest and their supervision.
struct Processes<'a> {
    /// The manifest's directory: every process's working directory.
    dir: &'a Path,
    /// Where `<name>.log` of each process goes.
    logs: PathBuf,
    specs: &'a [ProcessSection],
    /// A process that ran for a whole period has earned a fresh backoff.
    period: Duration,
    /// How long a process has between SIGTERM and SIGKILL.
    stop_timeout: Duration,
    slots: Vec<Slot>,
    /// One waiter per running process.
    waits: JoinSet<Ended>,
    /// The restarts of all processes together, against the intensity.
    window: RestartWindow,
    clock: Clock,
}

impl<'a> Processes<'a> {
    fn new(dir: &'a Path, logs: PathBuf, manifest: &'a Manifest, clock: Clock) -> Processes<'a> {
        let restart = &manifest.restart;
        let backoff = Backoff::new(
            Duration::from_millis(restart.backoff_initial_ms),
            Duration::from_millis(restart.backoff_max_ms),
        );
        Processes {
            dir,
            logs,
            specs: &manifest.processes,
            period: Duration::from_millis(restart.period_ms),
            stop_timeout: Duration::from_millis(restart.stop_timeout_ms),
            slots: manifest
                .processes
                .iter()
                .map(|_| Slot {
                    pid: None,
                    generation: 0,
                    backoff: backoff.clone(),
                    started_at: clock.0,
                    restart_at: None,
                })
                .collect(),
            waits: JoinSet::new(),
            window: RestartWindow::new(manifest.intensity()),
            clock,
        }
    }

    /// Starts every process, in the manifest's order.
    fn start_all(&mut self) -> Result<()> {
        for index in 0..self.slots.len() {
            self.start(index)?;
        }
        Ok(())
    }

    fn start(&mut self, index: usize) -> Result<()> {
        let spec = &self.specs[index];
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.logs.join(format!("{}.log", spec.name)))?;
        let mut child = Command::new(resolve(&spec.program))
            .args(&spec.args)
            .current_dir(self.dir)
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("cannot start {} ({})", spec.name, spec.program))?;
        let slot = &mut self.slots[index];
        slot.generation += 1;
        slot.pid = child.id();
        slot.started_at = Instant::now();
        slot.restart_at = None;
        let generation = slot.generation;
        self.clock.say(format!(
            "started {} (pid {})",
            spec.name,
            slot.pid.unwrap_or(0)
        ));
        self.waits
            .spawn(async move { (index, generation, child.wait().await) });
        Ok(())
    }

    /// Restarts what exits until `shutdown`: true, or false when the restart intensity
    /// was exceeded.
    async fn supervise(&mut self, shutdown: CancellationToken) -> bool {
        loop {
            let next_restart = self.slots.iter().filter_map(|s| s.restart_at).min();
            tokio::select! {
                _ = shutdown.cancelled() => return true,
                Some(joined) = self.waits.join_next() => {
                    let Ok(ended) = joined else { continue };
                    if !self.exited(ended) {
                        return false;
                    }
                }
                _ = async { tokio::time::sleep_until(next_restart.unwrap_or_else(Instant::now)).await }, if next_restart.is_some() => {
                    self.restart_due();
                }
            }
        }
    }

    /// Decides on an exit after its restart type and the intensity: false to give up.
    fn exited(&mut self, (index, generation, status): Ended) -> bool {
        let spec = &self.specs[index];
        let slot = &mut self.slots[index];
        if slot.generation != generation {
            return true;
        }
        slot.pid = None;
        let ended_normally = status.as_ref().is_ok_and(ExitStatus::success);
        let status = status
            .map(|s| s.to_string())
            .unwrap_or_else(|e| e.to_string());
        let name = &spec.name;
        if !spec.restart.restarts(ended_normally) {
            self.clock.say(format!(
                "{name} exited ({status}); {} processes are not restarted",
                spec.restart
            ));
            return true;
        }
        if slot.started_at.elapsed() >= self.period {
            slot.backoff.reset();
        }
        let now = Instant::now();
        if !self.window.allow(now) {
            let intensity = self.window.intensity();
            self.clock.say(format!(
                "{name} exited ({status}); more than {} restarts within {:?}: giving up",
                intensity.max_restarts, intensity.period
            ));
            return false;
        }
        let pause = slot.backoff.next_pause();
        self.clock.say(format!(
            "{name} exited ({status}); restarting in {} ms",
            pause.as_millis()
        ));
        slot.restart_at = Some(now + pause);
        true
    }

    /// Starts the processes whose restart is due; one that cannot start is tried again
    /// after its next pause.
    fn restart_due(&mut self) {
        let now = Instant::now();
        for index in 0..self.slots.len() {
            if self.slots[index].restart_at.is_some_and(|t| t <= now) {
                if let Err(e) = self.start(index) {
                    let pause = self.slots[index].backoff.next_pause();
                    self.clock
                        .say(format!("{e:#}; retrying in {} ms", pause.as_millis()));
                    self.slots[index].restart_at = Some(now + pause);
                }
            }
        }
    }

    /// Stops the running processes, last first: SIGTERM, then SIGKILL after the
    /// stop timeout.
    async fn stop_all(&mut self) {
        for index in (0..self.slots.len()).rev() {
            if let Some(pid) = self.slots[index].pid.take() {
                self.stop(index, pid).await;
            }
        }
    }

    async fn stop(&mut self, index: usize, pid: u32) {
        let name = &self.specs[index].name;
        let generation = self.slots[index].generation;
        let pid = nix::unistd::Pid::from_raw(pid as i32);
        if let Err(e) = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM) {
            self.clock
                .say(format!("cannot signal {name} ({e}); waiting for it"));
        }
        let deadline = Instant::now() + self.stop_timeout;
        loop {
            match tokio::time::timeout_at(deadline, self.waits.join_next()).await {
                Ok(Some(Ok((i, g, status)))) if i == index && g == generation => {
                    self.clock
                        .say(format!("stopped {name} ({})", describe(status)));
                    return;
                }
                Ok(Some(Ok((i, g, status)))) => {
                    // Another process ended meanwhile (e.g. it got the same signal).
                    if self.slots[i].generation == g && self.slots[i].pid.take().is_some() {
                        self.clock.say(format!(
                            "stopped {} ({})",
                            self.specs[i].name,
                            describe(status)
                        ));
                    }
                }
                Ok(Some(Err(_))) => {}
                Ok(None) => return,
                Err(_) => {
                    if let Err(e) = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGKILL) {
                        self.clock.say(format!("cannot kill {name}: {e}"));
                    }
                    self.clock.say(format!(
                        "{name} did not stop within {:?}; killed",
                        self.stop_timeout
                    ));
                    return;
                }
            }
        }
    }
}

fn describe(status: std::io::Result<ExitStatus>) -> String {
    status
        .map(|s| s.to_string())
        .unwrap_or_else(|e| e.to_string())
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

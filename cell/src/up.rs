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
//! It also listens on `DIR/run/<host>.sock` for `cell upgrade` ([`crate::upgrade`]):
//! one process at a time is replaced by its successor through a planned hand-over,
//! and the successor is supervised in its place.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use holon::{Backoff, RestartWindow};
use tokio::process::Command;
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use crate::manifest::{Manifest, ProcessSection, RouterSection};
use crate::upgrade::{UpgradeOutcome, UpgradeRequest};

/// An upgrade asked on the control socket, and where its outcome goes.
type Upgrade = (UpgradeRequest, oneshot::Sender<UpgradeOutcome>);

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

/// The control socket `cell upgrade` talks to; removed when dropped.
struct Control {
    path: PathBuf,
    accept: tokio::task::JoinHandle<()>,
}

impl Control {
    /// Listens on `DIR/run/<host>.sock` (only this user may connect): each connection
    /// carries one upgrade request, answered with its outcome.
    fn listen(dir: &Path, host: &str) -> Result<(Control, mpsc::Receiver<Upgrade>)> {
        use std::os::unix::fs::PermissionsExt;
        let path = crate::upgrade::socket_path(dir, host);
        let run = path.parent().expect("the socket is in DIR/run");
        std::fs::create_dir_all(run)?;
        std::fs::set_permissions(run, std::fs::Permissions::from_mode(0o700))?;
        if path.exists() {
            if std::os::unix::net::UnixStream::connect(&path).is_ok() {
                anyhow::bail!(
                    "another cell up for host {host} runs here ({} answers)",
                    path.display()
                );
            }
            // Left by a cell up that was killed.
            std::fs::remove_file(&path)?;
        }
        let listener = tokio::net::UnixListener::bind(&path)
            .with_context(|| format!("cannot listen on {}", path.display()))?;
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600))?;
        let (sender, upgrades) = mpsc::channel(4);
        let accept = tokio::spawn(async move {
            loop {
                match listener.accept().await {
                    Ok((stream, _)) => {
                        tokio::spawn(serve_control(stream, sender.clone()));
                    }
                    Err(e) => {
                        tracing::warn!(error = %e, "the control socket failed; cell upgrade is unavailable");
                        return;
                    }
                }
            }
        });
        Ok((Control { path, accept }, upgrades))
    }
}

impl Drop for Control {
    fn drop(&mut self) {
        self.accept.abort();
        if let Err(e) = std::fs::remove_file(&self.path) {
            tracing::warn!(path = %self.path.display(), error = %e, "cannot remove the control socket");
        }
    }
}

/// One `cell upgrade` connection: its request to the supervisor, the outcome back.
async fn serve_control(stream: tokio::net::UnixStream, upgrades: mpsc::Sender<Upgrade>) {
    use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
    let (read, mut write) = stream.into_split();
    let mut line = String::new();
    let outcome = match tokio::time::timeout(
        Duration::from_secs(10),
        BufReader::new(read).read_line(&mut line),
    )
    .await
    {
        Ok(Ok(_)) => match serde_json::from_str::<UpgradeRequest>(line.trim()) {
            Ok(request) => {
                let (reply, outcome) = oneshot::channel();
                if upgrades.send((request, reply)).await.is_err() {
                    failed("cell up is stopping")
                } else {
                    outcome
                        .await
                        .unwrap_or_else(|_| failed("cell up stopped before the upgrade ended"))
                }
            }
            Err(e) => failed(&format!("not an upgrade request: {e}")),
        },
        Ok(Err(e)) => failed(&format!("cannot read the request: {e}")),
        Err(_) => failed("no request within 10 s"),
    };
    let mut answer = serde_json::to_vec(&outcome).expect("an outcome serializes");
    answer.push(b'\n');
    if let Err(e) = write.write_all(&answer).await {
        tracing::warn!(error = %e, ok = outcome.ok, "cannot tell cell upgrade how the upgrade went");
    }
}

/// How long a successor's `--check` may take.
const CHECK_WITHIN: Duration = Duration::from_secs(30);

/// Answers `cell upgrade` that the upgrade cannot be done.
fn refuse(reply: oneshot::Sender<UpgradeOutcome>, message: String) {
    if reply.send(failed(&message)).is_err() {
        tracing::warn!(%message, "cell upgrade went away before its answer");
    }
}

fn not_running(name: &str) -> String {
    format!("{name} is not running now (it is restarting or ended); try again when it runs")
}

fn failed(message: &str) -> UpgradeOutcome {
    UpgradeOutcome {
        ok: false,
        message: message.to_string(),
    }
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
    /// Its successor, started by `cell upgrade`, until the hand-over ends.
    successor: Option<Successor>,
    /// True while a successor's config is being checked (before it starts).
    checking: bool,
}

/// A successor's command line that passed (or failed) its `--check`.
struct Checked {
    index: usize,
    program: String,
    args: Vec<String>,
    request: UpgradeRequest,
    reply: oneshot::Sender<UpgradeOutcome>,
    /// Why it failed, if it did.
    failure: Option<String>,
}

/// A successor that is stopped because its predecessor exited without handing over to
/// it (no successor served within the stand-in limit): SIGTERM, SIGKILL at `kill_at`.
struct Retired {
    index: usize,
    generation: u64,
    pid: u32,
    kill_at: Instant,
}

/// A successor that is taking a process over.
struct Successor {
    pid: Option<u32>,
    generation: u64,
    /// Its command line, the process's from now on.
    program: String,
    args: Vec<String>,
    started_at: Instant,
    /// Where `cell upgrade` learns how it went.
    reply: oneshot::Sender<UpgradeOutcome>,
}

/// How one process ended: its index, generation and exit status.
type Ended = (usize, u64, std::io::Result<ExitStatus>);

/// The processes of the manifest and their supervision.
struct Processes<'a> {
    /// The manifest's directory: every process's working directory.
    dir: &'a Path,
    /// Where `<name>.log` of each process goes.
    logs: PathBuf,
    /// The processes' specs: the manifest's, with the command lines of upgrades.
    specs: Vec<ProcessSection>,
    /// Every start gets the next generation (of all processes), so an exit is matched
    /// with the start it ends.
    generations: u64,
    /// A process that ran for a whole period has earned a fresh backoff.
    period: Duration,
    /// How long a process has between SIGTERM and SIGKILL.
    stop_timeout: Duration,
    slots: Vec<Slot>,
    /// One waiter per running process.
    waits: JoinSet<Ended>,
    /// Successors' `--check` runs, so that the supervision goes on while they run;
    /// the process each is for, by task.
    checks: JoinSet<Checked>,
    checking: HashMap<tokio::task::Id, usize>,
    /// Successors being stopped because their predecessor gave up on them.
    retired: Vec<Retired>,
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
            specs: manifest.processes.clone(),
            generations: 0,
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
                    successor: None,
                    checking: false,
                })
                .collect(),
            waits: JoinSet::new(),
            checks: JoinSet::new(),
            checking: HashMap::new(),
            retired: Vec::new(),
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
        let (program, args) = (spec.program.clone(), spec.args.clone());
        let (pid, generation) = self.spawn(index, &program, &args)?;
        let slot = &mut self.slots[index];
        slot.generation = generation;
        slot.pid = pid;
        slot.started_at = Instant::now();
        slot.restart_at = None;
        self.clock.say(format!(
            "started {} (pid {})",
            self.specs[index].name,
            pid.unwrap_or(0)
        ));
        Ok(())
    }

    /// Starts `program` with `args` as process `index` (its log appended to), waited
    /// for in `waits`: its pid and generation.
    fn spawn(
        &mut self,
        index: usize,
        program: &str,
        args: &[String],
    ) -> Result<(Option<u32>, u64)> {
        let name = &self.specs[index].name;
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(self.logs.join(format!("{name}.log")))?;
        let mut child = Command::new(resolve(program))
            .args(args)
            .current_dir(self.dir)
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("cannot start {name} ({program})"))?;
        self.generations += 1;
        let generation = self.generations;
        let pid = child.id();
        self.waits
            .spawn(async move { (index, generation, child.wait().await) });
        Ok((pid, generation))
    }

    /// Begins the upgrade of one process: checks the successor's command line (its
    /// `--check` runs as a task; [`Processes::checked`] goes on), then starts it with
    /// `--take-over`; the outcome goes to `reply` when the hand-over ends (see
    /// [`Processes::exited`]), or now if it cannot begin.
    fn upgrade(&mut self, request: UpgradeRequest, reply: oneshot::Sender<UpgradeOutcome>) {
        let Some(index) = self.specs.iter().position(|s| s.name == request.name) else {
            let names: Vec<&str> = self.specs.iter().map(|s| s.name.as_str()).collect();
            return refuse(
                reply,
                format!(
                    "no process {} runs here (this host's are: {})",
                    request.name,
                    names.join(", ")
                ),
            );
        };
        let spec = &self.specs[index];
        let slot = &self.slots[index];
        if slot.successor.is_some() || slot.checking {
            return refuse(reply, format!("{} is being upgraded already", spec.name));
        }
        if slot.pid.is_none() {
            return refuse(reply, not_running(&spec.name));
        }
        let (program, args) = match crate::upgrade::successor_command(
            &spec.program,
            &spec.args,
            request.binary.as_deref(),
            request.config.as_deref(),
        ) {
            Ok(command) => command,
            Err(e) => return refuse(reply, format!("{}: {e:#}", spec.name)),
        };
        self.slots[index].checking = true;
        let name = spec.name.clone();
        let mut check = Command::new(resolve(&program));
        check
            .args(&args)
            .arg("--check")
            .current_dir(self.dir)
            .stdin(Stdio::null())
            .kill_on_drop(true);
        let task = self.checks.spawn(async move {
            let output = tokio::time::timeout(CHECK_WITHIN, check.output()).await;
            // A config that fails its check leaves the running process alone.
            let failure = match output {
                Ok(Ok(output)) if output.status.success() => None,
                Ok(Ok(output)) => Some(format!(
                    "the successor of {name} does not pass its check; {name} runs on unchanged: {}",
                    String::from_utf8_lossy(&output.stderr).trim()
                )),
                Ok(Err(e)) => Some(format!("cannot run {program}: {e}; {name} runs on unchanged")),
                Err(_) => Some(format!(
                    "{program} --check did not end within {CHECK_WITHIN:?}; {name} runs on unchanged"
                )),
            };
            Checked {
                index,
                program,
                args,
                request,
                reply,
                failure,
            }
        });
        self.checking.insert(task.id(), index);
    }

    /// Starts a successor whose check passed.
    fn checked(&mut self, checked: Checked) {
        let Checked {
            index,
            program,
            args,
            request,
            reply,
            failure,
        } = checked;
        self.slots[index].checking = false;
        if let Some(failure) = failure {
            return refuse(reply, failure);
        }
        let name = self.specs[index].name.clone();
        if self.slots[index].pid.is_none() {
            return refuse(reply, not_running(&name));
        }
        let mut successor_args = args.clone();
        successor_args.extend([
            "--take-over".to_string(),
            "--take-over-wait-ms".to_string(),
            request.wait_ms.to_string(),
        ]);
        match self.spawn(index, &program, &successor_args) {
            Ok((pid, generation)) => {
                self.clock.say(format!(
                    "upgrading {name}: started its successor (pid {}), which takes over when {name} has finished its step",
                    pid.unwrap_or(0)
                ));
                self.slots[index].successor = Some(Successor {
                    pid,
                    generation,
                    program,
                    args,
                    started_at: Instant::now(),
                    reply,
                });
            }
            Err(e) => refuse(reply, format!("{e:#}; {name} runs on unchanged")),
        }
    }

    /// Restarts what exits until `shutdown`, and carries out upgrades: true, or false
    /// when the restart intensity was exceeded.
    async fn supervise(
        &mut self,
        shutdown: CancellationToken,
        mut upgrades: mpsc::Receiver<Upgrade>,
    ) -> bool {
        loop {
            let next_restart = self.slots.iter().filter_map(|s| s.restart_at).min();
            let next_kill = self.retired.iter().map(|r| r.kill_at).min();
            tokio::select! {
                _ = shutdown.cancelled() => return true,
                Some((request, reply)) = upgrades.recv() => self.upgrade(request, reply),
                Some(checked) = self.checks.join_next_with_id(), if !self.checks.is_empty() => {
                    match checked {
                        Ok((task, checked)) => {
                            self.checking.remove(&task);
                            self.checked(checked);
                        }
                        Err(e) => {
                            if let Some(index) = self.checking.remove(&e.id()) {
                                self.slots[index].checking = false;
                            }
                            tracing::error!(error = %e, "a successor's check task failed; its cell upgrade gets no answer");
                        }
                    }
                }
                _ = async { tokio::time::sleep_until(next_kill.unwrap_or_else(Instant::now)).await }, if next_kill.is_some() => {
                    self.kill_retired();
                }
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

    /// Stops the successor of process `index`, whose predecessor exited (`status`)
    /// without handing over to it, and tells `cell upgrade`.
    fn retire(&mut self, index: usize, successor: Successor, status: &std::io::Result<ExitStatus>) {
        let name = &self.specs[index].name;
        let message = format!(
            "{name} exited ({}) after handing over: its successor (pid {}) did not serve within {:?}. The successor is stopped and {name} is started again from its previous binary and config, on its journal. The end of logs/{name}.log:\n{}",
            match status {
                Ok(status) => status.to_string(),
                Err(e) => e.to_string(),
            },
            successor.pid.unwrap_or(0),
            holon::takeover::STAND_IN_LIMIT,
            crate::upgrade::log_tail(&self.logs.join(format!("{name}.log")), 15)
        );
        self.clock.say(format!(
            "upgrade of {name} failed: its successor did not serve; starting {name} again as it was"
        ));
        if let Some(pid) = successor.pid {
            let target = nix::unistd::Pid::from_raw(pid as i32);
            if let Err(e) = nix::sys::signal::kill(target, nix::sys::signal::Signal::SIGTERM) {
                self.clock
                    .say(format!("cannot signal the successor of {name}: {e}"));
            }
            self.retired.push(Retired {
                index,
                generation: successor.generation,
                pid,
                kill_at: Instant::now() + self.stop_timeout,
            });
        }
        if successor.reply.send(failed(&message)).is_err() {
            tracing::warn!(%name, "cell upgrade went away before its answer");
        }
    }

    /// SIGKILLs the retired successors whose stop timeout has passed.
    fn kill_retired(&mut self) {
        let now = Instant::now();
        for retired in self.retired.iter_mut().filter(|r| r.kill_at <= now) {
            let name = &self.specs[retired.index].name;
            let target = nix::unistd::Pid::from_raw(retired.pid as i32);
            match nix::sys::signal::kill(target, nix::sys::signal::Signal::SIGKILL) {
                Ok(()) => self.clock.say(format!(
                    "the successor of {name} did not stop within {:?}; killed",
                    self.stop_timeout
                )),
                Err(e) => self
                    .clock
                    .say(format!("cannot kill the successor of {name}: {e}")),
            }
            // Its waiter reports the end; it is not killed twice.
            retired.kill_at = now + Duration::from_secs(3600);
        }
    }

    /// Decides on an exit after its restart type and the intensity: false to give up.
    fn exited(&mut self, (index, generation, status): Ended) -> bool {
        let name = self.specs[index].name.clone();
        if let Some(at) = self.retired.iter().position(|r| r.generation == generation) {
            self.retired.swap_remove(at);
            self.clock.say(format!(
                "stopped the successor of {name} ({})",
                describe(status)
            ));
            return true;
        }
        let slot = &mut self.slots[index];
        if slot
            .successor
            .as_ref()
            .is_some_and(|s| s.generation == generation)
        {
            let successor = slot.successor.take().expect("checked");
            // Exit code 3: the running process refused (it said so, and serves on).
            // Any other end may come after the running process let go: it then stands
            // in for a while and exits, and is started again as before.
            let refused = status
                .as_ref()
                .is_ok_and(|s| s.code() == Some(i32::from(holon::takeover::EXIT_REFUSED)));
            let what = match refused {
                true => format!("{name} refused to hand over and runs on unchanged"),
                false => format!(
                    "if {name} had already let go, it stands in for up to {:?}, exits, and is started again from its previous binary and config on its journal",
                    holon::takeover::STAND_IN_LIMIT
                ),
            };
            let message = format!(
                "the successor of {name} exited ({}) before {name} ended; {what}. The end of logs/{name}.log:\n{}",
                describe(status),
                crate::upgrade::log_tail(&self.logs.join(format!("{name}.log")), 15)
            );
            self.clock
                .say(format!("upgrade of {name} failed: its successor exited"));
            if successor.reply.send(failed(&message)).is_err() {
                tracing::warn!(%name, "cell upgrade went away before its answer");
            }
            return true;
        }
        if slot.generation != generation {
            return true;
        }
        let predecessor_ok = status.as_ref().is_ok_and(ExitStatus::success);
        let mut successor = slot.successor.take();
        if let Some(successor) = successor.take_if(|_| predecessor_ok) {
            let before = slot.pid.unwrap_or(0);
            slot.generation = successor.generation;
            slot.pid = successor.pid;
            slot.started_at = successor.started_at;
            slot.backoff.reset();
            let spec = &mut self.specs[index];
            spec.program = successor.program;
            spec.args = successor.args;
            let message = format!(
                "upgraded {name}: pid {before} ({}) handed over to pid {} in {} ms",
                describe(status),
                successor.pid.unwrap_or(0),
                successor.started_at.elapsed().as_millis()
            );
            self.clock.say(&message);
            let outcome = UpgradeOutcome { ok: true, message };
            if successor.reply.send(outcome).is_err() {
                tracing::warn!(%name, "cell upgrade went away before its answer");
            }
            return true;
        }
        if let Some(successor) = successor {
            // The predecessor let go and no successor served within its stand-in limit
            // (it exits 1 then): the successor is stopped and the process is started
            // again below, from its previous command line, on its journal.
            self.retire(index, successor, &status);
        }
        let slot = &mut self.slots[index];
        let spec = &self.specs[index];
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
        for index in 0..self.slots.len() {
            if let Some(successor) = self.slots[index].successor.take() {
                if let Some(pid) = successor.pid {
                    self.stop(index, pid, successor.generation).await;
                }
                if successor
                    .reply
                    .send(failed("cell up is stopping: the upgrade was abandoned"))
                    .is_err()
                {
                    tracing::warn!("cell upgrade went away before its answer");
                }
            }
        }
        for index in (0..self.slots.len()).rev() {
            if let Some(pid) = self.slots[index].pid.take() {
                let generation = self.slots[index].generation;
                self.stop(index, pid, generation).await;
            }
        }
    }

    /// Stops one process (`generation` of process `index`): SIGTERM, then SIGKILL after
    /// the stop timeout.
    async fn stop(&mut self, index: usize, pid: u32, generation: u64) {
        let name = &self.specs[index].name;
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

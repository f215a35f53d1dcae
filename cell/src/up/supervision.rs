//! The supervision of a cell's processes, like an OTP supervisor (one_for_one): they
//! are started, restarted after their restart type, backoff and the intensity, and
//! stopped in reverse order; [`upgrade`] holds how one is replaced by its successor.
//!
//! What to do when a process exits is decided by the project's one supervision machine
//! ([`holon::supervisor::machine`]: one_for_one, one intensity for the whole cell, a
//! backoff per process that starts over after it ran a whole period); this module is
//! its executor for processes (spawn, signal, wait), and first sorts out the exits that
//! are no restart decision: those of successors, of retired ones and of older starts.

mod upgrade;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use anyhow::{Context, Result};
use holon::supervisor::{Action, Event, Machine, Strategy};
use holon::Backoff;
use tokio::process::Command;
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::control::{failed, Upgrade};
use crate::up::manifest::{Manifest, ProcessSection};
use upgrade::{Checked, Retired, Successor};

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
pub(super) struct Clock(pub(super) Instant);

impl Clock {
    pub(super) fn say(self, text: impl std::fmt::Display) {
        println!("[{:8.2}s] {text}", self.0.elapsed().as_secs_f64());
    }
}

/// One process of the manifest, as `cell up` tracks it.
struct Slot {
    /// While it runs.
    pid: Option<u32>,
    /// How many times it was started: an exit of an older generation is stale.
    generation: u64,
    /// When it is due to start again, after it exited.
    restart_at: Option<Instant>,
    /// Its successor, started by `cell upgrade`, until the hand-over ends.
    successor: Option<Successor>,
    /// True while a successor's config is being checked (before it starts).
    checking: bool,
}

/// How one process ended: its index, generation and exit status.
type Ended = (usize, u64, std::io::Result<ExitStatus>);

/// The processes of the manifest and their supervision.
pub(super) struct Processes<'a> {
    /// The manifest's directory: every process's working directory.
    dir: &'a Path,
    /// Where `<name>.log` of each process goes.
    logs: PathBuf,
    /// The processes' specs: the manifest's, with the command lines of upgrades.
    specs: Vec<ProcessSection>,
    /// Every start gets the next generation (of all processes), so an exit is matched
    /// with the start it ends.
    generations: u64,
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
    /// What to do when a process exits: restarts of all processes together against the
    /// intensity, a backoff per process.
    machine: Machine<usize>,
    clock: Clock,
}

impl<'a> Processes<'a> {
    pub(super) fn new(
        dir: &'a Path,
        logs: PathBuf,
        manifest: &'a Manifest,
        clock: Clock,
    ) -> Processes<'a> {
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
            stop_timeout: Duration::from_millis(restart.stop_timeout_ms),
            slots: manifest
                .processes
                .iter()
                .map(|_| Slot {
                    pid: None,
                    generation: 0,
                    restart_at: None,
                    successor: None,
                    checking: false,
                })
                .collect(),
            waits: JoinSet::new(),
            checks: JoinSet::new(),
            checking: HashMap::new(),
            retired: Vec::new(),
            machine: Machine::new(Strategy::OneForOne, manifest.intensity()).backoff(backoff),
            clock,
        }
    }

    /// Starts every process, in the manifest's order.
    pub(super) fn start_all(&mut self) -> Result<()> {
        for index in 0..self.slots.len() {
            let restart = self.specs[index].restart;
            let added = Event::Added {
                child: index,
                restart,
            };
            for action in self.machine.handle(added, Instant::now()) {
                if let Action::Start(index) = action {
                    self.start(index)?;
                }
            }
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
        slot.restart_at = None;
        let spec = &self.specs[index];
        let role = match spec.standby {
            true => " as a standby: it serves when it holds its controller's claim",
            false => "",
        };
        self.clock.say(format!(
            "started {} (pid {}){role}",
            spec.name,
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

    /// Restarts what exits until `shutdown`, and carries out upgrades: true, or false
    /// when the restart intensity was exceeded.
    pub(super) async fn supervise(
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

    /// Decides on an exit after its restart type and the intensity: false to give up.
    /// The exits that are no restart decision come first: a retired successor's, a
    /// successor's before its predecessor ended, an older start's, and the predecessor's
    /// that handed over.
    fn exited(&mut self, (index, generation, status): Ended) -> bool {
        if let Some(at) = self.retired.iter().position(|r| r.generation == generation) {
            self.retired.swap_remove(at);
            let name = &self.specs[index].name;
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
            self.successor_exited(index, successor, status);
            return true;
        }
        if slot.generation != generation {
            return true;
        }
        let predecessor_ok = status.as_ref().is_ok_and(ExitStatus::success);
        let mut successor = slot.successor.take();
        if let Some(successor) = successor.take_if(|_| predecessor_ok) {
            self.handed_over(index, successor, status);
            return true;
        }
        if let Some(successor) = successor {
            // The predecessor let go and no successor served within its stand-in limit
            // (it exits 1 then): the successor is stopped and the process is started
            // again below, from its previous command line, on its journal.
            self.retire(index, successor, &status);
        }
        self.child_exited(index, status)
    }

    /// A supervised process exited: the machine decides whether and when it restarts,
    /// or that the supervisor gives up (false).
    fn child_exited(&mut self, index: usize, status: std::io::Result<ExitStatus>) -> bool {
        self.slots[index].pid = None;
        let normally = status.as_ref().is_ok_and(ExitStatus::success);
        let status = describe(status);
        let exited = Event::Exited {
            child: index,
            normally,
            why: status.clone(),
        };
        let now = Instant::now();
        for action in self.machine.handle(exited, now) {
            let name = &self.specs[index].name;
            match action {
                Action::Done(_) => self.clock.say(format!(
                    "{name} exited ({status}); {} processes are not restarted",
                    self.specs[index].restart
                )),
                Action::GiveUp { error, .. } => {
                    self.clock.say(format!(
                        "{name} exited ({status}); more than {} restarts within {:?}: giving up",
                        error.max_restarts, error.period
                    ));
                    // The caller stops the rest (and abandons upgrades under way).
                    return false;
                }
                Action::RestartAfter(i, pause) => {
                    self.clock.say(format!(
                        "{name} exited ({status}); restarting in {} ms",
                        pause.as_millis()
                    ));
                    self.slots[i].restart_at = Some(now + pause);
                }
                // With a backoff and one_for_one the machine neither starts at once nor
                // stops others.
                Action::Start(i) => self.slots[i].restart_at = Some(now),
                Action::Stop(others) => {
                    tracing::error!(
                        ?others,
                        "cell up supervises one_for_one: nothing else is stopped"
                    )
                }
            }
        }
        true
    }

    /// Starts the processes whose restart is due; one that cannot start is tried again
    /// after its next pause.
    fn restart_due(&mut self) {
        let now = Instant::now();
        for index in 0..self.slots.len() {
            if self.slots[index].restart_at.is_none_or(|t| t > now) {
                continue;
            }
            self.slots[index].restart_at = None;
            for action in self.machine.handle(Event::RestartDue { child: index }, now) {
                match action {
                    Action::Start(i) => {
                        if let Err(e) = self.start(i) {
                            let failed = Event::StartFailed {
                                child: i,
                                why: format!("{e:#}"),
                            };
                            for action in self.machine.handle(failed, now) {
                                if let Action::RestartAfter(i, pause) = action {
                                    self.clock.say(format!(
                                        "{e:#}; retrying in {} ms",
                                        pause.as_millis()
                                    ));
                                    self.slots[i].restart_at = Some(now + pause);
                                }
                            }
                        }
                    }
                    Action::RestartAfter(i, pause) => self.slots[i].restart_at = Some(now + pause),
                    _ => {}
                }
            }
        }
    }

    /// Stops the running processes, last first: SIGTERM, then SIGKILL after the
    /// stop timeout.
    pub(super) async fn stop_all(&mut self) {
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

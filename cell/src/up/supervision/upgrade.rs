//! `cell upgrade` as the supervisor carries it out: the successor's `--check`, its
//! start with `--take-over`, and the stop of a successor that did not take over.

use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use tokio::process::Command;
use tokio::sync::oneshot;
use tokio::time::Instant;

use holon::supervisor::Event;

use super::{describe, resolve, Processes};
use crate::up::control::failed;
use crate::up::upgrade::{UpgradeOutcome, UpgradeRequest};

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

/// A successor's command line that passed (or failed) its `--check`.
pub(super) struct Checked {
    pub(super) index: usize,
    pub(super) program: String,
    pub(super) args: Vec<String>,
    pub(super) request: UpgradeRequest,
    pub(super) reply: oneshot::Sender<UpgradeOutcome>,
    /// Why it failed, if it did.
    pub(super) failure: Option<String>,
}

/// A successor that is stopped because its predecessor exited without handing over to
/// it (no successor served within the stand-in limit): SIGTERM, SIGKILL at `kill_at`.
pub(super) struct Retired {
    pub(super) index: usize,
    pub(super) generation: u64,
    pub(super) pid: u32,
    pub(super) kill_at: Instant,
}

/// A successor that is taking a process over.
pub(super) struct Successor {
    pub(super) pid: Option<u32>,
    pub(super) generation: u64,
    /// Its command line, the process's from now on.
    pub(super) program: String,
    pub(super) args: Vec<String>,
    pub(super) started_at: Instant,
    /// Where `cell upgrade` learns how it went.
    pub(super) reply: oneshot::Sender<UpgradeOutcome>,
}

impl Processes<'_> {
    /// Begins the upgrade of one process: checks the successor's command line (its
    /// `--check` runs as a task; [`Processes::checked`] goes on), then starts it with
    /// `--take-over`; the outcome goes to `reply` when the hand-over ends (see
    /// [`Processes::exited`]), or now if it cannot begin.
    pub(super) fn upgrade(
        &mut self,
        request: UpgradeRequest,
        reply: oneshot::Sender<UpgradeOutcome>,
    ) {
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
        let (program, args) = match crate::up::upgrade::successor_command(
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
    pub(super) fn checked(&mut self, checked: Checked) {
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

    /// The successor of process `index` exited before its predecessor ended: the
    /// upgrade failed, and `cell upgrade` is told why.
    pub(super) fn successor_exited(
        &mut self,
        index: usize,
        successor: Successor,
        status: std::io::Result<ExitStatus>,
    ) {
        let name = &self.specs[index].name;
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
            crate::up::upgrade::log_tail(&self.logs.join(format!("{name}.log")), 15)
        );
        self.clock
            .say(format!("upgrade of {name} failed: its successor exited"));
        if successor.reply.send(failed(&message)).is_err() {
            tracing::warn!(%name, "cell upgrade went away before its answer");
        }
    }

    /// Process `index` exited well after its successor took over: the successor is
    /// supervised in its place, and `cell upgrade` is told.
    pub(super) fn handed_over(
        &mut self,
        index: usize,
        successor: Successor,
        status: std::io::Result<ExitStatus>,
    ) {
        let slot = &mut self.slots[index];
        let before = slot.pid.unwrap_or(0);
        slot.generation = successor.generation;
        slot.pid = successor.pid;
        let replaced = Event::Replaced {
            child: index,
            started_at: successor.started_at,
        };
        self.machine.handle(replaced, Instant::now());
        let spec = &mut self.specs[index];
        spec.program = successor.program;
        spec.args = successor.args;
        let name = &spec.name;
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
    }

    /// Stops the successor of process `index`, whose predecessor exited (`status`)
    /// without handing over to it, and tells `cell upgrade`.
    pub(super) fn retire(
        &mut self,
        index: usize,
        successor: Successor,
        status: &std::io::Result<ExitStatus>,
    ) {
        let name = &self.specs[index].name;
        let message = format!(
            "{name} exited ({}) after handing over: its successor (pid {}) did not serve within {:?}. The successor is stopped and {name} is started again from its previous binary and config, on its journal. The end of logs/{name}.log:\n{}",
            match status {
                Ok(status) => status.to_string(),
                Err(e) => e.to_string(),
            },
            successor.pid.unwrap_or(0),
            holon::takeover::STAND_IN_LIMIT,
            crate::up::upgrade::log_tail(&self.logs.join(format!("{name}.log")), 15)
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
    pub(super) fn kill_retired(&mut self) {
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
}

//! A resource holon's PackML unit: its state, unit mode, counters and first-out stop
//! reason, as a pure machine owned by the agenda manager (the agenda decides what a
//! state does to bookings and the running step; this decides the state).
//!
//! | event | condition | next |
//! |---|---|---|
//! | an operator's command | the state accepts it ([`PackmlState::accepts`]), not Suspend, Unsuspend or Complete | its acting state, then its wait state once the acting state's work is done (below) |
//! | | otherwise | refused, naming the state; nothing changes |
//! | an operator's mode change | Stopped, Idle or Aborted | the mode changes |
//! | | otherwise | refused; nothing changes |
//! | controller `fault` / `estop` | not Aborting, Aborted or Clearing | Aborting (stop reason: the fault) |
//! | controller not ready (it was ready) | Execute | Suspending |
//! | controller ready | Suspended | Unsuspending |
//! | a step ends | | processed + 1 if done, defective + 1 if failed |
//! | after every event: the acting state's work is done | Holding, Stopping, Aborting, Suspending: no step runs; Clearing: the controller is not in fault or estop; Starting, Unholding, Unsuspending, Resetting: at once | its wait state ([`PackmlState::completes_to`]) |
//!
//! Suspended is the resource's own: it suspends while its controller is away and
//! unsuspends when it is back, keeping its bookings, as it always has. An operator
//! holds it instead (Hold); Suspend and Unsuspend are refused.
//!
//! The stop reason is first-out: the first event that took the unit out of Execute is
//! kept (and shown after it returns) until the next one after a return to Execute.
//!
//! Restored from the journal (a restart, a successor), an acting state whose work was
//! under way resumes from the wait state it led to: a step running at the crash is
//! reported `interrupted`, so Holding is Held, Stopping Stopped, Aborting Aborted; the
//! controller's states (Suspending, Suspended, Unsuspending) come back as Execute and
//! follow the controller again.

use std::collections::BTreeMap;

use schemas::packml::OperatorJob;
use schemas::packml::{STOP_CONTROLLER_AWAY, STOP_CONTROLLER_ESTOP, STOP_CONTROLLER_FAULT};
use schemas::{
    ControllerStatus, PackmlCommand, PackmlState, PackmlStatus, Refusal, StopReason, UnitMode,
};
use serde::{Deserialize, Serialize};

/// What a change of state asks of the agenda.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Consequence {
    /// Nothing beyond the state.
    None,
    /// Hand every booking back (Stop).
    HandBack,
    /// Tell the execution to abort its step, and hand every booking back (Abort, or a
    /// controller fault).
    Abort,
}

/// The unit; what the journal keeps of it is the whole of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PackmlUnit {
    /// `StateCurrent`.
    state: PackmlState,
    /// `UnitModeCurrent`.
    mode: UnitMode,
    /// The first-out stop reason.
    stop_reason: Option<StopReason>,
    /// Whether the next stop event replaces the stop reason: true once the unit was in
    /// Execute after the last one was recorded.
    #[serde(default = "yes")]
    first_out_armed: bool,
    /// Steps (jobs) done.
    processed: u64,
    /// Steps (jobs) that ended failed.
    defective: u64,
    /// When the current state was entered (Unix ms).
    since: u64,
    /// Milliseconds spent in each state before the current stay.
    cumulative_ms: BTreeMap<PackmlState, u64>,
    /// The last single job an operator ran (Maintenance mode).
    #[serde(default)]
    operator_job: Option<OperatorJob>,
    /// How many operator jobs it has run: the next one's number.
    #[serde(default)]
    operator_jobs: u64,
}

fn yes() -> bool {
    true
}

impl PackmlUnit {
    /// A unit that has never run, in `state` and `mode` (from the holon's config).
    pub fn new(state: PackmlState, mode: UnitMode, now: u64) -> PackmlUnit {
        PackmlUnit {
            state,
            mode,
            stop_reason: None,
            first_out_armed: true,
            processed: 0,
            defective: 0,
            since: now,
            cumulative_ms: BTreeMap::new(),
            operator_job: None,
            operator_jobs: 0,
        }
    }

    /// Whether an operator may run a single job now: Execute in Maintenance.
    pub fn allows_operator_job(&self) -> bool {
        self.state == PackmlState::Execute && self.mode == UnitMode::Maintenance
    }

    /// An operator's job begins: its conversation id (`maintenance/<n>`).
    pub fn operator_job_began(&mut self, service_type: &str, by: &str, now: u64) -> String {
        self.operator_jobs += 1;
        let conversation_id = format!("maintenance/{}", self.operator_jobs);
        self.operator_job = Some(OperatorJob {
            conversation_id: conversation_id.clone(),
            service_type: service_type.to_string(),
            by: by.to_string(),
            at: now,
            outcome: None,
            done: false,
        });
        conversation_id
    }

    /// The operator's job of `conversation_id` ended so.
    pub fn operator_job_ended(&mut self, conversation_id: &str, outcome: String, done: bool) {
        if let Some(job) = self
            .operator_job
            .as_mut()
            .filter(|job| job.conversation_id == conversation_id)
        {
            job.outcome = Some(outcome);
            job.done = done;
        }
    }

    /// The unit as the journal kept it, resumed (see the module's documentation).
    pub fn restored(mut self) -> PackmlUnit {
        let resumed = match self.state {
            PackmlState::Suspending | PackmlState::Suspended | PackmlState::Unsuspending => {
                PackmlState::Execute
            }
            PackmlState::Clearing => PackmlState::Clearing,
            acting => acting.completes_to().unwrap_or(acting),
        };
        if resumed != self.state {
            self.enter(resumed, self.since);
        }
        self
    }

    pub fn state(&self) -> PackmlState {
        self.state
    }

    pub fn mode(&self) -> UnitMode {
        self.mode
    }

    /// When the current state was entered (Unix ms).
    pub fn since(&self) -> u64 {
        self.since
    }

    /// Whether orders' work is taken: Execute in Production.
    pub fn takes_orders(&self) -> bool {
        self.state == PackmlState::Execute && self.mode == UnitMode::Production
    }

    /// The commands an operator may give now.
    pub fn commands(&self) -> Vec<PackmlCommand> {
        self.state
            .commands()
            .into_iter()
            .filter(|c| !operators_cannot(*c))
            .collect()
    }

    /// An operator's command: the acting state entered and what it asks of the
    /// agenda, or the refusal (nothing changed).
    pub fn command(
        &mut self,
        command: PackmlCommand,
        by: &str,
        now: u64,
    ) -> Result<Consequence, Refusal> {
        if operators_cannot(command) {
            return Err(Refusal::NotSupported { command });
        }
        let acting = self.state.accepts(command)?;
        if matches!(
            command,
            PackmlCommand::Hold | PackmlCommand::Stop | PackmlCommand::Abort
        ) {
            self.stop_reason(command.number(), format!("{command} by {by}"), now);
        }
        self.enter(acting, now);
        Ok(match command {
            PackmlCommand::Stop => Consequence::HandBack,
            PackmlCommand::Abort => Consequence::Abort,
            _ => Consequence::None,
        })
    }

    /// An operator's change of the unit mode.
    pub fn set_mode(&mut self, mode: UnitMode) -> Result<(), Refusal> {
        if !self.state.allows_mode_change() {
            return Err(Refusal::ModeNotInState { state: self.state });
        }
        self.mode = mode;
        Ok(())
    }

    /// The controller's state changed; `was_ready` is whether it was ready before.
    /// `said`: what the controller said of it in its own words (a status reply's
    /// `{message}`), kept in the stop reason.
    pub fn controller(
        &mut self,
        status: ControllerStatus,
        said: Option<&str>,
        now: u64,
    ) -> Consequence {
        match status {
            ControllerStatus::Fault | ControllerStatus::Estop => {
                if matches!(
                    self.state,
                    PackmlState::Aborting | PackmlState::Aborted | PackmlState::Clearing
                ) {
                    return Consequence::None;
                }
                let id = if status == ControllerStatus::Fault {
                    STOP_CONTROLLER_FAULT
                } else {
                    STOP_CONTROLLER_ESTOP
                };
                let message = match said {
                    Some(said) => format!("the controller reported {status}: {said}"),
                    None => format!("the controller reported {status}"),
                };
                self.stop_reason(id, message, now);
                self.enter(PackmlState::Aborting, now);
                Consequence::Abort
            }
            ControllerStatus::Disconnected => {
                if self.state == PackmlState::Execute {
                    self.stop_reason(
                        STOP_CONTROLLER_AWAY,
                        "the controller is not connected".into(),
                        now,
                    );
                    self.enter(PackmlState::Suspending, now);
                }
                Consequence::None
            }
            ControllerStatus::Ready => {
                if self.state == PackmlState::Suspended {
                    self.enter(PackmlState::Unsuspending, now);
                }
                Consequence::None
            }
        }
    }

    /// A step ended: counted.
    pub fn step_ended(&mut self, done: bool) {
        if done {
            self.processed += 1;
        } else {
            self.defective += 1;
        }
    }

    /// Completes acting states whose work is done: `running` is whether a step runs,
    /// `controller` the controller's state. True when the state changed.
    pub fn settle(&mut self, running: bool, controller: ControllerStatus, now: u64) -> bool {
        let mut changed = false;
        while let Some(next) = self.state.completes_to() {
            let done = match self.state {
                PackmlState::Holding
                | PackmlState::Stopping
                | PackmlState::Aborting
                | PackmlState::Suspending => !running,
                PackmlState::Clearing => !matches!(
                    controller,
                    ControllerStatus::Fault | ControllerStatus::Estop
                ),
                _ => true,
            };
            if !done {
                break;
            }
            self.enter(next, now);
            changed = true;
        }
        changed
    }

    /// The figures for the state snapshot.
    pub fn status(&self) -> PackmlStatus {
        let state_requested = self.state.completes_to().unwrap_or(self.state);
        PackmlStatus {
            state: self.state,
            state_number: self.state.number(),
            state_requested,
            mode: self.mode,
            processed: self.processed,
            defective: self.defective,
            stop_reason: self.stop_reason.clone(),
            since: self.since,
            cumulative_ms: self.cumulative_ms.clone(),
            commands: self.commands(),
            operator_job: self.operator_job.clone(),
        }
    }

    fn stop_reason(&mut self, id: i32, message: String, now: u64) {
        if self.first_out_armed {
            self.stop_reason = Some(StopReason {
                id,
                message,
                at: now,
            });
            self.first_out_armed = false;
        }
    }

    fn enter(&mut self, state: PackmlState, now: u64) {
        *self.cumulative_ms.entry(self.state).or_default() += now.saturating_sub(self.since);
        self.state = state;
        self.since = now;
        if state == PackmlState::Execute {
            self.first_out_armed = true;
        }
    }
}

/// Commands a resource holon does not take from operators: it suspends by itself, and
/// it never completes.
fn operators_cannot(command: PackmlCommand) -> bool {
    matches!(
        command,
        PackmlCommand::Suspend | PackmlCommand::Unsuspend | PackmlCommand::Complete
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use PackmlState as S;

    fn unit() -> PackmlUnit {
        PackmlUnit::new(S::Execute, UnitMode::Production, 1_000)
    }

    #[test]
    fn hold_waits_for_the_running_step_then_unhold_resumes() {
        let mut u = unit();
        assert_eq!(
            u.command(PackmlCommand::Hold, "op", 2_000),
            Ok(Consequence::None)
        );
        assert_eq!(u.state(), S::Holding);
        assert!(!u.takes_orders());
        assert!(!u.settle(true, ControllerStatus::Ready, 2_500));
        assert_eq!(u.state(), S::Holding);
        assert!(u.settle(false, ControllerStatus::Ready, 3_000));
        assert_eq!(u.state(), S::Held);
        u.command(PackmlCommand::Unhold, "op", 4_000).unwrap();
        u.settle(false, ControllerStatus::Ready, 4_000);
        assert_eq!(u.state(), S::Execute);
        assert!(u.takes_orders());
        let status = u.status();
        assert_eq!(status.cumulative_ms[&S::Execute], 1_000);
        assert_eq!(status.cumulative_ms[&S::Holding], 1_000);
        assert_eq!(status.cumulative_ms[&S::Held], 1_000);
        assert_eq!(status.stop_reason.unwrap().id, 4);
    }

    #[test]
    fn stop_hands_back_then_reset_and_start_lead_to_execute() {
        let mut u = unit();
        assert_eq!(
            u.command(PackmlCommand::Stop, "op", 2_000),
            Ok(Consequence::HandBack)
        );
        u.settle(false, ControllerStatus::Ready, 2_000);
        assert_eq!(u.state(), S::Stopped);
        u.command(PackmlCommand::Reset, "op", 3_000).unwrap();
        u.settle(false, ControllerStatus::Ready, 3_000);
        assert_eq!(u.state(), S::Idle);
        assert!(!u.takes_orders());
        u.command(PackmlCommand::Start, "op", 4_000).unwrap();
        u.settle(false, ControllerStatus::Ready, 4_000);
        assert_eq!(u.state(), S::Execute);
    }

    #[test]
    fn abort_then_clear_leads_to_stopped_once_the_fault_is_gone() {
        let mut u = unit();
        assert_eq!(
            u.command(PackmlCommand::Abort, "op", 2_000),
            Ok(Consequence::Abort)
        );
        assert!(!u.settle(true, ControllerStatus::Ready, 2_000));
        u.settle(false, ControllerStatus::Ready, 2_100);
        assert_eq!(u.state(), S::Aborted);
        u.command(PackmlCommand::Clear, "op", 3_000).unwrap();
        assert!(!u.settle(false, ControllerStatus::Estop, 3_000));
        assert_eq!(u.state(), S::Clearing);
        u.settle(false, ControllerStatus::Ready, 3_500);
        assert_eq!(u.state(), S::Stopped);
    }

    #[test]
    fn a_controller_fault_aborts_with_the_fault_as_stop_reason() {
        for (status, id) in [
            (ControllerStatus::Fault, STOP_CONTROLLER_FAULT),
            (ControllerStatus::Estop, STOP_CONTROLLER_ESTOP),
        ] {
            let mut u = unit();
            assert_eq!(u.controller(status, None, 2_000), Consequence::Abort);
            u.settle(false, status, 2_000);
            assert_eq!(u.state(), S::Aborted);
            let reason = u.status().stop_reason.unwrap();
            assert_eq!(reason.id, id);
            assert!(reason.message.contains(status.as_str()), "{reason:?}");
        }
        // The controller's own words, when it gave any, are the stop reason's.
        let mut u = unit();
        u.controller(ControllerStatus::Fault, Some("overtravel axis 3"), 2_000);
        assert_eq!(
            u.status().stop_reason.unwrap().message,
            "the controller reported fault: overtravel axis 3"
        );
        for (status, _) in [
            (ControllerStatus::Fault, STOP_CONTROLLER_FAULT),
            (ControllerStatus::Estop, STOP_CONTROLLER_ESTOP),
        ] {
            let mut u = unit();
            u.controller(status, None, 2_000);
            u.settle(false, status, 2_000);
            // Aborted already: another fault changes nothing.
            assert_eq!(u.controller(status, None, 2_500), Consequence::None);
        }
    }

    #[test]
    fn the_controller_away_suspends_and_its_return_unsuspends() {
        let mut u = unit();
        u.controller(ControllerStatus::Disconnected, None, 2_000);
        u.settle(false, ControllerStatus::Disconnected, 2_000);
        assert_eq!(u.state(), S::Suspended);
        assert_eq!(u.status().stop_reason.unwrap().id, STOP_CONTROLLER_AWAY);
        u.controller(ControllerStatus::Ready, None, 3_000);
        u.settle(false, ControllerStatus::Ready, 3_000);
        assert_eq!(u.state(), S::Execute);
        // Held: the controller's comings and goings do not move it.
        u.command(PackmlCommand::Hold, "op", 4_000).unwrap();
        u.settle(false, ControllerStatus::Ready, 4_000);
        u.controller(ControllerStatus::Disconnected, None, 5_000);
        u.controller(ControllerStatus::Ready, None, 6_000);
        assert_eq!(u.state(), S::Held);
    }

    #[test]
    fn the_stop_reason_is_first_out_until_execute_again() {
        let mut u = unit();
        u.command(PackmlCommand::Hold, "alice", 2_000).unwrap();
        u.command(PackmlCommand::Stop, "bob", 2_500).unwrap();
        u.settle(false, ControllerStatus::Ready, 2_500);
        let first = u.status().stop_reason.unwrap();
        assert_eq!((first.id, first.message.as_str()), (4, "Hold by alice"));
        for command in [PackmlCommand::Reset, PackmlCommand::Start] {
            u.command(command, "bob", 3_000).unwrap();
            u.settle(false, ControllerStatus::Ready, 3_000);
        }
        assert_eq!(u.status().stop_reason.unwrap().id, 4, "kept in Execute");
        u.command(PackmlCommand::Abort, "carol", 4_000).unwrap();
        assert_eq!(u.status().stop_reason.unwrap().message, "Abort by carol");
    }

    #[test]
    fn refusals_name_the_state_and_change_nothing() {
        let mut u = unit();
        let before = u.clone();
        assert_eq!(
            u.command(PackmlCommand::Unhold, "op", 2_000),
            Err(Refusal::NotInState {
                command: PackmlCommand::Unhold,
                state: S::Execute
            })
        );
        for command in [
            PackmlCommand::Suspend,
            PackmlCommand::Unsuspend,
            PackmlCommand::Complete,
        ] {
            assert_eq!(
                u.command(command, "op", 2_000),
                Err(Refusal::NotSupported { command })
            );
        }
        assert_eq!(
            u.set_mode(UnitMode::Maintenance),
            Err(Refusal::ModeNotInState { state: S::Execute })
        );
        assert_eq!(u, before);
        assert_eq!(
            u.commands(),
            [
                PackmlCommand::Stop,
                PackmlCommand::Hold,
                PackmlCommand::Abort
            ]
        );
    }

    #[test]
    fn maintenance_takes_no_orders() {
        let mut u = PackmlUnit::new(S::Idle, UnitMode::Production, 0);
        u.set_mode(UnitMode::Maintenance).unwrap();
        u.command(PackmlCommand::Start, "op", 1).unwrap();
        u.settle(false, ControllerStatus::Ready, 1);
        assert_eq!(u.state(), S::Execute);
        assert!(!u.takes_orders());
    }

    #[test]
    fn counters_count_steps_done_and_failed() {
        let mut u = unit();
        u.step_ended(true);
        u.step_ended(true);
        u.step_ended(false);
        let status = u.status();
        assert_eq!((status.processed, status.defective), (2, 1));
    }

    #[test]
    fn restored_acting_states_resume_from_the_wait_state_they_led_to() {
        let cases = [
            (S::Holding, S::Held),
            (S::Held, S::Held),
            (S::Stopping, S::Stopped),
            (S::Aborting, S::Aborted),
            (S::Clearing, S::Clearing),
            (S::Starting, S::Execute),
            (S::Resetting, S::Idle),
            (S::Suspended, S::Execute),
            (S::Suspending, S::Execute),
            (S::Idle, S::Idle),
        ];
        for (kept, resumed) in cases {
            let mut u = unit();
            u.state = kept;
            let text = serde_json::to_string(&u).unwrap();
            let back: PackmlUnit = serde_json::from_str(&text).unwrap();
            assert_eq!(back.restored().state(), resumed, "{kept}");
        }
    }
}

//! The execution machine ([`ExecutionMachine`]): the seed's Figure 5 (the Execution
//! component's behaviour) as a pure state machine, owned by the execution component
//! ([`crate::component::execution`]).
//!
//! `init` until the controller reports `ready`; then `ready -> step 1 -> ... -> ready`,
//! the steps of each service type coming from the holon's config (pick_n_place: `pick`
//! until `picking_done`, then `place` until `placing_done`). Each step sends one command
//! through the Interfacing component and waits for one of its results. A failed step is
//! never retried here: the order decides (the step may have moved the part).
//!
//! | state | event | actions | next |
//! |---|---|---|---|
//! | `init` | controller `ready` | ready | `ready` |
//! | `init` | controller not ready (disconnected, `fault`, `estop`), a change | unavailable with the status | `init` |
//! | `init` | start | finished: failed `unavailable` (fenced: `controller_disconnected`, as an earlier holder may have begun it) | `init` |
//! | `ready` | start | command of step 1 | step 1 |
//! | `ready` | controller not ready | unavailable | `init` |
//! | step n | start (another job) | that job finished: failed `busy` (fenced: `controller_disconnected`) | step n |
//! | step n | reply to its command with a result the step expects, steps left | command of step n+1 | step n+1 |
//! | step n | the same, last step | finished: done with every step's result | `ready` (or `init`) |
//! | step n | reply `error` | finished: failed `controller_error` | `ready` (or `init`) |
//! | step n | `CommandFailed` `StaleEpoch` (the controller refused a fenced resource's epoch: deposed) | finished: deposed (no result: the new holder's word counts) | `ready` (or `init`) |
//! | step n | reply with a result the step does not expect | finished: failed `unexpected_result` | `ready` (or `init`) |
//! | step n | its command timed out / the connection broke / the protocol broke | finished: failed `controller_timeout` / `controller_disconnected` / `controller_protocol_error` | `ready` (or `init`) |
//! | step n | controller disconnected | finished: failed `controller_disconnected`; unavailable | `init` |
//! | step n, fenced | its command timed out / the connection broke / the protocol broke, or the controller disconnected | its step's state asked of the controller once it is ready | step n, unsettled |
//! | step n, unsettled | controller `ready` | its step's state asked | step n, unsettled |
//! | step n, unsettled | step state `done` with a result | as that reply (the next step's command, or finished: done) | step n+1, or `ready` |
//! | step n, unsettled | step state `failed` | as a reply `error` | `ready` (or `init`) |
//! | step 1, unsettled | step state unknown (the controller never began it: nothing of the job ran) | finished: failed `not_begun` | `ready` (or `init`) |
//! | step n > 1, unsettled | step state unknown (the controller never began it) | finished: failed `controller_disconnected` | `ready` (or `init`) |
//! | step n, unsettled | the state cannot be asked now (not connected, no answer in time) | asked again once the controller is ready | step n, unsettled |
//! | step n, unsettled | the controller cannot tell (no fence, refused) | finished: failed `controller_disconnected` | `ready` (or `init`) |
//! | step n | controller `fault` / `estop` | finished: failed `controller_fault`; unavailable | `init` |
//! | step n | abort (PackML Abort) | the controller is told to abort | step n, aborting |
//! | step n | the controller says its command's move has left its origin (`departed`) | departed: the job's requester is told (once per time the controller says it) | step n |
//! | step n, aborting | reply with a result the last step expects | finished: done (it completed before the abort took) | `ready` (or `init`) |
//! | step n, aborting | any other reply, a command failure, the controller not ready | finished: failed `aborted` | `ready` (or `init`) |
//! | `init`, `ready` | abort | nothing (no step runs) | same |
//! | any | a reply or failure of another command (late) | nothing | same |
//!
//! A step's command, and every change of step, is followed by a `StateChanged` action.
//!
//! A fenced resource's controller runs each step id at most once and keeps its outcome
//! (`docs/controller-protocol.md`, "Fencing (standby)"), so a step whose answer was lost
//! with the connection is not reported failed: its outcome is asked (`unsettled`), and
//! a step the controller completed is reported done, never run again by an order that
//! was told it failed. While unsettled the agenda manager is not told the controller is
//! away: the job is still running.

use std::sync::Arc;

use robot_bridge::client::{
    CommandFailure, ControllerEvent, ControllerStatus, FenceError, StepStatus,
};
use schemas::{HolonId, Reason, RobotCommand};
use serde_json::{Map, Value};

use crate::catalog::ServiceCatalog;
use crate::machine::agenda::{Job, Outcome};

/// What the execution component reacts to.
#[derive(Debug, Clone, PartialEq)]
pub enum ExecutionEvent {
    /// From the agenda manager: execute this job.
    Start(Job),
    /// From the agenda manager: abort the running step now (PackML Abort).
    Abort,
    /// From the interfacing component.
    Controller(ControllerEvent),
}

/// What the agenda manager asks of the execution component (its job mailbox).
#[derive(Debug, Clone, PartialEq)]
pub enum ExecutionRequest {
    /// Execute this job.
    Start(Job),
    /// Abort the running step (PackML Abort).
    Abort,
}

/// What the task around the execution FSM must do.
#[derive(Debug, Clone, PartialEq)]
pub enum ExecutionAction {
    /// Send this command to the controller.
    Command(RobotCommand),
    /// Tell the controller to stop now (its dialect's abort).
    AbortController,
    /// Ask the controller the state of the running step (its step id: the job's
    /// conversation, `#`, the step's index), whose command's answer was lost.
    AskStepStatus,
    /// Tell the agenda manager: ready to execute.
    Ready,
    /// Tell the agenda manager: cannot execute (controller away, fault or estop), with
    /// what the controller said of it in its own words, if anything.
    Unavailable(ControllerStatus, Option<String>),
    /// Tell the job's requester that its move has left its origin (the controller said
    /// `departed`): sent once, not journalled, not repeated (docs/material-flow.md,
    /// "Departure").
    Departed {
        /// The job's conversation.
        conversation_id: String,
        /// Who booked the job.
        requester: HolonId,
        /// The job's service, e.g. `transport`.
        service_type: String,
        /// The requester's inbox (where `done` goes).
        reply_to: String,
    },
    /// Tell the agenda manager how the job ended.
    Finished {
        conversation_id: String,
        outcome: Outcome,
    },
    /// The state changed (a step began or ended): publish a snapshot.
    StateChanged,
}

#[derive(Debug, Clone, PartialEq)]
pub enum ExecutionState {
    /// Waiting for the controller to be connected and ready.
    Init,
    Ready,
    /// Executing `job`: step `step` is waiting for the reply to `command_id`.
    Running {
        /// Boxed: the state is moved at each transition, the job stays where it is.
        job: Box<Job>,
        step: usize,
        command_id: u64,
        results: Map<String, Value>,
        /// The controller was told to abort: the step ends `aborted` unless it
        /// completed the job first.
        aborting: bool,
        /// A fenced resource's step whose command's answer was lost: its outcome is
        /// asked of the controller.
        unsettled: bool,
    },
}

/// As the transition log shows it: `init`, `ready`, `step 2`.
impl std::fmt::Display for ExecutionState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ExecutionState::Init => f.write_str("init"),
            ExecutionState::Ready => f.write_str("ready"),
            ExecutionState::Running {
                step,
                aborting: true,
                ..
            } => write!(f, "step {}, aborting", step + 1),
            ExecutionState::Running {
                step,
                unsettled: true,
                ..
            } => write!(f, "step {}, unsettled", step + 1),
            ExecutionState::Running { step, .. } => write!(f, "step {}", step + 1),
        }
    }
}

#[derive(Debug, Clone)]
pub struct ExecutionMachine {
    catalog: Arc<ServiceCatalog>,
    state: ExecutionState,
    controller: ControllerStatus,
    /// What the controller said of its state in its own words (a status reply's
    /// `{message}`), if anything.
    said: Option<String>,
    next_command_id: u64,
    /// How far apart its command ids are: 1, or the number of lanes when it is one lane
    /// of several ([`lanes::Executions`]), each lane's ids its own.
    command_id_stride: u64,
    /// Whether the controller fences (a standby resource's): a lost answer is asked.
    fenced: bool,
}

impl ExecutionMachine {
    pub fn new(catalog: Arc<ServiceCatalog>) -> Self {
        ExecutionMachine {
            catalog,
            state: ExecutionState::Init,
            controller: ControllerStatus::Disconnected,
            said: None,
            next_command_id: 1,
            command_id_stride: 1,
            fenced: false,
        }
    }

    /// The same machine numbering its commands `first`, `first + stride`, ...: one lane
    /// of several on one controller connection, whose replies are told apart by id.
    pub fn with_command_ids(mut self, first: u64, stride: u64) -> Self {
        self.next_command_id = first.max(1);
        self.command_id_stride = stride.max(1);
        self
    }

    /// The same machine for a fenced controller: a step whose answer was lost is asked
    /// of the controller, not failed.
    pub fn fenced(mut self, fenced: bool) -> Self {
        self.fenced = fenced;
        self
    }

    pub fn state(&self) -> &ExecutionState {
        &self.state
    }

    pub fn controller(&self) -> ControllerStatus {
        self.controller
    }

    /// The action of the step in progress, e.g. `pick`.
    /// The conversation of the job running, if one is.
    pub fn current_conversation(&self) -> Option<&str> {
        match &self.state {
            ExecutionState::Running { job, .. } => Some(&job.conversation_id),
            _ => None,
        }
    }

    /// The job running and the index of its step in progress: a fenced resource's step
    /// id (`<conversation_id>#<index>`).
    pub fn current_step_index(&self) -> Option<(&str, usize)> {
        match &self.state {
            ExecutionState::Running { job, step, .. } => Some((&job.conversation_id, *step)),
            _ => None,
        }
    }

    pub fn current_step(&self) -> Option<String> {
        match &self.state {
            ExecutionState::Running { job, step, .. } => self
                .catalog
                .get(&job.service_type)
                .and_then(|d| d.steps.get(*step))
                .map(|s| s.action.clone()),
            _ => None,
        }
    }

    pub fn handle(&mut self, event: ExecutionEvent) -> Vec<ExecutionAction> {
        match event {
            ExecutionEvent::Start(job) => self.start(job),
            ExecutionEvent::Abort => self.abort(),
            ExecutionEvent::Controller(ControllerEvent::Status(status, said)) => {
                self.status(status, said)
            }
            ExecutionEvent::Controller(ControllerEvent::Reply {
                id,
                result,
                message,
            }) => self.reply(id, result, message),
            ExecutionEvent::Controller(ControllerEvent::StepStatus { step, status }) => {
                self.settled(step.as_str(), status)
            }
            ExecutionEvent::Controller(ControllerEvent::Departed { id }) => self.departed(id),
            ExecutionEvent::Controller(ControllerEvent::CommandFailed { id, failure }) => {
                if !self.is_waiting_for(id) {
                    return vec![];
                }
                if let CommandFailure::StaleEpoch { .. } = failure {
                    // Deposed: the controller has a newer holder and ran nothing of this
                    // command. Not the controller's error: this resource steps down and
                    // says nothing of the job (the order may have booked the same
                    // conversation with the new holder, which then goes on from the
                    // controller's record of its steps; an order that did not asks the
                    // new holder what became of it).
                    let detail =
                        format!("{failure}; this resource steps down, this step was not run here");
                    return self.end(Outcome::Deposed { detail });
                }
                let unknown_outcome = matches!(
                    failure,
                    CommandFailure::Timeout(_)
                        | CommandFailure::Disconnected
                        | CommandFailure::Protocol(_)
                );
                if self.fenced && unknown_outcome && !self.is_aborting() {
                    return self.unsettle();
                }
                if self.is_aborting() {
                    return self.fail(
                        Reason::Aborted,
                        format!("aborted by an operator: {failure}"),
                    );
                }
                let why = match failure {
                    CommandFailure::Timeout(_) => Reason::ControllerTimeout,
                    CommandFailure::Disconnected | CommandFailure::NotConnected => {
                        Reason::ControllerDisconnected
                    }
                    CommandFailure::Protocol(_) => Reason::ControllerProtocol,
                    CommandFailure::Unwritable(_) => Reason::InvalidInfo,
                    CommandFailure::Aborted => Reason::Aborted,
                    CommandFailure::Stopped(_) => Reason::ControllerFault,
                    // Ended deposed above.
                    CommandFailure::StaleEpoch { .. } => Reason::StaleEpoch,
                };
                self.fail(why, failure.to_string())
            }
        }
    }

    fn is_aborting(&self) -> bool {
        matches!(&self.state, ExecutionState::Running { aborting: true, .. })
    }

    /// PackML Abort: the controller is told to stop; the step ends when it says so.
    fn abort(&mut self) -> Vec<ExecutionAction> {
        match &mut self.state {
            ExecutionState::Running { aborting, .. } if !*aborting => {
                *aborting = true;
                vec![
                    ExecutionAction::AbortController,
                    ExecutionAction::StateChanged,
                ]
            }
            _ => vec![],
        }
    }

    /// The controller says command `id`'s move has left its origin: the job's requester
    /// is told, if the running step waits for that command and the job has an inbox
    /// (an operator's job has none). The step goes on.
    fn departed(&mut self, id: u64) -> Vec<ExecutionAction> {
        match &self.state {
            ExecutionState::Running { job, .. } if self.is_waiting_for(id) => {
                if job.reply_to.is_empty() {
                    return vec![];
                }
                vec![ExecutionAction::Departed {
                    conversation_id: job.conversation_id.clone(),
                    requester: job.requester.clone(),
                    service_type: job.service_type.clone(),
                    reply_to: job.reply_to.clone(),
                }]
            }
            _ => vec![],
        }
    }

    /// Whether its running step waits for the answer to command `id`.
    pub fn is_waiting_for(&self, id: u64) -> bool {
        matches!(&self.state, ExecutionState::Running { command_id, .. } if *command_id == id)
    }

    fn idle_state(&self) -> ExecutionState {
        if self.controller.is_ready() {
            ExecutionState::Ready
        } else {
            ExecutionState::Init
        }
    }

    fn start(&mut self, mut job: Job) -> Vec<ExecutionAction> {
        if !matches!(self.state, ExecutionState::Ready) {
            // The agenda manager only starts a ready execution; a race with a controller
            // status change ends here.
            // Not sent: `busy` and `unavailable` tell the order nothing of it ran
            // (`Reason::never_reached_controller`). A fenced resource's job may have
            // been begun by an earlier holder of the controller (a standby took over,
            // an order booked the same conversation again): not said, it may have run.
            let (why, detail) = match self.state {
                _ if self.fenced => (
                    Reason::ControllerDisconnected,
                    "the controller is not ready for it, and an earlier holder of this fenced controller may have begun it",
                ),
                ExecutionState::Running { .. } => (Reason::Busy, "another job is running"),
                _ => (Reason::Unavailable, "the controller is not ready"),
            };
            return vec![ExecutionAction::Finished {
                conversation_id: job.conversation_id,
                outcome: Outcome::Failed {
                    reason: why,
                    detail: detail.into(),
                },
            }];
        }
        // Read when it was booked; only a job that came without them is read here, once.
        if job.parameters.is_none() {
            job.parameters = self
                .catalog
                .parameters(&job.service_type, &job.info)
                .ok()
                .map(Arc::new);
        }
        self.state = ExecutionState::Running {
            job: Box::new(job),
            step: 0,
            command_id: 0,
            results: Map::new(),
            aborting: false,
            unsettled: false,
        };
        self.send_step()
    }

    /// Sends the command of the current step (or fails the job if it cannot be built).
    fn send_step(&mut self) -> Vec<ExecutionAction> {
        let ExecutionState::Running {
            job,
            step,
            command_id,
            ..
        } = &mut self.state
        else {
            return vec![];
        };
        let definition = self.catalog.get(&job.service_type);
        let (Some(definition), Some(parameters)) = (definition, &job.parameters) else {
            return self.fail(
                Reason::InvalidInfo,
                "the job's info does not fit its steps".into(),
            );
        };
        let Some(current) = definition.steps.get(*step) else {
            return self.fail(Reason::InvalidInfo, "the service has no such step".into());
        };
        *command_id = self.next_command_id;
        self.next_command_id += self.command_id_stride;
        vec![
            ExecutionAction::Command(RobotCommand {
                id: *command_id,
                action: current.action.clone(),
                pos: parameters.poses.get(*step).copied().flatten(),
                program: parameters.program.clone(),
                info: parameters.scalars.clone(),
            }),
            ExecutionAction::StateChanged,
        ]
    }

    fn reply(&mut self, id: u64, result: String, message: Option<String>) -> Vec<ExecutionAction> {
        if !self.is_waiting_for(id) {
            // A late reply to a command whose step already failed: ignored.
            return vec![];
        }
        let ExecutionState::Running {
            job,
            step,
            results,
            aborting,
            ..
        } = &mut self.state
        else {
            return vec![];
        };
        let aborting = *aborting;
        let Some(current) = self
            .catalog
            .get(&job.service_type)
            .and_then(|d| d.steps.get(*step))
            .cloned()
        else {
            return self.fail(Reason::InvalidInfo, "the service has no such step".into());
        };
        let steps = self
            .catalog
            .get(&job.service_type)
            .map_or(0, |d| d.steps.len());
        let completes = result != schemas::robot::RESULT_ERROR
            && current.until.contains(&result)
            && *step + 1 == steps;
        if aborting && !completes {
            let detail = format!(
                "aborted by an operator during {} (the controller answered {result:?}{})",
                current.action,
                message.map(|m| format!(": {m}")).unwrap_or_default()
            );
            return self.fail(Reason::Aborted, detail);
        }
        if result == schemas::robot::RESULT_ERROR {
            let detail = format!(
                "{} failed: {}",
                current.action,
                message.unwrap_or_else(|| "no message".into())
            );
            return self.fail(Reason::ControllerError, detail);
        }
        if !current.until.contains(&result) {
            let detail = format!(
                "{} answered {result:?}, expected {}",
                current.action,
                current.until.join(" or ")
            );
            return self.fail(Reason::UnexpectedResult, detail);
        }
        results.insert(current.action.clone(), Value::String(result));
        *step += 1;
        if *step < steps {
            return self.send_step();
        }
        let ExecutionState::Running { job, results, .. } =
            std::mem::replace(&mut self.state, ExecutionState::Init)
        else {
            unreachable!("checked above");
        };
        self.state = self.idle_state();
        vec![ExecutionAction::Finished {
            conversation_id: job.conversation_id,
            outcome: Outcome::Done { results },
        }]
    }

    fn fail(&mut self, why: Reason, detail: String) -> Vec<ExecutionAction> {
        self.end(Outcome::Failed {
            reason: why,
            // A controller's text goes into a message: bounded.
            detail: schemas::bounded_detail(detail),
        })
    }

    /// The running job ends with `outcome` before its last step.
    fn end(&mut self, outcome: Outcome) -> Vec<ExecutionAction> {
        let previous = std::mem::replace(&mut self.state, ExecutionState::Init);
        self.state = self.idle_state();
        let mut actions = Vec::new();
        if let ExecutionState::Running { job, .. } = previous {
            actions.push(ExecutionAction::Finished {
                conversation_id: job.conversation_id,
                outcome,
            });
        }
        actions
    }

    fn status(&mut self, status: ControllerStatus, said: Option<String>) -> Vec<ExecutionAction> {
        let was_ready = self.controller.is_ready();
        let previous = std::mem::replace(&mut self.controller, status);
        let said_before = std::mem::replace(&mut self.said, said.clone());
        // The controller's own words, where it gave any: `fault: overtravel axis 3`.
        let reported = match &said {
            Some(said) => format!("{status}: {said}"),
            None => status.to_string(),
        };
        let mut actions = Vec::new();
        let running = matches!(self.state, ExecutionState::Running { .. });
        if running && self.fenced && status == ControllerStatus::Disconnected && !self.is_aborting()
        {
            // Its step's answer may be lost with the connection: asked once it is back.
            return self.unsettle();
        }
        if running && status.is_ready() && self.is_unsettled() {
            return vec![ExecutionAction::AskStepStatus];
        }
        if !status.is_ready() && running {
            let (why, detail) = match status {
                _ if self.is_aborting() => (
                    Reason::Aborted,
                    format!("aborted by an operator; the controller then reported {reported}"),
                ),
                ControllerStatus::Disconnected => (
                    Reason::ControllerDisconnected,
                    "the connection to the controller broke".to_string(),
                ),
                ControllerStatus::Ready | ControllerStatus::Fault | ControllerStatus::Estop => (
                    Reason::ControllerFault,
                    format!("the controller reported {reported}"),
                ),
            };
            actions.extend(self.fail(why, detail));
        }
        match (&self.state, status.is_ready()) {
            (ExecutionState::Init, true) => {
                self.state = ExecutionState::Ready;
                actions.push(ExecutionAction::Ready);
            }
            (ExecutionState::Ready, false) => {
                self.state = ExecutionState::Init;
                actions.push(ExecutionAction::Unavailable(status, said));
            }
            (ExecutionState::Init, false)
                if was_ready || status != previous || said != said_before =>
            {
                actions.push(ExecutionAction::Unavailable(status, said));
            }
            _ => {}
        }
        if actions.is_empty() {
            actions.push(ExecutionAction::StateChanged);
        }
        actions
    }
}

impl ExecutionMachine {
    fn is_unsettled(&self) -> bool {
        matches!(
            &self.state,
            ExecutionState::Running {
                unsettled: true,
                ..
            }
        )
    }

    /// The running step's answer is lost: its outcome is asked of the controller (now,
    /// if it is ready; else once it is).
    fn unsettle(&mut self) -> Vec<ExecutionAction> {
        let ExecutionState::Running { unsettled, .. } = &mut self.state else {
            return vec![];
        };
        let first = !std::mem::replace(unsettled, true);
        let mut actions = Vec::new();
        if self.controller.is_ready() {
            actions.push(ExecutionAction::AskStepStatus);
        }
        if first {
            actions.push(ExecutionAction::StateChanged);
        }
        actions
    }

    /// The controller's word on step `step` (`<conversation>#<index>`), asked while the
    /// running step is unsettled.
    fn settled(
        &mut self,
        step: &str,
        status: Result<StepStatus, FenceError>,
    ) -> Vec<ExecutionAction> {
        let ExecutionState::Running {
            job,
            step: index,
            command_id,
            unsettled,
            ..
        } = &mut self.state
        else {
            return vec![];
        };
        if !*unsettled || format!("{}#{index}", job.conversation_id) != step {
            // Asked for an earlier step, or already settled.
            return vec![];
        }
        let id = *command_id;
        match status {
            Ok(StepStatus::Done { result }) => {
                *unsettled = false;
                self.reply(id, result, None)
            }
            Ok(StepStatus::Failed { message }) => {
                *unsettled = false;
                self.reply(id, schemas::robot::RESULT_ERROR.into(), Some(message))
            }
            Ok(StepStatus::Unknown) if *index == 0 => self.fail(
                Reason::NotBegun,
                format!("the connection broke before the controller began step {step}, the job's first: nothing of it ran"),
            ),
            Ok(StepStatus::Unknown) => self.fail(
                Reason::ControllerDisconnected,
                format!("the connection broke before the controller began step {step}"),
            ),
            // The client asks again while it runs.
            Ok(StepStatus::Running) => vec![],
            Err(FenceError::NotConnected | FenceError::Gone) => vec![],
            Err(FenceError::Timeout(_)) if self.controller.is_ready() => {
                vec![ExecutionAction::AskStepStatus]
            }
            Err(FenceError::Timeout(_)) => vec![],
            Err(e) => self.fail(
                Reason::ControllerDisconnected,
                format!("the connection broke during step {step}, and the controller cannot tell its outcome: {e}"),
            ),
        }
    }
}

pub mod lanes;
#[cfg(test)]
mod tests;

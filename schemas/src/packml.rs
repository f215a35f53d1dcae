//! PackML (ISA-TR88.00.02): the states, commands and unit modes every resource holon
//! follows, numbered as ISA-TR88.00.02-2022, OPC 30050, Beckhoff and Siemens' lpmlv2022
//! number them (not as the ROS-Industrial package does), and the command table that
//! says which command each state accepts.
//!
//! | command | accepted in | goes to (acting state) | then, when its work is done |
//! |---|---|---|---|
//! | Reset (1) | Stopped, Complete | Resetting | Idle |
//! | Start (2) | Idle | Starting | Execute |
//! | Stop (3) | every state but Stopping, Stopped, Clearing, Aborting, Aborted | Stopping | Stopped |
//! | Hold (4) | Execute, Suspended | Holding | Held |
//! | Unhold (5) | Held | Unholding | Execute |
//! | Suspend (6) | Execute | Suspending | Suspended |
//! | Unsuspend (7) | Suspended | Unsuspending | Execute |
//! | Abort (8) | every state but Aborting, Aborted | Aborting | Aborted |
//! | Clear (9) | Aborted | Clearing | Stopped |
//! | Complete (10) | nowhere: a resource never completes its production | | |
//!
//! A command another state does not accept is refused with that state named
//! ([`Refusal::NotInState`]) and changes nothing. The unit mode changes only in
//! Stopped, Idle or Aborted ([`PackmlState::allows_mode_change`]).
//!
//! What a state means for a resource holon (its bookings, its running step) is the
//! holon's ([`docs/packml.md`]); this module only numbers and checks.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// A PackML state; `number()` is its `StateCurrent`.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum PackmlState {
    Undefined,
    Clearing,
    Stopped,
    Starting,
    Idle,
    Suspended,
    Execute,
    Stopping,
    Aborting,
    Aborted,
    Holding,
    Held,
    Unholding,
    Suspending,
    Unsuspending,
    Resetting,
    Completing,
    Complete,
}

impl PackmlState {
    /// Every state, in the order of their numbers (0 to 17).
    pub const ALL: [PackmlState; 18] = [
        PackmlState::Undefined,
        PackmlState::Clearing,
        PackmlState::Stopped,
        PackmlState::Starting,
        PackmlState::Idle,
        PackmlState::Suspended,
        PackmlState::Execute,
        PackmlState::Stopping,
        PackmlState::Aborting,
        PackmlState::Aborted,
        PackmlState::Holding,
        PackmlState::Held,
        PackmlState::Unholding,
        PackmlState::Suspending,
        PackmlState::Unsuspending,
        PackmlState::Resetting,
        PackmlState::Completing,
        PackmlState::Complete,
    ];

    /// Its `StateCurrent` number (ISA-TR88.00.02-2022, OPC 30050).
    pub fn number(self) -> i32 {
        PackmlState::ALL
            .iter()
            .position(|s| *s == self)
            .expect("every state is in ALL") as i32
    }

    /// The state numbered `number`, if there is one.
    pub fn from_number(number: i32) -> Option<PackmlState> {
        usize::try_from(number)
            .ok()
            .and_then(|i| PackmlState::ALL.get(i).copied())
    }

    /// Its name as PackML writes it: `Execute`, `Held`.
    pub fn name(self) -> &'static str {
        match self {
            PackmlState::Undefined => "Undefined",
            PackmlState::Clearing => "Clearing",
            PackmlState::Stopped => "Stopped",
            PackmlState::Starting => "Starting",
            PackmlState::Idle => "Idle",
            PackmlState::Suspended => "Suspended",
            PackmlState::Execute => "Execute",
            PackmlState::Stopping => "Stopping",
            PackmlState::Aborting => "Aborting",
            PackmlState::Aborted => "Aborted",
            PackmlState::Holding => "Holding",
            PackmlState::Held => "Held",
            PackmlState::Unholding => "Unholding",
            PackmlState::Suspending => "Suspending",
            PackmlState::Unsuspending => "Unsuspending",
            PackmlState::Resetting => "Resetting",
            PackmlState::Completing => "Completing",
            PackmlState::Complete => "Complete",
        }
    }

    /// An acting state: the unit is doing the work that leads to the next wait state
    /// ([`PackmlState::completes_to`]).
    pub fn is_acting(self) -> bool {
        self.completes_to().is_some()
    }

    /// The wait state an acting state leads to once its work is done ("state
    /// complete"); `None` for a wait state (and Execute, which runs until commanded).
    pub fn completes_to(self) -> Option<PackmlState> {
        match self {
            PackmlState::Clearing => Some(PackmlState::Stopped),
            PackmlState::Starting => Some(PackmlState::Execute),
            PackmlState::Stopping => Some(PackmlState::Stopped),
            PackmlState::Aborting => Some(PackmlState::Aborted),
            PackmlState::Holding => Some(PackmlState::Held),
            PackmlState::Unholding => Some(PackmlState::Execute),
            PackmlState::Suspending => Some(PackmlState::Suspended),
            PackmlState::Unsuspending => Some(PackmlState::Execute),
            PackmlState::Resetting => Some(PackmlState::Idle),
            PackmlState::Completing => Some(PackmlState::Complete),
            _ => None,
        }
    }

    /// The state a command leads to from this one (its acting state), or why not.
    pub fn accepts(self, command: PackmlCommand) -> Result<PackmlState, Refusal> {
        use PackmlState as S;
        let target = match command {
            PackmlCommand::Reset => {
                matches!(self, S::Stopped | S::Complete).then_some(S::Resetting)
            }
            PackmlCommand::Start => (self == S::Idle).then_some(S::Starting),
            PackmlCommand::Stop => (!matches!(
                self,
                S::Stopping | S::Stopped | S::Clearing | S::Aborting | S::Aborted
            ))
            .then_some(S::Stopping),
            PackmlCommand::Hold => matches!(self, S::Execute | S::Suspended).then_some(S::Holding),
            PackmlCommand::Unhold => (self == S::Held).then_some(S::Unholding),
            PackmlCommand::Suspend => (self == S::Execute).then_some(S::Suspending),
            PackmlCommand::Unsuspend => (self == S::Suspended).then_some(S::Unsuspending),
            PackmlCommand::Abort => {
                (!matches!(self, S::Aborting | S::Aborted)).then_some(S::Aborting)
            }
            PackmlCommand::Clear => (self == S::Aborted).then_some(S::Clearing),
            PackmlCommand::Complete => return Err(Refusal::NotSupported { command }),
        };
        target.ok_or(Refusal::NotInState {
            command,
            state: self,
        })
    }

    /// The commands this state accepts (what an operator's screen offers).
    pub fn commands(self) -> Vec<PackmlCommand> {
        PackmlCommand::ALL
            .into_iter()
            .filter(|c| self.accepts(*c).is_ok())
            .collect()
    }

    /// Whether the unit mode may change in this state (Stopped, Idle, Aborted).
    pub fn allows_mode_change(self) -> bool {
        matches!(
            self,
            PackmlState::Stopped | PackmlState::Idle | PackmlState::Aborted
        )
    }
}

impl std::fmt::Display for PackmlState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A PackML command (`CntrlCmd`); `number()` is its value.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PackmlCommand {
    Reset,
    Start,
    Stop,
    Hold,
    Unhold,
    Suspend,
    Unsuspend,
    Abort,
    Clear,
    Complete,
}

impl PackmlCommand {
    /// Every command, in the order of their numbers (1 to 10).
    pub const ALL: [PackmlCommand; 10] = [
        PackmlCommand::Reset,
        PackmlCommand::Start,
        PackmlCommand::Stop,
        PackmlCommand::Hold,
        PackmlCommand::Unhold,
        PackmlCommand::Suspend,
        PackmlCommand::Unsuspend,
        PackmlCommand::Abort,
        PackmlCommand::Clear,
        PackmlCommand::Complete,
    ];

    /// Its `CntrlCmd` number.
    pub fn number(self) -> i32 {
        PackmlCommand::ALL
            .iter()
            .position(|c| *c == self)
            .expect("every command is in ALL") as i32
            + 1
    }

    /// Its name as PackML writes it: `Hold`.
    pub fn name(self) -> &'static str {
        match self {
            PackmlCommand::Reset => "Reset",
            PackmlCommand::Start => "Start",
            PackmlCommand::Stop => "Stop",
            PackmlCommand::Hold => "Hold",
            PackmlCommand::Unhold => "Unhold",
            PackmlCommand::Suspend => "Suspend",
            PackmlCommand::Unsuspend => "Unsuspend",
            PackmlCommand::Abort => "Abort",
            PackmlCommand::Clear => "Clear",
            PackmlCommand::Complete => "Complete",
        }
    }
}

impl std::fmt::Display for PackmlCommand {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A command's name or number, as people and tools write it: `hold`, `Hold`, `4`.
impl std::str::FromStr for PackmlCommand {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if let Ok(number) = text.parse::<i32>() {
            return PackmlCommand::ALL
                .into_iter()
                .find(|c| c.number() == number)
                .ok_or_else(|| format!("no PackML command is numbered {number} (1 to 10)"));
        }
        PackmlCommand::ALL
            .into_iter()
            .find(|c| c.name().eq_ignore_ascii_case(text))
            .ok_or_else(|| {
                format!(
                    "unknown PackML command {text:?}: one of {}",
                    PackmlCommand::ALL.map(|c| c.name()).join(", ")
                )
            })
    }
}

/// A PackML unit mode (`UnitModeCurrent`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum UnitMode {
    /// Offers and takes orders' work.
    Production,
    /// Not offered to orders; an operator may run single jobs on it.
    Maintenance,
    /// Driven by hand at the controller: the holon takes no work at all.
    Manual,
}

impl UnitMode {
    /// Every mode, in the order of their numbers (1 to 3).
    pub const ALL: [UnitMode; 3] = [
        UnitMode::Production,
        UnitMode::Maintenance,
        UnitMode::Manual,
    ];

    /// Its `UnitModeCurrent` number.
    pub fn number(self) -> i32 {
        match self {
            UnitMode::Production => 1,
            UnitMode::Maintenance => 2,
            UnitMode::Manual => 3,
        }
    }

    /// The mode numbered `number`, if there is one.
    pub fn from_number(number: i32) -> Option<UnitMode> {
        UnitMode::ALL.into_iter().find(|m| m.number() == number)
    }

    pub fn name(self) -> &'static str {
        match self {
            UnitMode::Production => "Production",
            UnitMode::Maintenance => "Maintenance",
            UnitMode::Manual => "Manual",
        }
    }
}

impl std::fmt::Display for UnitMode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A mode's name or number: `maintenance`, `2`.
impl std::str::FromStr for UnitMode {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        if let Ok(number) = text.parse::<i32>() {
            return UnitMode::from_number(number)
                .ok_or_else(|| format!("no unit mode is numbered {number} (1 to 3)"));
        }
        UnitMode::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(text))
            .ok_or_else(|| {
                format!("unknown unit mode {text:?}: one of Production, Maintenance, Manual")
            })
    }
}

/// Why a command or a mode change was refused; nothing changed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema, thiserror::Error)]
#[serde(tag = "refusal", rename_all = "snake_case")]
pub enum Refusal {
    /// The current state does not accept the command.
    #[error("{command} is not allowed in {state}")]
    NotInState {
        command: PackmlCommand,
        state: PackmlState,
    },
    /// The unit mode changes only in Stopped, Idle or Aborted.
    #[error("the unit mode cannot change in {state} (only in Stopped, Idle or Aborted)")]
    ModeNotInState { state: PackmlState },
    /// A resource holon does not use this command.
    #[error("{command} is not used by a resource holon")]
    NotSupported { command: PackmlCommand },
    /// An operator's single job runs only in Maintenance mode, in Execute, on a free
    /// resource whose controller is ready.
    #[error("an operator's job runs only in Maintenance mode, in Execute, with nothing running and the controller ready (the resource is {state} in {mode} mode{why})")]
    JobNotAllowed {
        state: PackmlState,
        mode: UnitMode,
        /// What else stands in the way, e.g. `, a job runs`.
        why: String,
    },
    /// The job's service type or info does not fit the resource's steps.
    #[error("the job does not fit this resource: {detail}")]
    InvalidJob { detail: String },
}

/// The first-out stop reason (PackML `Admin.StopReason`): the first event that took
/// the unit out of Execute (a hold, a stop, an abort, a controller fault), kept until
/// it is back in Execute.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct StopReason {
    /// 1..=10: the command's number; 100: controller fault; 101: controller e-stop;
    /// 102: controller away (suspended).
    pub id: i32,
    /// For people: who or what, and why.
    pub message: String,
    /// When, in Unix milliseconds.
    pub at: u64,
}

/// [`StopReason::id`] of a controller fault.
pub const STOP_CONTROLLER_FAULT: i32 = 100;
/// [`StopReason::id`] of a controller emergency stop.
pub const STOP_CONTROLLER_ESTOP: i32 = 101;
/// [`StopReason::id`] of a controller that is not ready (disconnected).
pub const STOP_CONTROLLER_AWAY: i32 = 102;

/// A single job an operator runs on a resource in Maintenance mode (`cell packml NAME
/// --job ...`), and how it ended.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct OperatorJob {
    /// `maintenance/<n>`.
    pub conversation_id: String,
    pub service_type: String,
    /// Who asked.
    pub by: String,
    /// When it began (Unix ms).
    pub at: u64,
    /// How it ended (`done pick=picking_done ...`, `failed controller_error: ...`);
    /// none while it runs.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outcome: Option<String>,
    /// Whether it ended done.
    #[serde(default)]
    pub done: bool,
}

/// A resource's PackML figures, in its state snapshot (PackTags after ISA-TR88.00.02).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct PackmlStatus {
    /// `StateCurrent`.
    pub state: PackmlState,
    /// Its number (`StateCurrent` as an integer), for tools that trend it.
    pub state_number: i32,
    /// The wait state an acting state is heading for (`StateRequested`); the current
    /// state when none is under way.
    pub state_requested: PackmlState,
    /// `UnitModeCurrent`.
    pub mode: UnitMode,
    /// `ProdProcessedCount`: steps (jobs) done.
    pub processed: u64,
    /// `ProdDefectiveCount`: steps (jobs) that ended failed.
    pub defective: u64,
    /// `StopReason`, first-out.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_reason: Option<StopReason>,
    /// When the current state was entered (Unix ms): `StateCurrentTime` is now minus this.
    pub since: u64,
    /// `StateCumulativeTime`: milliseconds spent in each state (by name) before the
    /// current stay, over the holon's journalled life.
    #[serde(default)]
    pub cumulative_ms: std::collections::BTreeMap<PackmlState, u64>,
    /// The commands the current state accepts.
    pub commands: Vec<PackmlCommand>,
    /// The last single job an operator ran in Maintenance mode, if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator_job: Option<OperatorJob>,
}

/// An operator's single job: a service the resource offers, with its info (poses,
/// program) as a booking's would carry.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct JobRequest {
    pub service_type: String,
    #[serde(default)]
    pub info: serde_json::Map<String, serde_json::Value>,
}

/// What a PackML command or mode change asks of a resource (the payload of a query on
/// `resource/<name>/packml`): exactly one of `command`, `mode` and `job`.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PackmlRequest {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub command: Option<PackmlCommand>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mode: Option<UnitMode>,
    /// A single job to run now (Maintenance mode only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job: Option<JobRequest>,
    /// Who asks, for the stop reason and the log (e.g. `cell@host1`, `opcua:alice`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub by: Option<String>,
}

impl PackmlRequest {
    /// A command.
    pub fn command(command: PackmlCommand, by: &str) -> PackmlRequest {
        PackmlRequest {
            command: Some(command),
            mode: None,
            job: None,
            by: Some(by.to_string()),
        }
    }

    /// A unit mode change.
    pub fn mode(mode: UnitMode, by: &str) -> PackmlRequest {
        PackmlRequest {
            command: None,
            mode: Some(mode),
            job: None,
            by: Some(by.to_string()),
        }
    }

    /// A single job (Maintenance mode).
    pub fn job(job: JobRequest, by: &str) -> PackmlRequest {
        PackmlRequest {
            command: None,
            mode: None,
            job: Some(job),
            by: Some(by.to_string()),
        }
    }

    /// Reads a request and checks that it asks exactly one thing.
    pub fn from_json(payload: &[u8]) -> Result<PackmlRequest, crate::SchemaError> {
        let request: PackmlRequest =
            serde_json::from_slice(payload).map_err(|e| crate::SchemaError::Json(e.to_string()))?;
        let asked = [
            request.command.is_some(),
            request.mode.is_some(),
            request.job.is_some(),
        ];
        if asked.iter().filter(|a| **a).count() != 1 {
            return Err(crate::SchemaError::InvalidField {
                field: "packml request",
                why: "give exactly one of command, mode and job".into(),
            });
        }
        if request.by.as_ref().is_some_and(|by| by.len() > 128) {
            return Err(crate::SchemaError::InvalidField {
                field: "by",
                why: "at most 128 bytes".into(),
            });
        }
        Ok(request)
    }
}

/// The answer: the state (and mode) after the command, or the refusal.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct PackmlReply {
    /// An operator's job that began: its conversation (`maintenance/<n>`); its end is
    /// in the resource's state (`packml.operator_job`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job: Option<String>,
    /// The resource's state after the request (unchanged when refused).
    pub state: PackmlState,
    pub state_number: i32,
    pub mode: UnitMode,
    /// Why it was refused; none when it was accepted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub refused: Option<Refusal>,
    /// The refusal for people.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
}

#[cfg(test)]
mod tests;

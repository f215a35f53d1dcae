//! How a simulator behaves ([`SimConfig`]), and what of it is refused before it serves
//! ([`SimConfigError`]).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use schemas::ControllerState;

use super::physics;
#[cfg(doc)]
use super::{SimStats, Simulator};
use crate::dialect::{Correlation, Dialect, Sending};

/// How the simulator behaves.
#[derive(Debug, Clone)]
pub struct SimConfig {
    /// How long each action takes, unless `action_delays` names it.
    pub delay: Duration,
    /// How long particular actions take (`pick` -> 300 ms): a robot that is fast at
    /// some work and slow at other.
    pub action_delays: BTreeMap<String, Duration>,
    /// What a change of program costs: added to the first command whose `PROGRAM`
    /// differs from the last program run (a command without one changes nothing).
    pub changeover: Duration,
    pub error_every: Option<u64>,
    pub close_after: Option<u64>,
    pub hang_after: Option<u64>,
    pub garbage_after: Option<u64>,
    /// Every Nth `inspect` is answered `inspect_fail`.
    pub inspect_fail_every: Option<u64>,
    /// When the (N+1)th command of the process arrives, report `fault_state` instead of
    /// answering it (it is not executed), then `ready` again after `fault_for`.
    pub fault_after: Option<u64>,
    /// Every Nth command of the process faults the controller as `fault_after` does (a
    /// rehearsal that goes on: fault, ready, fault...).
    pub fault_every: Option<u64>,
    pub fault_state: Option<ControllerState>,
    pub fault_for: Duration,
    /// Every Nth command of the process takes the controller, for `fault_for`, into a
    /// state the dialect does not describe (its `ready` status said with `HOMING` for
    /// the state's word, [`Dialect::undescribed_status`]): as `fault_every` otherwise.
    pub unknown_state_every: Option<u64>,
    /// Rewritten (atomically) with [`SimStats`] as JSON after every command, once its
    /// reply is sent.
    pub count_file: Option<PathBuf>,
    /// The protocol spoken (None: holarchy-xml).
    pub dialect: Option<Arc<Dialect>>,
    /// Begin the (N+1)th command, then reset the connection halfway through it.
    pub reset_after: Option<u64>,
    /// Answer the (N+1)th command with a message over the dialect's size limit.
    pub oversize_after: Option<u64>,
    /// The (N+1)th command's answers echo another id than the command's (its id with a
    /// `9` after it: `ACK 239` for `JOB 23`); the command is executed.
    pub wrong_id_after: Option<u64>,
    /// Write every message in pieces of 1 to 3 bytes.
    pub fragment: bool,
    /// Write messages together (see the module docs).
    pub merge: bool,
    /// An abort that comes while an action runs finds it just ended: its `done` reply
    /// goes first (crossing the abort on the wire) and the abort has nothing to stop.
    pub abort_too_late: bool,
    /// Fenced mode (`--fenced`) with this session lease: one live session holds the
    /// claim, commands carry its epoch and step ids run at most once. None: unfenced,
    /// as without the fence (fence messages are refused `not_fenced`).
    pub fence_lease: Option<Duration>,
    /// The plant the controller acts in (`plant-sim`): what its actions can do,
    /// physically, and how long a move takes. None: any action runs.
    pub physics: Option<physics::PhysicsHook>,
    /// How many actions one connection has under way at once (default 1, at least 1):
    /// each ends at its own time and is answered with its own `done` (or `failed`)
    /// reply, matched to its command by id, so more than 1 needs a dialect whose replies
    /// carry the command's id (`correlation = "id"`) and whose actions end by a reply,
    /// not a poll. A command that comes while this many are under way waits until one
    /// ends (see the session's table).
    pub actions_at_once: usize,
}

impl Default for SimConfig {
    fn default() -> SimConfig {
        SimConfig {
            delay: Duration::ZERO,
            action_delays: BTreeMap::new(),
            changeover: Duration::ZERO,
            error_every: None,
            close_after: None,
            hang_after: None,
            garbage_after: None,
            inspect_fail_every: None,
            fault_after: None,
            fault_every: None,
            fault_state: None,
            fault_for: Duration::ZERO,
            unknown_state_every: None,
            count_file: None,
            dialect: None,
            reset_after: None,
            oversize_after: None,
            wrong_id_after: None,
            fragment: false,
            merge: false,
            abort_too_late: false,
            fence_lease: None,
            physics: None,
            actions_at_once: 1,
        }
    }
}

impl SimConfig {
    /// The dialect spoken.
    pub fn dialect(&self) -> Arc<Dialect> {
        self.dialect.clone().unwrap_or_else(Dialect::holarchy_xml)
    }

    /// Whether the simulator can serve as configured: [`Simulator::bind`] and
    /// [`Simulator::run`] refuse what this refuses.
    pub fn check(&self) -> Result<(), SimConfigError> {
        SimConfig::check_actions_at_once(self.actions_at_once, &self.dialect())
    }

    /// Whether `actions_at_once` = `n` can be served in `dialect`: at least 1, and more
    /// than 1 only where each reply names its command (`correlation = "id"`) and an
    /// action's end is a reply of its own (no poll, which names no action).
    pub fn check_actions_at_once(n: usize, dialect: &Dialect) -> Result<(), SimConfigError> {
        if n == 0 {
            return Err(SimConfigError::NoActionAtOnce);
        }
        if n == 1 {
            return Ok(());
        }
        if dialect.correlation == Correlation::OneInFlight {
            return Err(SimConfigError::OneInFlight {
                n,
                dialect: dialect.name.clone(),
            });
        }
        let polled = dialect
            .sequence
            .iter()
            .any(|e| matches!(e.sending, Sending::Poll(_)));
        if polled {
            return Err(SimConfigError::PolledEnd {
                n,
                dialect: dialect.name.clone(),
            });
        }
        Ok(())
    }
}

/// Why a simulator's settings are refused before it serves.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SimConfigError {
    /// `actions_at_once` is 0.
    #[error("actions_at_once must be at least 1 (it is 0)")]
    NoActionAtOnce,
    /// `actions_at_once` is more than 1 in a dialect with one request on the wire.
    #[error(
        "actions_at_once = {n}: several actions at once need a dialect whose replies carry the command's id (correlation = \"id\"); {dialect} has correlation = \"one_in_flight\""
    )]
    OneInFlight {
        /// The setting.
        n: usize,
        /// The dialect's name.
        dialect: String,
    },
    /// `actions_at_once` is more than 1 in a dialect that polls for an action's end.
    #[error(
        "actions_at_once = {n}: {dialect} polls for an action's end, and a poll names no action: one action at a time"
    )]
    PolledEnd {
        /// The setting.
        n: usize,
        /// The dialect's name.
        dialect: String,
    },
}

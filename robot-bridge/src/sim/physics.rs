//! The physical world a simulated controller acts in: asked before an action runs, told
//! when it ends. Without it (plain `robot-sim`) every action the dialect describes can
//! run; with it (`plant-sim`, [`crate::plant`]) an action can fail for a physical reason
//! (nothing at the port to pick, a full destination) and a move takes its travel time.

use std::fmt;
use std::sync::Arc;
use std::time::Duration;

use crate::dialect::Values;

/// What a controller's actions do to the plant around it.
///
/// An action is known by the values of the command that began it (`values`; in the
/// plant, a move by the part it moves, `info.part`: a part is moved by one move at a
/// time, the plant refuses a second while the first is under way). Several actions may
/// be under way at once on one controller (`SimConfig::actions_at_once`), each asked
/// and told with its own values:
///
/// | call | when | says |
/// |---|---|---|
/// | `begin(action, values)` | the command arrives | whether it can run, and how long it takes |
/// | `held(values)` | its time is up, and again every 50 ms while held | whether it is held up |
/// | `departed(values)` | every 50 ms while under way, until it says yes (only where the dialect has a `departed` reply for it) | whether its move has left its origin |
/// | `end(values, done)` | it ends (`true`) or is aborted (`false`) | whether its end is told |
/// | `epoch_granted()` | the fence grants a claim, before the grant is sent | |
pub trait Physics: Send + Sync {
    /// Whether the action the command `values` begins can run, physically, and how long
    /// it takes (None: as the simulator's own settings say). Err: the physical reason it
    /// cannot; the command is answered with its failed reply and not executed.
    fn begin(&self, action: &str, values: &Values) -> Result<Option<Duration>, String>;

    /// Whether the action the command `values` began is held up (a jammed track under a
    /// move): it does not end while it is; asked again shortly.
    fn held(&self, _values: &Values) -> bool {
        false
    }

    /// Whether the move the command `values` began has left its origin (the pallet is
    /// off the origin's port, on the track): the controller says so once, with the
    /// dialect's `departed` reply, and the move goes on to its end.
    fn departed(&self, _values: &Values) -> bool {
        false
    }

    /// The action the command `values` began ended: done (`true`), or stopped before its
    /// end (`false`: aborted). Returns whether the controller says so
    /// ([`Report::Unsaid`]: a pallet that stopped reporting arrives without a word).
    fn end(&self, values: &Values, done: bool) -> Report;

    /// The controller's fence granted an epoch: a physics that keeps the fence in its
    /// memory (the plant's) writes it now, before the grant is sent, so that a
    /// controller started again never grants that epoch twice.
    fn epoch_granted(&self) {}
}

/// Whether the controller tells of an action's end.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Report {
    Said,
    Unsaid,
}

/// A [`Physics`] as a simulator's setting.
#[derive(Clone)]
pub struct PhysicsHook(pub Arc<dyn Physics>);

impl fmt::Debug for PhysicsHook {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("PhysicsHook")
    }
}

//! The physical world a simulated controller acts in: asked before an action runs, told
//! when it ends. Without it (plain `robot-sim`) every action the dialect describes can
//! run; with it (`plant-sim`, [`crate::plant`]) an action can fail for a physical reason
//! (nothing at the port to pick, a full destination) and a move takes its travel time.

use std::fmt;
use std::sync::Arc;
use std::time::Duration;

use crate::dialect::Values;

/// What a controller's actions do to the plant around it.
pub trait Physics: Send + Sync {
    /// Whether the action the command `values` begins can run, physically, and how long
    /// it takes (None: as the simulator's own settings say). Err: the physical reason it
    /// cannot; the command is answered with its failed reply and not executed.
    fn begin(&self, action: &str, values: &Values) -> Result<Option<Duration>, String>;

    /// The action begun last ended: done (`true`), or stopped before its end (`false`:
    /// aborted).
    fn end(&self, done: bool);
}

/// A [`Physics`] as a simulator's setting.
#[derive(Clone)]
pub struct PhysicsHook(pub Arc<dyn Physics>);

impl fmt::Debug for PhysicsHook {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("PhysicsHook")
    }
}

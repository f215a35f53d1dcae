//! Fault injection: makes a component panic, as `exit(Pid, kill)` would in Erlang.
//! Reachable only through `resource/<name>/debug/crash`, declared with
//! `--allow-fault-injection`.

use tokio::sync::Notify;

/// One trigger per component; the component panics when its trigger is notified.
#[derive(Default)]
pub struct Faults {
    pub interfacing: Notify,
    pub execution: Notify,
    pub agenda: Notify,
    pub communication: Notify,
}

impl Faults {
    /// The trigger of the component called `component`.
    pub fn get(&self, component: &str) -> Option<&Notify> {
        match component {
            "interfacing" => Some(&self.interfacing),
            "execution" => Some(&self.execution),
            "agenda" => Some(&self.agenda),
            "communication" => Some(&self.communication),
            _ => None,
        }
    }
}

//! A transporter's moves as the agenda sees them (docs/material-flow.md, "Transporters"):
//! a booking whose info names where the part is and where it goes (`from`, `to`) takes
//! the layout's travel time for this transporter, not its service's nominal duration;
//! a move this transporter cannot make is refused. The layout comes in as an event
//! ([`super::AgendaEvent::Layout`]), so the machine stays pure.

use schemas::layout::LocationId;
use serde_json::{Map, Value};

use super::AgendaMachine;

/// A move a booking's info asks for: where the part is and where it goes.
fn move_of(info: &Map<String, Value>) -> Option<(LocationId, LocationId)> {
    let location = |key: &str| {
        let id = info.get(key)?.as_str()?;
        LocationId::try_from(id.to_string()).ok()
    };
    Some((location("from")?, location("to")?))
}

impl AgendaMachine {
    /// How long a job of `service_type` with `info` takes, as far as the agenda can
    /// tell: a move's travel time from the layout, else the service's nominal duration.
    pub(super) fn duration_ms(&self, service_type: &str, info: &Map<String, Value>) -> u64 {
        let nominal = self
            .catalog
            .get(service_type)
            .map(|d| d.nominal_duration.as_millis() as u64)
            .unwrap_or(0);
        let (Some(layout), Some((from, to))) = (&self.layout, move_of(info)) else {
            return nominal;
        };
        layout
            .routes(&from, &to)
            .into_iter()
            .find(|r| r.transporter == self.holon.name())
            .map_or(nominal, |r| r.travel_ms)
    }

    /// Why this transporter cannot make the move `info` asks for, if it is a move, the
    /// layout is known and this transporter has no way from one place to the other.
    pub(super) fn unreachable(&self, info: &Map<String, Value>) -> Option<String> {
        let layout = self.layout.as_ref()?;
        let part = layout.parts.get(self.holon.name())?;
        part.transporter.as_ref()?;
        let (from, to) = move_of(info)?;
        if let Some(unknown) = [&from, &to]
            .into_iter()
            .find(|l| layout.location(l).is_none())
        {
            return Some(format!(
                "{unknown} is not in the cell's layout (no serving resource states it)"
            ));
        }
        let reached = layout
            .routes(&from, &to)
            .iter()
            .any(|r| r.transporter == self.holon.name());
        (!reached).then(|| {
            format!(
                "{} does not move parts from {from} to {to} (as the cell's layout stands)",
                self.holon.name()
            )
        })
    }
}

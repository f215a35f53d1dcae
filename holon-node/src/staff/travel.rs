//! How a part reaches a station, as the cell's layout times it (pure): the staff counts
//! the move before each step of a route it forecasts (docs/material-flow.md, section
//! 3: a transporter's travel between two locations).

use schemas::layout::{CellLayout, LocationId, LocationRole};

/// How a part at some location reaches a station.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Reach {
    /// Nothing to count: the part is at the station already, or the staff does not
    /// know where it is (no part, no layout yet, or a place the layout does not
    /// know), or the station states no ports.
    There,
    /// It moves to the station's port `to`, in `travel_ms` (the fastest route there).
    Move { to: LocationId, travel_ms: u64 },
    /// No transporter of the layout can take it there.
    Unreachable,
}

/// How a part at `at` reaches `station`.
pub fn reach(layout: Option<&CellLayout>, at: Option<&LocationId>, station: &str) -> Reach {
    let (Some(layout), Some(at)) = (layout, at) else {
        return Reach::There;
    };
    let Some(part) = layout.parts.get(station) else {
        return Reach::There;
    };
    let ports: Vec<&LocationId> = part
        .locations
        .iter()
        .filter(|l| matches!(l.role, LocationRole::Port | LocationRole::Input))
        .map(|l| &l.id)
        .collect();
    // A place the layout does not know (it lags a resource just started) tells nothing.
    if ports.is_empty() || at.holon() == station || layout.location(at).is_none() {
        return Reach::There;
    }
    ports
        .into_iter()
        .filter_map(|port| {
            let fastest = layout
                .routes(at, port)
                .into_iter()
                .map(|r| r.travel_ms)
                .min()?;
            Some((fastest, port))
        })
        .min()
        .map_or(Reach::Unreachable, |(travel_ms, to)| Reach::Move {
            to: to.clone(),
            travel_ms,
        })
}

/// Where a part worked at `station` (arrived at `arrived`) leaves from: the station's
/// output if it has one, else where it arrived.
pub fn departure(layout: Option<&CellLayout>, station: &str, arrived: LocationId) -> LocationId {
    layout
        .and_then(|l| l.parts.get(station))
        .and_then(|part| {
            part.locations
                .iter()
                .find(|l| l.role == LocationRole::Output)
        })
        .map_or(arrived, |output| output.id.clone())
}

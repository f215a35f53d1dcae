//! The cell's layout: where parts can be, and what moves them (docs/material-flow.md).
//!
//! Each resource holon states its own part of the layout in its config (`[layout]`,
//! [`LayoutSection`]) and answers it on `resource/<name>/layout` ([`LayoutPart`]) while
//! it serves; the cell's layout is the union of the parts of the holons that serve
//! ([`CellLayout::assemble`]). A station started later joins the layout by starting, one
//! stopped leaves it; nothing central is edited.
//!
//! - A **location** is a place that holds parts (each on its carrier, where there is
//!   one) up to a capacity: a station's port, where its services work on the part
//!   (`port`, or an `input` and an `output`), a `buffer`, or where parts enter and leave
//!   the cell (`entry`, `exit`, `entry_exit`). Its id is its holon's name, a dot and its
//!   own name: `robot1.port`.
//! - A **transporter** moves parts between locations. A palletised conveyor
//!   ([`ConveyorSpec`]) is a loop with stoppers; a location reached by the conveyor
//!   docks at one of its stoppers (`dock = "conveyor1.s2"`). A transfer robot
//!   ([`TransferSpec`]) moves parts between two locations it names.

mod cell;
mod section;

pub use cell::{CellLayout, Problem, Route};
pub use section::{
    from_resource_config, part_from_toml, ConveyorSection, LayoutSection, LocationSection,
    TransferSection,
};

use std::fmt;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::validate_name;

/// The version of [`LayoutPart`] this release writes.
pub const LAYOUT_VERSION: u32 = 1;

/// A location's id: its holon's name, a dot, its own name (`robot1.port`).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct LocationId(String);

impl LocationId {
    /// The location `name` of the holon `holon`.
    pub fn new(holon: &str, name: &str) -> Result<LocationId, String> {
        validate_name("holon name", holon).map_err(|e| e.to_string())?;
        validate_name("location name", name).map_err(|e| e.to_string())?;
        Ok(LocationId(format!("{holon}.{name}")))
    }

    /// The holon that declares it.
    pub fn holon(&self) -> &str {
        self.0.split_once('.').map_or("", |(holon, _)| holon)
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

impl TryFrom<String> for LocationId {
    type Error = String;

    fn try_from(id: String) -> Result<Self, Self::Error> {
        match id.split_once('.') {
            Some((holon, name)) => LocationId::new(holon, name),
            None => Err(format!(
                "location {id:?}: not HOLON.NAME (a holon's name, a dot, the location's name)"
            )),
        }
    }
}

impl From<LocationId> for String {
    fn from(id: LocationId) -> String {
        id.0
    }
}

impl fmt::Display for LocationId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.0)
    }
}

impl JsonSchema for LocationId {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "LocationId".into()
    }

    fn json_schema(generator: &mut schemars::SchemaGenerator) -> schemars::Schema {
        String::json_schema(generator)
    }
}

/// What a location is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum LocationRole {
    /// A station's one port: parts arrive, are worked on and leave here.
    Port,
    /// A station's input: parts arrive and are worked on here.
    Input,
    /// A station's output: parts wait here to leave once worked on.
    Output,
    /// Parts wait here between stations.
    Buffer,
    /// Parts enter the cell here (a loading point).
    Entry,
    /// Parts leave the cell here (an unloading point).
    Exit,
    /// Parts enter and leave the cell here.
    EntryExit,
}

impl LocationRole {
    /// Whether a part may be moved here.
    pub fn takes_parts(self) -> bool {
        !matches!(self, LocationRole::Output | LocationRole::Entry)
    }

    /// Whether a part may be moved away from here.
    pub fn gives_parts(self) -> bool {
        !matches!(self, LocationRole::Input | LocationRole::Exit)
    }

    /// Whether it is a station's port (where the station's services work).
    pub fn is_station_port(self) -> bool {
        matches!(
            self,
            LocationRole::Port | LocationRole::Input | LocationRole::Output
        )
    }

    pub fn as_str(self) -> &'static str {
        match self {
            LocationRole::Port => "port",
            LocationRole::Input => "input",
            LocationRole::Output => "output",
            LocationRole::Buffer => "buffer",
            LocationRole::Entry => "entry",
            LocationRole::Exit => "exit",
            LocationRole::EntryExit => "entry_exit",
        }
    }
}

/// Where a conveyor reaches a location: one of its stoppers (`conveyor1.s2`).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct Dock {
    /// The conveyor's holon name.
    pub conveyor: String,
    /// The stopper's name on it.
    pub stopper: String,
}

impl TryFrom<String> for Dock {
    type Error = String;

    fn try_from(dock: String) -> Result<Self, Self::Error> {
        let Some((conveyor, stopper)) = dock.split_once('.') else {
            return Err(format!(
                "{dock:?}: not CONVEYOR.STOPPER (a conveyor's name, a dot, one of its stoppers)"
            ));
        };
        validate_name("conveyor name", conveyor).map_err(|e| e.to_string())?;
        validate_name("stopper name", stopper).map_err(|e| e.to_string())?;
        Ok(Dock {
            conveyor: conveyor.into(),
            stopper: stopper.into(),
        })
    }
}

impl From<Dock> for String {
    fn from(dock: Dock) -> String {
        dock.to_string()
    }
}

impl fmt::Display for Dock {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}.{}", self.conveyor, self.stopper)
    }
}

impl JsonSchema for Dock {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Dock".into()
    }

    fn json_schema(generator: &mut schemars::SchemaGenerator) -> schemars::Schema {
        String::json_schema(generator)
    }
}

/// One location, as its holon declares it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LocationSpec {
    pub id: LocationId,
    pub role: LocationRole,
    /// How many parts (each on its carrier, where there is one) it holds at once; at
    /// least 1.
    pub capacity: u32,
    /// The conveyor stopper where it is reached, if a conveyor reaches it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dock: Option<Dock>,
}

/// A stopper on a conveyor's loop: where a pallet can be stopped, and a location
/// docked there reached.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Stopper {
    /// Its name (`s1`), unique on the conveyor.
    pub name: String,
    /// Its place along the loop, in mm from the loop's origin (less than its length).
    pub at_mm: u32,
    /// How many pallets fit on the track that ends at this stopper (the segment from the
    /// stopper before it), queueing; at least 1.
    #[serde(default = "default_queue")]
    pub queue: u32,
}

fn default_queue() -> u32 {
    2
}

/// A palletised conveyor: pallets ride one way round a loop, stopped at stoppers where
/// locations dock.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ConveyorSpec {
    /// The loop's length, in mm.
    pub length_mm: u32,
    /// The pallets' speed, in mm/s.
    pub speed_mm_s: u32,
    /// How many pallets ride the loop (the carriers of the parts it moves).
    pub pallets: u32,
    /// Its stoppers, in the order a pallet meets them.
    pub stoppers: Vec<Stopper>,
    /// How long a pallet takes to leave the loop into a docked location, or to come
    /// back onto it, in ms.
    #[serde(default)]
    pub dock_ms: u64,
}

impl ConveyorSpec {
    /// The time a pallet takes from stopper `from` to stopper `to`, one way round the
    /// loop (0 from a stopper to itself), or None if either is not a stopper of it.
    pub fn travel_ms(&self, from: &str, to: &str) -> Option<u64> {
        let at = |name: &str| {
            self.stoppers
                .iter()
                .find(|s| s.name == name)
                .map(|s| s.at_mm)
        };
        let (from, to) = (at(from)?, at(to)?);
        let length = u64::from(self.length_mm);
        let distance = (u64::from(to) + length - u64::from(from)) % length;
        Some(distance * 1000 / u64::from(self.speed_mm_s.max(1)))
    }

    /// How many pallets the loop's tracks hold in all.
    pub fn track_capacity(&self) -> u64 {
        self.stoppers.iter().map(|s| u64::from(s.queue)).sum()
    }
}

/// A robot (or any mechanism) that moves parts between two locations.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TransferSpec {
    /// The two locations it moves parts between, either way.
    pub between: [LocationId; 2],
    /// How long one move takes, in ms.
    pub move_ms: u64,
}

/// What a transporter is.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum TransporterSpec {
    Conveyor(ConveyorSpec),
    Transfer(TransferSpec),
}

/// One holon's part of the layout, as it answers it on `resource/<name>/layout`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LayoutPart {
    /// [`LAYOUT_VERSION`].
    pub v: u32,
    /// The resource's name.
    pub holon: String,
    /// The locations it declares.
    #[serde(default)]
    pub locations: Vec<LocationSpec>,
    /// What it moves, if it is a transporter.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub transporter: Option<TransporterSpec>,
}

impl LayoutPart {
    pub fn from_json(bytes: &[u8]) -> Result<LayoutPart, String> {
        let part: LayoutPart = serde_json::from_slice(bytes).map_err(|e| e.to_string())?;
        if part.v != LAYOUT_VERSION {
            return Err(format!(
                "layout version {} (this release reads {LAYOUT_VERSION})",
                part.v
            ));
        }
        Ok(part)
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("a layout part serializes")
    }

    /// The same part with its times in the wall time of a plant run at `scale`
    /// ([`crate::TimeScale`]): a conveyor `scale` times as fast with its docking in
    /// 1/`scale` of the time, a transfer's move in 1/`scale`. What a holon of a scaled
    /// cell answers, so that every holon's travel estimates are in one time.
    pub fn at_scale(mut self, scale: crate::TimeScale) -> LayoutPart {
        match &mut self.transporter {
            Some(TransporterSpec::Conveyor(c)) => {
                let faster = (f64::from(c.speed_mm_s) * scale.factor()).round();
                c.speed_mm_s = faster.min(f64::from(u32::MAX)) as u32;
                c.dock_ms = scale.wall_ms(c.dock_ms);
            }
            Some(TransporterSpec::Transfer(t)) => t.move_ms = scale.wall_ms(t.move_ms),
            None => {}
        }
        self
    }

    /// One line per location and one for the transporter, as `holon-node --check` and
    /// `cell layout` show them.
    pub fn describe(&self) -> Vec<String> {
        let mut lines: Vec<String> = self
            .locations
            .iter()
            .map(|l| {
                let dock = l
                    .dock
                    .as_ref()
                    .map(|d| format!(", at {d}"))
                    .unwrap_or_default();
                format!(
                    "{} ({}, capacity {}{dock})",
                    l.id,
                    l.role.as_str(),
                    l.capacity
                )
            })
            .collect();
        match &self.transporter {
            Some(TransporterSpec::Conveyor(c)) => {
                let stoppers: Vec<String> = c
                    .stoppers
                    .iter()
                    .map(|s| format!("{} at {} mm", s.name, s.at_mm))
                    .collect();
                lines.push(format!(
                    "conveyor: {} pallets on a {} mm loop at {} mm/s, stoppers {}",
                    c.pallets,
                    c.length_mm,
                    c.speed_mm_s,
                    stoppers.join(", ")
                ));
            }
            Some(TransporterSpec::Transfer(t)) => lines.push(format!(
                "transfer: between {} and {}, {} ms a move",
                t.between[0], t.between[1], t.move_ms
            )),
            None => {}
        }
        lines
    }
}

/// What is wrong with a layout: the field (as the config file names it) and why.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field}: {message}")]
pub struct LayoutError {
    /// The field, as the config file names it (`layout.locations[0].capacity`).
    pub field: String,
    pub message: String,
}

impl LayoutError {
    pub fn new(field: impl Into<String>, message: impl Into<String>) -> LayoutError {
        LayoutError {
            field: field.into(),
            message: message.into(),
        }
    }
}

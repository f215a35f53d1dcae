//! The robot controller protocol's messages (TCP/XML); the XML codec is in `robot-bridge`.

use std::fmt;
use std::str::FromStr;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::SchemaError;

/// A Cartesian pose: position in mm and orientation in degrees.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Pose {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    #[serde(default)]
    pub a: f64,
    #[serde(default)]
    pub b: f64,
    #[serde(default)]
    pub c: f64,
}

impl Pose {
    /// Every coordinate is a finite number (the controller cannot move to NaN).
    pub fn is_finite(&self) -> bool {
        [self.x, self.y, self.z, self.a, self.b, self.c]
            .iter()
            .all(|v| v.is_finite())
    }
}

/// Bridge to controller:
/// `<ROBOT_CMD><ID>..</ID><ACTION>..</ACTION><PROGRAM>..</PROGRAM><POS .../></ROBOT_CMD>`
/// (`PROGRAM` and `POS` optional).
#[derive(Debug, Clone, PartialEq)]
pub struct RobotCommand {
    pub id: u64,
    pub action: String,
    pub pos: Option<Pose>,
    /// The program (product variant) the command's job belongs to, from the job's
    /// `info.program`: a controller changes over (tooling, fixtures, program) when it
    /// differs from the last one it ran.
    pub program: Option<String>,
    /// The job's `info` fields, for a dialect's `{info.KEY}` placeholders (holarchy's own
    /// XML protocol does not send them).
    pub info: std::collections::BTreeMap<String, serde_json::Value>,
}

/// Controller to bridge: the result of one command.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RobotReply {
    pub id: u64,
    /// `picking_done`, `placing_done`, `inspect_pass`, `inspect_fail`, `arrived`, or `error`.
    pub result: String,
    /// Set with `error`: what went wrong.
    pub message: Option<String>,
}

/// The result a controller sends when a command failed.
pub const RESULT_ERROR: &str = "error";

/// The controller's state, sent on connect and on every change.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ControllerState {
    Ready,
    Fault,
    Estop,
}

impl ControllerState {
    pub fn as_str(self) -> &'static str {
        match self {
            ControllerState::Ready => "ready",
            ControllerState::Fault => "fault",
            ControllerState::Estop => "estop",
        }
    }
}

impl fmt::Display for ControllerState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for ControllerState {
    type Err = SchemaError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "ready" => Ok(ControllerState::Ready),
            "fault" => Ok(ControllerState::Fault),
            "estop" => Ok(ControllerState::Estop),
            other => Err(SchemaError::InvalidField {
                field: "STATE",
                why: format!("unknown controller state {other:?}"),
            }),
        }
    }
}

/// One document of the controller protocol, either direction.
#[derive(Debug, Clone, PartialEq)]
pub enum RobotMessage {
    Command(RobotCommand),
    Reply(RobotReply),
    Status(ControllerState),
}

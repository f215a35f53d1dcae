//! The dialect file as written (TOML), before it is checked and compiled. Every field is
//! documented in `docs/dialects.md`; unknown fields are errors.

use std::collections::BTreeMap;

use serde::Deserialize;

use super::binary::FieldSection;
use super::framing::ByteOrder;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DialectFile {
    /// The dialect's name, as `controller.dialect` names a shipped one.
    pub name: String,
    #[serde(default)]
    pub description: String,
    /// How a reply is tied to its command.
    pub correlation: Correlation,
    /// The messages each action's step sends, in order, and what answers each.
    pub sequence: Vec<ElementSection>,
    #[serde(default)]
    pub connection: ConnectionSection,
    pub framing: FramingSection,
    #[serde(default)]
    pub values: ValuesSection,
    pub status: StatusSection,
    /// Tables of wire forms: `[enums.NAME]`, `value = "wire"` or `value = ["wire", ...]`.
    #[serde(default)]
    pub enums: BTreeMap<String, BTreeMap<String, OneOrMany>>,
    /// Messages the holon sends.
    #[serde(default)]
    pub command: Vec<MessageSection>,
    /// Messages the controller sends.
    #[serde(default)]
    pub reply: Vec<ReplySection>,
    /// How the action under way is stopped (PackML Abort); none: it cannot be.
    pub abort: Option<AbortSection>,
    /// The fence for a standby holon (claim, heartbeat, epoch, step ids, step status);
    /// none: the controller cannot fence, and standby is refused.
    pub fence: Option<FenceSection>,
}

/// `[fence]`: the messages of the fence (`docs/controller-protocol.md`, "Fencing"). The
/// command template itself carries `{?epoch}` and `{?step}` sections.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FenceSection {
    /// The command that asks for the claim, with `{name}`.
    pub claim: String,
    /// The command that shows life while holding the claim, with `{epoch}`; not answered.
    pub heartbeat: String,
    /// The command that asks a step id's stored outcome, with `{step}`.
    pub step_status: String,
    /// The reply granting the claim (outcome `fence`), with `{epoch}` and `{lease_ms}`.
    pub granted: String,
    /// The reply refusing a claim or a heartbeat (outcome `fence`), with `{epoch}` (the
    /// holder's) and `{reason}` (`held`, `not_fenced`, `stale_epoch`, `invalid`).
    pub refused: String,
    /// The reply to `step_status` (outcome `fence`), with `{step}`, `{step_state}`
    /// (`done`, `failed`, `running`, `unknown`) and `{result}` / `{message}`.
    pub step_state: String,
    /// The reply refusing a command for a stale epoch (outcome `failed`), in the
    /// sequence's `expect`.
    pub stale: String,
}

/// `abort = { send = "...", expect = [...] }`: the message that stops the action under
/// way, and the replies that answer that message itself (none: the controller answers
/// only through the aborted command's own reply).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AbortSection {
    /// The command sent to stop; it may use the values of the command it aborts.
    pub send: String,
    /// The replies that answer the abort message itself: `accepted` (the controller
    /// stopped) or `rejected` (it had nothing to stop, or refused).
    #[serde(default)]
    pub expect: Vec<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Correlation {
    /// Each reply carries the command's `{id}`: several commands may be in flight.
    Id,
    /// Replies carry no id: one request is on the wire at a time, and the next waits.
    OneInFlight,
}

/// Who opens the TCP connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// The controller is the TCP server; the holon connects to `controller.address`.
    #[default]
    ControllerListens,
    /// The holon listens on `controller.address` and the controller connects to it.
    ControllerConnects,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConnectionSection {
    #[serde(default)]
    pub role: Role,
    /// A message the controller sends first on every connection, read and discarded.
    pub banner: Option<String>,
    pub keepalive: Option<KeepaliveSection>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct KeepaliveSection {
    /// The command sent when the link has been quiet for `every_ms`.
    pub send: String,
    pub every_ms: u64,
    /// The replies that answer it (none: it is not answered).
    #[serde(default)]
    pub expect: Vec<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FramingKind {
    Xml,
    Line,
    LengthPrefix,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FramingSection {
    pub kind: FramingKind,
    /// The most bytes one message may have (default 65536).
    pub max_message_bytes: Option<usize>,
    /// `line`: the bytes that end a line (default "\n").
    pub terminator: Option<String>,
    /// `length_prefix`: 2 or 4.
    pub prefix_bytes: Option<usize>,
    /// `length_prefix`: of the prefix and of binary fields (default "big").
    pub byte_order: Option<ByteOrder>,
    /// `length_prefix`: whether the length counts the prefix's own bytes (default false).
    pub prefix_counts_itself: Option<bool>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ValuesSection {
    /// Digits after the point for every number (default: the shortest exact form).
    pub decimals: Option<usize>,
    /// How a true job `info` value is written (default "true").
    #[serde(rename = "true")]
    pub true_text: Option<String>,
    #[serde(rename = "false")]
    pub false_text: Option<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StatusSource {
    /// The controller sends its state on connect and on every change.
    Pushed,
    /// The holon asks with the `poll` command every `every_ms`.
    Polled,
    /// The controller says nothing of its state: ready while connected.
    Connection,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StatusSection {
    pub source: StatusSource,
    pub poll: Option<String>,
    pub every_ms: Option<u64>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum OneOrMany {
    One(String),
    Many(Vec<String>),
}

impl OneOrMany {
    pub fn into_vec(self) -> Vec<String> {
        match self {
            OneOrMany::One(s) => vec![s],
            OneOrMany::Many(v) => v,
        }
    }
}

/// A message's body, one of three as the framing says.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MessageSection {
    pub name: String,
    /// `xml` framing: the document, with placeholders.
    pub xml: Option<String>,
    /// `line` framing: the line, with placeholders.
    pub text: Option<String>,
    /// `length_prefix` framing: the fields.
    pub fields: Option<Vec<FieldSection>>,
}

/// What a controller's message means.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The command was taken; the sequence goes on (or waits for more of this element).
    Accepted,
    /// (A poll's answer) the action still runs: poll again.
    Running,
    /// The step is done, with `result`.
    Done,
    /// A transporter's move has left its origin (the pallet is off the station's port,
    /// on the track): the command goes on, and still ends with a reply of its own. Said
    /// at most once per command, never alone in an element's `expect`.
    Departed,
    /// The action failed, with `message`.
    Failed,
    /// The controller refused the command (nothing was done), with `message`.
    Rejected,
    /// The controller's state (`state`), at any time.
    Status,
    /// Nothing to act on (a chatty controller's other messages), at any time.
    Ignore,
    /// A message of the fence (`[fence]`): a claim's answer or a step's stored state.
    Fence,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReplySection {
    pub name: String,
    pub outcome: Outcome,
    pub xml: Option<String>,
    pub text: Option<String>,
    /// `line` framing: a regular expression the holon matches instead of `text`; its named
    /// groups are values (`(?P<message>.*)`). robot-sim still writes `text`.
    pub regex: Option<String>,
    pub fields: Option<Vec<FieldSection>>,
    /// `done`: the step's result (default "{result}").
    pub result: Option<String>,
    /// `failed` / `rejected`: the reason told to the order (default "{message}" if the
    /// message has one, else the reply's name).
    pub message: Option<String>,
    /// `status`: ready, fault or estop (default "{state}").
    pub state: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ElementSection {
    /// Send this command once.
    pub send: Option<String>,
    /// Send this command every `every_ms` until a reply ends the step.
    pub poll: Option<String>,
    pub every_ms: Option<u64>,
    /// The replies that answer it.
    pub expect: Vec<String>,
    /// (robot-sim) the message that begins the action (default: the last `send`).
    #[serde(default)]
    pub starts: bool,
}

//! Controller dialects: a robot controller's protocol described in a TOML file, not in
//! code (`docs/dialects.md` is the guide, field by field).
//!
//! A [`Dialect`] says who opens the connection, how messages are framed ([`framing`]),
//! what each message the holon sends looks like and what each message the controller
//! sends means ([`Outcome`]), how replies are tied to commands, where the controller's
//! state comes from, and the sequence of messages one step takes. The same compiled
//! dialect drives both ends: the holon's controller client ([`crate::client`]) and
//! `robot-sim` ([`crate::sim`]).
//!
//! A dialect is checked whole when it is loaded: a bad template, an unknown placeholder,
//! a regular expression that does not compile, a sequence that can never end a step, are
//! errors that name the field, before the first job.

pub mod binary;
mod compile;
pub mod file;
pub mod framing;
mod messages;
mod playable;
pub mod template;
pub mod values;
pub mod xml;

use std::path::Path;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use bytes::Bytes;
use regex::Regex;
use schemas::ControllerState;

use crate::codec::{parse_tree, CodecError, Element as XmlElement};
use binary::BinaryTemplate;
use file::DialectFile;
pub use file::{Correlation, Outcome, Role, StatusSource};
use framing::{FrameCodec, Framing};
use template::{Escape, Template};
pub use values::{command_values, Enums, ValueFormat, Values};
use xml::XmlTemplate;

/// The dialects shipped in `deploy/dialects/`, by name.
pub const SHIPPED: &[(&str, &str)] = &[
    (
        "holarchy-xml",
        include_str!("../../../deploy/dialects/holarchy-xml.toml"),
    ),
    (
        "kuka-eki",
        include_str!("../../../deploy/dialects/kuka-eki.toml"),
    ),
    (
        "ur-dashboard",
        include_str!("../../../deploy/dialects/ur-dashboard.toml"),
    ),
    (
        "simple-message",
        include_str!("../../../deploy/dialects/simple-message.toml"),
    ),
];

/// The default dialect: holarchy's own TCP/XML protocol (`docs/controller-protocol.md`).
pub const DEFAULT: &str = "holarchy-xml";

/// Why a dialect cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DialectError {
    #[error("cannot read the dialect file {path}: {why}")]
    Read { path: String, why: String },
    #[error("{origin}: not a dialect file: {why}")]
    Syntax { origin: String, why: String },
    #[error("{origin}: {field}: {why}")]
    Invalid {
        origin: String,
        field: String,
        why: String,
    },
    #[error("no shipped dialect is called {0:?} (shipped: holarchy-xml, kuka-eki, ur-dashboard, simple-message; or give a path to a .toml file)")]
    Unknown(String),
}

/// A message's body as this dialect's framing writes and reads it.
#[derive(Debug, Clone)]
pub enum Body {
    Xml(XmlTemplate),
    Text(Template),
    Binary(BinaryTemplate),
}

/// A message the holon sends.
#[derive(Debug, Clone)]
pub struct Command {
    pub name: String,
    pub body: Body,
}

/// A message the controller sends, and what it means.
#[derive(Debug, Clone)]
pub struct Reply {
    pub name: String,
    pub outcome: Outcome,
    /// How robot-sim writes it (None: only a regex was given).
    pub body: Option<Body>,
    /// How the holon reads a text line, when a regex replaces the template.
    pub regex: Option<Regex>,
    pub result: Template,
    pub message: Template,
    pub state: Template,
}

/// How one element of the sequence is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sending {
    /// Once.
    Send,
    /// Again every interval while the answer is `running` (or `accepted`).
    Poll(Duration),
}

/// One element of a step's sequence.
#[derive(Debug, Clone)]
pub struct Element {
    pub sending: Sending,
    /// Index into [`Dialect::commands`].
    pub command: usize,
    /// Indices into [`Dialect::replies`].
    pub expect: Vec<usize>,
    /// (robot-sim) the message that begins the action.
    pub starts: bool,
}

/// Where the controller's state comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Status {
    Pushed,
    Polled { command: usize, every: Duration },
    Connection,
}

/// The keep-alive: `command` after `every` of quiet, answered by one of `expect`.
#[derive(Debug, Clone)]
pub struct Keepalive {
    pub command: usize,
    pub every: Duration,
    pub expect: Vec<usize>,
}

/// How the action under way is stopped (PackML Abort).
#[derive(Debug, Clone)]
pub struct Abort {
    /// The message that stops it: an index into [`Dialect::commands`]. Written with the
    /// values of the command it aborts (its `{id}`, where the dialect correlates by id).
    pub command: usize,
    /// The replies that answer the abort message itself, indices into
    /// [`Dialect::replies`]: `accepted` (the controller stopped) or `rejected` (it had
    /// nothing to stop). Empty: the controller answers only through the aborted
    /// command's own reply.
    pub expect: Vec<usize>,
}

/// The fence of a standby holon: indices of its messages ([`Dialect::commands`],
/// [`Dialect::replies`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fence {
    /// `{name}` asks for the claim.
    pub claim: usize,
    /// `{epoch}` shows life; not answered.
    pub heartbeat: usize,
    /// `{step}` asks a step's stored outcome.
    pub step_status: usize,
    /// The claim granted: `{epoch}`, `{lease_ms}`.
    pub granted: usize,
    /// A claim or heartbeat refused: `{epoch}` (the holder's), `{reason}`.
    pub refused: usize,
    /// A step's stored state: `{step}`, `{step_state}`, `{result}`, `{message}`.
    pub step_state: usize,
    /// A command refused for a stale epoch (in the sequence's `expect`).
    pub stale: usize,
}

/// A message as read off the wire, parsed once and matched against the rules.
#[derive(Debug)]
pub enum Parsed {
    Xml(XmlElement),
    Text(String),
    Binary(Bytes),
}

/// A compiled, checked dialect.
#[derive(Debug, Clone)]
pub struct Dialect {
    pub name: String,
    pub description: String,
    pub role: Role,
    pub framing: Framing,
    pub max_message_bytes: usize,
    pub format: ValueFormat,
    pub correlation: Correlation,
    pub status: Status,
    pub banner: Option<String>,
    pub keepalive: Option<Keepalive>,
    pub enums: Enums,
    pub commands: Vec<Command>,
    pub replies: Vec<Reply>,
    pub sequence: Vec<Element>,
    /// How the action under way is stopped; None: the dialect cannot abort.
    pub abort: Option<Abort>,
    /// The fence (claim, epochs, step ids); None: the controller cannot fence, so a
    /// standby holon is refused.
    pub fence: Option<Fence>,
}

impl Dialect {
    /// A shipped dialect by name, or a dialect file by path (anything with a `/` or
    /// ending in `.toml`; relative to `base` when given).
    pub fn load(spec: &str, base: Option<&Path>) -> Result<Arc<Dialect>, DialectError> {
        if !spec.contains('/') && !spec.ends_with(".toml") {
            return Self::shipped(spec);
        }
        let path = match base {
            Some(base) if Path::new(spec).is_relative() => base.join(spec),
            _ => Path::new(spec).to_path_buf(),
        };
        let text = std::fs::read_to_string(&path).map_err(|e| DialectError::Read {
            path: path.display().to_string(),
            why: e.to_string(),
        })?;
        Dialect::from_toml(&text, &path.display().to_string()).map(Arc::new)
    }

    /// A shipped dialect, compiled once per process, when first asked for: a holon on
    /// one dialect compiles that one only (compiling all four at a resource's start
    /// took about 12 ms and 2.7 MB of heap: docs/benchmarks.md, "The start path and
    /// footprint again").
    pub fn shipped(name: &str) -> Result<Arc<Dialect>, DialectError> {
        static COMPILED: [OnceLock<Arc<Dialect>>; SHIPPED.len()] =
            [const { OnceLock::new() }; SHIPPED.len()];
        let index = SHIPPED
            .iter()
            .position(|(n, _)| *n == name)
            .ok_or_else(|| DialectError::Unknown(name.to_string()))?;
        let (name, text) = SHIPPED[index];
        let dialect = COMPILED[index].get_or_init(|| {
            let dialect = Dialect::from_toml(text, &format!("deploy/dialects/{name}.toml"))
                .unwrap_or_else(|e| panic!("the shipped dialect {name} is invalid: {e}"));
            Arc::new(dialect)
        });
        Ok(dialect.clone())
    }

    /// holarchy's own protocol.
    pub fn holarchy_xml() -> Arc<Dialect> {
        Self::shipped(DEFAULT).expect("shipped")
    }

    /// Parses and checks a dialect file's text; `origin` names it in errors.
    pub fn from_toml(text: &str, origin: &str) -> Result<Dialect, DialectError> {
        let file: DialectFile = toml::from_str(text).map_err(|e| DialectError::Syntax {
            origin: origin.to_string(),
            why: e.to_string(),
        })?;
        compile::compile(file, origin)
    }

    pub fn frame_codec(&self) -> FrameCodec {
        FrameCodec {
            framing: self.framing.clone(),
            max: self.max_message_bytes,
        }
    }

    /// Whether the controller can fence a standby holon (claim, epochs, step ids).
    pub fn fencing_supported(&self) -> bool {
        self.fence.is_some()
    }

    /// Whether the controller can be told to stop the action under way.
    pub fn can_abort(&self) -> bool {
        self.abort.is_some()
    }

    pub fn command_index(&self, name: &str) -> Option<usize> {
        self.commands.iter().position(|c| c.name == name)
    }

    pub fn reply_index(&self, name: &str) -> Option<usize> {
        self.replies.iter().position(|r| r.name == name)
    }

    /// Writes a body (without framing).
    pub fn write(&self, body: &Body, values: &Values) -> Result<Vec<u8>, String> {
        match body {
            Body::Xml(t) => t.render(values, &self.enums).map(String::into_bytes),
            Body::Text(t) => t
                .render(values, &self.enums, Escape::Plain)
                .map(String::into_bytes)
                .map_err(|e| e.to_string()),
            Body::Binary(t) => t.render(values, &self.enums),
        }
    }

    /// Writes command `index` with `values`.
    pub fn write_command(&self, index: usize, values: &Values) -> Result<Vec<u8>, String> {
        let command = &self.commands[index];
        self.write(&command.body, values)
            .map_err(|e| format!("command {}: {e}", command.name))
    }

    /// Parses one framed message; an error is a protocol error.
    pub fn parse(&self, frame: &[u8]) -> Result<Parsed, CodecError> {
        match &self.framing {
            Framing::Xml => parse_tree(frame).map(Parsed::Xml),
            Framing::Line { .. } => String::from_utf8(frame.to_vec())
                .map(|line| Parsed::Text(line.trim_end_matches(['\r', '\n']).to_string()))
                .map_err(|_| {
                    CodecError::BadMessage(format!(
                        "a line that is not UTF-8: {}",
                        crate::shown::shown(frame, false)
                    ))
                }),
            Framing::LengthPrefix { .. } => Ok(Parsed::Binary(Bytes::copy_from_slice(frame))),
        }
    }

    /// Reads `parsed` as `body`: `Ok(None)` when it has another shape, `Err` when it has
    /// this shape but a value is wrong.
    fn read(&self, body: &Body, parsed: &Parsed) -> Result<Option<Values>, String> {
        let mut values = Values::default();
        match (body, parsed) {
            (Body::Xml(t), Parsed::Xml(element)) => match t.capture(element, &self.enums)? {
                Ok(v) => values = v,
                Err(_) => return Ok(None),
            },
            (Body::Text(t), Parsed::Text(line)) => {
                if !t.capture(line, &self.enums, &mut values)? {
                    return Ok(None);
                }
            }
            (Body::Binary(t), Parsed::Binary(bytes)) => {
                match t.capture(bytes, &self.enums, &self.format)? {
                    Ok(v) => values = v,
                    Err(_) => return Ok(None),
                }
            }
            _ => return Ok(None),
        }
        Ok(Some(values))
    }

    /// Reads `parsed` as reply `index`.
    pub fn read_reply(&self, index: usize, parsed: &Parsed) -> Result<Option<Values>, String> {
        let reply = &self.replies[index];
        let values = match (&reply.regex, parsed) {
            (Some(regex), Parsed::Text(line)) => {
                let Some(found) = regex.captures(line) else {
                    return Ok(None);
                };
                let mut values = Values::default();
                for name in regex.capture_names().flatten() {
                    let Some(m) = found.name(name) else { continue };
                    // Read through the table the reply's text names for it, as the
                    // text's placeholder would be: `{state:safety}` and a group
                    // `(?P<state>...)` read `NORMAL` as `ready`.
                    let value = match reply
                        .body
                        .as_ref()
                        .and_then(|b| messages::table_of(b, name))
                    {
                        Some(table) => self
                            .enums
                            .decode(&table, m.as_str())
                            .map_err(|e| format!("{}: {e}", reply.name))?
                            .to_string(),
                        None => m.as_str().to_string(),
                    };
                    values.set(name, value);
                }
                values
            }
            _ => match &reply.body {
                Some(body) => match self.read(body, parsed)? {
                    Some(values) => values,
                    None => return Ok(None),
                },
                None => return Ok(None),
            },
        };
        if let Some(id) = values.get("id") {
            if id.parse::<u64>().is_err() {
                return Err(format!(
                    "{}: the id {id:?} is not an unsigned integer",
                    reply.name
                ));
            }
        }
        Ok(Some(values))
    }

    /// Reads `parsed` as command `index` (robot-sim).
    pub fn read_command(&self, index: usize, parsed: &Parsed) -> Result<Option<Values>, String> {
        self.read(&self.commands[index].body, parsed)
    }

    /// What an outcome says: the step's result (`done`), the reason
    /// (`failed`, `rejected`), or the state (`status`), from the reply's values and the
    /// command's.
    pub fn evaluate(&self, template: &Template, reply: &Values, command: &Values) -> String {
        let lookup = |name: &str| reply.get(name).or_else(|| command.get(name));
        template
            .render_from(&lookup, &self.enums, Escape::Plain)
            .unwrap_or_else(|e| format!("({e})"))
    }

    /// The controller state a `status` reply reports.
    pub fn state_of(&self, reply: usize, values: &Values) -> Result<ControllerState, String> {
        let text = self.evaluate(&self.replies[reply].state, values, &Values::default());
        text.parse().map_err(|_| {
            format!(
                "{}: the state {text:?} is not ready, fault or estop",
                self.replies[reply].name
            )
        })
    }

    /// The reply that may come at any time (`status` or `ignore`) a message is, tried in
    /// the order of the file, with its values and, for a `status`, its state. A reply
    /// whose shape fits but whose value is wrong for it (a value outside its enum table,
    /// a state that is not ready, fault or estop) does not take the message: the next
    /// is tried. When none takes it, the first such wrong value is the error (the
    /// message meant to be one of them); when none had its shape, `Ok(None)`.
    pub fn read_unsolicited(
        &self,
        parsed: &Parsed,
    ) -> Result<Option<(usize, Values, Option<ControllerState>)>, String> {
        let mut wrong = None;
        for reply in self.unsolicited() {
            let values = match self.read_reply(reply, parsed) {
                Ok(None) => continue,
                Ok(Some(values)) => values,
                Err(why) => {
                    wrong.get_or_insert(why);
                    continue;
                }
            };
            if self.replies[reply].outcome == Outcome::Ignore {
                return Ok(Some((reply, values, None)));
            }
            match self.state_of(reply, &values) {
                Ok(state) => return Ok(Some((reply, values, Some(state)))),
                Err(why) => {
                    wrong.get_or_insert(why);
                }
            }
        }
        match wrong {
            Some(why) => Err(why),
            None => Ok(None),
        }
    }

    /// Replies that may come at any time: `status` and `ignore`.
    pub fn unsolicited(&self) -> impl Iterator<Item = usize> + '_ {
        self.replies
            .iter()
            .enumerate()
            .filter(|(_, r)| matches!(r.outcome, Outcome::Status | Outcome::Ignore))
            .map(|(i, _)| i)
    }

    /// Checks, at start, that a step of `action` can be written: every message of the
    /// sequence, and the abort, renders (an action missing from an enum table is found
    /// here, not at the first job). `info.KEY` values are taken as given.
    pub fn check_action(&self, action: &str) -> Result<(), String> {
        let mut values = Values::default();
        values.set("id", "1".into());
        values.set("action", action.into());
        values.set("program", "p".into());
        values.set("pose", String::new());
        for name in ["x", "y", "z", "a", "b", "c"] {
            values.set(name, self.format.number(0.0));
        }
        for command in &self.commands {
            for t in messages::templates_of(&command.body) {
                for (name, _) in t.names() {
                    if name.starts_with("info.") {
                        values.set(&name, "0".into());
                    }
                }
            }
        }
        if let Some(abort) = &self.abort {
            self.write_command(abort.command, &values)?;
        }
        for element in &self.sequence {
            self.write_command(element.command, &values)?;
            // What an answer makes of the command's values (`result = "{action:done}"`).
            for &r in &element.expect {
                let reply = &self.replies[r];
                for (field, t) in [("result", &reply.result), ("message", &reply.message)] {
                    for (name, table) in t.names() {
                        let (Some(table), Some(value)) = (table, values.get(&name)) else {
                            continue;
                        };
                        if values::is_command_name(&name) {
                            self.enums
                                .encode(&table, value)
                                .map_err(|e| format!("reply {}: its {field}: {e}", reply.name))?;
                        }
                    }
                }
            }
        }
        Ok(())
    }

    /// What is valid but likely a mistake, for `--check` to say (it does not refuse the
    /// dialect): each a sentence.
    pub fn warnings(&self) -> Vec<String> {
        let mut warnings = Vec::new();
        if self.abort.is_none() {
            warnings.push(format!(
                "the dialect {} has no `abort`: an operator's Abort (PackML) cannot stop the controller's motion; the step in flight runs to its end (docs/dialects.md, section 4.8)",
                self.name
            ));
        }
        for state in self.unsayable_states() {
            warnings.push(format!(
                "no status reply of the dialect {} says {state}: the holon cannot learn that the controller is in {state}, and robot-sim cannot play it (--fault-after)",
                self.name
            ));
        }
        warnings
    }

    /// Whether command `index`'s message writes the value `name` (`id`: whether an id a
    /// reply echoes can be compared with the command's).
    pub fn command_writes(&self, index: usize, name: &str) -> bool {
        messages::templates_of(&self.commands[index].body)
            .iter()
            .any(|t| t.names().iter().any(|(n, _)| n == name))
    }

    /// Whether reply `index` reads the value `name` (from its text, or its regex's
    /// named groups when it has one).
    pub fn reply_reads(&self, index: usize, name: &str) -> bool {
        let reply = &self.replies[index];
        match (&reply.regex, &reply.body) {
            // The holon reads a line through the regex alone when there is one.
            (Some(regex), _) => regex.capture_names().flatten().any(|n| n == name),
            (None, Some(body)) => messages::captures(body, None).iter().any(|n| n == name),
            (None, None) => false,
        }
    }
}

#[cfg(test)]
mod tests;

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
pub mod file;
pub mod framing;
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
pub use file::{Correlation, Outcome, Role, StatusSource};
use file::{DialectFile, FramingKind, MessageSection, ReplySection};
use framing::{ByteOrder, FrameCodec, Framing};
use template::Template;
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
}

fn invalid(origin: &str, field: impl Into<String>, why: impl Into<String>) -> DialectError {
    DialectError::Invalid {
        origin: origin.to_string(),
        field: field.into(),
        why: why.into(),
    }
}

fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

/// Reads escapes in a terminator: `\n`, `\r`, `\t`, `\0`, `\xHH`.
fn unescape_bytes(text: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let mut chars = text.chars();
    while let Some(c) = chars.next() {
        if c != '\\' {
            let mut buf = [0; 4];
            out.extend_from_slice(c.encode_utf8(&mut buf).as_bytes());
            continue;
        }
        match chars.next() {
            Some('n') => out.push(b'\n'),
            Some('r') => out.push(b'\r'),
            Some('t') => out.push(b'\t'),
            Some('0') => out.push(0),
            Some('\\') => out.push(b'\\'),
            Some('x') => {
                let hex: String = chars.by_ref().take(2).collect();
                let byte = u8::from_str_radix(&hex, 16)
                    .map_err(|_| format!("\\x{hex} is not two hex digits"))?;
                out.push(byte);
            }
            other => return Err(format!("unknown escape \\{}", other.unwrap_or(' '))),
        }
    }
    Ok(out)
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

    /// A shipped dialect, compiled once per process.
    pub fn shipped(name: &str) -> Result<Arc<Dialect>, DialectError> {
        static COMPILED: OnceLock<Vec<(&'static str, Arc<Dialect>)>> = OnceLock::new();
        let compiled = COMPILED.get_or_init(|| {
            SHIPPED
                .iter()
                .map(|(name, text)| {
                    let dialect = Dialect::from_toml(text, &format!("deploy/dialects/{name}.toml"))
                        .unwrap_or_else(|e| panic!("the shipped dialect {name} is invalid: {e}"));
                    (*name, Arc::new(dialect))
                })
                .collect()
        });
        compiled
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, d)| d.clone())
            .ok_or_else(|| DialectError::Unknown(name.to_string()))
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
        compile(file, origin)
    }

    pub fn frame_codec(&self) -> FrameCodec {
        FrameCodec {
            framing: self.framing.clone(),
            max: self.max_message_bytes,
        }
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
                .render(values, &self.enums, &|v| v.to_string())
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
                .map_err(|_| CodecError::Malformed("a line that is not UTF-8".into())),
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
                    if let Some(m) = found.name(name) {
                        values.set(name, m.as_str().to_string());
                    }
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
        let mut all = reply.clone();
        all.fill_from(command);
        template
            .render(&all, &self.enums, &|v| v.to_string())
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

    /// Replies that may come at any time: `status` and `ignore`.
    pub fn unsolicited(&self) -> impl Iterator<Item = usize> + '_ {
        self.replies
            .iter()
            .enumerate()
            .filter(|(_, r)| matches!(r.outcome, Outcome::Status | Outcome::Ignore))
            .map(|(i, _)| i)
    }

    /// Checks, at start, that a step of `action` can be written: every message of the
    /// sequence renders (an action missing from an enum table is found here, not at the
    /// first job). `info.KEY` values are taken as given.
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
            for t in templates_of(&command.body) {
                for (name, _) in t.names() {
                    if name.starts_with("info.") {
                        values.set(&name, "0".into());
                    }
                }
            }
        }
        for element in &self.sequence {
            self.write_command(element.command, &values)?;
        }
        Ok(())
    }

    /// Checks that robot-sim can write every reply this dialect needs.
    pub fn check_simulatable(&self) -> Result<(), String> {
        for reply in &self.replies {
            if reply.body.is_none() {
                return Err(format!(
                    "reply {}: robot-sim writes replies from `text`, and this one has only a regex",
                    reply.name
                ));
            }
        }
        Ok(())
    }
}

/// A message's body as the file gives it: `xml`, `text` or `fields`.
type Given<'a> = (
    Option<&'a String>,
    Option<&'a String>,
    Option<&'a Vec<binary::FieldSection>>,
);

fn body_of(
    origin: &str,
    at: &str,
    kind: FramingKind,
    order: ByteOrder,
    (xml, text, fields): Given<'_>,
    regex_given: bool,
) -> Result<Option<Body>, DialectError> {
    let given = [xml.is_some(), text.is_some(), fields.is_some()]
        .iter()
        .filter(|g| **g)
        .count();
    let wants = match kind {
        FramingKind::Xml => "xml",
        FramingKind::Line => "text",
        FramingKind::LengthPrefix => "fields",
    };
    if given > 1 {
        return Err(invalid(origin, at, "give one of xml, text and fields"));
    }
    let body = match (kind, xml, text, fields) {
        (FramingKind::Xml, Some(x), None, None) => {
            Body::Xml(XmlTemplate::parse(x).map_err(|e| invalid(origin, format!("{at}.xml"), e))?)
        }
        (FramingKind::Line, None, Some(t), None) => Body::Text(
            Template::parse(t).map_err(|e| invalid(origin, format!("{at}.text"), e.to_string()))?,
        ),
        (FramingKind::LengthPrefix, None, None, Some(f)) => Body::Binary(
            BinaryTemplate::parse(f, order)
                .map_err(|e| invalid(origin, format!("{at}.{e}"), "in this field"))?,
        ),
        (FramingKind::Line, None, None, None) if regex_given => return Ok(None),
        _ => {
            return Err(invalid(
                origin,
                at,
                format!("the framing is {kind:?}, so the message is given as `{wants}`")
                    .to_lowercase(),
            ))
        }
    };
    Ok(Some(body))
}

fn templates_of(body: &Body) -> Vec<&Template> {
    match body {
        Body::Xml(t) => vec![&t.text],
        Body::Text(t) => vec![t],
        Body::Binary(t) => t.templates().collect(),
    }
}

/// Checks every placeholder of `templates` against `allowed` and the enum tables.
fn check_names(
    origin: &str,
    at: &str,
    templates: &[&Template],
    allowed: fn(&str) -> bool,
    enums: &Enums,
) -> Result<(), DialectError> {
    for t in templates {
        for (name, table) in t.names() {
            let bare = name.trim_start_matches('?');
            if !allowed(bare) {
                return Err(invalid(
                    origin,
                    at,
                    format!("{{{name}}} is not a value here (a command has id, action, program, pose, x y z a b c and info.KEY; a reply also result, message, state)"),
                ));
            }
            if let Some(table) = table {
                if !enums.has_table(&table) {
                    return Err(invalid(
                        origin,
                        at,
                        format!("{{{name}:{table}}} names no [enums.{table}]"),
                    ));
                }
            }
        }
    }
    Ok(())
}

fn captures(body: &Body, regex: Option<&Regex>) -> Vec<String> {
    let mut names: Vec<String> = match body {
        Body::Xml(t) => t.text.names().into_iter().map(|(n, _)| n).collect(),
        Body::Text(t) => t.names().into_iter().map(|(n, _)| n).collect(),
        Body::Binary(t) => t
            .templates()
            .flat_map(|t| t.names())
            .map(|(n, _)| n)
            .collect(),
    };
    if let Some(regex) = regex {
        names.extend(regex.capture_names().flatten().map(str::to_string));
    }
    names
}

fn compile_reply(
    origin: &str,
    index: usize,
    section: &ReplySection,
    kind: FramingKind,
    order: ByteOrder,
    enums: &Enums,
) -> Result<Reply, DialectError> {
    let at = format!("reply[{index}] ({})", section.name);
    if !valid_name(&section.name) {
        return Err(invalid(
            origin,
            format!("reply[{index}].name"),
            "1 to 64 letters, digits, _ or -",
        ));
    }
    let regex = match &section.regex {
        Some(_) if kind != FramingKind::Line => {
            return Err(invalid(
                origin,
                format!("{at}.regex"),
                "a regex reads text lines only (framing kind line)",
            ))
        }
        Some(r) => {
            let regex =
                Regex::new(r).map_err(|e| invalid(origin, format!("{at}.regex"), e.to_string()))?;
            for name in regex.capture_names().flatten() {
                if !values::is_reply_name(name) {
                    return Err(invalid(
                        origin,
                        format!("{at}.regex"),
                        format!("the group (?P<{name}>) is not a value a reply has"),
                    ));
                }
            }
            Some(regex)
        }
        None => None,
    };
    let body = body_of(
        origin,
        &at,
        kind,
        order,
        (
            section.xml.as_ref(),
            section.text.as_ref(),
            section.fields.as_ref(),
        ),
        regex.is_some(),
    )?;
    if let Some(body) = &body {
        check_names(
            origin,
            &at,
            &templates_of(body),
            values::is_reply_name,
            enums,
        )?;
    }
    let captured = match &body {
        Some(body) => captures(body, regex.as_ref()),
        None => regex
            .as_ref()
            .map(|r| r.capture_names().flatten().map(str::to_string).collect())
            .unwrap_or_default(),
    };
    let parse =
        |field: &str, text: Option<&String>, default: &str| -> Result<Template, DialectError> {
            let text = text.map(String::as_str).unwrap_or(default);
            let t = Template::parse(text)
                .map_err(|e| invalid(origin, format!("{at}.{field}"), e.to_string()))?;
            check_names(
                origin,
                &format!("{at}.{field}"),
                &[&t],
                values::is_reply_name,
                enums,
            )?;
            Ok(t)
        };
    let message_default = if captured.iter().any(|n| n == "message") {
        "{message}".to_string()
    } else {
        section.name.replace(['{', '}'], "")
    };
    let result = parse("result", section.result.as_ref(), "{result}")?;
    let message = parse("message", section.message.as_ref(), &message_default)?;
    let state = parse("state", section.state.as_ref(), "{state}")?;
    // What the outcome needs must come from the message or the command.
    let reachable = |t: &Template| {
        t.names().iter().all(|(n, _)| {
            let n = n.trim_start_matches('?');
            captured.iter().any(|c| c == n) || values::is_command_name(n)
        })
    };
    match section.outcome {
        Outcome::Done if !reachable(&result) => {
            return Err(invalid(origin, format!("{at}.result"), format!("{:?} uses a value the message does not carry (give `result`, e.g. \"{{action:done}}\" or a literal)", result.source)))
        }
        Outcome::Status => {
            if !reachable(&state) || state.names().iter().any(|(n, _)| values::is_command_name(n)) {
                return Err(invalid(origin, format!("{at}.state"), format!("{:?}: the state must come from the message (a {{state}} or {{state:TABLE}} it carries) or be a literal", state.source)));
            }
            if let Some(literal) = state.literal() {
                literal.parse::<ControllerState>().map_err(|_| invalid(origin, format!("{at}.state"), format!("{literal:?} is not ready, fault or estop")))?;
            }
            if let Some((_, Some(table))) = state.single_value() {
                for key in enums.keys(table) {
                    key.parse::<ControllerState>().map_err(|_| invalid(origin, format!("enums.{table}"), format!("{key:?}: a state table maps ready, fault and estop only")))?;
                }
            }
        }
        _ => {}
    }
    Ok(Reply {
        name: section.name.clone(),
        outcome: section.outcome,
        body,
        regex,
        result,
        message,
        state,
    })
}

fn compile(file: DialectFile, origin: &str) -> Result<Dialect, DialectError> {
    if !valid_name(&file.name) {
        return Err(invalid(origin, "name", "1 to 64 letters, digits, _ or -"));
    }
    // Framing.
    let f = &file.framing;
    let max = f.max_message_bytes.unwrap_or(64 * 1024);
    if !(16..=16 * 1024 * 1024).contains(&max) {
        return Err(invalid(
            origin,
            "framing.max_message_bytes",
            "from 16 to 16777216",
        ));
    }
    let order = f.byte_order.unwrap_or(ByteOrder::Big);
    let only = |field: &str, given: bool, kind: &str| -> Result<(), DialectError> {
        if given {
            Err(invalid(
                origin,
                format!("framing.{field}"),
                format!("only for kind = \"{kind}\""),
            ))
        } else {
            Ok(())
        }
    };
    let framing = match f.kind {
        FramingKind::Xml => {
            only("terminator", f.terminator.is_some(), "line")?;
            only("prefix_bytes", f.prefix_bytes.is_some(), "length_prefix")?;
            only("byte_order", f.byte_order.is_some(), "length_prefix")?;
            only(
                "prefix_counts_itself",
                f.prefix_counts_itself.is_some(),
                "length_prefix",
            )?;
            Framing::Xml
        }
        FramingKind::Line => {
            only("prefix_bytes", f.prefix_bytes.is_some(), "length_prefix")?;
            only("byte_order", f.byte_order.is_some(), "length_prefix")?;
            only(
                "prefix_counts_itself",
                f.prefix_counts_itself.is_some(),
                "length_prefix",
            )?;
            let terminator = unescape_bytes(f.terminator.as_deref().unwrap_or("\n"))
                .map_err(|e| invalid(origin, "framing.terminator", e))?;
            if terminator.is_empty() || terminator.len() > 4 {
                return Err(invalid(origin, "framing.terminator", "1 to 4 bytes"));
            }
            Framing::Line { terminator }
        }
        FramingKind::LengthPrefix => {
            only("terminator", f.terminator.is_some(), "line")?;
            let bytes = f.prefix_bytes.unwrap_or(4);
            if bytes != 2 && bytes != 4 {
                return Err(invalid(origin, "framing.prefix_bytes", "2 or 4"));
            }
            Framing::LengthPrefix {
                bytes,
                order,
                counts_itself: f.prefix_counts_itself.unwrap_or(false),
            }
        }
    };
    // Values and enums.
    let format = ValueFormat {
        decimals: file.values.decimals,
        true_text: file
            .values
            .true_text
            .clone()
            .unwrap_or_else(|| "true".into()),
        false_text: file
            .values
            .false_text
            .clone()
            .unwrap_or_else(|| "false".into()),
    };
    if format.decimals.is_some_and(|d| d > 17) {
        return Err(invalid(origin, "values.decimals", "at most 17"));
    }
    let mut enums = Enums::default();
    for (table, entries) in file.enums {
        if !template_name(&table) {
            return Err(invalid(
                origin,
                format!("enums.{table}"),
                "a table's name is lower-case letters, digits and _",
            ));
        }
        if entries.is_empty() {
            return Err(invalid(origin, format!("enums.{table}"), "an empty table"));
        }
        let mut seen = std::collections::BTreeSet::new();
        for (value, wire) in entries {
            let wire = wire.into_vec();
            if wire.is_empty() || wire.iter().any(String::is_empty) {
                return Err(invalid(
                    origin,
                    format!("enums.{table}.{value}"),
                    "give one or more non-empty wire forms",
                ));
            }
            for w in &wire {
                if !seen.insert(w.clone()) {
                    return Err(invalid(origin, format!("enums.{table}.{value}"), format!("{w:?} already stands for another value: reading it back would be ambiguous")));
                }
            }
            enums.insert(&table, &value, wire);
        }
    }
    // Messages.
    let mut commands = Vec::new();
    for (i, c) in file.command.iter().enumerate() {
        commands.push(compile_command(
            origin, i, c, f.kind, order, &enums, &commands,
        )?);
    }
    let mut replies: Vec<Reply> = Vec::new();
    for (i, r) in file.reply.iter().enumerate() {
        let reply = compile_reply(origin, i, r, f.kind, order, &enums)?;
        if replies.iter().any(|o| o.name == reply.name) {
            return Err(invalid(
                origin,
                format!("reply[{i}].name"),
                format!("{:?} is used twice", reply.name),
            ));
        }
        replies.push(reply);
    }
    let command_named = |field: &str, name: &str| {
        commands
            .iter()
            .position(|c: &Command| c.name == name)
            .ok_or_else(|| invalid(origin, field, format!("no [[command]] is named {name:?}")))
    };
    let reply_named = |field: &str, name: &str| {
        replies
            .iter()
            .position(|r| r.name == name)
            .ok_or_else(|| invalid(origin, field, format!("no [[reply]] is named {name:?}")))
    };
    // Correlation: with ids, every answer to a command carries the id.
    if file.correlation == Correlation::Id {
        for (i, c) in commands.iter().enumerate() {
            let names: Vec<String> = templates_of(&c.body)
                .iter()
                .flat_map(|t| t.names())
                .map(|(n, _)| n)
                .collect();
            if !names.iter().any(|n| n == "id") {
                return Err(invalid(
                    origin,
                    format!("command[{i}] ({})", c.name),
                    "correlation = \"id\": every command carries {id}",
                ));
            }
        }
        for (i, r) in replies.iter().enumerate() {
            let carries = r
                .body
                .as_ref()
                .map(|b| captures(b, r.regex.as_ref()))
                .unwrap_or_default();
            if !matches!(r.outcome, Outcome::Status | Outcome::Ignore)
                && !carries.iter().any(|n| n == "id")
            {
                return Err(invalid(
                    origin,
                    format!("reply[{i}] ({})", r.name),
                    "correlation = \"id\": every answer to a command carries {id}",
                ));
            }
        }
    }
    // The sequence.
    if file.sequence.is_empty() {
        return Err(invalid(origin, "sequence", "at least one element"));
    }
    let mut sequence = Vec::new();
    for (i, e) in file.sequence.iter().enumerate() {
        let at = format!("sequence[{i}]");
        let (sending, name) = match (&e.send, &e.poll, e.every_ms) {
            (Some(name), None, None) => (Sending::Send, name),
            (None, Some(name), Some(ms)) if ms > 0 => {
                (Sending::Poll(Duration::from_millis(ms)), name)
            }
            (None, Some(_), _) => {
                return Err(invalid(
                    origin,
                    format!("{at}.every_ms"),
                    "a poll needs every_ms > 0",
                ))
            }
            (Some(_), None, Some(_)) => {
                return Err(invalid(
                    origin,
                    format!("{at}.every_ms"),
                    "only a poll repeats",
                ))
            }
            _ => return Err(invalid(origin, &at, "give send or poll")),
        };
        let command = command_named(
            &format!("{at}.{}", if e.send.is_some() { "send" } else { "poll" }),
            name,
        )?;
        if e.expect.is_empty() {
            return Err(invalid(
                origin,
                format!("{at}.expect"),
                "at least one reply",
            ));
        }
        let mut expect = Vec::new();
        for name in &e.expect {
            let r = reply_named(&format!("{at}.expect"), name)?;
            if matches!(replies[r].outcome, Outcome::Status | Outcome::Ignore) {
                return Err(invalid(
                    origin,
                    format!("{at}.expect"),
                    format!(
                        "{name:?} is a {:?} reply, which may come at any time; expect answers only",
                        replies[r].outcome
                    )
                    .to_lowercase(),
                ));
            }
            expect.push(r);
        }
        let outcomes: Vec<Outcome> = expect.iter().map(|&r| replies[r].outcome).collect();
        if let Sending::Poll(_) = sending {
            if !outcomes.contains(&Outcome::Running) {
                return Err(invalid(
                    origin,
                    format!("{at}.expect"),
                    "a poll expects a `running` reply (the action goes on)",
                ));
            }
        }
        sequence.push(Element {
            sending,
            command,
            expect,
            starts: e.starts,
        });
    }
    let last = sequence.last().expect("not empty");
    if !last
        .expect
        .iter()
        .any(|&r| replies[r].outcome == Outcome::Done)
    {
        return Err(invalid(
            origin,
            format!("sequence[{}].expect", sequence.len() - 1),
            "the last element must expect a `done` reply, or no step could end",
        ));
    }
    match sequence.iter().filter(|e| e.starts).count() {
        0 => {
            // The last `send` begins the action.
            if let Some(e) = sequence
                .iter_mut()
                .rev()
                .find(|e| e.sending == Sending::Send)
            {
                e.starts = true;
            } else {
                sequence[0].starts = true;
            }
        }
        1 => {}
        _ => {
            return Err(invalid(
                origin,
                "sequence",
                "only one element starts the action",
            ))
        }
    }
    // Status.
    let status = match (file.status.source, &file.status.poll, file.status.every_ms) {
        (StatusSource::Pushed, None, None) => Status::Pushed,
        (StatusSource::Connection, None, None) => Status::Connection,
        (StatusSource::Polled, Some(name), Some(ms)) if ms > 0 => Status::Polled {
            command: command_named("status.poll", name)?,
            every: Duration::from_millis(ms),
        },
        (StatusSource::Polled, _, _) => {
            return Err(invalid(
                origin,
                "status",
                "source = \"polled\" needs poll (a command) and every_ms > 0",
            ))
        }
        _ => {
            return Err(invalid(
                origin,
                "status",
                "poll and every_ms are for source = \"polled\" only",
            ))
        }
    };
    if status != Status::Connection && !replies.iter().any(|r| r.outcome == Outcome::Status) {
        return Err(invalid(
            origin,
            "status",
            "a pushed or polled state needs a [[reply]] with outcome = \"status\"",
        ));
    }
    let keepalive = match &file.connection.keepalive {
        None => None,
        Some(k) => {
            if k.every_ms == 0 {
                return Err(invalid(
                    origin,
                    "connection.keepalive.every_ms",
                    "more than 0",
                ));
            }
            let mut expect = Vec::new();
            for name in &k.expect {
                expect.push(reply_named("connection.keepalive.expect", name)?);
            }
            Some(Keepalive {
                command: command_named("connection.keepalive.send", &k.send)?,
                every: Duration::from_millis(k.every_ms),
                expect,
            })
        }
    };
    if let Some(banner) = &file.connection.banner {
        if banner.is_empty() || banner.len() > max {
            return Err(invalid(
                origin,
                "connection.banner",
                "1 byte up to max_message_bytes",
            ));
        }
        if f.kind == FramingKind::LengthPrefix {
            return Err(invalid(
                origin,
                "connection.banner",
                "a banner is text, not for length_prefix framing",
            ));
        }
        if f.kind == FramingKind::Xml && parse_tree(banner.as_bytes()).is_err() {
            return Err(invalid(
                origin,
                "connection.banner",
                "with xml framing the banner is one XML document",
            ));
        }
        if let Framing::Line { terminator } = &framing {
            if banner
                .as_bytes()
                .windows(terminator.len())
                .any(|w| w == terminator.as_slice())
            {
                return Err(invalid(
                    origin,
                    "connection.banner",
                    "one line: it holds the terminator",
                ));
            }
        }
    }
    Ok(Dialect {
        name: file.name,
        description: file.description,
        role: file.connection.role,
        framing,
        max_message_bytes: max,
        format,
        correlation: file.correlation,
        status,
        banner: file.connection.banner,
        keepalive,
        enums,
        commands,
        replies,
        sequence,
    })
}

fn template_name(name: &str) -> bool {
    name.chars().next().is_some_and(|c| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
}

fn compile_command(
    origin: &str,
    index: usize,
    section: &MessageSection,
    kind: FramingKind,
    order: ByteOrder,
    enums: &Enums,
    earlier: &[Command],
) -> Result<Command, DialectError> {
    let at = format!("command[{index}] ({})", section.name);
    if !valid_name(&section.name) {
        return Err(invalid(
            origin,
            format!("command[{index}].name"),
            "1 to 64 letters, digits, _ or -",
        ));
    }
    if earlier.iter().any(|c| c.name == section.name) {
        return Err(invalid(
            origin,
            format!("command[{index}].name"),
            format!("{:?} is used twice", section.name),
        ));
    }
    let body = body_of(
        origin,
        &at,
        kind,
        order,
        (
            section.xml.as_ref(),
            section.text.as_ref(),
            section.fields.as_ref(),
        ),
        false,
    )?
    .expect("a command always has a body");
    check_names(
        origin,
        &at,
        &templates_of(&body),
        values::is_command_name,
        enums,
    )?;
    Ok(Command {
        name: section.name.clone(),
        body,
    })
}

#[cfg(test)]
mod tests;

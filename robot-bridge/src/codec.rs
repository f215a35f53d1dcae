//! The TCP/XML codec of the robot controller protocol.
//!
//! A stream carries one XML document after another, framed only by the end of each root
//! element. Decoding is two steps:
//!
//! 1. [`find_document`] scans the bytes received so far for the end of the first complete
//!    document. It understands just enough XML to frame (tags with quoted attributes,
//!    comments, CDATA, processing instructions such as the XML declaration) and enforces
//!    the limits: no DOCTYPE, at most [`MAX_DOCUMENT_BYTES`] per document and at most
//!    [`MAX_DEPTH`] nested elements. A document cut off by the end of the buffer is
//!    *incomplete*, never complete.
//! 2. [`parse_document`] parses one complete document with quick-xml, which checks that it
//!    is well-formed, and maps it to a [`RobotMessage`].
//!
//! The holon also writes `ROBOT_ABORT` ([`encode_abort`]): stop the command with this
//! `ID` now (PackML Abort); the controller answers that command's `ROBOT_CMD` with
//! `RESULT` `error`, `MESSAGE` `aborted`. The codec does not decode it (it is not a
//! [`RobotMessage`]); robot-sim reads it through the `holarchy-xml` dialect.
//!
//! [`RobotCodec`] puts both behind tokio-util's `Decoder`/`Encoder` for a framed socket.
//! After any decode error the stream cannot be resynchronised: drop the connection.

use bytes::{Buf, BytesMut};
use quick_xml::escape::{escape, resolve_predefined_entity};
use quick_xml::events::Event;
use quick_xml::Reader;
use schemas::{ControllerState, Pose, RobotCommand, RobotMessage, RobotReply};
use tokio_util::codec::{Decoder, Encoder};

/// The largest document accepted, in bytes (the contract's 64 KiB).
pub const MAX_DOCUMENT_BYTES: usize = 64 * 1024;

/// The deepest element nesting accepted (the protocol itself needs 2).
pub const MAX_DEPTH: usize = 8;

/// What can be wrong with the bytes a peer sent.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    #[error("DOCTYPE declarations are not allowed")]
    DoctypeRejected,
    #[error("document exceeds {MAX_DOCUMENT_BYTES} bytes")]
    TooLarge,
    #[error("message exceeds {0} bytes")]
    TooLargeFor(usize),
    /// A message that is not what its framing carries (a text line that is not UTF-8,
    /// a length prefix that cannot be).
    #[error("{0}")]
    BadMessage(String),
    #[error("document nests elements deeper than {MAX_DEPTH}")]
    TooDeep,
    #[error("malformed XML: {0}")]
    Malformed(String),
    #[error("unknown document <{0}>")]
    UnknownDocument(String),
    #[error("<{root}> lacks <{field}>")]
    MissingField {
        root: &'static str,
        field: &'static str,
    },
    #[error("<{root}> has an invalid {field}: {why}")]
    InvalidField {
        root: &'static str,
        field: &'static str,
        why: String,
    },
    #[error("the connection closed inside a document")]
    ClosedInsideDocument,
    #[error("connection I/O: {0}")]
    Io(String),
}

impl CodecError {
    /// Whether the connection broke (a reset, or the peer gone in the middle of
    /// a document) rather than the peer sending bytes that break the protocol.
    /// A controller killed mid-message is a lost controller, not a faulty one.
    pub fn is_broken_connection(&self) -> bool {
        matches!(self, CodecError::ClosedInsideDocument | CodecError::Io(_))
    }
}

impl From<std::io::Error> for CodecError {
    fn from(e: std::io::Error) -> Self {
        CodecError::Io(e.to_string())
    }
}

/// Where the first document in a buffer lies.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Frame {
    /// Only whitespace (or nothing) so far; `skip` bytes of it can be dropped.
    Empty { skip: usize },
    /// A document has begun at `start` but has not ended.
    Incomplete { start: usize },
    /// `buf[start..end]` is one complete document.
    Complete { start: usize, end: usize },
}

const BOM: &[u8] = b"\xEF\xBB\xBF";

fn find(buf: &[u8], from: usize, needle: &[u8]) -> Option<usize> {
    buf.get(from..)?
        .windows(needle.len())
        .position(|w| w == needle)
        .map(|p| p + from)
}

/// Finds the end of the tag that opens at `buf[from] == b'<'`, skipping quoted attribute
/// values (which may contain `>`). Returns the index of the closing `>`.
fn find_tag_end(buf: &[u8], from: usize) -> Option<usize> {
    let mut quote = None;
    for (i, &b) in buf.iter().enumerate().skip(from + 1) {
        match quote {
            Some(q) if b == q => quote = None,
            Some(_) => {}
            None if b == b'"' || b == b'\'' => quote = Some(b),
            None if b == b'>' => return Some(i),
            None => {}
        }
    }
    None
}

/// Frames the first document of `buf` (see the module docs). Never panics.
pub fn find_document(buf: &[u8]) -> Result<Frame, CodecError> {
    find_document_within(buf, MAX_DOCUMENT_BYTES).map_err(|e| match e {
        CodecError::TooLargeFor(_) => CodecError::TooLarge,
        other => other,
    })
}

/// [`find_document`] with a limit of `max` bytes per document instead of
/// [`MAX_DOCUMENT_BYTES`] (a dialect's `max_message_bytes`).
pub fn find_document_within(buf: &[u8], max: usize) -> Result<Frame, CodecError> {
    let mut i = 0;
    if buf.starts_with(BOM) {
        i = BOM.len();
    }
    while i < buf.len() && buf[i].is_ascii_whitespace() {
        i += 1;
    }
    if i == buf.len() {
        return Ok(Frame::Empty { skip: i });
    }
    let start = i;
    let mut depth = 0usize;
    let incomplete = |i: usize| {
        if i - start > max {
            Err(CodecError::TooLargeFor(max))
        } else {
            Ok(Frame::Incomplete { start })
        }
    };
    loop {
        if i - start > max {
            return Err(CodecError::TooLargeFor(max));
        }
        let Some(&b) = buf.get(i) else {
            return incomplete(buf.len());
        };
        if b != b'<' {
            if depth == 0 {
                if b.is_ascii_whitespace() {
                    i += 1;
                    continue;
                }
                return Err(CodecError::Malformed(
                    "text outside the root element".into(),
                ));
            }
            // Character data: jump to the next markup.
            match buf[i..].iter().position(|&c| c == b'<') {
                Some(p) => i += p,
                None => return incomplete(buf.len()),
            }
            continue;
        }
        let Some(&next) = buf.get(i + 1) else {
            return incomplete(buf.len());
        };
        match next {
            b'?' => match find(buf, i + 2, b"?>") {
                Some(end) => i = end + 2,
                None => return incomplete(buf.len()),
            },
            b'!' => {
                let rest = &buf[i..];
                let starts = |p: &[u8]| {
                    let n = rest.len().min(p.len());
                    rest[..n] == p[..n]
                };
                if rest.len() < 4 && starts(b"<!--") || rest.len() < 9 && starts(b"<![CDATA[") {
                    return incomplete(buf.len());
                }
                if rest.starts_with(b"<!--") {
                    match find(buf, i + 4, b"-->") {
                        Some(end) => i = end + 3,
                        None => return incomplete(buf.len()),
                    }
                } else if rest.starts_with(b"<![CDATA[") {
                    if depth == 0 {
                        return Err(CodecError::Malformed(
                            "CDATA outside the root element".into(),
                        ));
                    }
                    match find(buf, i + 9, b"]]>") {
                        Some(end) => i = end + 3,
                        None => return incomplete(buf.len()),
                    }
                } else if rest.len() < 9 && starts(b"<!DOCTYPE") {
                    return incomplete(buf.len());
                } else if rest.starts_with(b"<!DOCTYPE") {
                    return Err(CodecError::DoctypeRejected);
                } else {
                    return Err(CodecError::Malformed("unexpected markup <!".into()));
                }
            }
            b'/' => {
                let Some(end) = find_tag_end(buf, i) else {
                    return incomplete(buf.len());
                };
                if depth == 0 {
                    return Err(CodecError::Malformed("end tag without start tag".into()));
                }
                depth -= 1;
                i = end + 1;
                if depth == 0 {
                    return Ok(Frame::Complete { start, end: i });
                }
            }
            _ => {
                let Some(end) = find_tag_end(buf, i) else {
                    return incomplete(buf.len());
                };
                let self_closing = buf[end - 1] == b'/' && end > i + 1;
                i = end + 1;
                if self_closing {
                    if depth == 0 {
                        return Ok(Frame::Complete { start, end: i });
                    }
                } else {
                    depth += 1;
                    if depth > MAX_DEPTH {
                        return Err(CodecError::TooDeep);
                    }
                }
            }
        }
    }
}

/// One parsed element: the little tree the protocol (and an XML dialect) needs.
#[derive(Debug, Default)]
pub struct Element {
    /// The element's name, compared literally (no namespaces).
    pub name: String,
    /// Its attributes, unescaped, in document order.
    pub attributes: Vec<(String, String)>,
    /// Its text (character data, CDATA and entities resolved), untrimmed.
    pub text: String,
    /// Its child elements, in document order.
    pub children: Vec<Element>,
}

impl Element {
    pub fn child(&self, name: &str) -> Option<&Element> {
        self.children.iter().find(|c| c.name == name)
    }

    pub fn attribute(&self, name: &str) -> Option<&str> {
        self.attributes
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }
}

fn malformed(e: impl std::fmt::Display) -> CodecError {
    CodecError::Malformed(e.to_string())
}

fn open_element(e: &quick_xml::events::BytesStart<'_>) -> Result<Element, CodecError> {
    let name = std::str::from_utf8(e.name().as_ref())
        .map_err(malformed)?
        .to_string();
    let mut attributes = Vec::new();
    for attribute in e.attributes() {
        let attribute = attribute.map_err(malformed)?;
        let key = std::str::from_utf8(attribute.key.as_ref())
            .map_err(malformed)?
            .to_string();
        let value = attribute.unescape_value().map_err(malformed)?.into_owned();
        attributes.push((key, value));
    }
    Ok(Element {
        name,
        attributes,
        ..Element::default()
    })
}

/// Parses one complete document (as framed by [`find_document`]) into its element tree.
pub fn parse_tree(doc: &[u8]) -> Result<Element, CodecError> {
    let text = std::str::from_utf8(doc).map_err(|e| malformed(format!("not UTF-8: {e}")))?;
    let mut reader = Reader::from_str(text);
    reader.config_mut().check_end_names = true;
    let mut stack: Vec<Element> = Vec::new();
    let mut root = None;
    loop {
        match reader.read_event().map_err(malformed)? {
            Event::Start(e) => {
                if root.is_some() {
                    return Err(malformed("content after the root element"));
                }
                stack.push(open_element(&e)?);
            }
            Event::Empty(e) => {
                let element = open_element(&e)?;
                match stack.last_mut() {
                    Some(parent) => parent.children.push(element),
                    None if root.is_none() => root = Some(element),
                    None => return Err(malformed("content after the root element")),
                }
            }
            Event::End(_) => {
                let element = stack.pop().ok_or_else(|| malformed("unbalanced end tag"))?;
                match stack.last_mut() {
                    Some(parent) => parent.children.push(element),
                    None => root = Some(element),
                }
            }
            Event::Text(t) => {
                let t = t.decode().map_err(malformed)?;
                match stack.last_mut() {
                    Some(element) => element.text.push_str(&t),
                    None if t.trim().is_empty() => {}
                    None => return Err(malformed("text outside the root element")),
                }
            }
            Event::CData(t) => {
                let t = t.decode().map_err(malformed)?;
                match stack.last_mut() {
                    Some(element) => element.text.push_str(&t),
                    None => return Err(malformed("CDATA outside the root element")),
                }
            }
            Event::GeneralRef(r) => {
                let resolved = match r.resolve_char_ref().map_err(malformed)? {
                    Some(c) => c.to_string(),
                    None => {
                        let name = r.decode().map_err(malformed)?;
                        resolve_predefined_entity(&name)
                            .ok_or_else(|| malformed(format!("unknown entity &{name};")))?
                            .to_string()
                    }
                };
                match stack.last_mut() {
                    Some(element) => element.text.push_str(&resolved),
                    None => return Err(malformed("entity outside the root element")),
                }
            }
            Event::DocType(_) => return Err(CodecError::DoctypeRejected),
            Event::Decl(_) | Event::PI(_) | Event::Comment(_) => {}
            Event::Eof => break,
        }
    }
    if !stack.is_empty() {
        return Err(malformed("document ends inside an element"));
    }
    root.ok_or_else(|| malformed("no root element"))
}

fn text_field<'a>(
    element: &'a Element,
    root: &'static str,
    field: &'static str,
) -> Result<&'a str, CodecError> {
    element
        .child(field)
        .map(|c| c.text.trim())
        .ok_or(CodecError::MissingField { root, field })
}

fn id_field(element: &Element, root: &'static str) -> Result<u64, CodecError> {
    let text = text_field(element, root, "ID")?;
    text.parse().map_err(|_| CodecError::InvalidField {
        root,
        field: "ID",
        why: format!("{text:?} is not an unsigned integer"),
    })
}

fn pose(element: &Element) -> Result<Pose, CodecError> {
    let coordinate = |name: &'static str| -> Result<f64, CodecError> {
        let Some(text) = element.attribute(name) else {
            return Ok(0.0);
        };
        let value: f64 = text.trim().parse().map_err(|_| CodecError::InvalidField {
            root: "ROBOT_CMD",
            field: "POS",
            why: format!("{name}={text:?} is not a number"),
        })?;
        if !value.is_finite() {
            return Err(CodecError::InvalidField {
                root: "ROBOT_CMD",
                field: "POS",
                why: format!("{name} is not finite"),
            });
        }
        Ok(value)
    };
    Ok(Pose {
        x: coordinate("X")?,
        y: coordinate("Y")?,
        z: coordinate("Z")?,
        a: coordinate("A")?,
        b: coordinate("B")?,
        c: coordinate("C")?,
    })
}

/// The elements of a command that carry a job's material flow (docs/material-flow.md)
/// and the `info` keys they come from: the part, where it is, where it goes.
pub const MATERIAL_FIELDS: [(&str, &str); 3] = [("PART", "part"), ("FROM", "from"), ("TO", "to")];

/// Parses one complete document into a protocol message.
pub fn parse_document(doc: &[u8]) -> Result<RobotMessage, CodecError> {
    let root = parse_tree(doc)?;
    match root.name.as_str() {
        "ROBOT_CMD" => {
            let action = text_field(&root, "ROBOT_CMD", "ACTION")?;
            if action.is_empty() {
                return Err(CodecError::InvalidField {
                    root: "ROBOT_CMD",
                    field: "ACTION",
                    why: "it is empty".into(),
                });
            }
            let program = match root.child("PROGRAM").map(|p| p.text.trim()) {
                Some("") => {
                    return Err(CodecError::InvalidField {
                        root: "ROBOT_CMD",
                        field: "PROGRAM",
                        why: "it is empty".into(),
                    })
                }
                program => program.map(str::to_string),
            };
            // The part a command is about and where it moves (material flow): the
            // job's info.part, info.from and info.to.
            let mut info = std::collections::BTreeMap::new();
            for (field, key) in MATERIAL_FIELDS {
                if let Some(value) = root.child(field).map(|e| e.text.trim()) {
                    info.insert(key.to_string(), serde_json::Value::from(value));
                }
            }
            Ok(RobotMessage::Command(RobotCommand {
                id: id_field(&root, "ROBOT_CMD")?,
                action: action.to_string(),
                pos: root.child("POS").map(pose).transpose()?,
                program,
                info,
            }))
        }
        "ROBOT_REPLY" => {
            let result = text_field(&root, "ROBOT_REPLY", "RESULT")?;
            if result.is_empty() {
                return Err(CodecError::InvalidField {
                    root: "ROBOT_REPLY",
                    field: "RESULT",
                    why: "it is empty".into(),
                });
            }
            Ok(RobotMessage::Reply(RobotReply {
                id: id_field(&root, "ROBOT_REPLY")?,
                result: result.to_string(),
                message: root.child("MESSAGE").map(|m| m.text.trim().to_string()),
            }))
        }
        "ROBOT_STATUS" => {
            let state = text_field(&root, "ROBOT_STATUS", "STATE")?;
            let state: ControllerState = state.parse().map_err(|_| CodecError::InvalidField {
                root: "ROBOT_STATUS",
                field: "STATE",
                why: format!("{state:?} is not ready, fault or estop"),
            })?;
            Ok(RobotMessage::Status(state))
        }
        other => Err(CodecError::UnknownDocument(other.to_string())),
    }
}

/// Writes one message as a single-line XML document.
pub fn encode_message(message: &RobotMessage) -> String {
    match message {
        RobotMessage::Command(cmd) => {
            let pos = match &cmd.pos {
                Some(p) => format!(
                    "<POS X=\"{:?}\" Y=\"{:?}\" Z=\"{:?}\" A=\"{:?}\" B=\"{:?}\" C=\"{:?}\"></POS>",
                    p.x, p.y, p.z, p.a, p.b, p.c
                ),
                None => String::new(),
            };
            let program = match &cmd.program {
                Some(p) => format!("<PROGRAM>{}</PROGRAM>", escape(p.as_str())),
                None => String::new(),
            };
            let material: String = MATERIAL_FIELDS
                .iter()
                .filter_map(|(field, key)| {
                    let value = cmd.info.get(*key)?.as_str()?;
                    Some(format!("<{field}>{}</{field}>", escape(value)))
                })
                .collect();
            format!(
                "<ROBOT_CMD><ID>{}</ID><ACTION>{}</ACTION>{program}{material}{pos}</ROBOT_CMD>",
                cmd.id,
                escape(cmd.action.as_str())
            )
        }
        RobotMessage::Reply(reply) => {
            let message = match &reply.message {
                Some(m) => format!("<MESSAGE>{}</MESSAGE>", escape(m.as_str())),
                None => String::new(),
            };
            format!(
                "<ROBOT_REPLY><ID>{}</ID><RESULT>{}</RESULT>{message}</ROBOT_REPLY>",
                reply.id,
                escape(reply.result.as_str())
            )
        }
        RobotMessage::Status(state) => {
            format!("<ROBOT_STATUS><STATE>{state}</STATE></ROBOT_STATUS>")
        }
    }
}

/// Writes the abort of command `id` as a single-line XML document (the `holarchy-xml`
/// dialect's abort, byte for byte).
pub fn encode_abort(id: u64) -> String {
    format!("<ROBOT_ABORT><ID>{id}</ID></ROBOT_ABORT>")
}

/// tokio-util codec for a framed controller connection (either side).
#[derive(Debug, Default)]
pub struct RobotCodec;

impl Decoder for RobotCodec {
    type Item = RobotMessage;
    type Error = CodecError;

    fn decode(&mut self, buf: &mut BytesMut) -> Result<Option<RobotMessage>, CodecError> {
        match find_document(buf)? {
            Frame::Empty { skip } => {
                buf.advance(skip);
                Ok(None)
            }
            Frame::Incomplete { start } => {
                buf.advance(start);
                Ok(None)
            }
            Frame::Complete { start, end } => {
                let doc = buf.split_to(end);
                parse_document(&doc[start..]).map(Some)
            }
        }
    }

    fn decode_eof(&mut self, buf: &mut BytesMut) -> Result<Option<RobotMessage>, CodecError> {
        match self.decode(buf)? {
            Some(message) => Ok(Some(message)),
            None if buf.iter().all(u8::is_ascii_whitespace) => Ok(None),
            None => Err(CodecError::ClosedInsideDocument),
        }
    }
}

impl Encoder<&RobotMessage> for RobotCodec {
    type Error = CodecError;

    fn encode(&mut self, message: &RobotMessage, buf: &mut BytesMut) -> Result<(), CodecError> {
        buf.extend_from_slice(encode_message(message).as_bytes());
        Ok(())
    }
}

#[cfg(test)]
mod tests;

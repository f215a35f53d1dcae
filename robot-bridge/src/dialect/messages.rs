//! Compiling one message of a dialect file: its body (an XML document, a text line, or
//! binary fields) and, for a reply, what it means; every placeholder checked.

use regex::Regex;
use schemas::ControllerState;

use super::binary::{self, BinaryTemplate};
use super::file::{FramingKind, MessageSection, Outcome, ReplySection};
use super::framing::ByteOrder;
use super::template::Template;
use super::values::{self, Enums};
use super::xml::XmlTemplate;
use super::{Body, Command, DialectError, Reply};

pub(super) fn invalid(
    origin: &str,
    field: impl Into<String>,
    why: impl Into<String>,
) -> DialectError {
    DialectError::Invalid {
        origin: origin.to_string(),
        field: field.into(),
        why: why.into(),
    }
}

pub(super) fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
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

pub(super) fn templates_of(body: &Body) -> Vec<&Template> {
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

pub(super) fn captures(body: &Body, regex: Option<&Regex>) -> Vec<String> {
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

pub(super) fn compile_reply(
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
    let regex = reply_regex(origin, &at, section.regex.as_deref(), kind)?;
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
        Outcome::Status => check_state(origin, &at, &state, reachable(&state), enums)?,
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

/// A reply's `regex`: for text lines only, each named group a value a reply has.
fn reply_regex(
    origin: &str,
    at: &str,
    regex: Option<&str>,
    kind: FramingKind,
) -> Result<Option<Regex>, DialectError> {
    match regex {
        Some(_) if kind != FramingKind::Line => Err(invalid(
            origin,
            format!("{at}.regex"),
            "a regex reads text lines only (framing kind line)",
        )),
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
            Ok(Some(regex))
        }
        None => Ok(None),
    }
}

/// A `status` reply's state: from the message (`reachable`) or a literal, and only
/// ready, fault or estop.
fn check_state(
    origin: &str,
    at: &str,
    state: &Template,
    reachable: bool,
    enums: &Enums,
) -> Result<(), DialectError> {
    if !reachable
        || state
            .names()
            .iter()
            .any(|(n, _)| values::is_command_name(n))
    {
        return Err(invalid(origin, format!("{at}.state"), format!("{:?}: the state must come from the message (a {{state}} or {{state:TABLE}} it carries) or be a literal", state.source)));
    }
    if let Some(literal) = state.literal() {
        literal.parse::<ControllerState>().map_err(|_| {
            invalid(
                origin,
                format!("{at}.state"),
                format!("{literal:?} is not ready, fault or estop"),
            )
        })?;
    }
    if let Some((_, Some(table))) = state.single_value() {
        for key in enums.keys(table) {
            key.parse::<ControllerState>().map_err(|_| {
                invalid(
                    origin,
                    format!("enums.{table}"),
                    format!("{key:?}: a state table maps ready, fault and estop only"),
                )
            })?;
        }
    }
    Ok(())
}

pub(super) fn compile_command(
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

/// The table through which `body` writes (and reads) the value `name`, if it names one.
pub(super) fn table_of(body: &Body, name: &str) -> Option<String> {
    templates_of(body)
        .iter()
        .flat_map(|t| t.names())
        .find(|(n, table)| n == name && table.is_some())
        .and_then(|(_, table)| table)
}

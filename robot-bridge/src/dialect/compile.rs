//! Checking a dialect file and compiling it into a [`Dialect`]: every error names the
//! field and the problem.
//!
//! [`compile`] takes the file's sections in the order a reader meets them, one step
//! each: the framing, the values and enums, the messages, the sequence
//! ([`sequence`]), the controller's state and keep-alive ([`status`]), the abort
//! ([`abort`]), the fence ([`fence`]) and the banner. The first error found is the one
//! reported.

mod abort;
mod fence;
mod sequence;
mod status;

use std::collections::{BTreeMap, BTreeSet};

use super::file::{
    DialectFile, FramingKind, FramingSection, MessageSection, OneOrMany, ReplySection,
    ValuesSection,
};
use super::framing::{ByteOrder, Framing};
use super::messages::{compile_command, compile_reply, invalid, valid_name};
use super::values::{Enums, ValueFormat};
use super::{Command, Dialect, DialectError, Reply};
use crate::codec::parse_tree;

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

pub(super) fn compile(file: DialectFile, origin: &str) -> Result<Dialect, DialectError> {
    if !valid_name(&file.name) {
        return Err(invalid(origin, "name", "1 to 64 letters, digits, _ or -"));
    }
    let (framing, max, order) = framing(&file.framing, origin)?;
    let format = value_format(&file.values, origin)?;
    let enums = enums(file.enums, origin)?;
    let kind = file.framing.kind;
    let (commands, replies) = messages(&file.command, &file.reply, kind, order, &enums, origin)?;
    let named = Named {
        origin,
        commands: &commands,
        replies: &replies,
    };
    let sequence = sequence::compile(&file.sequence, &named)?;
    sequence::check_correlation(file.correlation, &sequence, &named)?;
    let status = status::compile(&file.status, &named)?;
    let keepalive = status::keepalive(file.connection.keepalive.as_ref(), &named)?;
    let abort = abort::compile(
        file.abort.as_ref(),
        &sequence,
        &status,
        keepalive.as_ref(),
        &named,
    )?;
    let fence = fence::compile(file.fence.as_ref(), &sequence, abort.as_ref(), &named)?;
    if let Some(banner) = &file.connection.banner {
        check_banner(banner, kind, &framing, max, origin)?;
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
        abort,
        fence,
    })
}

/// The compiled messages, found by the names the rest of the file gives them.
struct Named<'a> {
    /// Where the dialect comes from, for errors.
    origin: &'a str,
    /// The `[[command]]` messages, in the file's order.
    commands: &'a [Command],
    /// The `[[reply]]` messages, in the file's order.
    replies: &'a [Reply],
}

impl Named<'_> {
    /// The index of the command called `name`, or an error naming `field`.
    fn command(&self, field: &str, name: &str) -> Result<usize, DialectError> {
        self.commands
            .iter()
            .position(|c| c.name == name)
            .ok_or_else(|| {
                invalid(
                    self.origin,
                    field,
                    format!("no [[command]] is named {name:?}"),
                )
            })
    }

    /// The index of the reply called `name`, or an error naming `field`.
    fn reply(&self, field: &str, name: &str) -> Result<usize, DialectError> {
        self.replies
            .iter()
            .position(|r| r.name == name)
            .ok_or_else(|| {
                invalid(
                    self.origin,
                    field,
                    format!("no [[reply]] is named {name:?}"),
                )
            })
    }
}

/// The `[framing]` section: the framing, the largest message and the byte order of
/// binary fields.
fn framing(f: &FramingSection, origin: &str) -> Result<(Framing, usize, ByteOrder), DialectError> {
    let max = f.max_message_bytes.unwrap_or(64 * 1024);
    if !(16..=16 * 1024 * 1024).contains(&max) {
        return Err(invalid(
            origin,
            "framing.max_message_bytes",
            "from 16 to 16777216",
        ));
    }
    let order = f.byte_order.unwrap_or(ByteOrder::Big);
    only_for_its_kind(f, origin)?;
    let framing = match f.kind {
        FramingKind::Xml => Framing::Xml,
        FramingKind::Line => {
            let terminator = unescape_bytes(f.terminator.as_deref().unwrap_or("\n"))
                .map_err(|e| invalid(origin, "framing.terminator", e))?;
            if terminator.is_empty() || terminator.len() > 4 {
                return Err(invalid(origin, "framing.terminator", "1 to 4 bytes"));
            }
            Framing::Line { terminator }
        }
        FramingKind::LengthPrefix => {
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
    Ok((framing, max, order))
}

/// A framing field given for a kind it does not belong to is an error.
fn only_for_its_kind(f: &FramingSection, origin: &str) -> Result<(), DialectError> {
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
    if f.kind != FramingKind::LengthPrefix {
        only("prefix_bytes", f.prefix_bytes.is_some(), "length_prefix")?;
        only("byte_order", f.byte_order.is_some(), "length_prefix")?;
        only(
            "prefix_counts_itself",
            f.prefix_counts_itself.is_some(),
            "length_prefix",
        )?;
    }
    if f.kind != FramingKind::Line {
        only("terminator", f.terminator.is_some(), "line")?;
    }
    Ok(())
}

/// The `[values]` section: how numbers and booleans are written.
fn value_format(values: &ValuesSection, origin: &str) -> Result<ValueFormat, DialectError> {
    let format = ValueFormat {
        decimals: values.decimals,
        true_text: values.true_text.clone().unwrap_or_else(|| "true".into()),
        false_text: values.false_text.clone().unwrap_or_else(|| "false".into()),
    };
    if format.decimals.is_some_and(|d| d > 17) {
        return Err(invalid(origin, "values.decimals", "at most 17"));
    }
    Ok(format)
}

/// The `[enums]` tables: each value's wire forms, none standing for two values.
fn enums(
    tables: BTreeMap<String, BTreeMap<String, OneOrMany>>,
    origin: &str,
) -> Result<Enums, DialectError> {
    let mut enums = Enums::default();
    for (table, entries) in tables {
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
        let mut seen = BTreeSet::new();
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
    Ok(enums)
}

/// The `[[command]]` and `[[reply]]` messages; no two replies share a name.
fn messages(
    command: &[MessageSection],
    reply: &[ReplySection],
    kind: FramingKind,
    order: ByteOrder,
    enums: &Enums,
    origin: &str,
) -> Result<(Vec<Command>, Vec<Reply>), DialectError> {
    let mut commands = Vec::new();
    for (i, c) in command.iter().enumerate() {
        commands.push(compile_command(
            origin, i, c, kind, order, enums, &commands,
        )?);
    }
    let mut replies: Vec<Reply> = Vec::new();
    for (i, r) in reply.iter().enumerate() {
        let reply = compile_reply(origin, i, r, kind, order, enums)?;
        if replies.iter().any(|o| o.name == reply.name) {
            return Err(invalid(
                origin,
                format!("reply[{i}].name"),
                format!("{:?} is used twice", reply.name),
            ));
        }
        replies.push(reply);
    }
    Ok((commands, replies))
}

/// `connection.banner`: what the controller says first, one message of its framing.
fn check_banner(
    banner: &str,
    kind: FramingKind,
    framing: &Framing,
    max: usize,
    origin: &str,
) -> Result<(), DialectError> {
    if banner.is_empty() || banner.len() > max {
        return Err(invalid(
            origin,
            "connection.banner",
            "1 byte up to max_message_bytes",
        ));
    }
    if kind == FramingKind::LengthPrefix {
        return Err(invalid(
            origin,
            "connection.banner",
            "a banner is text, not for length_prefix framing",
        ));
    }
    if kind == FramingKind::Xml && parse_tree(banner.as_bytes()).is_err() {
        return Err(invalid(
            origin,
            "connection.banner",
            "with xml framing the banner is one XML document",
        ));
    }
    if let Framing::Line { terminator } = framing {
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
    Ok(())
}

fn template_name(name: &str) -> bool {
    name.chars().next().is_some_and(|c| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
}

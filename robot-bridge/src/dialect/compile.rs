//! Checking a dialect file and compiling it into a [`Dialect`]: every error names the
//! field and the problem.

use super::file::{Correlation, DialectFile, FramingKind, Outcome, StatusSource};
use super::framing::{ByteOrder, Framing};
use super::messages::{
    captures, compile_command, compile_reply, invalid, templates_of, valid_name,
};
use super::values::{Enums, ValueFormat};
use super::{
    Abort, Command, Dialect, DialectError, Element, Fence, Keepalive, Reply, Sending, Status,
};
use crate::codec::parse_tree;
use std::time::Duration;

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
            if matches!(
                replies[r].outcome,
                Outcome::Status | Outcome::Ignore | Outcome::Fence
            ) {
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
    // Correlation: with ids, every message of the sequence carries the id, and so does at
    // least one answer of each (a status poll or keep-alive need not). An answer without
    // it (a `NAK` that names no command) answers the step whose message has had no
    // answer with its id yet, the oldest such (docs/dialects.md, section 4.4).
    if file.correlation == Correlation::Id {
        for element in &sequence {
            let c = &commands[element.command];
            let names: Vec<String> = templates_of(&c.body)
                .iter()
                .flat_map(|t| t.names())
                .map(|(n, _)| n)
                .collect();
            if !names.iter().any(|n| n == "id") {
                return Err(invalid(
                    origin,
                    format!("command {:?}", c.name),
                    "correlation = \"id\": every command of the sequence carries {id}",
                ));
            }
            let with_id = element.expect.iter().any(|&r| {
                let r = &replies[r];
                r.body
                    .as_ref()
                    .map(|b| captures(b, r.regex.as_ref()))
                    .unwrap_or_default()
                    .iter()
                    .any(|n| n == "id")
            });
            if !with_id {
                return Err(invalid(
                    origin,
                    format!("command {:?}", c.name),
                    "correlation = \"id\": at least one answer of each element of the sequence carries {id} (an answer without it answers the oldest step not yet answered with its id)",
                ));
            }
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
    let abort = match &file.abort {
        None => None,
        Some(a) => {
            let command = command_named("abort.send", &a.send)?;
            let mut users = sequence
                .iter()
                .enumerate()
                .filter(|(_, e)| e.command == command)
                .map(|(i, _)| format!("sequence[{i}]"))
                .collect::<Vec<_>>();
            if matches!(status, Status::Polled { command: c, .. } if c == command) {
                users.push("status.poll".into());
            }
            if keepalive.as_ref().is_some_and(|k| k.command == command) {
                users.push("connection.keepalive".into());
            }
            if let Some(user) = users.first() {
                return Err(invalid(
                    origin,
                    "abort.send",
                    format!("{:?} is also sent by {user}: the abort needs a message of its own, or the controller could not tell it", a.send),
                ));
            }
            let mut expect = Vec::new();
            for name in &a.expect {
                let r = reply_named("abort.expect", name)?;
                let outcome = replies[r].outcome;
                if !matches!(outcome, Outcome::Accepted | Outcome::Rejected) {
                    return Err(invalid(
                        origin,
                        "abort.expect",
                        format!("{name:?} is a {} reply; the abort's own answer is `accepted` (the controller stopped) or `rejected` (it had nothing to stop)", format!("{outcome:?}").to_lowercase()),
                    ));
                }
                let step = sequence
                    .iter()
                    .position(|e| e.expect.contains(&r))
                    .map(|i| format!("sequence[{i}]"));
                let keep = keepalive
                    .as_ref()
                    .is_some_and(|k| k.expect.contains(&r))
                    .then(|| "connection.keepalive".to_string());
                if let Some(other) = step.or(keep) {
                    return Err(invalid(
                        origin,
                        "abort.expect",
                        format!("{name:?} also answers {other}: the abort's answer must be told apart from the other answers"),
                    ));
                }
                expect.push(r);
            }
            Some(Abort { command, expect })
        }
    };
    let fence = match &file.fence {
        None => None,
        Some(f) => {
            let fence = Fence {
                claim: command_named("fence.claim", &f.claim)?,
                heartbeat: command_named("fence.heartbeat", &f.heartbeat)?,
                step_status: command_named("fence.step_status", &f.step_status)?,
                granted: reply_named("fence.granted", &f.granted)?,
                refused: reply_named("fence.refused", &f.refused)?,
                step_state: reply_named("fence.step_state", &f.step_state)?,
                stale: reply_named("fence.stale", &f.stale)?,
            };
            for (field, r) in [
                ("fence.granted", fence.granted),
                ("fence.refused", fence.refused),
                ("fence.step_state", fence.step_state),
            ] {
                if replies[r].outcome != Outcome::Fence {
                    return Err(invalid(
                        origin,
                        field,
                        "a fence reply has outcome = \"fence\"",
                    ));
                }
            }
            if !matches!(
                replies[fence.stale].outcome,
                Outcome::Failed | Outcome::Rejected
            ) {
                return Err(invalid(
                    origin,
                    "fence.stale",
                    "the stale-epoch refusal has outcome = \"failed\" or \"rejected\"",
                ));
            }
            if !sequence.iter().any(|e| e.expect.contains(&fence.stale)) {
                return Err(invalid(
                    origin,
                    "fence.stale",
                    "the stale-epoch refusal answers a command: put it in the sequence's expect",
                ));
            }
            let used = sequence
                .iter()
                .map(|e| e.command)
                .chain(abort.as_ref().map(|a| a.command));
            for c in used {
                if [fence.claim, fence.heartbeat, fence.step_status].contains(&c) {
                    return Err(invalid(origin, "fence", format!("{:?} is also a step's or the abort's message: the fence needs messages of its own", commands[c].name)));
                }
            }
            Some(fence)
        }
    };
    if replies.iter().any(|r| r.outcome == Outcome::Fence) && fence.is_none() {
        return Err(invalid(
            origin,
            "reply",
            "an outcome = \"fence\" reply needs a [fence] section",
        ));
    }
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
        abort,
        fence,
    })
}

fn template_name(name: &str) -> bool {
    name.chars().next().is_some_and(|c| c.is_ascii_lowercase())
        && name
            .chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_')
}

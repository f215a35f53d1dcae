//! The `[[sequence]]`: the messages one step takes, each with the replies it expects;
//! and, with `correlation = "id"`, the id each of them carries.

use std::time::Duration;

use super::super::file::{Correlation, ElementSection, Outcome};
use super::super::messages::{captures, invalid, templates_of};
use super::super::{DialectError, Element, Reply, Sending};
use super::Named;

/// The sequence's elements, one of them starting the action.
pub(super) fn compile(
    elements: &[ElementSection],
    named: &Named<'_>,
) -> Result<Vec<Element>, DialectError> {
    if elements.is_empty() {
        return Err(invalid(named.origin, "sequence", "at least one element"));
    }
    let mut sequence = Vec::new();
    for (i, e) in elements.iter().enumerate() {
        sequence.push(element(i, e, named)?);
    }
    let last = sequence.last().expect("not empty");
    if !last
        .expect
        .iter()
        .any(|&r| named.replies[r].outcome == Outcome::Done)
    {
        return Err(invalid(
            named.origin,
            format!("sequence[{}].expect", sequence.len() - 1),
            "the last element must expect a `done` reply, or no step could end",
        ));
    }
    mark_start(&mut sequence, named.origin)?;
    Ok(sequence)
}

/// One element: a message sent once or polled, and the answers it expects.
fn element(i: usize, e: &ElementSection, named: &Named<'_>) -> Result<Element, DialectError> {
    let origin = named.origin;
    let at = format!("sequence[{i}]");
    let (sending, name) = match (&e.send, &e.poll, e.every_ms) {
        (Some(name), None, None) => (Sending::Send, name),
        (None, Some(name), Some(ms)) if ms > 0 => (Sending::Poll(Duration::from_millis(ms)), name),
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
    let command = named.command(
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
    let expect = expected_answers(&at, &e.expect, named)?;
    let outcomes: Vec<Outcome> = expect.iter().map(|&r| named.replies[r].outcome).collect();
    if outcomes.iter().all(|&o| o == Outcome::Departed) {
        return Err(invalid(
            origin,
            format!("{at}.expect"),
            "a `departed` reply does not end the element: expect another answer too",
        ));
    }
    if let Sending::Poll(_) = sending {
        if outcomes.contains(&Outcome::Departed) {
            return Err(invalid(
                origin,
                format!("{at}.expect"),
                "a poll cannot expect a `departed` reply: the command's own element says it",
            ));
        }
        if !outcomes.contains(&Outcome::Running) {
            return Err(invalid(
                origin,
                format!("{at}.expect"),
                "a poll expects a `running` reply (the action goes on)",
            ));
        }
    }
    Ok(Element {
        sending,
        command,
        expect,
        starts: e.starts,
    })
}

/// An element's expected replies: answers only, not the kinds that may come at any time.
fn expected_answers(
    at: &str,
    names: &[String],
    named: &Named<'_>,
) -> Result<Vec<usize>, DialectError> {
    let mut expect = Vec::new();
    for name in names {
        let r = named.reply(&format!("{at}.expect"), name)?;
        if matches!(
            named.replies[r].outcome,
            Outcome::Status | Outcome::Ignore | Outcome::Fence
        ) {
            return Err(invalid(
                named.origin,
                format!("{at}.expect"),
                format!(
                    "{name:?} is a {:?} reply, which may come at any time; expect answers only",
                    named.replies[r].outcome
                )
                .to_lowercase(),
            ));
        }
        expect.push(r);
    }
    Ok(expect)
}

/// The element that starts the action: the one marked so, or else the last `send`.
fn mark_start(sequence: &mut [Element], origin: &str) -> Result<(), DialectError> {
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
            Ok(())
        }
        1 => Ok(()),
        _ => Err(invalid(
            origin,
            "sequence",
            "only one element starts the action",
        )),
    }
}

/// Correlation: with ids, every message of the sequence carries the id, and so does at
/// least one answer of each (a status poll or keep-alive need not). An answer without
/// it (a `NAK` that names no command) answers the step whose message has had no answer
/// with its id yet, the oldest such (docs/dialects.md, section 4.4).
pub(super) fn check_correlation(
    correlation: Correlation,
    sequence: &[Element],
    named: &Named<'_>,
) -> Result<(), DialectError> {
    if correlation != Correlation::Id {
        return Ok(());
    }
    for element in sequence {
        let c = &named.commands[element.command];
        let names: Vec<String> = templates_of(&c.body)
            .iter()
            .flat_map(|t| t.names())
            .map(|(n, _)| n)
            .collect();
        if !names.iter().any(|n| n == "id") {
            return Err(invalid(
                named.origin,
                format!("command {:?}", c.name),
                "correlation = \"id\": every command of the sequence carries {id}",
            ));
        }
        let mut answers = element.expect.iter().map(|&r| &named.replies[r]);
        if !answers
            .clone()
            .any(|r| r.outcome != Outcome::Departed && carries_id(r))
        {
            return Err(invalid(
                named.origin,
                format!("command {:?}", c.name),
                "correlation = \"id\": at least one answer of each element of the sequence carries {id} (an answer without it answers the oldest step not yet answered with its id)",
            ));
        }
        // A departure names its command: it is no answer of the oldest step.
        if let Some(r) = answers.find(|r| r.outcome == Outcome::Departed && !carries_id(r)) {
            return Err(invalid(
                named.origin,
                format!("reply {:?}", r.name),
                "correlation = \"id\": a `departed` reply carries {id}, the command whose move left",
            ));
        }
    }
    Ok(())
}

/// Whether `reply` reads the command's `{id}` (from its text, or its regex's groups).
fn carries_id(reply: &Reply) -> bool {
    reply
        .body
        .as_ref()
        .map(|b| captures(b, reply.regex.as_ref()))
        .unwrap_or_default()
        .iter()
        .any(|n| n == "id")
}

//! The `[abort]` section: the message that stops the action under way, and its own
//! answers, told apart from every other message and answer.

use super::super::file::{AbortSection, Outcome};
use super::super::messages::invalid;
use super::super::{Abort, DialectError, Element, Keepalive, Status};
use super::Named;

/// The abort, if the dialect has one.
pub(super) fn compile(
    section: Option<&AbortSection>,
    sequence: &[Element],
    status: &Status,
    keepalive: Option<&Keepalive>,
    named: &Named<'_>,
) -> Result<Option<Abort>, DialectError> {
    let Some(a) = section else {
        return Ok(None);
    };
    let command = named.command("abort.send", &a.send)?;
    let mut users = sequence
        .iter()
        .enumerate()
        .filter(|(_, e)| e.command == command)
        .map(|(i, _)| format!("sequence[{i}]"))
        .collect::<Vec<_>>();
    if matches!(status, Status::Polled { command: c, .. } if *c == command) {
        users.push("status.poll".into());
    }
    if keepalive.is_some_and(|k| k.command == command) {
        users.push("connection.keepalive".into());
    }
    if let Some(user) = users.first() {
        return Err(invalid(
            named.origin,
            "abort.send",
            format!("{:?} is also sent by {user}: the abort needs a message of its own, or the controller could not tell it", a.send),
        ));
    }
    let mut expect = Vec::new();
    for name in &a.expect {
        expect.push(answer(name, sequence, keepalive, named)?);
    }
    Ok(Some(Abort { command, expect }))
}

/// One of the abort's answers: `accepted` or `rejected`, and no other message's answer.
fn answer(
    name: &str,
    sequence: &[Element],
    keepalive: Option<&Keepalive>,
    named: &Named<'_>,
) -> Result<usize, DialectError> {
    let r = named.reply("abort.expect", name)?;
    let outcome = named.replies[r].outcome;
    if !matches!(outcome, Outcome::Accepted | Outcome::Rejected) {
        return Err(invalid(
            named.origin,
            "abort.expect",
            format!("{name:?} is a {} reply; the abort's own answer is `accepted` (the controller stopped) or `rejected` (it had nothing to stop)", format!("{outcome:?}").to_lowercase()),
        ));
    }
    let step = sequence
        .iter()
        .position(|e| e.expect.contains(&r))
        .map(|i| format!("sequence[{i}]"));
    let keep = keepalive
        .is_some_and(|k| k.expect.contains(&r))
        .then(|| "connection.keepalive".to_string());
    if let Some(other) = step.or(keep) {
        return Err(invalid(
            named.origin,
            "abort.expect",
            format!("{name:?} also answers {other}: the abort's answer must be told apart from the other answers"),
        ));
    }
    Ok(r)
}

//! Where the controller's state comes from (`[status]`), and the keep-alive that tells
//! the connection is alive (`connection.keepalive`).

use std::time::Duration;

use super::super::file::{KeepaliveSection, Outcome, StatusSection, StatusSource};
use super::super::messages::invalid;
use super::super::{DialectError, Keepalive, Status};
use super::Named;

/// The `[status]` section: pushed, polled, or the connection itself.
pub(super) fn compile(section: &StatusSection, named: &Named<'_>) -> Result<Status, DialectError> {
    let origin = named.origin;
    let status = match (section.source, &section.poll, section.every_ms) {
        (StatusSource::Pushed, None, None) => Status::Pushed,
        (StatusSource::Connection, None, None) => Status::Connection,
        (StatusSource::Polled, Some(name), Some(ms)) if ms > 0 => Status::Polled {
            command: named.command("status.poll", name)?,
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
    if status != Status::Connection && !named.replies.iter().any(|r| r.outcome == Outcome::Status) {
        return Err(invalid(
            origin,
            "status",
            "a pushed or polled state needs a [[reply]] with outcome = \"status\"",
        ));
    }
    Ok(status)
}

/// `connection.keepalive`: a message sent every so often, and its answers.
pub(super) fn keepalive(
    section: Option<&KeepaliveSection>,
    named: &Named<'_>,
) -> Result<Option<Keepalive>, DialectError> {
    let Some(k) = section else {
        return Ok(None);
    };
    if k.every_ms == 0 {
        return Err(invalid(
            named.origin,
            "connection.keepalive.every_ms",
            "more than 0",
        ));
    }
    let mut expect = Vec::new();
    for name in &k.expect {
        expect.push(named.reply("connection.keepalive.expect", name)?);
    }
    Ok(Some(Keepalive {
        command: named.command("connection.keepalive.send", &k.send)?,
        every: Duration::from_millis(k.every_ms),
        expect,
    }))
}

//! The `[fence]` section: the messages that claim the controller, keep the claim and ask
//! a step's state, and the replies that answer them.

use super::super::file::{FenceSection, Outcome};
use super::super::messages::invalid;
use super::super::{Abort, DialectError, Element, Fence};
use super::Named;

/// The fence, if the dialect has one; a `fence` reply without it is an error.
pub(super) fn compile(
    section: Option<&FenceSection>,
    sequence: &[Element],
    abort: Option<&Abort>,
    named: &Named<'_>,
) -> Result<Option<Fence>, DialectError> {
    let fence = match section {
        None => None,
        Some(f) => Some(fence(f, sequence, abort, named)?),
    };
    if named.replies.iter().any(|r| r.outcome == Outcome::Fence) && fence.is_none() {
        return Err(invalid(
            named.origin,
            "reply",
            "an outcome = \"fence\" reply needs a [fence] section",
        ));
    }
    Ok(fence)
}

fn fence(
    f: &FenceSection,
    sequence: &[Element],
    abort: Option<&Abort>,
    named: &Named<'_>,
) -> Result<Fence, DialectError> {
    let origin = named.origin;
    let fence = Fence {
        claim: named.command("fence.claim", &f.claim)?,
        heartbeat: named.command("fence.heartbeat", &f.heartbeat)?,
        step_status: named.command("fence.step_status", &f.step_status)?,
        granted: named.reply("fence.granted", &f.granted)?,
        refused: named.reply("fence.refused", &f.refused)?,
        step_state: named.reply("fence.step_state", &f.step_state)?,
        stale: named.reply("fence.stale", &f.stale)?,
    };
    for (field, r) in [
        ("fence.granted", fence.granted),
        ("fence.refused", fence.refused),
        ("fence.step_state", fence.step_state),
    ] {
        if named.replies[r].outcome != Outcome::Fence {
            return Err(invalid(
                origin,
                field,
                "a fence reply has outcome = \"fence\"",
            ));
        }
    }
    if !matches!(
        named.replies[fence.stale].outcome,
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
        .chain(abort.map(|a| a.command));
    for c in used {
        if [fence.claim, fence.heartbeat, fence.step_status].contains(&c) {
            return Err(invalid(origin, "fence", format!("{:?} is also a step's or the abort's message: the fence needs messages of its own", named.commands[c].name)));
        }
    }
    Ok(fence)
}

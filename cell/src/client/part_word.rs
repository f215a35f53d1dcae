//! `cell part ORDER --at LOCATION`: an operator's word on where an order's lost part is
//! (docs/material-flow.md, section 2). The order records it with who said it, in its
//! journal, and goes on from there; a word on a part that is not lost, on a location
//! that is neither end of its lost move, or on the origin of a move that had departed
//! whose place is another part's now, is refused and changes nothing.

use std::time::Duration;

use schemas::keys::CellKeys;
use schemas::layout::LocationId;

use crate::client::ask::AskError;

/// Tells the order-node hosting `order` that its lost part is at `location`; `by` says
/// who tells, for the order's journal. Asked until an order-node answers (one that is
/// restarting or handed over answers `unavailable`); asked again after it was
/// recorded, it is refused: the part is no longer lost, and the refusal says where it
/// is.
pub async fn tell(
    session: &zenoh::Session,
    keys: &CellKeys,
    order: &str,
    location: &LocationId,
    by: &str,
    timeout: Duration,
) -> Result<schemas::PartWordReply, AskError> {
    let failed = |e: &dyn std::fmt::Display| AskError::Failed(format!("{e:#}"));
    let word = schemas::PartWord {
        location: location.clone(),
    };
    let payload = serde_json::to_vec(&word).expect("serializes");
    let asked =
        crate::client::ask::until_answered(session, &keys.part(order), Some(payload), by, timeout)
            .await
            .map_err(|e| failed(&e))?;
    crate::client::ask::answer_of(asked, || {
        format!(
            "{} ({order}: unknown order, its order-node is down, or this identity may not say \
             where parts are)",
            keys.part(order)
        )
    })
}

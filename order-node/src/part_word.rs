//! An operator's word on where a lost part is (`cell part ORDER --at LOCATION`), as an
//! event of the order's own task.
//!
//! A part is lost when its move ended without its transporter saying where it is (the
//! transporter vanished mid-move, or the move failed on the way): the order holds until
//! the transporter, once back, says what became of the move, or an operator who looked
//! says where the part is. The word names the lost move's origin (the part never left)
//! or its destination (it arrived): those are where the part's places are held.
//!
//! As with a cancel ([`crate::cancel`]), the node's query handler writes nothing: it
//! checks the word against what the order last committed (an order whose part is not
//! lost, or a location that is neither end of the lost move, is refused `invalid` and
//! nothing changes), then sends a [`WordAsk`] to the order's task and waits (bounded).
//! The task, which alone writes the order's progress and is waiting for its lost part,
//! records where the part is and who said so in the journal (the order's audit trail,
//! `part_found`), answers, and goes on from there. A word that the part is back at the
//! origin of a move that had departed (its place there released) is taken only once
//! the task has reserved that place again; refused `unavailable` when it cannot be, and
//! nothing changes.

use std::time::Duration;

use schemas::layout::LocationId;
use schemas::{ErrorCode, PartPlace, PartWordReply};
use tokio::sync::{mpsc, oneshot};

use crate::progress::OrderProgress;

/// How many words may wait for one order's task.
pub const WORD_MAILBOX: usize = 4;

/// How long the node waits for an order's task to take a word.
pub const ANSWER_WITHIN: Duration = Duration::from_secs(5);

/// The answer to a word: the reply to send, or the error code and why.
pub type WordAnswer = Result<PartWordReply, (ErrorCode, String)>;

/// An operator's word for the order's task, with where its answer goes.
#[derive(Debug)]
pub struct WordAsk {
    /// The lost move the word is about (its conversation): a word that reaches the task
    /// after that part was found otherwise is refused, not applied to a later loss.
    pub conversation_id: String,
    /// Where the operator says the part is.
    pub location: LocationId,
    /// Who says it.
    pub by: String,
    /// The answer.
    pub reply: oneshot::Sender<WordAnswer>,
}

/// A new mailbox of words for one run of an order's task.
pub fn mailbox() -> (mpsc::Sender<WordAsk>, mpsc::Receiver<WordAsk>) {
    mpsc::channel(WORD_MAILBOX)
}

/// Checks a word against the order as last committed: the lost move's conversation it
/// is about, or why it is refused (`invalid`: nothing changes).
pub fn check(
    name: &str,
    progress: &OrderProgress,
    location: &LocationId,
) -> Result<String, (ErrorCode, String)> {
    let invalid = |why: String| (ErrorCode::Invalid, format!("{name}: {why}"));
    let Some(part) = &progress.part else {
        return Err(invalid(
            "its product moves no part (the plan does not say moves_parts)".into(),
        ));
    };
    let (PartPlace::Lost { from, to, .. }, Some(moving)) = (&part.place, &part.moving) else {
        return Err(invalid(format!(
            "its part is not lost: it is {}; nothing changed",
            part.place
        )));
    };
    if location != from && location != to {
        return Err(invalid(format!(
            "its part was moving from {from} to {to}: say which of the two it is at (put it \
             back at one of them first if it is elsewhere); nothing changed"
        )));
    }
    Ok(moving.conversation_id.clone())
}

/// Why a word on `name`'s part is refused when the node does not host it: it has
/// `ended` (only its journal has it: its part left the cell with it), or it is unknown.
pub fn not_hosted(name: &str, node: &str, ended: bool) -> (ErrorCode, String) {
    if ended {
        let why = format!("{name}: the order has ended, its part with it; nothing changed");
        (ErrorCode::Invalid, why)
    } else {
        let why = format!("{name} is not an order of {node}");
        (ErrorCode::UnknownOrder, why)
    }
}

/// Asks the task behind `words` to take the word: its answer, or `unavailable` when it
/// is not running or does not answer in time.
pub async fn ask(
    words: &mpsc::Sender<WordAsk>,
    name: &str,
    conversation_id: String,
    location: LocationId,
    by: String,
) -> WordAnswer {
    let unavailable = |why: &str| (ErrorCode::Unavailable, format!("{name}: {why}; ask again"));
    let (reply, answer) = oneshot::channel();
    let ask = WordAsk {
        conversation_id,
        location,
        by,
        reply,
    };
    match words.try_send(ask) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(_)) => {
            return Err(unavailable(
                "words on its part are waiting for the order already",
            ))
        }
        Err(mpsc::error::TrySendError::Closed(_)) => {
            return Err(unavailable("the order's task is restarting"))
        }
    }
    match tokio::time::timeout(ANSWER_WITHIN, answer).await {
        Ok(Ok(answer)) => answer,
        Ok(Err(_)) => Err(unavailable("the order's task ended before it answered")),
        Err(_) => Err(unavailable(
            "the order's task did not take the word in time",
        )),
    }
}

//! An operator's cancel of an order, as an event of the order's own task.
//!
//! The node's query handler does not write the order's progress: it sends a
//! [`CancelAsk`] to the order's mailbox and waits (bounded) for the task's answer. The
//! order's task, the only writer of its progress, records the cancel in the journal
//! (`cancel_requested`), answers, and only then stops its attempt (a running step is
//! let finish). A cancel asked again is answered from what was recorded; one asked
//! while the task is not running (between a journal error and its restart) is answered
//! `unavailable`, and `cell cancel` asks again.

use std::time::Duration;

use schemas::{CancelReply, ErrorCode};
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::context::{OrderContext, Progress};
use crate::progress::{OrderProgress, Phase};

/// How many cancels may wait for one order's task.
pub const CANCEL_MAILBOX: usize = 8;

/// How long the node waits for an order's task to answer a cancel.
pub const ANSWER_WITHIN: Duration = Duration::from_secs(2);

/// A cancel for the order's task, with where its answer goes.
#[derive(Debug)]
pub struct CancelAsk {
    /// The answer: the reply to send, or the error code and why.
    pub reply: oneshot::Sender<Result<CancelReply, (ErrorCode, String)>>,
}

/// A new mailbox of cancels for one run of an order's task.
pub fn mailbox() -> (mpsc::Sender<CancelAsk>, mpsc::Receiver<CancelAsk>) {
    mpsc::channel(CANCEL_MAILBOX)
}

/// Asks the task behind `asks` to cancel its order: its answer, or `unavailable` when
/// it is not running or does not answer in time.
pub async fn ask(
    asks: &mpsc::Sender<CancelAsk>,
    name: &str,
) -> Result<CancelReply, (ErrorCode, String)> {
    let unavailable = |why: &str| (ErrorCode::Unavailable, format!("{name}: {why}; ask again"));
    let (reply, answer) = oneshot::channel();
    match asks.try_send(CancelAsk { reply }) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(_)) => {
            return Err(unavailable("cancels are waiting for the order already"))
        }
        Err(mpsc::error::TrySendError::Closed(_)) => {
            return Err(unavailable("the order's task is restarting"))
        }
    }
    match tokio::time::timeout(ANSWER_WITHIN, answer).await {
        Ok(Ok(answer)) => answer,
        Ok(Err(_)) => Err(unavailable("the order's task ended before it answered")),
        Err(_) => Err(unavailable("the order's task did not answer in time")),
    }
}

/// Part of the order's task: answers the cancels of `asks` until the task ends. Each is
/// recorded in the journal before it is answered, then `operator_cancel` stops the
/// order's attempt.
pub async fn answer_cancels(
    ctx: &OrderContext,
    progress: &Progress,
    mut asks: mpsc::Receiver<CancelAsk>,
    operator_cancel: &CancellationToken,
) {
    while let Some(ask) = asks.recv().await {
        let answer = record(ctx, progress).await;
        if answer.as_ref().is_ok_and(|reply| reply.cancelled) {
            operator_cancel.cancel();
        }
        if ask.reply.send(answer).is_err() {
            warn!(holon = %progress.get().holon, "the cancel's asker left before the answer; it asks again and is answered from the journal");
        }
    }
}

/// Records the cancel (once) and says what happens next.
async fn record(
    ctx: &OrderContext,
    progress: &Progress,
) -> Result<CancelReply, (ErrorCode, String)> {
    let (name, ended, requested) = {
        let p = progress.get();
        (
            p.holon.name().to_string(),
            p.status.is_final(),
            p.cancel_requested,
        )
    };
    if ended {
        return Ok(refused(&name, &progress.get()));
    }
    if !requested {
        // Written first: on a journal error nothing changed and the cancel is refused.
        ctx.commit(progress, |p| p.cancel_requested = true)
            .await
            .map_err(|e| {
                (
                    ErrorCode::Internal,
                    format!("cannot record the cancel: {e}"),
                )
            })?;
        info!(holon = %progress.get().holon, "cancel requested by an operator, recorded");
    }
    let p = progress.get();
    Ok(CancelReply {
        order: name,
        cancelled: true,
        status: p.status,
        detail: match p.phase {
            Phase::Started(_) => {
                "its running step finishes first, then it ends as cancelled".into()
            }
            _ => "its bookings are cancelled and it ends as cancelled".into(),
        },
    })
}

/// The answer to a cancel of an order that has ended.
pub fn refused(name: &str, progress: &OrderProgress) -> CancelReply {
    CancelReply {
        order: name.to_string(),
        cancelled: false,
        status: progress.status,
        detail: format!("the order has already ended ({:?})", progress.status),
    }
}

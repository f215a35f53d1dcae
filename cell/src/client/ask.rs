//! Asking the cell's order-nodes: a `get` asked again until one answers.
//!
//! No answer at all means no order-node's queryable was reached: the node may be
//! restarting, or the router's routes may be settling for a moment; an `unavailable`
//! answer means the node is being handed over to its successor (an upgrade) and
//! nothing was done. What the cell asks them (a work order, a cancel) is safe to ask
//! again, so it is, every 100 ms (or after the answer's `retry_after_ms`), until
//! `timeout`.

use std::time::Duration;

use anyhow::{anyhow, Result};
use tokio::time::Instant;
use zenoh::query::Reply;

/// Why an order-node did not do what it was asked (a work order, a cancel).
#[derive(Debug, thiserror::Error)]
pub enum AskError {
    /// An order-node answered and refused it (nothing changed).
    #[error("the order-node refused ({code}): {message}")]
    Refused {
        code: schemas::ErrorCode,
        message: String,
    },
    /// No order-node answered within the time.
    #[error("no order-node answered on {0}")]
    NoAnswer(String),
    /// The question could not be asked, or the answer not read.
    #[error("{0}")]
    Failed(String),
}

/// An order-node's answer read as a `T` (its reply), or why there is none: its refusal,
/// `no_answer` when nobody answered, or an answer that could not be read.
pub fn answer_of<T: serde::de::DeserializeOwned>(
    asked: Option<Reply>,
    no_answer: impl FnOnce() -> String,
) -> Result<T, AskError> {
    match asked {
        Some(reply) => match reply.result() {
            Ok(sample) => serde_json::from_slice(&sample.payload().to_bytes())
                .map_err(|e| AskError::Failed(format!("{e:#}"))),
            Err(err) => Err(AskError::refusal(
                &err.payload().try_to_string().unwrap_or_default(),
            )),
        },
        None => Err(AskError::NoAnswer(no_answer())),
    }
}

impl AskError {
    /// The refusal in an error reply's body (`{"code", "message"}`), or its raw text.
    pub fn refusal(text: &str) -> AskError {
        match serde_json::from_str::<schemas::ErrorReply>(text) {
            Ok(e) => AskError::Refused {
                code: e.code,
                message: e.message,
            },
            Err(_) => AskError::Refused {
                code: schemas::ErrorCode::Other("unknown".into()),
                message: text.to_string(),
            },
        }
    }
}

/// The first reply to a `get` on `key` (with `payload`, and who asks as its attachment,
/// [`schemas::requested_by`]), asked again until one comes or `timeout` passes (`None`).
pub async fn until_answered(
    session: &zenoh::Session,
    key: &str,
    payload: Option<Vec<u8>>,
    by: &str,
    timeout: Duration,
) -> Result<Option<Reply>> {
    let deadline = Instant::now() + timeout;
    loop {
        let mut get = session.get(key).timeout(
            deadline
                .saturating_duration_since(Instant::now())
                .clamp(Duration::from_millis(500), Duration::from_secs(5)),
        );
        if let Some(payload) = &payload {
            get = get.payload(payload.clone());
        }
        if !by.is_empty() {
            get = get.attachment(by.as_bytes().to_vec());
        }
        let mut replies = get
            .with(holon::query::replies())
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let mut pause = Duration::from_millis(100);
        if let Some(reply) = replies.recv().await {
            match unavailable(&reply) {
                Some(retry_after) if Instant::now() + retry_after < deadline => {
                    pause = retry_after;
                }
                _ => return Ok(Some(reply)),
            }
        }
        if Instant::now() >= deadline {
            return Ok(None);
        }
        tokio::time::sleep(pause).await;
    }
}

/// When a reply says `unavailable` (nothing was done), how long to wait before asking
/// again.
fn unavailable(reply: &Reply) -> Option<Duration> {
    let error = reply.result().err()?;
    let body = schemas::ErrorReply::from_json(&error.payload().to_bytes())?;
    (body.code == schemas::ErrorCode::Unavailable)
        .then(|| Duration::from_millis(body.retry_after_ms.unwrap_or(100).clamp(10, 5000)))
}

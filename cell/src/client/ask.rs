//! Asking the cell's order-nodes: a `get` asked again until one answers.
//!
//! No answer at all means no order-node's queryable was reached: the node may be
//! restarting, or the router's routes may be settling for a moment; an `unavailable`
//! answer means the node is being handed over to its successor (an upgrade) and
//! nothing was done. In both cases nothing was done, so the question is asked again,
//! every 100 ms (or after the answer's `retry_after_ms`), until `timeout`. A node that
//! was reached and did not answer in time may have done it (a work order made, slowly):
//! that is said as such ([`AskError::TimedOut`]), never taken for a refusal, and not
//! asked again.

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
    /// No order-node was reached within the time (nothing was asked of any).
    #[error("no order-node answered on {0}")]
    NoAnswer(String),
    /// An order-node was reached but its answer did not come in time: it may have done
    /// what was asked all the same, so it is not asked again.
    #[error("asked on {0}, but the answer did not come in time: it may have been done all the same (look before asking again)")]
    TimedOut(String),
    /// The question could not be asked, or the answer not read.
    #[error("{0}")]
    Failed(String),
}

/// An order-node's answer read as a `T` (its reply), or why there is none: its refusal,
/// `no_answer` (the key asked) when nobody answered or the answer came too late, or an
/// answer that could not be read.
pub fn answer_of<T: serde::de::DeserializeOwned>(
    asked: Option<Reply>,
    no_answer: impl FnOnce() -> String,
) -> Result<T, AskError> {
    match asked {
        Some(reply) => match reply.result() {
            Ok(sample) => serde_json::from_slice(&sample.payload().to_bytes())
                .map_err(|e| AskError::Failed(format!("{e:#}"))),
            Err(_) if timed_out(&reply) => Err(AskError::TimedOut(no_answer())),
            Err(err) => Err(AskError::refusal(
                &err.payload().try_to_string().unwrap_or_default(),
            )),
        },
        None => Err(AskError::NoAnswer(no_answer())),
    }
}

/// Whether `reply` is zenoh's own end of a query whose answer did not come within its
/// timeout (an error reply `Timeout`, not an order-node's refusal, which is JSON): the
/// queryable was reached, and may have acted.
pub fn timed_out(reply: &Reply) -> bool {
    reply
        .result()
        .err()
        .is_some_and(|e| e.payload().to_bytes().as_ref() == b"Timeout")
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
/// Asked again only when nothing was done: no queryable was reached, or one answered
/// `unavailable`; a `get` that timed out ([`timed_out`]) is returned as it is.
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

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use super::*;

    /// A router of its own on a free port: its queryables answer its own `get`s.
    async fn router() -> zenoh::Session {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("a free port")
            .port();
        holon::ZenohSettings {
            mode: holon::Mode::Router,
            listen: vec![format!("tcp/127.0.0.1:{port}")],
            ..holon::ZenohSettings::default()
        }
        .open("ask.test", Duration::from_secs(5))
        .await
        .expect("a router")
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn an_answer_that_comes_too_late_is_not_a_refusal_and_is_not_asked_again() {
        let session = router().await;
        let asked = Arc::new(AtomicUsize::new(0));
        let counted = asked.clone();
        // Reached, and not answered in time (a node busy past the asker's time): the
        // query is held, as a node's queue holds it (one dropped unanswered would end
        // at once, with no reply).
        let held = Arc::new(std::sync::Mutex::new(Vec::new()));
        let holding = held.clone();
        let _slow = session
            .declare_queryable("t/slow")
            .callback(move |query| {
                counted.fetch_add(1, Ordering::SeqCst);
                holding.lock().unwrap().push(query);
            })
            .await
            .unwrap();
        let reply = until_answered(&session, "t/slow", None, "", Duration::from_millis(800))
            .await
            .unwrap();
        assert!(reply.as_ref().is_some_and(timed_out), "{reply:?}");
        let outcome = answer_of::<serde_json::Value>(reply, || "t/slow".into());
        assert!(
            matches!(outcome, Err(AskError::TimedOut(ref key)) if key == "t/slow"),
            "{outcome:?}"
        );
        assert_eq!(
            asked.load(Ordering::SeqCst),
            1,
            "asked again after a timeout"
        );
        held.lock().unwrap().clear();
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn a_refusal_is_a_refusal_and_nobody_reached_is_no_answer() {
        let session = router().await;
        let _refusing = session
            .declare_queryable("t/refusing")
            .callback(|query| {
                use zenoh::Wait;
                let refusal = schemas::ErrorReply::new(schemas::ErrorCode::Quota, "too many");
                query.reply_err(refusal.to_json()).wait().unwrap();
            })
            .await
            .unwrap();
        let reply = until_answered(&session, "t/refusing", None, "", Duration::from_secs(2))
            .await
            .unwrap();
        assert!(!reply.as_ref().is_some_and(timed_out));
        let outcome = answer_of::<serde_json::Value>(reply, || "t/refusing".into());
        assert!(
            matches!(
                outcome,
                Err(AskError::Refused {
                    code: schemas::ErrorCode::Quota,
                    ..
                })
            ),
            "{outcome:?}"
        );
        let reply = until_answered(&session, "t/nobody", None, "", Duration::from_millis(500))
            .await
            .unwrap();
        let outcome = answer_of::<serde_json::Value>(reply, || "t/nobody".into());
        assert!(matches!(outcome, Err(AskError::NoAnswer(_))), "{outcome:?}");
        session.close().await.unwrap();
    }
}

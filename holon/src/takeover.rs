//! A planned hand-over of a holon to its successor process: how a holon is upgraded
//! (new code, new config) while the cell runs, without handing its work back.
//!
//! The protocol, on `holarchy/<cell>/takeover/<kind>/<name>` ([`key`]):
//!
//! | step | successor (started with `--take-over`) | predecessor (the running holon) |
//! |---|---|---|
//! | 1 | loads and checks its config (a bad one: it exits 1, nothing changed), opens its session | serves |
//! | 2 | asks [`take_over`] with a [`Request`] (its data dir, how long it waits) | [`Listener::next`] gives the [`Offer`]; a different data dir is refused, and it serves on |
//! | 3 | waits | stops taking new work (requests get `unavailable` with a retry hint), finishes what it must (a resource: its running step), keeps its bookings |
//! | 4 | waits | declares its [`StandIn`] (answers `unavailable`, retry hint), stops its components, closes its journal, withdraws its token |
//! | 5 | gets `released` ([`Offer::release`]), waits until the token is gone | keeps standing in |
//! | 6 | claims the name, opens the journal, serves, declares its token | sees the token ([`until_successor`]), withdraws the stand-in, exits 0 |
//!
//! If the predecessor cannot finish in time (its running step outlasts the wait), it
//! answers `released: false` with why, and serves on: the upgrade is refused, not half
//! done. Requesters learn that the hand-over is planned from the holon's published
//! state (a resource's `handing_over`) and keep their bookings while it is away, for a
//! bound of their own.
//!
//! Only the holon's own identity may ask (access control grants each identity its own
//! `takeover/<kind>/<name>`), so in a secure cell only the holder of its certificate can
//! replace a holon.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::mpsc;
use tokio::time::Instant;
use tracing::{debug, info, warn};
use zenoh::query::{ConsolidationMode, Query};
use zenoh::sample::SampleKind;

use crate::presence::Holder;

/// How long a predecessor stands in for its successor, at most: a successor that has
/// not declared its token by then has failed to start (its requesters' own bounds then
/// decide what happens to their bookings).
pub const STAND_IN_LIMIT: Duration = Duration::from_secs(30);

/// How long a successor waits, after `released`, for the predecessor's token to go.
const TOKEN_GONE_WITHIN: Duration = Duration::from_secs(5);

/// How long the predecessor may take, beyond the request's `wait_ms` (finishing what it
/// must), to stop its components and close its journal before it answers: the
/// successor waits `wait_ms` plus this for the answer. It covers a resource's five
/// components' shutdown timeouts (5 s each, and 1 s each for one that has to be
/// aborted) with a margin, so a predecessor does not release after its successor gave
/// up (if it ever does, it stands in, exits 1 and is started again).
pub const RELEASE_ALLOWANCE: Duration = Duration::from_secs(45);

/// How long a successor waits for its predecessor's journal to be let go of (the file
/// lock) after `released`: a component that had to be aborted closes it a little later.
pub const JOURNAL_PATIENCE: Duration = Duration::from_secs(10);

/// The exit code of a successor whose predecessor refused to hand over: nothing
/// changed, the predecessor serves on (a supervisor such as `cell up` reports it so).
pub const EXIT_REFUSED: u8 = 3;

/// The key a holon is taken over on, from its presence key: `holarchy/<cell>/alive/<kind>/<name>`
/// or `holarchy/<cell>/host/<program>/<name>` gives `holarchy/<cell>/takeover/<kind>/<name>`.
pub fn key(presence_key: &str) -> String {
    let parts: Vec<&str> = presence_key.splitn(4, '/').collect();
    match parts.as_slice() {
        [root, cell, _, rest] => format!("{root}/{cell}/takeover/{rest}"),
        _ => format!("{presence_key}/takeover"),
    }
}

/// What a successor asks its predecessor.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Request {
    /// The successor process.
    pub successor: Holder,
    /// Its release (e.g. `0.2.0`), for the predecessor's log.
    pub version: String,
    /// Its data directory: the predecessor refuses a successor that would not take over
    /// its journal.
    pub data_dir: Option<PathBuf>,
    /// How long the predecessor may take to finish what it must (a resource: its
    /// running step), or else refuse. The successor waits this plus
    /// [`RELEASE_ALLOWANCE`] for the answer.
    pub wait_ms: u64,
}

/// The predecessor's answer.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Reply {
    /// True: it has stopped, closed its journal and withdrawn its token; the successor
    /// goes on. False: it serves on, and `detail` says why.
    pub released: bool,
    pub detail: String,
    /// The predecessor's release.
    pub version: String,
}

/// Why a take-over did not happen.
#[derive(Debug, thiserror::Error)]
pub enum TakeoverError {
    #[error("the running {holon} refused to hand over: {detail}; it serves on")]
    Refused { holon: String, detail: String },
    #[error("the running {holon} did not answer the hand-over within {waited:?}; it may still hand over, or serve on")]
    NoAnswer { holon: String, waited: Duration },
    #[error(
        "{holon} said it released its name, but its token is still visible after {0:?}",
        TOKEN_GONE_WITHIN
    )]
    StillHeld { holon: String },
    #[error("zenoh: {0}")]
    Zenoh(String),
}

/// How a take-over went.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TakenOver {
    /// The predecessor handed over; its answer.
    From(Reply),
    /// Nobody held the name: the successor starts as a first process would.
    Nobody,
}

/// Asks the holon on `presence_key` (named `holon` in messages) to hand over to this
/// process, waiting at most `request.wait_ms` for it to finish what it must.
pub async fn take_over(
    session: &zenoh::Session,
    presence_key: &str,
    holon: &str,
    request: &Request,
) -> Result<TakenOver, TakeoverError> {
    let zenoh = |e: zenoh::Error| TakeoverError::Zenoh(crate::zenoh_error::describe(&e));
    let ask_timeout = Duration::from_secs(5);
    if !crate::presence::held(session, presence_key, ask_timeout)
        .await
        .map_err(zenoh)?
    {
        info!(holon, "nothing to take over: no process holds the name");
        return Ok(TakenOver::Nobody);
    }
    let waited = Duration::from_millis(request.wait_ms) + RELEASE_ALLOWANCE;
    info!(
        holon,
        wait_ms = request.wait_ms,
        "asking the running process to hand over"
    );
    let payload = serde_json::to_vec(request).expect("a take-over request serializes");
    let mut replies = session
        .get(key(presence_key))
        .payload(payload)
        .consolidation(ConsolidationMode::None)
        .timeout(waited)
        .with(crate::query::replies())
        .await
        .map_err(zenoh)?;
    let reply = match replies.recv().await {
        None => {
            return Err(TakeoverError::NoAnswer {
                holon: holon.to_string(),
                waited,
            })
        }
        Some(reply) => reply,
    };
    let answer = match reply.result() {
        Ok(sample) => serde_json::from_slice::<Reply>(&sample.payload().to_bytes())
            .map_err(|e| format!("an answer that is not a take-over reply ({e})")),
        Err(error) => Err(error
            .payload()
            .try_to_string()
            .map(|s| s.into_owned())
            .unwrap_or_else(|_| "an error it did not explain".into())),
    };
    let answer = match answer {
        Ok(answer) if answer.released => answer,
        Ok(answer) => {
            return Err(TakeoverError::Refused {
                holon: holon.to_string(),
                detail: answer.detail,
            })
        }
        Err(detail) => {
            return Err(TakeoverError::Refused {
                holon: holon.to_string(),
                detail,
            })
        }
    };
    // The token's withdrawal went out before the answer; it is seen here within a
    // round trip or two.
    let gone_by = Instant::now() + TOKEN_GONE_WITHIN;
    while !crate::presence::tokens(session, presence_key, ask_timeout)
        .await
        .map_err(zenoh)?
        .is_empty()
    {
        if Instant::now() >= gone_by {
            return Err(TakeoverError::StillHeld {
                holon: holon.to_string(),
            });
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    info!(holon, predecessor = %answer.version, "the running process handed over");
    Ok(TakenOver::From(answer))
}

/// The predecessor's side: take-over requests as they arrive. Dropping it undeclares
/// the queryable.
pub struct Listener {
    _queryable: zenoh::query::Queryable<()>,
    offers: mpsc::Receiver<Offer>,
}

/// A successor's request, to be answered once.
pub struct Offer {
    pub request: Request,
    query: Query,
    /// When it arrived: the successor's wait runs from about then.
    received: Instant,
}

/// Listens for take-over requests for the holon on `presence_key`. A request that
/// cannot be read is refused here; at most a few wait (a second successor while one
/// hands over is refused at once).
pub async fn listen(session: &zenoh::Session, presence_key: &str) -> zenoh::Result<Listener> {
    let (sender, offers) = mpsc::channel(1);
    let queryable = session
        .declare_queryable(key(presence_key))
        .callback(move |query| {
            use zenoh::Wait;
            let payload = query
                .payload()
                .map(|p| p.to_bytes().into_owned())
                .unwrap_or_default();
            let refusal = match serde_json::from_slice::<Request>(&payload) {
                Ok(request) => match sender.try_send(Offer {
                    request,
                    query,
                    received: Instant::now(),
                }) {
                    Ok(()) => return,
                    Err(mpsc::error::TrySendError::Full(offer)) => (
                        offer.query,
                        "another successor is taking over already".to_string(),
                    ),
                    Err(mpsc::error::TrySendError::Closed(offer)) => {
                        (offer.query, "the holon is stopping".to_string())
                    }
                },
                Err(e) => (query, format!("not a take-over request: {e}")),
            };
            let (query, detail) = refusal;
            warn!(%detail, "take-over request refused");
            if let Err(e) = query.reply_err(detail.into_bytes()).wait() {
                warn!(error = %e, "cannot refuse a take-over request; the successor times out");
            }
        })
        .await?;
    Ok(Listener {
        _queryable: queryable,
        offers,
    })
}

impl Listener {
    /// The next request (cancel-safe; pending forever once the listener is closed).
    pub async fn next(&mut self) -> Offer {
        match self.offers.recv().await {
            Some(offer) => offer,
            None => std::future::pending().await,
        }
    }

    /// Stops listening: a request that waits (a second successor that asked while
    /// this holon prepared its hand-over) is refused with `detail`, not left to time out.
    pub async fn close(mut self, version: &str, detail: &str) {
        self.offers.close();
        while let Ok(offer) = self.offers.try_recv() {
            warn!(successor = %offer.request.successor, %detail, "take-over request refused");
            offer.refuse(version, detail).await;
        }
    }
}

impl Offer {
    /// Answers `released`: this process has let go of the name and its data.
    pub async fn release(self, version: &str) {
        self.answer(Reply {
            released: true,
            detail: "handed over".into(),
            version: version.to_string(),
        })
        .await
    }

    /// Answers that it will not hand over, and why; it serves on.
    pub async fn refuse(self, version: &str, detail: impl Into<String>) {
        self.answer(Reply {
            released: false,
            detail: detail.into(),
            version: version.to_string(),
        })
        .await
    }

    async fn answer(self, reply: Reply) {
        let age = self.received.elapsed();
        if reply.released && age > self.wait() + RELEASE_ALLOWANCE {
            warn!(?age, "releasing after the successor stopped waiting: nothing may take over, and this process exits after the stand-in limit (a supervisor restarts it)");
        }
        let payload = serde_json::to_vec(&reply).expect("a take-over reply serializes");
        if let Err(e) = self
            .query
            .reply(self.query.key_expr().clone(), payload)
            .await
        {
            warn!(error = %e, released = reply.released, "cannot answer the successor; it times out");
        }
    }

    /// How long the predecessor may take to finish what it must, from the request.
    pub fn wait(&self) -> Duration {
        Duration::from_millis(self.request.wait_ms)
    }

    /// What is left of [`Offer::wait`] now (the request's wait runs from its arrival).
    pub fn remaining(&self) -> Duration {
        self.wait().saturating_sub(self.received.elapsed())
    }
}

/// Answers a query that arrives while the holon is handed over.
pub type Answer = Arc<dyn Fn(&Query) + Send + Sync>;

/// Queryables that answer for a holon while it is handed over (between its
/// predecessor's stop and its successor's start): requests get `unavailable` with a
/// retry hint, not silence. Dropping it withdraws them.
pub struct StandIn {
    _queryables: Vec<zenoh::query::Queryable<()>>,
}

/// Declares a stand-in on each of `keys` (`complete` as the holon's own queryables
/// are, so a query that reaches one of them reaches the same number of answerers).
pub async fn stand_in(
    session: &zenoh::Session,
    keys: &[(String, bool)],
    answer: Answer,
) -> zenoh::Result<StandIn> {
    let mut queryables = Vec::new();
    for (key, complete) in keys {
        let answer = answer.clone();
        queryables.push(
            session
                .declare_queryable(key)
                .complete(*complete)
                .callback(move |query| answer(&query))
                .await?,
        );
        debug!(%key, "standing in");
    }
    Ok(StandIn {
        _queryables: queryables,
    })
}

/// How the predecessor's stand-in ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StandInEnd {
    /// The successor serves.
    Served,
    /// No successor served within [`STAND_IN_LIMIT`].
    NoSuccessor,
    /// The predecessor was told to stop (SIGTERM) while standing in.
    Shutdown,
}

/// Waits, standing in, until the successor serves on `presence_key`, for at most
/// [`STAND_IN_LIMIT`] or until `shutdown`.
pub async fn stand_by(
    session: &zenoh::Session,
    presence_key: &str,
    shutdown: &tokio_util::sync::CancellationToken,
) -> StandInEnd {
    tokio::select! {
        served = until_successor(session, presence_key, STAND_IN_LIMIT) => {
            if served { StandInEnd::Served } else { StandInEnd::NoSuccessor }
        }
        _ = shutdown.cancelled() => StandInEnd::Shutdown,
    }
}

/// The error a predecessor ends with when no successor served after it let go: its
/// supervisor starts it again (on its journal, where it left off).
#[derive(Debug, thiserror::Error)]
#[error("handed over to {successor}, which did not serve within {limit:?}: the name is free and the journal closed; start the holon again (a supervisor does)", limit = STAND_IN_LIMIT)]
pub struct NoSuccessor {
    pub successor: String,
}

/// Waits until a token appears on `presence_key` (the successor is serving), at most
/// `limit`: true if it did.
pub async fn until_successor(
    session: &zenoh::Session,
    presence_key: &str,
    limit: Duration,
) -> bool {
    let subscriber = match session
        .liveliness()
        .declare_subscriber(presence_key)
        .history(true)
        .await
    {
        Ok(subscriber) => subscriber,
        Err(e) => {
            warn!(error = %e, "cannot watch for the successor; standing in for the whole limit");
            tokio::time::sleep(limit).await;
            return false;
        }
    };
    let deadline = Instant::now() + limit;
    loop {
        match tokio::time::timeout_at(deadline, subscriber.recv_async()).await {
            Ok(Ok(sample)) if sample.kind() == SampleKind::Put => return true,
            Ok(Ok(_)) => continue,
            Ok(Err(_)) | Err(_) => return false,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_takeover_key_follows_the_presence_key() {
        assert_eq!(
            key("holarchy/demo/alive/resource/robot1"),
            "holarchy/demo/takeover/resource/robot1"
        );
        assert_eq!(
            key("holarchy/demo/host/order-node/orders1"),
            "holarchy/demo/takeover/order-node/orders1"
        );
    }
}

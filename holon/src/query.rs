//! Replies of zenoh queries in a channel that its reader may stop reading at any time.
//!
//! zenoh's default reply channel logs an ERROR ("sending on a closed channel") for every
//! reply that arrives after its reader was dropped: after the first acknowledgement was
//! taken, or a timeout. Those replies are expected and harmless; this channel drops them
//! without a word. It is unbounded, so a session that answers inside the `get` call
//! (see [`crate::presence::tokens`]) never blocks on it.

use tokio::sync::mpsc;
use zenoh::handlers::Callback;
use zenoh::query::Reply;

/// The receiving end: `recv().await` gives the next reply, `None` once the query ended.
pub type Replies = mpsc::UnboundedReceiver<Reply>;

/// A handler for `get(..).with(holon::query::replies())`.
pub fn replies() -> (Callback<Reply>, Replies) {
    let (sender, receiver) = mpsc::unbounded_channel();
    (
        Callback::from(move |reply| {
            // The reader has what it needed and went away: the reply is not wanted.
            let _unwanted = sender.send(reply);
        }),
        receiver,
    )
}

/// Declares a queryable on `key` that answers every query with the latest value of
/// `latest`, as JSON, on `key` itself (whatever wildcard the query used): a process
/// saying where it stands, as of the moment it is asked.
pub async fn answer_latest<T>(
    session: &zenoh::Session,
    key: &str,
    latest: tokio::sync::watch::Receiver<T>,
) -> zenoh::Result<zenoh::query::Queryable<()>>
where
    T: serde::Serialize + Send + Sync + 'static,
{
    let answer_key = key.to_string();
    session
        .declare_queryable(key)
        .callback(move |query| {
            use zenoh::Wait;
            let payload = serde_json::to_vec(&*latest.borrow()).expect("a report serializes");
            if let Err(e) = query.reply(&answer_key, payload).wait() {
                tracing::debug!(key = %answer_key, error = %e, "cannot answer a query for the latest report: the asker sees none from this process");
            }
        })
        .await
}

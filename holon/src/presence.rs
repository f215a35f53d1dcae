//! Presence: liveliness tokens under `holarchy/<cell>/alive/<kind>/<name>`.

use std::collections::BTreeSet;
use std::time::Duration;

use schemas::{CellKeys, HolonId};
use zenoh::sample::SampleKind;

/// The holons alive in a cell right now (those whose tokens the session can see).
pub async fn alive_holons(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<BTreeSet<HolonId>, zenoh::Error> {
    Ok(tokens(session, &keys.alive_all(), timeout)
        .await?
        .iter()
        .filter_map(|key| keys.holon_from_alive(key))
        .collect())
}

/// The keys of every liveliness token matching `key` now.
///
/// The replies go to an unbounded queue: a session that knows the tokens itself (a
/// router, and often a peer) answers inside the `get` call, before it returns, so a
/// bounded channel (zenoh's default holds 256) would fill with nobody draining it and
/// the call would never return, in a cell of more than 256 holons.
pub async fn tokens(
    session: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Result<Vec<String>, zenoh::Error> {
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    session
        .liveliness()
        .get(key)
        .timeout(timeout)
        .callback(move |reply| {
            if let Ok(sample) = reply.result() {
                let _ = tx.send(sample.key_expr().to_string());
            }
        })
        .await?;
    // The callback (and with it the sender) is dropped when the query ends.
    let mut keys = Vec::new();
    while let Some(key) = rx.recv().await {
        keys.push(key);
    }
    Ok(keys)
}

/// Waits until `holon`'s token is visible; false if it did not appear within `timeout`.
pub async fn wait_alive(
    session: &zenoh::Session,
    keys: &CellKeys,
    holon: &HolonId,
    timeout: Duration,
) -> Result<bool, zenoh::Error> {
    wait_token(session, &keys.alive(holon), timeout).await
}

/// Waits until a liveliness token on `key` is visible; false if none appeared in time.
pub async fn wait_token(
    session: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Result<bool, zenoh::Error> {
    let subscriber = session
        .liveliness()
        .declare_subscriber(key)
        .history(true)
        .await?;
    let deadline = tokio::time::Instant::now() + timeout;
    loop {
        match tokio::time::timeout_at(deadline, subscriber.recv_async()).await {
            Ok(Ok(sample)) if sample.kind() == SampleKind::Put => return Ok(true),
            Ok(Ok(_)) => continue,
            Ok(Err(_)) | Err(_) => return Ok(false),
        }
    }
}

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
    let replies = session
        .liveliness()
        .get(keys.alive_all())
        .timeout(timeout)
        .await?;
    let mut holons = BTreeSet::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            if let Some(id) = keys.holon_from_alive(sample.key_expr().as_str()) {
                holons.insert(id);
            }
        }
    }
    Ok(holons)
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

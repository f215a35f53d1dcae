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

/// The process that holds a name in the cell, as it answers a query on its presence
/// key (a regular query on the same key as its liveliness token).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Holder {
    /// The host it runs on.
    pub host: String,
    /// Its process id there.
    pub pid: u32,
    /// Its zenoh session id.
    pub zid: String,
    /// When it started, in Unix milliseconds.
    pub since: u64,
}

impl Holder {
    /// This process, on `session`.
    pub fn this_process(session: &zenoh::Session) -> Holder {
        Holder {
            host: host_name(),
            pid: std::process::id(),
            zid: session.zid().to_string(),
            since: schemas::unix_ms(),
        }
    }
}

impl std::fmt::Display for Holder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "host {}, pid {}, zenoh id {}",
            self.host, self.pid, self.zid
        )
    }
}

/// The name of this host (`HOSTNAME`, else the kernel's), for messages.
pub fn host_name() -> String {
    std::env::var("HOSTNAME")
        .ok()
        .filter(|h| !h.trim().is_empty())
        .or_else(|| {
            std::fs::read_to_string("/proc/sys/kernel/hostname")
                .ok()
                .map(|h| h.trim().to_string())
        })
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "unknown".into())
}

#[derive(Debug, thiserror::Error)]
pub enum ClaimError {
    #[error(
        "{name} is already running in this cell ({}); stop it first or give this process another name. \
         A process that stopped without closing its link (a host that lost power, a frozen \
         process) holds the name until its zenoh lease expires: try again after that",
        holder.as_ref().map(|h| h.to_string()).unwrap_or_else(|| "its host did not say who it is".into())
    )]
    Taken {
        name: String,
        holder: Option<Holder>,
    },
    #[error("zenoh: {0}")]
    Zenoh(zenoh::Error),
}

/// How long a starting process listens for another holder of its name.
pub const CLAIM_WINDOW: Duration = Duration::from_millis(500);

/// A name claimed in the cell: answers "who holds it" on the key until dropped.
pub struct Claim {
    _holder: zenoh::query::Queryable<()>,
}

/// Whether a liveliness token on `key` is visible in the cell, asked as soon as the
/// session is linked and routed (right after it opens, a query may see nobody yet).
pub async fn held(
    session: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Result<bool, zenoh::Error> {
    // Right after the session opens, its links may still be coming up: a query then
    // sees no one. Wait (briefly) until it is linked to a router or a peer.
    let linked_by = tokio::time::Instant::now() + timeout.min(Duration::from_secs(3));
    loop {
        let info = session.info();
        if info.routers_zid().await.next().is_some() || info.peers_zid().await.next().is_some() {
            break;
        }
        if tokio::time::Instant::now() >= linked_by {
            // Alone (the first process of a cell): nobody to be a twin of.
            break;
        }
        // Links come up within a few milliseconds on a LAN: look again soon.
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
    // Linked is not yet routed: the cell's declarations reach a new session a moment
    // after its links come up, and a query before that sees nobody. So the cell's
    // tokens are asked for until any shows (the declarations have arrived: the answer
    // says whether the name is taken), for at most CLAIM_WINDOW. A cell where nothing
    // shows within it is empty, or its declarations are slow: then a liveliness
    // subscriber with history listens one more window for the name, and it is asked
    // once more. A hot-added holon thus starts within a few query round trips; the first
    // process of a cell pays the window.
    let cell_tokens = format!(
        "{}/**",
        key.splitn(3, '/').take(2).collect::<Vec<_>>().join("/")
    );
    let routed_by = tokio::time::Instant::now() + CLAIM_WINDOW;
    loop {
        let seen = tokens(session, &cell_tokens, timeout).await?;
        if !seen.is_empty() {
            return Ok(seen.iter().any(|k| k == key));
        }
        if tokio::time::Instant::now() >= routed_by {
            return Ok(wait_token(session, key, CLAIM_WINDOW).await?
                || !tokens(session, key, timeout).await?.is_empty());
        }
        tokio::time::sleep(Duration::from_millis(2)).await;
    }
}

/// Claims `key` (a liveliness token's key) for `name`: refuses when a token on `key` is
/// visible (another process holds the name: a twin), naming that process; otherwise
/// declares a queryable on `key` that answers with this process's [`Holder`], so a twin
/// started later can say who holds the name. The caller declares the token itself when
/// it is ready. Two processes started within the same instant can both pass: the check
/// is for the common mistake (a config copied and not renamed), not a lock.
pub async fn claim(
    session: &zenoh::Session,
    key: &str,
    name: &str,
    timeout: Duration,
) -> Result<Claim, ClaimError> {
    let taken = held(session, key, timeout)
        .await
        .map_err(ClaimError::Zenoh)?;
    if taken {
        let holder = match session
            .get(key)
            .timeout(timeout)
            .with(crate::query::replies())
            .await
        {
            Ok(mut replies) => match tokio::time::timeout(timeout, replies.recv()).await {
                Ok(Some(reply)) => reply
                    .result()
                    .ok()
                    .and_then(|s| serde_json::from_slice(&s.payload().to_bytes()).ok()),
                _ => None,
            },
            Err(_) => None,
        };
        return Err(ClaimError::Taken {
            name: name.to_string(),
            holder,
        });
    }
    let me = serde_json::to_vec(&Holder::this_process(session)).unwrap_or_default();
    let holder = session
        .declare_queryable(key)
        .callback(move |query| {
            use zenoh::Wait;
            if let Err(e) = query.reply(query.key_expr().clone(), me.clone()).wait() {
                tracing::debug!(error = %e, "cannot answer who holds this name");
            }
        })
        .await
        .map_err(ClaimError::Zenoh)?;
    Ok(Claim { _holder: holder })
}

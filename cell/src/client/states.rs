//! Following the holons' states, as the cell's screens do (the dashboard, the OPC UA
//! server): every resource's and order's snapshot as it is published, and asked for
//! once (the subscriptions bring the changes from then on); the resources' asked again
//! every few seconds, so that a publication lost on its way is not shown stale for good. What is heard is handed to
//! a callback, which must not block (it runs in zenoh's callbacks): it queues it for
//! the task that owns the screen's model.

use std::time::Duration;

use anyhow::{anyhow, Result};
use schemas::{CellKeys, HolonId, HolonKind, OrderSnapshot, ResourceSnapshot};
use tracing::warn;

/// How long one ask for the states waits for their replies.
const ASK_TIMEOUT: Duration = Duration::from_secs(3);

/// After a resource's token appears, how long until its state is asked for once more: a
/// holon that has just joined can publish a change before the subscription reached it,
/// and zenoh would never route that change to us (seen: a resource turning `free` 1 ms
/// after its token appeared, shown `init` for good).
pub const ASK_NEWCOMER_AGAIN: Duration = Duration::from_secs(1);

/// How often the screens ask every resource's state again, whatever they heard: a
/// publication lost on its way (zenoh drops a sample when a link's queue stays full a
/// moment, as when a screen's process is starved of CPU) is then shown within this,
/// instead of at the resource's next change, which may never come (a held robot).
pub const ASK_RESOURCES_AGAIN: Duration = Duration::from_secs(5);

/// A holon's state, heard.
#[derive(Debug, Clone)]
pub enum Heard {
    Resource(Box<ResourceSnapshot>),
    Order(Box<OrderSnapshot>),
}

impl Heard {
    /// A resource's or an order's snapshot, from its payload; `None` for anything else.
    pub fn read(payload: &[u8]) -> Option<Heard> {
        if let Ok(snapshot) = serde_json::from_slice::<ResourceSnapshot>(payload) {
            return Some(Heard::Resource(Box::new(snapshot)));
        }
        serde_json::from_slice::<OrderSnapshot>(payload)
            .ok()
            .map(|snapshot| Heard::Order(Box::new(snapshot)))
    }
}

/// The subscriptions to the states followed, and the task asking the resources' states
/// again; dropping it ends them.
pub struct Following {
    _subscribers: Vec<zenoh::pubsub::Subscriber<()>>,
    asking_again: tokio::task::JoinHandle<()>,
}

impl Drop for Following {
    fn drop(&mut self) {
        self.asking_again.abort();
    }
}

/// Subscribes to the states on `which` (e.g. `resource/*/state` and `order/*/state`):
/// each snapshot goes to `heard`; and asks every resource's state again every
/// [`ASK_RESOURCES_AGAIN`] (the screen's model keeps what is newest and unchanged
/// snapshots change nothing).
pub async fn follow<F>(
    session: &zenoh::Session,
    keys: &CellKeys,
    which: &[String],
    heard: F,
) -> Result<Following>
where
    F: Fn(Heard) + Clone + Send + Sync + 'static,
{
    let z = |e: zenoh::Error| anyhow!("{}", holon::zenoh_error::describe(&e));
    let mut subscribers = Vec::with_capacity(which.len());
    for key in which {
        let heard = heard.clone();
        subscribers.push(
            session
                .declare_subscriber(key.clone())
                .callback(move |sample| {
                    if let Some(state) = Heard::read(&sample.payload().to_bytes()) {
                        heard(state);
                    }
                })
                .await
                .map_err(z)?,
        );
    }
    let asking_again = {
        let (session, key, heard) = (session.clone(), keys.resource_states(), heard.clone());
        tokio::spawn(async move {
            let mut every = tokio::time::interval(ASK_RESOURCES_AGAIN);
            every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            every.tick().await;
            loop {
                every.tick().await;
                ask(&session, std::slice::from_ref(&key), &heard).await;
            }
        })
    };
    Ok(Following {
        _subscribers: subscribers,
        asking_again,
    })
}

/// Follows the holons' liveliness tokens (`alive/**`, with their history): each
/// holon's token appearing (`true`) or vanishing (`false`) goes to `token`. When a
/// resource's appears, its state is asked for at once and again
/// [`ASK_NEWCOMER_AGAIN`] later, each reply handed to `heard`. Both callbacks must not
/// block (`token` runs in zenoh's callback). Dropping the subscriber ends it.
pub async fn follow_tokens<T, H>(
    session: &zenoh::Session,
    keys: &CellKeys,
    token: T,
    heard: H,
) -> Result<zenoh::pubsub::Subscriber<()>>
where
    T: Fn(HolonId, bool) + Send + Sync + 'static,
    H: Fn(Heard) + Clone + Send + Sync + 'static,
{
    let keys = keys.clone();
    let (runtime, asker) = (tokio::runtime::Handle::current(), session.clone());
    session
        .liveliness()
        .declare_subscriber(keys.alive_all())
        .history(true)
        .callback(move |sample| {
            let Some(holon) = keys.holon_from_alive(sample.key_expr().as_str()) else {
                return;
            };
            let appeared = sample.kind() == zenoh::sample::SampleKind::Put;
            if appeared && holon.kind() == HolonKind::Resource {
                let (asker, heard, key) = (asker.clone(), heard.clone(), keys.state(&holon));
                runtime.spawn(async move {
                    ask(&asker, std::slice::from_ref(&key), &heard).await;
                    tokio::time::sleep(ASK_NEWCOMER_AGAIN).await;
                    ask(&asker, &[key], &heard).await;
                });
            }
            token(holon, appeared);
        })
        .await
        .map_err(|e| anyhow!("{}", holon::zenoh_error::describe(&e)))
}

/// Asks for the states on `keys` (e.g. `resource/*/state`, or one holon's) and hands
/// each reply to `heard`.
pub async fn ask(session: &zenoh::Session, keys: &[String], heard: impl Fn(Heard)) {
    for key in keys {
        let Ok(mut replies) = session
            .get(key)
            .timeout(ASK_TIMEOUT)
            .with(holon::query::replies())
            .await
        else {
            warn!(%key, "cannot ask for the states; they arrive with their next change");
            continue;
        };
        while let Some(reply) = replies.recv().await {
            let Ok(sample) = reply.result() else { continue };
            if let Some(state) = Heard::read(&sample.payload().to_bytes()) {
                heard(state);
            }
        }
    }
}

//! The order-node process: hosts order holons, one supervised task each.
//!
//! It answers `orders/submit` (declared complete, so a default `get` reaches exactly one
//! order-node) and answers `order/*/state` for the orders it hosts. Orders are named
//! `<node>-<n>`, so several order-nodes in one cell never collide. A panicking order task
//! is restarted from its progress (at most 3 times, then the order fails).

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::{ErrorReply, HolonId, SubmitReply, WorkOrder};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};
use zenoh::key_expr::KeyExpr;
use zenoh::query::Query;

use crate::config::OrderNodeConfig;
use crate::order::{self, OrderContext, Presence};
use crate::progress::OrderProgress;

/// Restarts of one order task before the order is failed.
const MAX_ORDER_RESTARTS: u32 = 3;

#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error(transparent)]
    Session(#[from] holon::session::SessionError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("invalid work order: {0}")]
    WorkOrder(String),
}

/// The running order tasks, and which order each one runs.
#[derive(Default)]
struct Tasks {
    set: JoinSet<Result<(), String>>,
    names: std::collections::HashMap<tokio::task::Id, String>,
}

struct Hosted {
    progress: Arc<Mutex<OrderProgress>>,
    restarts: u32,
}

struct Host {
    config: OrderNodeConfig,
    context: Arc<OrderContext>,
    orders: Mutex<BTreeMap<String, Hosted>>,
    next: AtomicU64,
}

impl Host {
    fn create(
        &self,
        work: &WorkOrder,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) -> Vec<String> {
        let mut names = Vec::new();
        for _ in 0..work.count {
            let n = self.next.fetch_add(1, Ordering::SeqCst);
            let name = format!("{}-{n}", self.config.name);
            let holon = HolonId::order(&name).expect("node names are validated");
            let progress = Arc::new(Mutex::new(OrderProgress::new(
                holon,
                &work.product,
                self.config.orders.max_attempts,
            )));
            self.orders
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(
                    name.clone(),
                    Hosted {
                        progress: progress.clone(),
                        restarts: 0,
                    },
                );
            self.spawn(&name, progress, tasks, cancel);
            names.push(name);
        }
        info!(node = %self.config.name, product = %work.product, count = work.count, first = names.first().map(String::as_str).unwrap_or(""), "orders created");
        names
    }

    fn spawn(
        &self,
        name: &str,
        progress: Arc<Mutex<OrderProgress>>,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) {
        let context = self.context.clone();
        let cancel = cancel.child_token();
        let handle = tasks.set.spawn(order::run(context, progress, cancel));
        tasks.names.insert(handle.id(), name.to_string());
    }

    fn snapshots_matching(&self, key: &KeyExpr<'_>) -> Vec<(String, Vec<u8>)> {
        let orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        orders
            .values()
            .filter_map(|hosted| {
                let snapshot = hosted
                    .progress
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .snapshot();
                let state_key = self.config.keys.state(&snapshot.holon);
                let ke = KeyExpr::try_from(state_key.clone()).ok()?;
                ke.intersects(key).then(|| {
                    (
                        state_key,
                        serde_json::to_vec(&snapshot).expect("serializes"),
                    )
                })
            })
            .collect()
    }
}

/// Parses `PRODUCT:COUNT` (or `PRODUCT`, count 1) from the command line.
pub fn parse_submit(text: &str) -> Result<WorkOrder, NodeError> {
    let (product, count) = match text.split_once(':') {
        Some((p, c)) => (
            p,
            c.parse::<u32>().map_err(|_| {
                NodeError::WorkOrder(format!("{text:?}: COUNT must be a positive number"))
            })?,
        ),
        None => (text, 1),
    };
    let work = WorkOrder {
        product: product.to_string(),
        count,
        priority: 0,
    };
    work.validate()
        .map_err(|e| NodeError::WorkOrder(format!("{text:?}: {e}")))?;
    Ok(work)
}

enum Incoming {
    Submit(Query),
    State(Query),
}

/// Runs the order-node until `shutdown` is cancelled.
pub async fn run(
    config: OrderNodeConfig,
    submits: Vec<WorkOrder>,
    shutdown: CancellationToken,
) -> Result<(), NodeError> {
    let z = |e: zenoh::Error| NodeError::Zenoh(e.to_string());
    let session = config.zenoh.open(Duration::from_secs(10)).await?;
    let presence = Presence::watch(&session, &config.keys).await.map_err(z)?;
    let context = Arc::new(OrderContext {
        session: session.clone(),
        keys: config.keys.clone(),
        settings: config.orders,
        presence,
    });
    let host = Arc::new(Host {
        config: config.clone(),
        context,
        orders: Mutex::new(BTreeMap::new()),
        next: AtomicU64::new(1),
    });
    let (incoming_tx, mut incoming) = mpsc::unbounded_channel();
    let submit_tx = incoming_tx.clone();
    let _submit = session
        .declare_queryable(config.keys.orders_submit())
        .complete(true)
        .callback(move |query| {
            let _ = submit_tx.send(Incoming::Submit(query));
        })
        .await
        .map_err(z)?;
    let _states = session
        .declare_queryable(config.keys.order_states())
        .callback(move |query| {
            let _ = incoming_tx.send(Incoming::State(query));
        })
        .await
        .map_err(z)?;
    let token = session
        .liveliness()
        .declare_token(config.keys.host("order-node", &config.name))
        .await
        .map_err(z)?;
    info!(node = %config.name, cell = %config.keys.cell(), "order-node ready");

    let orders_cancel = CancellationToken::new();
    let mut tasks = Tasks::default();
    for work in &submits {
        host.create(work, &mut tasks, &orders_cancel);
    }
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => break,
            Some(query) = incoming.recv() => match query {
                Incoming::Submit(query) => submit(&host, query, &mut tasks, &orders_cancel).await,
                Incoming::State(query) => {
                    for (key, payload) in host.snapshots_matching(query.key_expr()) {
                        let _ = query.reply(key, payload).await;
                    }
                }
            },
            Some(joined) = tasks.set.join_next_with_id(), if !tasks.set.is_empty() => {
                let (id, why) = match joined {
                    Ok((id, Ok(()))) => {
                        tasks.names.remove(&id);
                        continue;
                    }
                    Ok((id, Err(e))) => (id, e),
                    Err(e) if e.is_panic() => {
                        let id = e.id();
                        let payload = e.into_panic();
                        let message = payload
                            .downcast_ref::<&str>()
                            .map(|s| s.to_string())
                            .or_else(|| payload.downcast_ref::<String>().cloned())
                            .unwrap_or_default();
                        (id, format!("panicked: {message}"))
                    }
                    Err(e) => {
                        tasks.names.remove(&e.id());
                        continue;
                    }
                };
                let Some(name) = tasks.names.remove(&id) else { continue };
                error!(node = %config.name, order = %name, error = %why, "order task failed");
                restart(&host, &name, &mut tasks, &orders_cancel);
            }
        }
    }
    info!(node = %config.name, "stopping: orders in progress stop where they stand");
    orders_cancel.cancel();
    let _ = tokio::time::timeout(Duration::from_secs(5), async {
        while tasks.set.join_next().await.is_some() {}
    })
    .await;
    let _ = token.undeclare().await;
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
    info!(node = %config.name, "order-node stopped");
    Ok(())
}

fn restart(host: &Host, name: &str, tasks: &mut Tasks, cancel: &CancellationToken) {
    let mut orders = host.orders.lock().unwrap_or_else(|e| e.into_inner());
    let Some(hosted) = orders.get_mut(name) else {
        return;
    };
    hosted.restarts += 1;
    let progress = hosted.progress.clone();
    if hosted.restarts > MAX_ORDER_RESTARTS {
        progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .fail(format!("the order task failed {MAX_ORDER_RESTARTS} times"));
        return;
    }
    warn!(order = %name, restarts = hosted.restarts, "restarting order");
    drop(orders);
    host.spawn(name, progress, tasks, cancel);
}

async fn submit(host: &Host, query: Query, tasks: &mut Tasks, cancel: &CancellationToken) {
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let work: WorkOrder = match serde_json::from_slice::<WorkOrder>(&payload) {
        Ok(work) => match work.validate() {
            Ok(()) => work,
            Err(e) => {
                let _ = query
                    .reply_err(ErrorReply::new("invalid", e.to_string()).to_json())
                    .await;
                return;
            }
        },
        Err(e) => {
            warn!(node = %host.config.name, error = %e, "malformed work order");
            let _ = query
                .reply_err(ErrorReply::new("malformed", e.to_string()).to_json())
                .await;
            return;
        }
    };
    let orders = host.create(&work, tasks, cancel);
    let reply = serde_json::to_vec(&SubmitReply { orders }).expect("serializes");
    if let Err(e) = query.reply(query.key_expr().clone(), reply).await {
        warn!(node = %host.config.name, error = %e, "cannot answer the work order");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_submit_flags() {
        assert_eq!(parse_submit("breaker:3").unwrap().count, 3);
        assert_eq!(parse_submit("breaker").unwrap().count, 1);
        assert!(parse_submit("breaker:0").is_err());
        assert!(parse_submit("breaker:x").is_err());
        assert!(parse_submit("Breaker:1").is_err());
    }
}

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

use schemas::{CancelReply, ErrorReply, HolonId, SubmitReply, WorkOrder};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};
use zenoh::key_expr::KeyExpr;
use zenoh::query::Query;

use crate::config::OrderNodeConfig;
use crate::context::{OrderContext, OrderError, MAX_CONCURRENT_ROUNDS, ORDER_RECORD};
use crate::order;
use crate::presence::Presence;
use crate::progress::OrderProgress;
use holon::journal::Journal;
use holon::{Intensity, RestartWindow};

/// An order task may fail and be restarted at most this often (the project's one
/// restart policy, [`holon::restart`]: order tasks are transient children); past it the
/// order fails.
const ORDER_RESTARTS: Intensity = Intensity {
    max_restarts: 3,
    period: Duration::from_secs(60),
};

/// How often finished orders are checked against `journal.keep_finished_ms`, at most
/// (a shorter retention is checked as often as it lasts).
const RETENTION_SWEEP: Duration = Duration::from_secs(60);

/// How many queries wait for the node's loop before new ones are refused `unavailable`.
const QUERY_QUEUE: usize = 1024;

#[derive(Debug, thiserror::Error)]
pub enum OrderNodeError {
    #[error(transparent)]
    Session(#[from] holon::session::SessionError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("invalid work order: {0}")]
    WorkOrder(String),
    #[error(transparent)]
    Journal(#[from] holon::journal::JournalError),
    #[error(transparent)]
    Claim(#[from] holon::presence::ClaimError),
}

/// How long a work order waits for its product holon to be seen before it is refused
/// `unknown_product`.
const PRODUCT_GRACE: Duration = Duration::from_secs(2);

/// How long an order waits before it tries again a journal that could not write.
const JOURNAL_RETRY: Duration = Duration::from_secs(1);

/// The journal record of the next order number.
const NEXT_RECORD: (&str, &str) = ("meta", "next_order");

/// The running order tasks, and which order each one runs.
#[derive(Default)]
struct Tasks {
    set: JoinSet<Result<(), OrderError>>,
    names: std::collections::HashMap<tokio::task::Id, String>,
}

struct Hosted {
    progress: Arc<Mutex<OrderProgress>>,
    /// The task's restarts, against [`ORDER_RESTARTS`].
    restarts: RestartWindow,
    /// Cancelled when an operator cancels the order (`cell cancel`).
    operator_cancel: CancellationToken,
}

struct Host {
    config: OrderNodeConfig,
    context: Arc<OrderContext>,
    orders: Mutex<BTreeMap<String, Hosted>>,
    next: AtomicU64,
}

impl Host {
    /// Creates the orders of a work order, written to the journal before they start
    /// (and before the submitter is told their names).
    fn create(
        &self,
        work: &WorkOrder,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) -> Result<Vec<String>, String> {
        let first = self.next.fetch_add(work.count as u64, Ordering::SeqCst);
        if let Some(journal) = &self.context.journal {
            journal
                .put(NEXT_RECORD.0, NEXT_RECORD.1, &(first + work.count as u64))
                .map_err(|e| e.to_string())?;
        }
        let mut created = Vec::new();
        for n in first..first + work.count as u64 {
            let name = format!("{}-{n}", self.config.name);
            let holon = HolonId::order(&name).expect("node names are validated");
            let progress =
                OrderProgress::new(holon, &work.product, self.config.orders.max_attempts);
            self.context.save(&progress).map_err(|e| e.to_string())?;
            created.push((name, progress));
        }
        let mut names = Vec::new();
        for (name, progress) in created {
            self.host(&name, progress, tasks, cancel);
            names.push(name);
        }
        info!(node = %self.config.name, product = %work.product, count = work.count, first = names.first().map(String::as_str).unwrap_or(""), "orders created");
        Ok(names)
    }

    /// Hosts an order: running ones get a task.
    fn host(
        &self,
        name: &str,
        progress: OrderProgress,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) {
        let running = !progress.status.is_final();
        let mut progress = progress;
        if !running && progress.finished_at.is_none() {
            // Finished before its end was stamped (an older journal): kept from now on.
            progress.finished_at = Some(schemas::unix_ms());
        }
        let operator_cancel = CancellationToken::new();
        if progress.cancel_requested {
            operator_cancel.cancel();
        }
        let progress = Arc::new(Mutex::new(progress));
        self.orders
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(
                name.to_string(),
                Hosted {
                    progress: progress.clone(),
                    restarts: RestartWindow::new(ORDER_RESTARTS),
                    operator_cancel,
                },
            );
        if running {
            self.spawn(name, progress, tasks, cancel, Duration::ZERO);
        }
    }

    /// The progress of `name` if it is an order of this node.
    fn progress(&self, name: &str) -> Option<OrderProgress> {
        let orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        let progress = orders
            .get(name)?
            .progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        Some(progress)
    }

    fn spawn(
        &self,
        name: &str,
        progress: Arc<Mutex<OrderProgress>>,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
        delay: Duration,
    ) {
        let context = self.context.clone();
        let cancel = cancel.child_token();
        let operator_cancel = self
            .orders
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(name)
            .map(|h| h.operator_cancel.clone())
            .unwrap_or_default();
        let handle = tasks.set.spawn(async move {
            if !delay.is_zero() {
                tokio::select! {
                    _ = tokio::time::sleep(delay) => {}
                    _ = cancel.cancelled() => return Ok(()),
                }
            }
            order::run(context, progress, cancel, operator_cancel).await
        });
        tasks.names.insert(handle.id(), name.to_string());
    }

    /// Hosts the orders recovered from the journal (resuming the unfinished ones) and
    /// creates those of `--submit`.
    fn resume(
        &self,
        recovered: Vec<(String, OrderProgress)>,
        submits: &[WorkOrder],
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) {
        let node = &self.config.name;
        if !recovered.is_empty() {
            let resumed = recovered
                .iter()
                .filter(|(_, p)| !p.status.is_final())
                .count();
            info!(%node, orders = recovered.len(), resumed, "orders recovered from the journal");
        }
        for (name, progress) in recovered {
            self.host(&name, progress, tasks, cancel);
        }
        for work in submits {
            if let Err(e) = self.create(work, tasks, cancel) {
                error!(%node, error = %e, "cannot create the orders of --submit");
            }
        }
    }

    /// Forgets the orders that finished more than `keep` ago: out of the journal first,
    /// then out of memory (an order whose delete fails stays until the next sweep).
    /// Returns how many were forgotten.
    fn forget_finished(&self, keep: Duration) -> usize {
        let now = schemas::unix_ms();
        let keep_ms = keep.as_millis() as u64;
        let mut orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        let expired: Vec<String> = orders
            .iter()
            .filter(|(_, hosted)| {
                let p = hosted.progress.lock().unwrap_or_else(|e| e.into_inner());
                p.status.is_final()
                    && p.finished_at
                        .is_some_and(|at| now.saturating_sub(at) > keep_ms)
            })
            .map(|(name, _)| name.clone())
            .collect();
        let mut forgotten = 0;
        for name in expired {
            if let Some(journal) = &self.context.journal {
                if let Err(e) = journal.delete(ORDER_RECORD, &name) {
                    warn!(node = %self.config.name, order = %name, error = %e, "cannot remove a finished order from the journal; tried again at the next sweep");
                    continue;
                }
            }
            orders.remove(&name);
            forgotten += 1;
        }
        if forgotten > 0 {
            info!(node = %self.config.name, orders = forgotten, ?keep, "finished orders left the journal");
        }
        forgotten
    }

    /// Unfinished orders hosted here.
    fn unfinished(&self) -> usize {
        let orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        orders
            .values()
            .filter(|h| {
                !h.progress
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .status
                    .is_final()
            })
            .count()
    }

    /// Records an operator's cancel of `name` and tells its task; what to answer.
    fn cancel(&self, name: &str) -> Result<CancelReply, String> {
        let orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        let hosted = orders
            .get(name)
            .ok_or_else(|| format!("{name} is not an order of {}", self.config.name))?;
        let mut progress = hosted.progress.lock().unwrap_or_else(|e| e.into_inner());
        if progress.status.is_final() {
            return Ok(CancelReply {
                order: name.to_string(),
                cancelled: false,
                status: progress.status,
                detail: format!("the order has already ended ({:?})", progress.status),
            });
        }
        if !progress.cancel_requested {
            // Written first: on a journal error nothing changed and the cancel is refused.
            let mut next = progress.clone();
            next.cancel_requested = true;
            self.context.save(&next).map_err(|e| e.to_string())?;
            *progress = next;
        }
        hosted.operator_cancel.cancel();
        info!(node = %self.config.name, order = %name, "cancel requested by an operator");
        Ok(CancelReply {
            order: name.to_string(),
            cancelled: true,
            status: progress.status,
            detail: match progress.phase {
                crate::progress::Phase::Started(_) => {
                    "its running step finishes first, then it ends as cancelled".into()
                }
                _ => "its bookings are cancelled and it ends as cancelled".into(),
            },
        })
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
pub fn parse_submit(text: &str) -> Result<WorkOrder, OrderNodeError> {
    let (product, count) = match text.split_once(':') {
        Some((p, c)) => (
            p,
            c.parse::<u32>().map_err(|_| {
                OrderNodeError::WorkOrder(format!("{text:?}: COUNT must be a positive number"))
            })?,
        ),
        None => (text, 1),
    };
    let work = WorkOrder {
        product: product.to_string(),
        count,
        priority: 0,
        // Given at start-up, before the cell may be complete: the orders wait for
        // their plan.
        queue: true,
    };
    work.validate()
        .map_err(|e| OrderNodeError::WorkOrder(format!("{text:?}: {e}")))?;
    Ok(work)
}

/// A query to the node, by the queryable it came to.
enum NodeQuery {
    Cancel(Query),
    Submit(Query),
    State(Query),
    Inbox(Query),
}

/// Queues a query for the node's loop from a queryable's callback (which must not
/// block): refused `unavailable` when [`QUERY_QUEUE`] are already waiting.
fn enqueue(queue: &mpsc::Sender<NodeQuery>, query: NodeQuery) {
    use zenoh::Wait;
    match queue.try_send(query) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(
            NodeQuery::Cancel(query)
            | NodeQuery::Submit(query)
            | NodeQuery::State(query)
            | NodeQuery::Inbox(query),
        )) => {
            warn!(key = %query.key_expr(), "{QUERY_QUEUE} queries are waiting for the order-node: this one is refused unavailable");
            let busy = schemas::ErrorReply::new(
                "unavailable",
                format!(
                    "{QUERY_QUEUE} requests are waiting for this order-node; ask again shortly"
                ),
            );
            if let Err(e) = query.reply_err(busy.to_json()).wait() {
                warn!(error = %e, "cannot refuse a query; the asker times out");
            }
        }
        Err(mpsc::error::TrySendError::Closed(_)) => {
            debug!("a query arrived while the order-node stops: left unanswered, the asker times out or delivers again")
        }
    }
}

/// Runs the order-node until `shutdown` is cancelled.
pub async fn run(
    config: OrderNodeConfig,
    submits: Vec<WorkOrder>,
    shutdown: CancellationToken,
) -> Result<(), OrderNodeError> {
    let session = config
        .zenoh
        .open(
            &holon::tls::identity("order-node", &config.name),
            Duration::from_secs(10),
        )
        .await?;
    // A twin (an order-node of the same name alive in the cell) would number its
    // orders like this one: refused before anything is declared.
    let _claim = holon::presence::claim(
        &session,
        &config.keys.host("order-node", &config.name),
        &format!("order-node {}", config.name),
        Duration::from_secs(10),
    )
    .await?;
    let (journal, (recovered, next)) = open_journal(&config)?;
    let presence = Presence::follow(&session, &config.keys)
        .await
        .map_err(zenoh_error)?;
    let host = Arc::new(Host {
        config: config.clone(),
        context: Arc::new(OrderContext {
            session: session.clone(),
            keys: config.keys.clone(),
            settings: config.orders,
            presence,
            inboxes: Default::default(),
            rounds: tokio::sync::Semaphore::new(MAX_CONCURRENT_ROUNDS),
            idle: Default::default(),
            journal,
            journal_failing: Default::default(),
        }),
        orders: Mutex::new(BTreeMap::new()),
        next: AtomicU64::new(next),
    });
    let (queue, mut queries) = mpsc::channel(QUERY_QUEUE);
    let endpoints = Endpoints::declare(&session, &host, queue).await?;
    let token = session
        .liveliness()
        .declare_token(config.keys.host("order-node", &config.name))
        .await
        .map_err(zenoh_error)?;
    info!(node = %config.name, cell = %config.keys.cell(), "order-node ready");

    let orders_cancel = CancellationToken::new();
    let mut tasks = Tasks::default();
    host.resume(recovered, &submits, &mut tasks, &orders_cancel);
    // A short retention is checked more often (at most every RETENTION_SWEEP).
    let every = config
        .keep_finished
        .unwrap_or(RETENTION_SWEEP)
        .clamp(Duration::from_millis(100), RETENTION_SWEEP);
    let mut sweep = tokio::time::interval(every);
    sweep.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => break,
            _ = sweep.tick(), if config.keep_finished.is_some() => {
                if let Some(keep) = config.keep_finished {
                    host.forget_finished(keep);
                }
            }
            Some(query) = queries.recv() => answer(&host, query, &mut tasks, &orders_cancel).await,
            Some(joined) = tasks.set.join_next_with_id(), if !tasks.set.is_empty() => {
                task_ended(&host, joined, &mut tasks, &orders_cancel).await;
            }
        }
    }
    info!(node = %config.name, "stopping: orders in progress stop where they stand");
    orders_cancel.cancel();
    let stopped = tokio::time::timeout(Duration::from_secs(5), async {
        while tasks.set.join_next().await.is_some() {}
    })
    .await;
    if stopped.is_err() {
        warn!(node = %config.name, "order tasks did not stop within 5 s; they end with the process (their progress is in the journal)");
    }
    if let Err(e) = token.undeclare().await {
        warn!(node = %config.name, error = %e, "cannot withdraw the order-node's token; it goes with the session");
    }
    drop(endpoints);
    match tokio::time::timeout(Duration::from_secs(5), session.close()).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => warn!(node = %config.name, error = %e, "cannot close the zenoh session"),
        Err(_) => warn!(node = %config.name, "the zenoh session did not close within 5 s"),
    }
    info!(node = %config.name, "order-node stopped");
    Ok(())
}

fn zenoh_error(e: zenoh::Error) -> OrderNodeError {
    OrderNodeError::Zenoh(holon::zenoh_error::describe(&e))
}

/// What the journal holds at start-up: the orders recorded in it and the number of the
/// next order.
type Recovered = (Vec<(String, OrderProgress)>, u64);

/// The journal, if the node has a data directory, with what it holds.
fn open_journal(
    config: &OrderNodeConfig,
) -> Result<(Option<Arc<Journal>>, Recovered), OrderNodeError> {
    let Some(dir) = &config.data_dir else {
        warn!(node = %config.name, "no data directory: orders are not durable (use --data-dir)");
        return Ok((None, (Vec::new(), 1)));
    };
    let journal = Journal::open(
        dir,
        &format!("order-node-{}.sqlite", config.name),
        config.durability,
    )?;
    let recovered = journal.list::<OrderProgress>(ORDER_RECORD)?;
    let next = journal
        .get::<u64>(NEXT_RECORD.0, NEXT_RECORD.1)?
        .unwrap_or(1);
    Ok((Some(Arc::new(journal)), (recovered, next)))
}

/// The node's queryables; dropping them undeclares them.
struct Endpoints {
    _submit: zenoh::query::Queryable<()>,
    _states: zenoh::query::Queryable<()>,
    _inboxes: zenoh::query::Queryable<()>,
    _cancels: zenoh::query::Queryable<()>,
}

impl Endpoints {
    /// Declares `orders/submit`, and the node's orders' `state`, `inbox` and `cancel`;
    /// every query goes to `queue` (results for running orders straight to them).
    async fn declare(
        session: &zenoh::Session,
        host: &Host,
        queue: mpsc::Sender<NodeQuery>,
    ) -> Result<Endpoints, OrderNodeError> {
        let keys = &host.config.keys;
        let name = &host.config.name;
        let to_queue = |wrap: fn(Query) -> NodeQuery| {
            let queue = queue.clone();
            move |query| enqueue(&queue, wrap(query))
        };
        let _submit = session
            .declare_queryable(keys.orders_submit())
            .complete(true)
            .callback(to_queue(NodeQuery::Submit))
            .await
            .map_err(zenoh_error)?;
        let _states = session
            .declare_queryable(keys.node_orders(name, "state"))
            .callback(to_queue(NodeQuery::State))
            .await
            .map_err(zenoh_error)?;
        // Results reach running orders straight from this callback; those for orders
        // that are not running (duplicates, late reports of abandoned attempts) are
        // answered by the node's loop.
        let inboxes = host.context.inboxes.clone();
        let inbox_queue = queue.clone();
        let _inboxes = session
            .declare_queryable(keys.node_orders(name, "inbox"))
            .callback(move |query| {
                if let Some(query) = inboxes.route(query) {
                    enqueue(&inbox_queue, NodeQuery::Inbox(query));
                }
            })
            .await
            .map_err(zenoh_error)?;
        let _cancels = session
            .declare_queryable(keys.node_orders(name, "cancel"))
            .callback(to_queue(NodeQuery::Cancel))
            .await
            .map_err(zenoh_error)?;
        Ok(Endpoints {
            _submit,
            _states,
            _inboxes,
            _cancels,
        })
    }
}

/// Answers one query to the node.
async fn answer(host: &Host, query: NodeQuery, tasks: &mut Tasks, cancel_all: &CancellationToken) {
    match query {
        NodeQuery::Submit(query) => submit(host, query, tasks, cancel_all).await,
        NodeQuery::Inbox(query) => acknowledge_finished(host, query).await,
        NodeQuery::Cancel(query) => cancel(host, query).await,
        NodeQuery::State(query) => {
            for (key, payload) in host.snapshots_matching(query.key_expr()) {
                if let Err(e) = query.reply(&key, payload).await {
                    warn!(node = %host.config.name, %key, error = %e, "cannot answer a state read; the reader gets fewer orders");
                }
            }
        }
    }
}

/// An order task ended: done (the order ended), waiting for the journal (resumed after
/// a pause, not counted as a failure), or failed (restarted under the restart policy).
async fn task_ended(
    host: &Host,
    joined: Result<(tokio::task::Id, Result<(), OrderError>), tokio::task::JoinError>,
    tasks: &mut Tasks,
    cancel_all: &CancellationToken,
) {
    let node = &host.config.name;
    let (id, why) = match joined {
        Ok((id, Ok(()))) => {
            tasks.names.remove(&id);
            return;
        }
        Ok((id, Err(OrderError::Journal(why)))) => {
            // Not the order's fault: resumed from its last written progress once the
            // journal can write again (tried every second), not counted against its
            // restarts.
            let Some(name) = tasks.names.remove(&id) else {
                return;
            };
            debug!(%node, order = %name, error = %why, "order waits for the journal");
            let progress = host
                .orders
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get(&name)
                .map(|h| h.progress.clone());
            if let Some(progress) = progress {
                host.spawn(&name, progress, tasks, cancel_all, JOURNAL_RETRY);
            }
            return;
        }
        Ok((id, Err(e))) => (id, e.to_string()),
        Err(e) if e.is_panic() => {
            let id = e.id();
            let why = format!(
                "panicked: {}",
                holon::supervisor::panic_message(e.into_panic())
            );
            (id, why)
        }
        Err(e) => {
            tasks.names.remove(&e.id());
            return;
        }
    };
    let Some(name) = tasks.names.remove(&id) else {
        return;
    };
    error!(%node, order = %name, error = %why, "order task failed");
    restart(host, &name, tasks, cancel_all).await;
}

/// Restarts a failed order task, unless it failed more often than [`ORDER_RESTARTS`]
/// allows: then the order fails, recorded in the journal and published, so it does not
/// resume after a restart of the node.
async fn restart(host: &Host, name: &str, tasks: &mut Tasks, cancel: &CancellationToken) {
    let (progress, allowed) = {
        let mut orders = host.orders.lock().unwrap_or_else(|e| e.into_inner());
        let Some(hosted) = orders.get_mut(name) else {
            return;
        };
        (
            hosted.progress.clone(),
            hosted.restarts.allow(tokio::time::Instant::now()),
        )
    };
    if allowed {
        warn!(order = %name, "restarting order");
        host.spawn(name, progress, tasks, cancel, Duration::ZERO);
        return;
    }
    let why = format!(
        "the order task failed more than {} times within {:?}",
        ORDER_RESTARTS.max_restarts, ORDER_RESTARTS.period
    );
    error!(order = %name, reason = %why, "order failed");
    if let Err(e) = host.context.commit(&progress, |p| p.fail(why)) {
        // Not recorded: the order resumes after a restart of the node, as before.
        error!(order = %name, error = %e, "cannot record that the order failed; it stays unfinished in the journal");
    }
    host.context.publish(&progress).await;
}

/// Why a work order for `product` cannot be planned now: no product holon of that name
/// is alive (the product tokens, asked for once). `None` when it is there.
async fn product_missing(host: &Host, product: &str) -> Option<String> {
    let keys = &host.config.keys;
    let alive = match holon::presence::tokens(
        &host.context.session,
        &keys.alive_kind(schemas::HolonKind::Product),
        Duration::from_secs(2),
    )
    .await
    {
        Ok(alive) => alive,
        // Presence unknown: accept, the orders wait for their plan as before.
        Err(e) => {
            warn!(node = %host.config.name, error = %e, "cannot ask which products are alive");
            return None;
        }
    };
    let names: Vec<String> = alive
        .iter()
        .filter_map(|k| keys.holon_from_alive(k))
        .map(|h| h.name().to_string())
        .collect();
    if names.iter().any(|n| n == product) {
        return None;
    }
    // A node that has just joined may not know every token yet (a peer learns the
    // others' declarations as its links come up): a product that shows up within the
    // grace is there.
    if let Ok(holon) = HolonId::new(schemas::HolonKind::Product, product) {
        if let Ok(true) =
            holon::presence::wait_token(&host.context.session, &keys.alive(&holon), PRODUCT_GRACE)
                .await
        {
            return None;
        }
    }
    Some(format!(
        "no product holon {product:?} is alive in cell {} (alive: {}); start it, or submit with queue (cell submit --queue) to let the orders wait for its plan",
        keys.cell(),
        if names.is_empty() { "none".to_string() } else { names.join(", ") }
    ))
}

/// Refuses a work order: nothing was created.
async fn refuse_work(host: &Host, query: &Query, refusal: ErrorReply) {
    if let Err(e) = query.reply_err(refusal.to_json()).await {
        warn!(node = %host.config.name, code = %refusal.code, error = %e, "cannot refuse the work order; the submitter times out (nothing was created)");
    }
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
                return refuse_work(host, &query, ErrorReply::new("invalid", e.to_string())).await
            }
        },
        Err(e) => {
            warn!(node = %host.config.name, error = %e, "malformed work order");
            return refuse_work(host, &query, ErrorReply::new("malformed", e.to_string())).await;
        }
    };
    if !work.queue {
        if let Some(why) = product_missing(host, &work.product).await {
            warn!(node = %host.config.name, product = %work.product, "work order refused: {why}");
            if let Err(e) = query
                .reply_err(ErrorReply::new("unknown_product", why).to_json())
                .await
            {
                warn!(node = %host.config.name, error = %e, "cannot refuse the work order");
            }
            return;
        }
    }
    let limits = &host.config.orders;
    let unfinished = host.unfinished();
    let refusal = if work.count > limits.max_orders_per_submit {
        Some(format!(
            "count {} is over this node's limit of {} orders per work order (orders.max_orders_per_submit)",
            work.count, limits.max_orders_per_submit
        ))
    } else if unfinished + work.count as usize > limits.max_unfinished_orders {
        Some(format!(
            "{unfinished} orders are unfinished; {} more would pass this node's limit of {} (orders.max_unfinished_orders)",
            work.count, limits.max_unfinished_orders
        ))
    } else {
        None
    };
    if let Some(why) = refusal {
        warn!(node = %host.config.name, product = %work.product, count = work.count, "work order refused: {why}");
        if let Err(e) = query
            .reply_err(ErrorReply::new("quota", why).to_json())
            .await
        {
            warn!(node = %host.config.name, error = %e, "cannot refuse the work order");
        }
        return;
    }
    let orders = match host.create(&work, tasks, cancel) {
        Ok(orders) => orders,
        Err(e) => {
            error!(node = %host.config.name, error = %e, "cannot record the work order");
            let refusal = ErrorReply::new("unavailable", format!("cannot record the orders: {e}"));
            return refuse_work(host, &query, refusal).await;
        }
    };
    let reply = serde_json::to_vec(&SubmitReply { orders }).expect("serializes");
    if let Err(e) = query.reply(query.key_expr().clone(), reply).await {
        warn!(node = %host.config.name, error = %e, "cannot answer the work order");
    }
}

/// An operator's cancel of one order (`order/<name>/cancel`).
async fn cancel(host: &Host, query: Query) {
    let key = query.key_expr().as_str().to_string();
    let name = key
        .strip_suffix("/cancel")
        .and_then(|k| k.rsplit('/').next())
        .unwrap_or_default();
    let answer = match host.cancel(name) {
        Ok(reply) => {
            let payload = serde_json::to_vec(&reply).expect("serializes");
            query.reply(host.config.keys.cancel(name), payload).await
        }
        Err(why) => {
            warn!(node = %host.config.name, order = %name, "cancel refused: {why}");
            query
                .reply_err(ErrorReply::new("unknown_order", why).to_json())
                .await
        }
    };
    if let Err(e) = answer {
        warn!(node = %host.config.name, order = %name, error = %e, "cannot answer a cancel");
    }
}

/// Acknowledges a result sent to a finished order of this node (it was recorded, or
/// belongs to an attempt the order abandoned); anything else is left to the order.
async fn acknowledge_finished(host: &Host, query: Query) {
    let key = query.key_expr().as_str().to_string();
    let Some(name) = crate::inbox::order_name(&key).map(str::to_string) else {
        return;
    };
    let Some(progress) = host.progress(&name) else {
        warn!(order = %name, "result for an order this node does not host refused");
        if let Err(e) = query
            .reply_err(
                ErrorReply::new(
                    "unknown_order",
                    format!("{name} is not an order of {}", host.config.name),
                )
                .to_json(),
            )
            .await
        {
            warn!(order = %name, error = %e, "cannot refuse a result");
        }
        return;
    };
    if !progress.status.is_final() {
        // Hosted, but its task is not running now (restarting after a journal error):
        // unanswered, so the resource delivers the result again.
        debug!(order = %name, "result for an order that is not running left for a later delivery");
        return;
    }
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let message = match schemas::Service::from_json(&payload) {
        Ok(message) => message,
        Err(err) => {
            warn!(order = %name, bytes = payload.len(), error = %err, "undecodable message for a finished order refused");
            if let Err(e) = query
                .reply_err(ErrorReply::new("malformed", err.to_string()).to_json())
                .await
            {
                warn!(order = %name, error = %e, "cannot refuse an undecodable message");
            }
            return;
        }
    };
    {
        if !progress.knows(message.provider.as_ref()) {
            warn!(order = %name, conversation_id = %message.conversation_id, "result for a finished order from a resource it never booked refused");
            if let Err(e) = query
                .reply_err(
                    ErrorReply::new("not_booked", "this order never booked that resource")
                        .to_json(),
                )
                .await
            {
                warn!(order = %name, error = %e, "cannot refuse a result");
            }
            return;
        }
        info!(order = %name, conversation_id = %message.conversation_id, message_type = %message.message_type, "result for a finished order acknowledged");
        let mut ack = message;
        ack.result = Some(true);
        if let Err(e) = query.reply(query.key_expr().clone(), ack.to_json()).await {
            warn!(order = %name, error = %e, "cannot acknowledge a result of a finished order; the resource delivers it again");
        }
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

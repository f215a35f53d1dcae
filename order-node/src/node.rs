//! The order-node process: hosts order holons, one supervised task each.
//!
//! It answers `orders/submit` (declared complete, so a default `get` reaches exactly one
//! order-node) and answers `order/*/state` for the orders it hosts. Orders are named
//! `<node>-<n>`, so several order-nodes in one cell never collide. The orders and their
//! tasks are [`crate::host`]'s; the queries are answered by [`crate::queries`].

use std::sync::Arc;
use std::time::Duration;

use holon::journal::Journal;
use schemas::WorkOrder;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use crate::config::OrderNodeConfig;
use crate::context::OrderContext;
use crate::host::{task_ended, Finished, Host, Tasks};
use crate::journal::OrderJournal;
use crate::presence::Presence;
use crate::queries::{answer, Endpoints, NodeQuery, QUERY_QUEUE};
use crate::recovery::recover;

pub use crate::error::OrderNodeError;
pub use crate::recovery::Recovered;

/// How often finished orders are checked against `journal.keep_finished_ms`, at most
/// (a shorter retention is checked as often as it lasts).
const RETENTION_SWEEP: Duration = Duration::from_secs(60);

/// This build's release, published in its orders' states and named in hand-overs.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// When a request refused during a hand-over is to be asked again.
const HANDOVER_RETRY: Duration = Duration::from_millis(100);

/// Parses `PRODUCT[:COUNT[:PRIORITY]]` (count 1 and priority 0 when left out) from
/// the command line.
pub fn parse_submit(text: &str) -> Result<WorkOrder, OrderNodeError> {
    let invalid = |why: &str| OrderNodeError::WorkOrder(format!("{text:?}: {why}"));
    let mut parts = text.split(':');
    let product = parts.next().unwrap_or_default();
    let count = match parts.next() {
        Some(count) => count
            .parse::<u32>()
            .map_err(|_| invalid("COUNT must be a positive number"))?,
        None => 1,
    };
    let priority = match parts.next() {
        Some(priority) => priority
            .parse::<i32>()
            .map_err(|_| invalid("PRIORITY must be a whole number"))?,
        None => 0,
    };
    if parts.next().is_some() {
        return Err(invalid("expected PRODUCT[:COUNT[:PRIORITY]]"));
    }
    let work = WorkOrder {
        product: product.to_string(),
        count,
        priority,
        due: None,
        // Given at start-up, before the cell may be complete: the orders wait for
        // their plan.
        queue: true,
    };
    work.validate().map_err(|e| invalid(&e.to_string()))?;
    Ok(work)
}

/// What gives this process the node's name and orders: a claim of the name (SQLite),
/// or the leader key on etcd; with the journal and what it holds.
struct Authority {
    /// The name claimed in the cell (a node without etcd).
    claim: Option<holon::presence::Claim>,
    /// The leader key won on etcd (a node with a standby).
    elected: Option<crate::standby::Elected>,
    /// The orders' journal, if any.
    journal: Option<Arc<OrderJournal>>,
    /// What the journal holds.
    recovered: Recovered,
}

/// Why the node's loop ended.
enum Ending {
    /// The node stops (`shutdown`).
    Stopping,
    /// A successor takes over: the offer it accepted.
    HandingOver(Box<holon::takeover::Offer>),
    /// The leader key on etcd is no longer this process's: why.
    Deposed(String),
}

/// Runs the order-node until `shutdown` is cancelled.
pub async fn run(
    config: OrderNodeConfig,
    submits: Vec<WorkOrder>,
    shutdown: CancellationToken,
) -> Result<(), OrderNodeError> {
    let life = holon::life::Life {
        presence_key: config.keys.host("order-node", &config.name),
        holder: format!("order-node {}", config.name),
        version: VERSION,
        take_over: config.take_over,
        data_dir: config.data_dir.clone(),
        startup_timeout: Duration::from_secs(10),
    };
    let tls_identity = holon::role::identity(holon::role::Role::OrderNode, &config.name);
    let Some(holon::life::Opened { session, .. }) =
        life.open(&config.zenoh, &tls_identity, &shutdown).await?
    else {
        return Ok(());
    };
    let (presence, authority) = match authority(&config, &life, &session, &shutdown).await {
        Ok(Some(found)) => found,
        // Stopped while standing by, or failed.
        other => {
            holon::life::close(&life.holder, session).await;
            return other.map(|_| ());
        }
    };
    let Authority {
        claim,
        elected,
        journal,
        recovered: (recovered, finished, next),
    } = authority;
    let context = OrderContext::new(session.clone(), &config, presence, journal);
    let mut host = Host::new(config.clone(), Arc::new(context), finished, next);
    let (queue, mut queries) = mpsc::channel(QUERY_QUEUE);
    let endpoints = Endpoints::declare(&session, &host, queue)
        .await
        .map_err(zenoh_error)?;
    let holon::life::Announced {
        token,
        mut successors,
    } = life.announce(&session).await?;
    if let Some(elected) = &elected {
        info!(node = %config.name, epoch = elected.leader.epoch(), "serving at epoch {}: the order-node's leader key on etcd is this process's", elected.leader.epoch());
    }
    let orders_cancel = CancellationToken::new();
    let mut tasks = Tasks::default();
    host.resume(recovered, &submits, &mut tasks, &orders_cancel);
    let mut node = Loop {
        host: &mut host,
        tasks: &mut tasks,
        queries: &mut queries,
        orders_cancel: &orders_cancel,
    };
    let ending = node
        .serve(&life, &mut successors, elected.as_ref(), &shutdown)
        .await;
    successors.close(VERSION, ending.refusal()).await;
    let mut token = Some(token);
    let mut endpoints = Some(endpoints);
    if let Ending::Deposed(why) = &ending {
        // Another process may serve this name already: from now on this one answers
        // nothing and shows nothing, before its orders stop.
        error!(node = %config.name, why = %why, "deposed: the order-node's leader key on etcd is no longer this process's; it stops at once (token and queryables withdrawn, order tasks stopped; their writes are refused by etcd anyway)");
        drop(endpoints.take());
        withdraw(&config.name, token.take()).await;
    }
    let started = std::time::Instant::now();
    let handing_over = matches!(ending, Ending::HandingOver(_));
    info!(node = %config.name, handing_over, "stopping: orders in progress stop where they stand");
    stop_orders(&config.name, &mut tasks, &orders_cancel).await;
    // While handed over, submits, cancels and results get `unavailable` with a retry
    // hint from a stand-in (submits and cancels are asked again by `cell`, results
    // delivered again by the resources), until the successor serves.
    let stand_in = match handing_over {
        true => stand_in(&session, &config).await,
        false => None,
    };
    drop(endpoints);
    let mut ended = Ok(());
    // A hand-over is refused with etcd: there is a claim (SQLite) whenever there is one.
    let deposed = match (ending, claim, token.take()) {
        (Ending::HandingOver(offer), Some(claim), Some(token)) => {
            // The journal closes with the last holder of the host: the successor opens it.
            drop(queries);
            drop(host);
            ended = life
                .let_go(&session, token, claim, *offer, started, &shutdown)
                .await
                .map_err(OrderNodeError::from);
            None
        }
        (Ending::Deposed(why), _, token) => {
            withdraw(&config.name, token).await;
            Some(why)
        }
        (_, _, token) => {
            withdraw(&config.name, token).await;
            None
        }
    };
    drop(stand_in);
    if let Some(elected) = elected {
        match deposed {
            Some(why) => ended = Err(crate::standby::deposed_error(&elected, why).await),
            // Stopped: the key is given up, so that a standby serves at once.
            None => crate::standby::resign(&config.name, elected.leader).await,
        }
    }
    holon::life::close(&life.holder, session).await;
    if let Err(e @ OrderNodeError::Deposed { .. }) = &ended {
        error!(node = %config.name, error = %e, "order-node stopped: deposed");
    } else {
        info!(node = %config.name, "order-node stopped");
    }
    ended
}

/// The presence of the resources, followed from the start (a standby's too: an
/// order-node that takes over knows which resources are fenced before it hears from
/// them again), and the node's authority over its name. `None` when it stopped while
/// standing by.
async fn authority(
    config: &OrderNodeConfig,
    life: &holon::life::Life,
    session: &zenoh::Session,
    shutdown: &CancellationToken,
) -> Result<Option<(Arc<Presence>, Authority)>, OrderNodeError> {
    let presence = Presence::follow(session, &config.keys)
        .await
        .map_err(zenoh_error)?;
    let authority = match &config.etcd {
        None => {
            // A twin (an order-node of the same name alive in the cell) would number its
            // orders like this one: refused before anything is declared.
            let claim = life.claim(session).await?;
            let (journal, recovered) = open_journal(config)?;
            Authority {
                claim: Some(claim),
                elected: None,
                journal,
                recovered,
            }
        }
        // With etcd the leader key is the authority, not zenoh's liveliness: no twin
        // check. A primary that froze or was cut off keeps its token until its link
        // lease ends, and would be taken for a twin; it cannot act meanwhile (its writes
        // are fenced on its epoch) and withdraws its token once it hears it is deposed.
        Some(etcd) => match crate::standby::stand_by(config, etcd, session, shutdown).await? {
            Some(mut elected) => Authority {
                claim: None,
                recovered: std::mem::take(&mut elected.recovered),
                journal: Some(elected.journal.clone()),
                elected: Some(elected),
            },
            None => return Ok(None),
        },
    };
    Ok(Some((presence, authority)))
}

impl Ending {
    /// What a successor that asks now is told.
    fn refusal(&self) -> &'static str {
        match self {
            Ending::HandingOver(_) => "another successor is taking over already",
            Ending::Deposed(_) => "the order-node is deposed",
            Ending::Stopping => "the order-node is stopping",
        }
    }
}

/// The node's loop: the one owner of its orders ([`Host`]) and of their tasks.
struct Loop<'a> {
    /// The orders.
    host: &'a mut Host,
    /// Their tasks.
    tasks: &'a mut Tasks,
    /// The queries the endpoints' callbacks queued for the loop.
    queries: &'a mut mpsc::Receiver<NodeQuery>,
    /// Stops every order task.
    orders_cancel: &'a CancellationToken,
}

impl Loop<'_> {
    /// Serves queries, supervises the order tasks and sweeps finished orders, until
    /// the node stops, is deposed, or hands over to a successor.
    async fn serve(
        &mut self,
        life: &holon::life::Life,
        successors: &mut holon::takeover::Listener,
        elected: Option<&crate::standby::Elected>,
        shutdown: &CancellationToken,
    ) -> Ending {
        let config = self.host.config.clone();
        // A short retention is checked more often (at most every RETENTION_SWEEP).
        let every = config
            .keep_finished
            .unwrap_or(RETENTION_SWEEP)
            .clamp(Duration::from_millis(100), RETENTION_SWEEP);
        let mut sweep = tokio::time::interval(every);
        sweep.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        // Never ends without etcd.
        let mut until_deposed = Box::pin(async {
            match elected {
                Some(elected) => crate::standby::deposed(elected).await,
                None => std::future::pending().await,
            }
        });
        loop {
            tokio::select! {
                _ = shutdown.cancelled() => return Ending::Stopping,
                why = &mut until_deposed => return Ending::Deposed(why),
                offer = successors.next() => {
                    info!(node = %config.name, successor = %offer.request.successor, version = %offer.request.version, "a successor asks to take over");
                    match self.hand_over_refusal(life, &offer.request, elected.is_some()) {
                        Some(detail) => {
                            warn!(node = %config.name, %detail, "hand-over refused");
                            offer.refuse(VERSION, detail).await;
                        }
                        None => return Ending::HandingOver(Box::new(offer)),
                    }
                }
                _ = sweep.tick(), if config.keep_finished.is_some() => {
                    if let Some(keep) = config.keep_finished {
                        self.host.forget_finished(keep);
                    }
                }
                Some(query) = self.queries.recv() => {
                    answer(self.host, query, self.tasks, self.orders_cancel).await
                }
                Some(joined) = self.tasks.set.join_next_with_id(), if !self.tasks.set.is_empty() => {
                    task_ended(self.host, joined, self.tasks, self.orders_cancel).await;
                }
            }
        }
    }

    /// Why a successor may not take over now; `None` when it may.
    fn hand_over_refusal(
        &self,
        life: &holon::life::Life,
        request: &holon::takeover::Request,
        on_etcd: bool,
    ) -> Option<String> {
        let config = &self.host.config;
        if on_etcd {
            return Some("its journal is on etcd: start the successor beside it (a standby), then stop this one, which gives its leader key up".into());
        }
        if !life.opens_my_journal(request) {
            return Some(format!(
                "its data dir {:?} is not this order-node's {:?}: its orders would not resume there",
                request.data_dir, config.data_dir
            ));
        }
        if self
            .host
            .context
            .journal_failing
            .load(std::sync::atomic::Ordering::SeqCst)
        {
            return Some("its journal cannot be written: its successor could not record its orders' progress either; it serves on (its orders wait until the journal can be written)".into());
        }
        None
    }
}

/// Stops the order tasks where they stand: cancelled, and aborted if they have not
/// ended within 5 s (their progress is in the journal).
async fn stop_orders(node: &str, tasks: &mut Tasks, orders_cancel: &CancellationToken) {
    orders_cancel.cancel();
    let stopped = tokio::time::timeout(Duration::from_secs(5), async {
        while tasks.set.join_next().await.is_some() {}
    })
    .await;
    if stopped.is_err() {
        // Their progress is in the journal; aborted now, so that they let go of it
        // (a successor opens it next).
        warn!(%node, left = tasks.set.len(), "order tasks did not stop within 5 s; aborted (their progress is in the journal)");
        tasks.set.abort_all();
        let aborted = tokio::time::timeout(Duration::from_secs(1), async {
            while tasks.set.join_next().await.is_some() {}
        })
        .await;
        if aborted.is_err() {
            warn!(%node, left = tasks.set.len(), "aborted order tasks have not ended within 1 s");
        }
    }
}

/// Stands in for the successor on the node's request keys while it is handed over.
async fn stand_in(
    session: &zenoh::Session,
    config: &OrderNodeConfig,
) -> Option<holon::takeover::StandIn> {
    let keys = [
        (config.keys.orders_submit(), true),
        (config.keys.node_orders(&config.name, "cancel"), false),
        (config.keys.node_orders(&config.name, "inbox"), false),
    ];
    match holon::takeover::stand_in(session, &keys, stand_in_answer(config.name.clone())).await {
        Ok(stand_in) => Some(stand_in),
        Err(e) => {
            warn!(node = %config.name, error = %e, "cannot stand in for the successor: requests in the gap go unanswered");
            None
        }
    }
}

/// Withdraws the node's token, if it still has one.
async fn withdraw(node: &str, token: Option<zenoh::liveliness::LivelinessToken>) {
    if let Some(token) = token {
        if let Err(e) = token.undeclare().await {
            warn!(%node, error = %e, "cannot withdraw the order-node's token; it goes with the session");
        }
    }
}

/// The stand-in's answer while the node is handed over: `unavailable`, ask again.
fn stand_in_answer(node: String) -> holon::takeover::Answer {
    let refusal = schemas::ErrorReply::unavailable(
        "the order-node is being handed over to its successor (an upgrade); ask again shortly",
        HANDOVER_RETRY,
    )
    .to_json();
    Arc::new(move |query: &zenoh::query::Query| {
        use zenoh::Wait;
        if let Err(e) = query.reply_err(refusal.clone()).wait() {
            warn!(%node, error = %e, "cannot answer a request while handed over; the requester asks again after its timeout");
        }
    })
}

fn zenoh_error(e: zenoh::Error) -> OrderNodeError {
    OrderNodeError::Zenoh(holon::zenoh_error::describe(&e))
}

/// The journal, if the node has a data directory, with what it holds.
fn open_journal(
    config: &OrderNodeConfig,
) -> Result<(Option<Arc<OrderJournal>>, Recovered), OrderNodeError> {
    let Some(dir) = &config.data_dir else {
        warn!(node = %config.name, "no data directory: orders are not durable (use --data-dir)");
        return Ok((None, (Vec::new(), Finished::new(), 1)));
    };
    // A successor opens the journal its predecessor is closing.
    let patience = match config.take_over {
        Some(_) => holon::takeover::JOURNAL_PATIENCE,
        None => std::time::Duration::ZERO,
    };
    let journal = Journal::open_when_free(
        dir,
        &format!("order-node-{}.sqlite", config.name),
        config.durability,
        patience,
    )?;
    let journal = OrderJournal::Local(journal);
    let recovered = recover(&journal, &config.name)?;
    Ok((Some(Arc::new(journal)), recovered))
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
        assert_eq!(parse_submit("breaker:2:100").unwrap().priority, 100);
        assert_eq!(parse_submit("breaker:2:-5").unwrap().priority, -5);
        assert!(parse_submit("breaker:2:1001").is_err());
        assert!(parse_submit("breaker:2:high").is_err());
        assert!(parse_submit("breaker:2:1:9").is_err());
    }
}

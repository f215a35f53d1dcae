//! The order-node process: hosts order holons, one supervised task each.
//!
//! It answers `orders/submit` (declared complete, so a default `get` reaches exactly one
//! order-node) and answers `order/*/state` for the orders it hosts. Orders are named
//! `<node>-<n>`, so several order-nodes in one cell never collide. The orders and their
//! tasks are [`crate::host`]'s; the queries are answered by [`crate::queries`].

use std::collections::BTreeMap;
use std::sync::atomic::AtomicU64;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use holon::journal::Journal;
use schemas::WorkOrder;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use crate::config::OrderNodeConfig;
use crate::context::{OrderContext, MAX_CONCURRENT_ROUNDS};
use crate::host::{task_ended, Finished, Host, Tasks};
use crate::journal::OrderJournal;
use crate::presence::Presence;
use crate::queries::{answer, Endpoints, QUERY_QUEUE};
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
    // Followed from the start, a standby's too: an order-node that takes over knows
    // which resources are fenced before it hears from them again.
    let presence = match Presence::follow(&session, &config.keys).await {
        Ok(presence) => presence,
        Err(e) => {
            holon::life::close(&life.holder, session).await;
            return Err(zenoh_error(e));
        }
    };
    let (claim, elected, journal, (recovered, finished, next)) = match &config.etcd {
        None => {
            // A twin (an order-node of the same name alive in the cell) would number its
            // orders like this one: refused before anything is declared.
            let claim = match life.claim(&session).await {
                Ok(claim) => claim,
                Err(e) => {
                    holon::life::close(&life.holder, session).await;
                    return Err(e.into());
                }
            };
            let (journal, recovered) = open_journal(&config)?;
            (Some(claim), None, journal, recovered)
        }
        // With etcd the leader key is the authority, not zenoh's liveliness: no twin
        // check. A primary that froze or was cut off keeps its token until its link
        // lease ends, and would be taken for a twin; it cannot act meanwhile (its writes
        // are fenced on its epoch) and withdraws its token once it hears it is deposed.
        Some(etcd) => match crate::standby::stand_by(&config, etcd, &session, &shutdown).await {
            Ok(Some(mut elected)) => {
                let recovered = std::mem::take(&mut elected.recovered);
                let journal = Some(elected.journal.clone());
                (None, Some(elected), journal, recovered)
            }
            Ok(None) => {
                holon::life::close(&life.holder, session).await;
                return Ok(());
            }
            Err(e) => {
                holon::life::close(&life.holder, session).await;
                return Err(e);
            }
        },
    };
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
            bookings_in_flight: Default::default(),
            advice_pause: Default::default(),
        }),
        orders: Mutex::new(BTreeMap::new()),
        finished: Mutex::new(finished),
        next: AtomicU64::new(next),
    });
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
    // A short retention is checked more often (at most every RETENTION_SWEEP).
    let every = config
        .keep_finished
        .unwrap_or(RETENTION_SWEEP)
        .clamp(Duration::from_millis(100), RETENTION_SWEEP);
    let mut sweep = tokio::time::interval(every);
    sweep.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Never ends without etcd.
    let mut until_deposed = Box::pin(async {
        match &elected {
            Some(elected) => crate::standby::deposed(elected).await,
            None => std::future::pending().await,
        }
    });
    let (handing_over, deposed) = loop {
        tokio::select! {
            _ = shutdown.cancelled() => break (None, None),
            why = &mut until_deposed => break (None, Some(why)),
            offer = successors.next() => {
                let request = &offer.request;
                info!(node = %config.name, successor = %request.successor, version = %request.version, "a successor asks to take over");
                if elected.is_some() {
                    let detail = "its journal is on etcd: start the successor beside it (a standby), then stop this one, which gives its leader key up";
                    warn!(node = %config.name, detail, "hand-over refused");
                    offer.refuse(VERSION, detail).await;
                    continue;
                }
                if !life.opens_my_journal(request) {
                    let detail = format!(
                        "its data dir {:?} is not this order-node's {:?}: its orders would not resume there",
                        request.data_dir, config.data_dir
                    );
                    warn!(node = %config.name, %detail, "hand-over refused");
                    offer.refuse(VERSION, detail).await;
                    continue;
                }
                if host.context.journal_failing.load(std::sync::atomic::Ordering::SeqCst) {
                    let detail = "its journal cannot be written: its successor could not record its orders' progress either; it serves on (its orders wait until the journal can be written)";
                    warn!(node = %config.name, detail, "hand-over refused");
                    offer.refuse(VERSION, detail).await;
                    continue;
                }
                break (Some(offer), None);
            }
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
    };
    drop(until_deposed);
    let refusal = match (&handing_over, &deposed) {
        (Some(_), _) => "another successor is taking over already",
        (None, Some(_)) => "the order-node is deposed",
        (None, None) => "the order-node is stopping",
    };
    successors.close(VERSION, refusal).await;
    let mut token = Some(token);
    let mut endpoints = Some(endpoints);
    if let Some(why) = &deposed {
        // Another process may serve this name already: from now on this one answers
        // nothing and shows nothing, before its orders stop.
        error!(node = %config.name, why = %why, "deposed: the order-node's leader key on etcd is no longer this process's; it stops at once (token and queryables withdrawn, order tasks stopped; their writes are refused by etcd anyway)");
        drop(endpoints.take());
        withdraw(&config.name, token.take()).await;
    }
    let started = std::time::Instant::now();
    info!(node = %config.name, handing_over = handing_over.is_some(), "stopping: orders in progress stop where they stand");
    orders_cancel.cancel();
    let stopped = tokio::time::timeout(Duration::from_secs(5), async {
        while tasks.set.join_next().await.is_some() {}
    })
    .await;
    if stopped.is_err() {
        // Their progress is in the journal; aborted now, so that they let go of it
        // (a successor opens it next).
        warn!(node = %config.name, left = tasks.set.len(), "order tasks did not stop within 5 s; aborted (their progress is in the journal)");
        tasks.set.abort_all();
        let aborted = tokio::time::timeout(Duration::from_secs(1), async {
            while tasks.set.join_next().await.is_some() {}
        })
        .await;
        if aborted.is_err() {
            warn!(node = %config.name, left = tasks.set.len(), "aborted order tasks have not ended within 1 s");
        }
    }
    // While handed over, submits, cancels and results get `unavailable` with a retry
    // hint from a stand-in (submits and cancels are asked again by `cell`, results
    // delivered again by the resources), until the successor serves.
    let stand_in = match &handing_over {
        Some(_) => match holon::takeover::stand_in(
            &session,
            &[
                (config.keys.orders_submit(), true),
                (config.keys.node_orders(&config.name, "cancel"), false),
                (config.keys.node_orders(&config.name, "inbox"), false),
            ],
            stand_in_answer(config.name.clone()),
        )
        .await
        {
            Ok(stand_in) => Some(stand_in),
            Err(e) => {
                warn!(node = %config.name, error = %e, "cannot stand in for the successor: requests in the gap go unanswered");
                None
            }
        },
        None => None,
    };
    drop(endpoints);
    let mut ended = Ok(());
    // A hand-over is refused with etcd: there is a claim (SQLite) whenever there is one.
    match (handing_over, claim, token.take()) {
        (Some(offer), Some(claim), Some(token)) => {
            // The journal closes with the last holder of the host: the successor opens it.
            drop(queries);
            drop(host);
            ended = life
                .let_go(&session, token, claim, offer, started, &shutdown)
                .await
                .map_err(OrderNodeError::from);
        }
        (_, _, token) => withdraw(&config.name, token).await,
    }
    drop(stand_in);
    if let Some(elected) = elected {
        match deposed {
            Some(why) => ended = Err(crate::standby::deposed_error(&elected, why).await),
            // Stopped: the key is given up, so that a standby serves at once.
            None => crate::standby::resign(&config.name, elected.leader).await,
        }
    }
    holon::life::close(&life.holder, session).await;
    match &ended {
        Err(e @ OrderNodeError::Deposed { .. }) => {
            error!(node = %config.name, error = %e, "order-node stopped: deposed")
        }
        _ => info!(node = %config.name, "order-node stopped"),
    }
    ended
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

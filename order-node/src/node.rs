//! The order-node process: hosts order holons, one supervised task each.
//!
//! It answers `orders/submit` (declared complete, so a default `get` reaches exactly one
//! order-node) and answers `order/*/state` for the orders it hosts. Orders are named
//! `<node>-<n>`, so several order-nodes in one cell never collide. The orders and their
//! tasks are [`crate::host`]'s; the queries are answered by [`crate::queries`].

use std::sync::Arc;
use std::time::Duration;

use holon::journal::Journal;
use holon::life::{Behaviour, Leaving, LivelinessClaim, Next, StandInSpec, Start, Work};
use schemas::WorkOrder;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use crate::config::OrderNodeConfig;
use crate::context::OrderContext;
use crate::host::{task_ended, Host, Tasks};
use crate::journal::OrderJournal;
use crate::presence::Presence;
use crate::queries::{answer, Endpoints, NodeQuery, QUERY_QUEUE};
use crate::recovery::recover;
pub use crate::standby::Grant;

pub use crate::error::OrderNodeError;
pub use crate::recovery::Recovered;

/// How often finished orders are checked against `journal.keep_finished_ms`, at most
/// (a shorter retention is checked as often as it lasts).
const RETENTION_SWEEP: Duration = Duration::from_secs(60);

/// This build's release, published in its orders' states and named in hand-overs.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

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
        submit_id: None,
    };
    work.validate().map_err(|e| invalid(&e.to_string()))?;
    Ok(work)
}

/// Runs the order-node until `shutdown` is cancelled, until it hands over to a
/// successor, or until it is deposed (its journal on etcd). Its leadership is the
/// leader key on etcd when its journal is there ([`crate::standby::EtcdLeader`]), else
/// the name's liveliness claim.
pub async fn run(
    config: OrderNodeConfig,
    submits: Vec<WorkOrder>,
    shutdown: CancellationToken,
) -> Result<(), OrderNodeError> {
    let process = holon::life::Process {
        life: holon::life::Life {
            presence_key: config.keys.host("order-node", &config.name),
            holder: format!("order-node {}", config.name),
            version: VERSION,
            take_over: config.take_over,
            data_dir: config.data_dir.clone(),
            startup_timeout: Duration::from_secs(10),
        },
        zenoh: &config.zenoh,
        tls_identity: holon::role::identity(holon::role::Role::OrderNode, &config.name),
    };
    let node = OrderNode {
        config: &config,
        submits,
        presence: None,
    };
    let ended = match &config.etcd {
        // With etcd the leader key is the authority, not zenoh's liveliness: no twin
        // check. A primary that froze or was cut off keeps its token until its link
        // lease ends, and would be taken for a twin; it cannot act meanwhile (its writes
        // are fenced on its epoch) and withdraws its token once it hears it is deposed.
        Some(etcd) => {
            let leader = crate::standby::EtcdLeader::new(&config, etcd);
            holon::life::run(process, node, leader, shutdown).await
        }
        // A twin (an order-node of the same name alive in the cell) would number its
        // orders like this one: refused before anything is declared.
        None => holon::life::run(process, node, LivelinessClaim::default(), shutdown).await,
    };
    if let Err(e @ OrderNodeError::Deposed { .. }) = &ended {
        error!(node = %config.name, error = %e, "order-node stopped: deposed");
    } else {
        info!(node = %config.name, "order-node stopped");
    }
    ended
}

/// The order-node's own part of its life: it hosts orders.
pub struct OrderNode<'a> {
    /// Its config.
    config: &'a OrderNodeConfig,
    /// The work orders of the command line, submitted when it serves.
    submits: Vec<WorkOrder>,
    /// The resources' presence, followed from the start.
    presence: Option<Arc<Presence>>,
}

impl Behaviour for OrderNode<'_> {
    type Grant = Grant;
    type Work = Hosting;
    type Error = OrderNodeError;

    /// The presence of the resources, followed from the start (a standby's too: an
    /// order-node that takes over knows which resources are fenced before it hears
    /// from them again).
    async fn opened(&mut self, session: &zenoh::Session) -> Result<(), OrderNodeError> {
        let presence = Presence::follow(session, &self.config.keys)
            .await
            .map_err(zenoh_error)?;
        self.presence = Some(presence);
        Ok(())
    }

    /// Opens the journal (unless the leadership gave it), restores the orders and
    /// declares the node's queryables.
    async fn start(&mut self, start: Start<Grant>) -> Result<Hosting, OrderNodeError> {
        let config = self.config;
        let (
            journal,
            Recovered {
                hosted: recovered,
                finished,
                submits,
                next,
            },
        ) = match start.grant {
            Some((journal, recovered)) => (Some(journal), recovered),
            None => open_journal(config)?,
        };
        let presence = self
            .presence
            .clone()
            .expect("presence is followed once opened");
        let context = OrderContext::new(start.session.clone(), config, presence, journal);
        let host = Host::new(config.clone(), Arc::new(context), finished, submits, next);
        let (queue, queries) = mpsc::channel(QUERY_QUEUE);
        let endpoints = Endpoints::declare(&start.session, &host, queue)
            .await
            .map_err(zenoh_error)?;
        // A short retention is checked more often (at most every RETENTION_SWEEP).
        let every = config
            .keep_finished
            .unwrap_or(RETENTION_SWEEP)
            .clamp(Duration::from_millis(100), RETENTION_SWEEP);
        let mut sweep = tokio::time::interval(every);
        sweep.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        Ok(Hosting {
            host,
            tasks: Tasks::default(),
            queries,
            orders_cancel: CancellationToken::new(),
            endpoints: Some(endpoints),
            sweep,
            resume: Some((recovered, std::mem::take(&mut self.submits))),
            orders_stopped: false,
        })
    }
}

/// The orders to resume and the work orders to submit once the node serves.
type Resume = (
    Vec<(String, crate::progress::OrderProgress)>,
    Vec<WorkOrder>,
);

/// The node at work: the one owner of its orders ([`Host`]) and of their tasks.
pub struct Hosting {
    /// The orders.
    host: Host,
    /// Their tasks.
    tasks: Tasks,
    /// The queries the endpoints' callbacks queued for the node.
    queries: mpsc::Receiver<NodeQuery>,
    /// Stops every order task.
    orders_cancel: CancellationToken,
    /// Its queryables, until they go.
    endpoints: Option<Endpoints>,
    /// When finished orders are checked against their retention.
    sweep: tokio::time::Interval,
    /// What it resumes once it serves.
    resume: Option<Resume>,
    /// Whether its order tasks were stopped.
    orders_stopped: bool,
}

/// What the node handles next.
pub enum Turn {
    /// Finished orders are checked against their retention.
    Sweep,
    /// A query its endpoints queued.
    Query(NodeQuery),
    /// An order's task ended.
    Joined(
        Result<(tokio::task::Id, Result<(), crate::context::OrderError>), tokio::task::JoinError>,
    ),
}

impl Hosting {
    /// Stops the order tasks where they stand, once.
    async fn stop_orders(&mut self, how: &Leaving) {
        if self.orders_stopped {
            return;
        }
        self.orders_stopped = true;
        let handing_over = *how == Leaving::HandingOver;
        let node = &self.host.config.name;
        info!(%node, handing_over, "stopping: orders in progress stop where they stand");
        stop_orders(node, &mut self.tasks, &self.orders_cancel).await;
    }
}

impl Work for Hosting {
    type Event = Turn;
    type Error = OrderNodeError;

    /// Resumes the orders its journal held and submits the command line's.
    async fn serving(&mut self) {
        if let Some((recovered, submits)) = self.resume.take() {
            self.host
                .resume(recovered, &submits, &mut self.tasks, &self.orders_cancel);
        }
    }

    async fn next(&mut self) -> Next<Turn, OrderNodeError> {
        let keep = self.host.config.keep_finished.is_some();
        tokio::select! {
            _ = self.sweep.tick(), if keep => Next::Event(Turn::Sweep),
            Some(query) = self.queries.recv() => Next::Event(Turn::Query(query)),
            Some(joined) = self.tasks.set.join_next_with_id(), if !self.tasks.set.is_empty() => Next::Event(Turn::Joined(joined)),
            else => std::future::pending().await,
        }
    }

    async fn handle(&mut self, turn: Turn) {
        match turn {
            Turn::Sweep => {
                if let Some(keep) = self.host.config.keep_finished {
                    self.host.forget_finished(keep);
                }
            }
            Turn::Query(query) => {
                answer(&mut self.host, query, &mut self.tasks, &self.orders_cancel).await
            }
            Turn::Joined(joined) => {
                task_ended(&mut self.host, joined, &mut self.tasks, &self.orders_cancel).await
            }
        }
    }

    /// A successor with another data directory would not resume its orders; a journal
    /// that cannot be written could not record their progress there either.
    fn refusal(&self, request: &holon::takeover::Request) -> Option<String> {
        let config = &self.host.config;
        if !holon::life::same_data_dir(config.data_dir.as_deref(), request.data_dir.as_deref()) {
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

    async fn leave(&mut self, how: &Leaving) {
        match how {
            Leaving::Deposed(why) => {
                // Another process may serve this name already: from now on this one
                // answers nothing and shows nothing, before its orders stop.
                error!(node = %self.host.config.name, why = %why, "deposed: the order-node's leader key on etcd is no longer this process's; it stops at once (token and queryables withdrawn, order tasks stopped; their writes are refused by etcd anyway)");
                drop(self.endpoints.take());
            }
            Leaving::Stopping => {
                self.stop_orders(how).await;
                drop(self.endpoints.take());
            }
            // While handed over, submits, cancels and results get `unavailable` with a
            // retry hint from a stand-in (submits and cancels are asked again by
            // `cell`, results delivered again by the resources), until the successor
            // serves.
            Leaving::HandingOver => self.stop_orders(how).await,
            Leaving::WorkEnded => {}
        }
    }

    /// On `orders/submit` and its orders' `cancel`, `part` and `inbox`.
    fn stand_in(&self) -> StandInSpec {
        let config = &self.host.config;
        StandInSpec {
            keys: vec![
                (config.keys.orders_submit(), true),
                (config.keys.node_orders(&config.name, "cancel"), false),
                (config.keys.node_orders(&config.name, "part"), false),
                (config.keys.node_orders(&config.name, "inbox"), false),
            ],
            answer: holon::life::unavailable_answer(
                &format!("order-node {}", config.name),
                "the order-node is being handed over to its successor (an upgrade); ask again shortly".into(),
            ),
        }
    }

    /// Its orders stopped and its queryables gone; the journal closes with the host
    /// (the successor opens it).
    async fn stop(mut self, how: &Leaving) -> Result<(), OrderNodeError> {
        self.stop_orders(how).await;
        drop(self.endpoints.take());
        drop(self.queries);
        drop(self.host);
        Ok(())
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

fn zenoh_error(e: zenoh::Error) -> OrderNodeError {
    OrderNodeError::Zenoh(holon::zenoh_error::describe(&e))
}

/// The journal, if the node has a data directory, with what it holds.
fn open_journal(
    config: &OrderNodeConfig,
) -> Result<(Option<Arc<OrderJournal>>, Recovered), OrderNodeError> {
    let Some(dir) = &config.data_dir else {
        warn!(node = %config.name, "no data directory: orders are not durable (use --data-dir)");
        return Ok((
            None,
            Recovered {
                next: 1,
                ..Recovered::default()
            },
        ));
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

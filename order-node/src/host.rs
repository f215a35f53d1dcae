//! The orders an order-node hosts, and their tasks: created from work orders, resumed
//! from the journal, restarted under the one restart policy when they fail, and
//! forgotten once finished for longer than the retention.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use holon::{Intensity, RestartWindow};
use schemas::{CancelReply, HolonId, WorkOrder};
use tokio::task::JoinSet;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};
use zenoh::key_expr::KeyExpr;

use crate::config::OrderNodeConfig;
use crate::context::{OrderContext, OrderError, ORDER_RECORD};
use crate::order;
use crate::progress::OrderProgress;

/// An order task may fail and be restarted at most this often (the project's one
/// restart policy, [`holon::restart`]: order tasks are transient children); past it the
/// order fails.
const ORDER_RESTARTS: Intensity = Intensity {
    max_restarts: 3,
    period: Duration::from_secs(60),
};

/// How long an order waits before it tries again a journal that could not write.
const JOURNAL_RETRY: Duration = Duration::from_secs(1);

/// The most finished orders one sweep removes (one commit): a node that was down for
/// long removes its backlog over a few sweeps, without a long pause.
const FORGET_AT_ONCE: usize = 2000;

/// The journal record of the next order number.
pub const NEXT_RECORD: (&str, &str) = ("meta", "next_order");

/// The running order tasks, and which order each one runs.
#[derive(Default)]
pub struct Tasks {
    /// The running tasks; each ends `Ok` when its order ended (or the node stops).
    pub set: JoinSet<Result<(), OrderError>>,
    /// Which order each task runs.
    pub names: std::collections::HashMap<tokio::task::Id, String>,
}

pub struct Hosted {
    /// The order's progress: written by its task, read for queries.
    pub progress: Arc<Mutex<OrderProgress>>,
    /// The task's restarts, against [`ORDER_RESTARTS`].
    pub restarts: RestartWindow,
    /// Cancelled when an operator cancels the order (`cell cancel`).
    pub operator_cancel: CancellationToken,
}

pub struct Host {
    pub config: OrderNodeConfig,
    /// What the orders share.
    pub context: Arc<OrderContext>,
    /// Every order of this node, running or finished (until the retention ends), by name.
    pub orders: Mutex<BTreeMap<String, Hosted>>,
    /// The number of the next order (journalled before the orders are created).
    pub next: AtomicU64,
}

impl Host {
    /// Creates the orders of a work order, written to the journal before they start
    /// (and before the submitter is told their names).
    pub fn create(
        &self,
        work: &WorkOrder,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) -> Result<Vec<String>, String> {
        let first = self.next.fetch_add(work.count as u64, Ordering::SeqCst);
        let next = first + work.count as u64;
        let created: Vec<(String, OrderProgress)> = (first..next)
            .map(|n| {
                let name = format!("{}-{n}", self.config.name);
                let holon = HolonId::order(&name).expect("node names are validated");
                let progress =
                    OrderProgress::new(holon, &work.product, self.config.orders.max_attempts)
                        .with_urgency(work.priority, work.due);
                (name, progress)
            })
            .collect();
        // The next number and every new order in one commit: all of the work order is
        // written, or none of it (and the submit is refused).
        if let Some(journal) = &self.context.journal {
            let next = serde_json::to_value(next).expect("a number serializes");
            let orders = created.iter().map(|(name, progress)| {
                (
                    ORDER_RECORD,
                    name.as_str(),
                    serde_json::to_value(progress).expect("progress serializes"),
                )
            });
            let records: Vec<(&str, &str, serde_json::Value)> =
                std::iter::once((NEXT_RECORD.0, NEXT_RECORD.1, next))
                    .chain(orders)
                    .collect();
            holon::journal::blocking(|| {
                journal.put_all(records.iter().map(|(k, i, v)| (*k, *i, v)))
            })
            .map_err(|e| e.to_string())?;
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
    pub fn host(
        &self,
        name: &str,
        progress: OrderProgress,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) {
        let running = !progress.status.is_final();
        let mut progress = progress;
        if !running && progress.finished_at.is_none() {
            // Finished before ends were stamped (an older journal): kept from now on,
            // and recorded so, or a node restarted more often than the retention would
            // never forget it.
            progress.finished_at = Some(schemas::unix_ms());
            if let Err(e) = self.context.save(&progress) {
                warn!(order = %name, error = %e, "cannot record when a finished order ended; it is forgotten a retention after this start");
            }
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
    pub fn progress(&self, name: &str) -> Option<OrderProgress> {
        let orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        let progress = orders
            .get(name)?
            .progress
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone();
        Some(progress)
    }

    pub fn spawn(
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
    pub fn resume(
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

    /// Whether `name` is an order this node created and has since forgotten (it finished
    /// longer ago than the retention): numbered below the next order, and not hosted.
    pub fn forgotten(&self, name: &str) -> bool {
        let Some(number) = name
            .strip_prefix(&format!("{}-", self.config.name))
            .and_then(|n| n.parse::<u64>().ok())
        else {
            return false;
        };
        number < self.next.load(Ordering::SeqCst)
            && !self
                .orders
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .contains_key(name)
    }

    /// Forgets the orders that finished more than `keep` ago (at most
    /// [`FORGET_AT_ONCE`]): out of the journal first, in one commit, then out of memory.
    /// When the delete fails they stay until the next sweep. Returns how many went.
    pub fn forget_finished(&self, keep: Duration) -> usize {
        let now = schemas::unix_ms();
        let keep_ms = keep.as_millis() as u64;
        let expired: Vec<String> = self
            .orders
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .iter()
            .filter(|(_, hosted)| {
                let p = hosted.progress.lock().unwrap_or_else(|e| e.into_inner());
                p.status.is_final()
                    && p.finished_at
                        .is_some_and(|at| now.saturating_sub(at) > keep_ms)
            })
            .map(|(name, _)| name.clone())
            .take(FORGET_AT_ONCE)
            .collect();
        if expired.is_empty() {
            return 0;
        }
        if let Some(journal) = &self.context.journal {
            if let Err(e) = holon::journal::blocking(|| journal.delete(ORDER_RECORD, &expired)) {
                warn!(node = %self.config.name, orders = expired.len(), error = %e, "cannot remove finished orders from the journal; tried again at the next sweep");
                return 0;
            }
        }
        let mut orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
        for name in &expired {
            orders.remove(name);
        }
        info!(node = %self.config.name, orders = expired.len(), ?keep, "finished orders left the journal");
        expired.len()
    }

    /// Unfinished orders hosted here.
    pub fn unfinished(&self) -> usize {
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
    pub fn cancel(&self, name: &str) -> Result<CancelReply, String> {
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

    pub fn snapshots_matching(&self, key: &KeyExpr<'_>) -> Vec<(String, Vec<u8>)> {
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

/// An order task ended: done (the order ended), waiting for the journal (resumed after
/// a pause, not counted as a failure), or failed (restarted under the restart policy).
pub async fn task_ended(
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

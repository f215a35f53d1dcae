//! The orders an order-node hosts, and their tasks: created from work orders, resumed
//! from the journal, restarted under the one restart policy when they fail, and
//! forgotten once finished for longer than the retention.
//!
//! [`task_ended`] executes the one supervision machine ([`holon::supervisor::machine`])
//! for the order tasks: `simple_one_for_one`, transient, an intensity per order (past it
//! the order fails, not the node); a journal fault is a pause it sorts out itself.
//!
//! Only unfinished orders are held in memory. An order leaves memory when it finishes
//! (its final progress was written to the journal before it was final in memory): from
//! then on what is asked about it (its state, a cancel, a late result) is answered from
//! the journal, until the retention sweep deletes it there. What stays in memory of a
//! finished order is its number and when it ended (see [`Host::finished`]). Without a
//! journal there is nowhere else to read them from: finished orders stay in memory until
//! the retention ends, as they always did.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use holon::supervisor::{Action, Event, Machine, Scope, Strategy};
use holon::{Intensity, RestartType};
use schemas::layout::LocationId;
use schemas::{CancelReply, ErrorCode, HolonId, WorkOrder};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};
use zenoh::key_expr::KeyExpr;

use crate::cancel::CancelAsk;
use crate::config::OrderNodeConfig;
use crate::context::{OrderContext, OrderError, Progress, ProgressView, ORDER_RECORD};
use crate::journal::OrderJournalError;
use crate::order;
use crate::part_word::{WordAnswer, WordAsk};
use crate::progress::OrderProgress;
use crate::submits::{Submits, Submitted, SUBMIT_RECORD};

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

/// The most finished orders read from the journal in one go for a state read.
const READ_AT_ONCE: usize = 256;

/// The journal record of the next order number.
pub const NEXT_RECORD: (&str, &str) = ("meta", "next_order");

/// The running order tasks, which order each one runs, and their supervision.
pub struct Tasks {
    /// The running tasks; each ends `Ok` when its order ended (or the node stops).
    pub set: JoinSet<Result<(), OrderError>>,
    /// Which order each task runs.
    pub names: std::collections::HashMap<tokio::task::Id, String>,
    /// What to do when an order's task ends: the unfinished orders, each with its
    /// restarts against [`ORDER_RESTARTS`].
    pub supervision: Machine<String>,
}

impl Default for Tasks {
    fn default() -> Tasks {
        Tasks {
            set: JoinSet::new(),
            names: Default::default(),
            supervision: Machine::new(Strategy::SimpleOneForOne, ORDER_RESTARTS)
                .scope(Scope::PerChild),
        }
    }
}

/// An order held in memory: unfinished (or finished, without a journal).
pub struct Hosted {
    /// The order's progress as its writer last committed it (the running task's, or
    /// the node's while no task runs): read for queries.
    pub progress: ProgressView,
    /// Cancelled by the order's task once it recorded an operator's cancel (`cell
    /// cancel`); cancelled at the start for an order whose journal says so.
    pub operator_cancel: CancellationToken,
    /// The mailbox of the order's running task for cancels ([`crate::cancel`]); closed
    /// while no task runs.
    pub cancel_asks: mpsc::Sender<CancelAsk>,
    /// The mailbox of the order's running task for operators' words on its lost part
    /// ([`crate::part_word`]); closed while no task runs.
    pub part_words: mpsc::Sender<WordAsk>,
}

/// A finished order that is only in the journal, as memory keeps it: when it ended and
/// how (16 bytes: enough to count and filter a listing without reading the journal).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Ended {
    /// When it finished (Unix ms).
    pub at: u64,
    /// How it finished.
    pub status: schemas::OrderStatus,
}

/// The finished orders that are only in the journal, by order number.
pub type Finished = BTreeMap<u64, Ended>;

/// The orders of an order-node, and what they share: owned by the node's loop, which
/// alone changes it (the order tasks write their own progress, seen here through each
/// order's [`ProgressView`]).
pub struct Host {
    /// The node's configuration.
    pub config: OrderNodeConfig,
    /// What the orders share.
    pub context: Arc<OrderContext>,
    /// The orders held in memory, by name: the unfinished ones, and finished ones that
    /// cannot be read from the journal (no journal, or their end could not be recorded)
    /// until the retention ends.
    pub orders: BTreeMap<String, Hosted>,
    /// The finished orders read from the journal when asked for, until the retention
    /// sweep deletes them there (about 20 bytes each: two numbers in a map). An order
    /// is in `orders` or here, never in both.
    pub finished: Finished,
    /// The named work orders it made ([`crate::submits`]), remembered as long as
    /// finished orders are.
    pub submits: Submits,
    /// The number of the next order (journalled before the orders are created).
    pub next: u64,
}

impl Hosted {
    /// A writer of the order's progress for whoever writes it next (a new run of its
    /// task, or the node failing the order for good), seeded with the last committed
    /// progress: the view follows the new writer from now on.
    fn writer(&mut self) -> Progress {
        let (writer, view) = Progress::new(self.progress.borrow().clone());
        self.progress = view;
        writer
    }
}

impl Host {
    /// The orders of a node that holds none in memory yet: `finished` (in the journal),
    /// the named work orders it made and the number of the next order as recovered.
    pub fn new(
        config: OrderNodeConfig,
        context: Arc<OrderContext>,
        finished: Finished,
        submits: Submits,
        next: u64,
    ) -> Host {
        Host {
            config,
            context,
            orders: BTreeMap::new(),
            finished,
            submits,
            next,
        }
    }

    /// Creates the orders of a work order, written to the journal before they start
    /// (and before the submitter is told their names).
    pub fn create(
        &mut self,
        work: &WorkOrder,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) -> Result<Vec<String>, String> {
        let first = self.next;
        let next = first + work.count as u64;
        // Used up even when the write below fails: a number is never given twice.
        self.next = next;
        let named = work.submit_id.as_ref().map(|id| {
            let made = Submitted {
                product: work.product.clone(),
                count: work.count,
                first,
                at: schemas::unix_ms(),
            };
            (id.clone(), made)
        });
        let created: Vec<(String, OrderProgress)> = (first..next)
            .map(|n| {
                let name = order_name_of(&self.config.name, n);
                let holon = HolonId::order(&name).expect("node names are validated");
                let progress =
                    OrderProgress::new(holon, &work.product, self.config.orders.max_attempts)
                        .with_urgency(work.priority, work.due);
                (name, progress)
            })
            .collect();
        // The next number, every new order and the work order's name in one commit:
        // all of the work order is written, or none of it (and the submit is refused).
        if let Some(journal) = &self.context.journal {
            let next = serde_json::to_value(next).expect("a number serializes");
            let orders = created.iter().map(|(name, progress)| {
                (
                    ORDER_RECORD,
                    name.as_str(),
                    serde_json::to_value(progress).expect("progress serializes"),
                )
            });
            let name = named.as_ref().map(|(id, made)| {
                let made = serde_json::to_value(made).expect("a work order's name serializes");
                (SUBMIT_RECORD, id.as_str(), made)
            });
            let records: Vec<(&str, &str, serde_json::Value)> =
                std::iter::once((NEXT_RECORD.0, NEXT_RECORD.1, next))
                    .chain(orders)
                    .chain(name)
                    .collect();
            holon::journal::blocking(|| {
                journal.put_all(records.iter().map(|(k, i, v)| (*k, *i, v)))
            })
            .map_err(|e| e.to_string())?;
        }
        if let Some((id, made)) = named {
            self.submits.insert(id, made);
        }
        let mut names = Vec::new();
        for (name, progress) in created {
            self.host(&name, progress, tasks, cancel);
            names.push(name);
        }
        info!(node = %self.config.name, product = %work.product, count = work.count, first = names.first().map(String::as_str).unwrap_or(""), "orders created");
        Ok(names)
    }

    /// Hosts an order: running ones get a task; finished ones stay in the journal.
    pub fn host(
        &mut self,
        name: &str,
        progress: OrderProgress,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) {
        let running = !progress.status.is_final();
        let mut progress = progress;
        let mut recorded = true;
        if !running && progress.finished_at.is_none() {
            // Finished before ends were stamped (an older journal): kept from now on,
            // and recorded so, or a node restarted more often than the retention would
            // never forget it.
            progress.finished_at = Some(schemas::unix_ms());
            if let Err(e) = self.context.save(&progress) {
                warn!(order = %name, error = %e, "cannot record when a finished order ended; it is forgotten a retention after this start");
                // The journal's copy lacks the end: this one is answered from memory.
                recorded = false;
            }
        }
        if !running && recorded && self.leave_memory(name, &progress) {
            return;
        }
        let operator_cancel = CancellationToken::new();
        if progress.cancel_requested {
            operator_cancel.cancel();
        }
        self.orders.insert(
            name.to_string(),
            Hosted {
                progress: Progress::new(progress).1,
                operator_cancel,
                cancel_asks: crate::cancel::mailbox().0,
                part_words: crate::part_word::mailbox().0,
            },
        );
        if running {
            let added = Event::Added {
                child: name.to_string(),
                restart: RestartType::Transient,
            };
            for action in tasks.supervision.handle(added, Instant::now()) {
                if let Action::Start(name) = action {
                    self.spawn(&name, tasks, cancel, Duration::ZERO);
                }
            }
        }
    }

    /// The number of `name` if it is the name this node gives its order of that number.
    pub(crate) fn number(&self, name: &str) -> Option<u64> {
        order_number(&self.config.name, name)
    }

    /// Lets a finished order's progress go from memory, to be read from the journal
    /// from now on: true when it can be (there is a journal, which holds this very
    /// progress, and the order ended at a known time); the caller drops its copy.
    fn leave_memory(&mut self, name: &str, progress: &OrderProgress) -> bool {
        if self.context.journal.is_none() {
            return false;
        }
        let (Some(number), Some(at)) = (self.number(name), progress.finished_at) else {
            return false;
        };
        self.finished.insert(
            number,
            Ended {
                at,
                status: progress.status,
            },
        );
        true
    }

    /// An order's task ended: when its order finished, it leaves memory (its final
    /// progress was written to the journal before it was final in memory). An order
    /// stopped with the node, or waiting to be restarted, stays.
    pub fn retire(&mut self, name: &str) {
        let Some(hosted) = self.orders.get(name) else {
            return;
        };
        let progress = hosted.progress.borrow().clone();
        if progress.status.is_final() && self.leave_memory(name, &progress) {
            self.orders.remove(name);
            debug!(node = %self.config.name, order = %name, "finished order left memory; read from the journal from now on");
        }
    }

    /// Whether `name` is a finished order that is only in the journal.
    fn in_journal(&self, name: &str) -> bool {
        self.number(name)
            .is_some_and(|n| self.finished.contains_key(&n))
    }

    /// Reads finished orders from the journal, without holding a runtime worker.
    pub(crate) fn read_finished(
        &self,
        names: &[String],
    ) -> Result<Vec<(String, OrderProgress)>, OrderJournalError> {
        let Some(journal) = &self.context.journal else {
            return Ok(Vec::new());
        };
        if names.is_empty() {
            return Ok(Vec::new());
        }
        holon::journal::blocking(|| journal.get_many(ORDER_RECORD, names))
    }

    /// The progress of `name` if it is an order of this node: from memory while it is
    /// unfinished, from the journal once it finished.
    pub fn progress(&self, name: &str) -> Result<Option<OrderProgress>, OrderJournalError> {
        if let Some(hosted) = self.orders.get(name) {
            return Ok(Some(hosted.progress.borrow().clone()));
        }
        if !self.in_journal(name) {
            return Ok(None);
        }
        Ok(self
            .read_finished(&[name.to_string()])?
            .pop()
            .map(|(_, progress)| progress))
    }

    /// Starts a run of the task of `name`, a hosted order, after `delay`: the run is
    /// its progress's writer, and gets a mailbox of its own for cancels.
    pub fn spawn(
        &mut self,
        name: &str,
        tasks: &mut Tasks,
        cancel: &CancellationToken,
        delay: Duration,
    ) {
        let Some(hosted) = self.orders.get_mut(name) else {
            return;
        };
        let context = self.context.clone();
        let cancel = cancel.child_token();
        let progress = hosted.writer();
        // This run of the task gets a mailbox of its own: the node's table keeps where
        // to send.
        let (asks, cancel_asks) = crate::cancel::mailbox();
        hosted.cancel_asks = asks;
        let (words, part_words) = crate::part_word::mailbox();
        hosted.part_words = words;
        let operator_cancel = hosted.operator_cancel.clone();
        let handle = tasks.set.spawn(async move {
            if !delay.is_zero() {
                tokio::select! {
                    _ = tokio::time::sleep(delay) => {}
                    _ = cancel.cancelled() => return Ok(()),
                }
            }
            let mailboxes = order::Mailboxes {
                cancel_asks,
                part_words,
            };
            order::run(context, progress, cancel, operator_cancel, mailboxes).await
        });
        tasks.names.insert(handle.id(), name.to_string());
    }

    /// Hosts the orders recovered from the journal (resuming the unfinished ones) and
    /// creates those of `--submit`.
    pub fn resume(
        &mut self,
        recovered: Vec<(String, OrderProgress)>,
        submits: &[WorkOrder],
        tasks: &mut Tasks,
        cancel: &CancellationToken,
    ) {
        let node = self.config.name.clone();
        let finished = self.finished.len();
        if !recovered.is_empty() || finished > 0 {
            let resumed = recovered
                .iter()
                .filter(|(_, p)| !p.status.is_final())
                .count();
            info!(%node, orders = recovered.len() + finished, resumed, "orders recovered from the journal");
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
    /// longer ago than the retention): numbered below the next order, and neither in
    /// memory nor among the finished orders of the journal.
    pub fn forgotten(&self, name: &str) -> bool {
        let Some(number) = name
            .strip_prefix(&format!("{}-", self.config.name))
            .and_then(|n| n.parse::<u64>().ok())
        else {
            return false;
        };
        number < self.next && !self.orders.contains_key(name) && !self.in_journal(name)
    }

    /// Unfinished orders hosted here.
    pub fn unfinished(&self) -> usize {
        self.orders
            .values()
            .filter(|h| !h.progress.borrow().status.is_final())
            .count()
    }

    /// An operator's cancel of `name`: asked of the order's task, which records it
    /// ([`crate::cancel`]); an ended order's is refused from what is recorded.
    pub async fn cancel(&self, name: &str) -> Result<CancelReply, (ErrorCode, String)> {
        let asks = match self.orders.get(name) {
            Some(hosted) => {
                let progress = hosted.progress.borrow();
                if progress.status.is_final() {
                    return Ok(crate::cancel::refused(name, &progress));
                }
                Some(hosted.cancel_asks.clone())
            }
            None => None,
        };
        if let Some(asks) = asks {
            return crate::cancel::ask(&asks, name).await;
        }
        // Finished (or unknown): refused, as it ended.
        let progress = self
            .progress(name)
            .map_err(|e| {
                (
                    ErrorCode::Internal,
                    format!("cannot read {name} from the journal: {e}"),
                )
            })?
            .ok_or_else(|| {
                (
                    ErrorCode::UnknownOrder,
                    format!("{name} is not an order of {}", self.config.name),
                )
            })?;
        Ok(crate::cancel::refused(name, &progress))
    }

    /// An operator's word that the lost part of `name` is at `location` (`by` says who):
    /// checked against what the order last committed, then taken by the order's task,
    /// which records it ([`crate::part_word`]).
    pub async fn part_word(&self, name: &str, location: LocationId, by: String) -> WordAnswer {
        let Some(hosted) = self.orders.get(name) else {
            let ended = self.progress(name).ok().flatten().is_some();
            return Err(crate::part_word::not_hosted(name, &self.config.name, ended));
        };
        let conversation_id = crate::part_word::check(name, &hosted.progress.borrow(), &location)?;
        let words = hosted.part_words.clone();
        crate::part_word::ask(&words, name, conversation_id, location, by).await
    }

    /// The states of the orders whose `order/<name>/state` intersects `key`, by name:
    /// (key, snapshot as JSON). Unfinished orders from memory, finished ones from the
    /// journal (when it cannot be read, only those in memory, and a warning).
    pub fn snapshots_matching(&self, key: &KeyExpr<'_>) -> Vec<(String, Vec<u8>)> {
        let state = |snapshot: &schemas::OrderSnapshot| -> Option<(String, Vec<u8>)> {
            let state_key = self.config.keys.state(&snapshot.holon);
            let ke = KeyExpr::try_from(state_key.clone()).ok()?;
            ke.intersects(key)
                .then(|| (state_key, serde_json::to_vec(snapshot).expect("serializes")))
        };
        let mut states: Vec<(String, (String, Vec<u8>))> = self
            .orders
            .iter()
            .filter_map(|(name, hosted)| {
                let snapshot = hosted.progress.borrow().snapshot();
                Some((name.clone(), state(&snapshot)?))
            })
            .collect();
        // A wildcard read (`order/*/state`, a dashboard's first look) gets the orders
        // in memory only: the finished ones of a long history are listed a page at a
        // time ([`Host::page`]), and read one by one by their own keys.
        if key.is_wild() {
            states.sort_by(|a, b| a.0.cmp(&b.0));
            return states.into_iter().map(|(_, state)| state).collect();
        }
        let wanted: Vec<String> = self
            .finished
            .keys()
            .map(|number| order_name_of(&self.config.name, *number))
            .filter(|name| {
                HolonId::order(name).is_ok_and(|holon| {
                    KeyExpr::try_from(self.config.keys.state(&holon))
                        .is_ok_and(|ke| ke.intersects(key))
                })
            })
            .collect();
        // A few at a time: only their snapshots are held, not every progress at once.
        for chunk in wanted.chunks(READ_AT_ONCE) {
            match self.read_finished(chunk) {
                Ok(read) => states.extend(
                    read.into_iter()
                        .filter_map(|(name, progress)| Some((name, state(&progress.snapshot())?))),
                ),
                Err(e) => {
                    warn!(node = %self.config.name, orders = wanted.len(), error = %e, "cannot read finished orders from the journal; the reader gets the unfinished ones only");
                    states.retain(|(name, _)| self.orders.contains_key(name));
                    break;
                }
            }
        }
        // In the order of their names, as when every order was in one map.
        states.sort_by(|a, b| a.0.cmp(&b.0));
        states.into_iter().map(|(_, state)| state).collect()
    }
}

/// The name node `node` gives its order of `number`: `<node>-<number>`.
pub fn order_name_of(node: &str, number: u64) -> String {
    format!("{node}-{number}")
}

/// The number of `name` if it is the name node `node` gives its order of that number
/// (`<node>-<n>`).
pub fn order_number(node: &str, name: &str) -> Option<u64> {
    let number = name
        .strip_prefix(node)?
        .strip_prefix('-')?
        .parse::<u64>()
        .ok()?;
    (order_name_of(node, number) == name).then_some(number)
}

/// An order task ended: done (the order ended), waiting for the journal (resumed after
/// a pause, not counted as a failure), or failed (restarted under the restart policy,
/// or, past it, the order fails).
pub async fn task_ended(
    host: &mut Host,
    joined: Result<(tokio::task::Id, Result<(), OrderError>), tokio::task::JoinError>,
    tasks: &mut Tasks,
    cancel_all: &CancellationToken,
) {
    let (id, normally, why) = match joined {
        Ok((id, Ok(()))) => (id, true, String::new()),
        Ok((id, Err(OrderError::Journal(why)))) => {
            // Not the order's fault: resumed from its last written progress once the
            // journal can write again (tried every second), not counted against its
            // restarts (the machine is not told: to it the order runs on).
            let Some(name) = tasks.names.remove(&id) else {
                return;
            };
            debug!(node = %host.config.name, order = %name, error = %why, "order waits for the journal");
            host.spawn(&name, tasks, cancel_all, JOURNAL_RETRY);
            return;
        }
        Ok((id, Err(e))) => (id, false, e.to_string()),
        Err(e) if e.is_panic() => {
            let id = e.id();
            let why = format!(
                "panicked: {}",
                holon::supervisor::panic_message(e.into_panic())
            );
            (id, false, why)
        }
        Err(e) => {
            // Aborted: the node is stopping.
            if let Some(name) = tasks.names.remove(&e.id()) {
                tasks
                    .supervision
                    .handle(Event::Removed { child: name }, Instant::now());
            }
            return;
        }
    };
    let Some(name) = tasks.names.remove(&id) else {
        return;
    };
    if !normally {
        error!(node = %host.config.name, order = %name, error = %why, "order task failed");
    }
    let exited = Event::Exited {
        child: name.clone(),
        normally,
        why,
    };
    for action in tasks.supervision.handle(exited, Instant::now()) {
        match action {
            Action::Done(name) => host.retire(&name),
            Action::Start(name) | Action::RestartAfter(name, _) => {
                if host.orders.contains_key(&name) {
                    warn!(order = %name, "restarting order");
                    host.spawn(&name, tasks, cancel_all, Duration::ZERO);
                }
            }
            Action::GiveUp { child, .. } => fail(host, &child).await,
            // simple_one_for_one stops no other order.
            Action::Stop(_) => {}
        }
    }
}

/// Fails an order whose task failed more often than [`ORDER_RESTARTS`] allows, recorded
/// in the journal and published, so it does not resume after a restart of the node.
async fn fail(host: &mut Host, name: &str) {
    // No task runs it any more: the node writes its end.
    let Some(progress) = host.orders.get_mut(name).map(Hosted::writer) else {
        return;
    };
    let why = format!(
        "the order task failed more than {} times within {:?}",
        ORDER_RESTARTS.max_restarts, ORDER_RESTARTS.period
    );
    error!(order = %name, reason = %why, "order failed");
    if let Err(e) = host.context.commit(&progress, |p| p.fail(why)).await {
        // Not recorded: the order resumes after a restart of the node, as before.
        error!(order = %name, error = %e, "cannot record that the order failed; it stays unfinished in the journal");
    }
    host.context.publish(&progress).await;
    host.retire(name);
}

mod retention;
#[cfg(test)]
mod tests;

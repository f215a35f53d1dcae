//! What every order of a node shares: the session, the settings, the presence of the
//! resources, the inboxes, the journal, and the pacing of orders that wait.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::watch;
use tracing::{error, info, warn};

use crate::advice_pause::AdvicePause;
use crate::config::OrderSettings;
use crate::home_line::HomeLine;
use crate::inbox::Inboxes;
use crate::journal::OrderJournal;
use crate::presence::Presence;
use crate::progress::OrderProgress;
use crate::ranking::BookingsInFlight;
use crate::station_line::StationLine;

/// What every order of a node shares.
pub struct OrderContext {
    /// The node's zenoh session.
    pub session: zenoh::Session,
    /// The cell's keys.
    pub keys: schemas::CellKeys,
    /// How the orders negotiate (`[orders]` of the node's config).
    pub settings: OrderSettings,
    /// Which resources are alive and whose turn it is on each.
    pub presence: Arc<Presence>,
    /// Where results reach the running orders (one queryable for the node).
    pub inboxes: Arc<Inboxes>,
    /// Permits for proposal rounds in flight (see [`MAX_CONCURRENT_ROUNDS`]).
    pub rounds: tokio::sync::Semaphore,
    /// Orders waiting after a round nobody proposed in, or for a plan (see
    /// [`IDLE_POLL_SPACING`]).
    pub idle: Arc<std::sync::atomic::AtomicUsize>,
    /// The journal (SQLite or etcd); `None`: orders are kept in memory only.
    pub journal: Option<Arc<OrderJournal>>,
    /// Permits for orders waiting on a journal commit with a thread of their own (see
    /// [`JOURNAL_WAITERS`]).
    pub journal_waiters: tokio::sync::Semaphore,
    /// Set while journal writes fail (logged once per fault, not per order).
    pub journal_failing: AtomicBool,
    /// Bookings asked and not answered yet, per resource (see [`BookingsInFlight`]).
    pub bookings_in_flight: BookingsInFlight,
    /// Whether the staff answers: asking stops for a while when it does not.
    pub advice_pause: AdvicePause,
    /// The line at the stations: parts in the cell take turns to look for a station
    /// place, oldest first.
    pub line: StationLine,
    /// The parts waiting outside the cell for a home, with their priorities: a part
    /// leaves a freed home to a part of a higher priority.
    pub homes: HomeLine,
    /// The cell's layout, followed from the first order whose plan moves parts
    /// ([`OrderContext::layout`]) until the node's orders are dropped.
    pub layout: CellLayoutFollowing,
}

/// The cell's layout, followed once an order asks for it.
#[derive(Default)]
pub struct CellLayoutFollowing(tokio::sync::OnceCell<holon::layout::Follower>);

/// How many orders wait on a journal commit at once with a thread of their own. A
/// commit blocks its caller (an fsync, etcd's answer) and each order task that waits
/// on one takes a thread from the runtime's blocking pool (`block_in_place`): with 200
/// parts in flight the node grew to about 210 threads (docs/benchmarks.md, "The
/// order-node's memory under moving parts, profiled"). The rest wait for a permit
/// without a thread; the writers holding one still share a commit (the journal's
/// group commit).
pub const JOURNAL_WAITERS: usize = 8;

/// The journal kind of order records.
pub const ORDER_RECORD: &str = "order";

impl OrderContext {
    /// What the orders of a node configured by `config` share, on `session`.
    pub fn new(
        session: zenoh::Session,
        config: &crate::config::OrderNodeConfig,
        presence: Arc<Presence>,
        journal: Option<Arc<OrderJournal>>,
    ) -> OrderContext {
        let (freed, appeared) = presence.room_news();
        OrderContext {
            line: StationLine::start(freed, appeared),
            homes: HomeLine::default(),
            session,
            keys: config.keys.clone(),
            settings: config.orders,
            presence,
            inboxes: Default::default(),
            rounds: tokio::sync::Semaphore::new(MAX_CONCURRENT_ROUNDS),
            idle: Default::default(),
            journal,
            journal_waiters: tokio::sync::Semaphore::new(JOURNAL_WAITERS),
            journal_failing: Default::default(),
            bookings_in_flight: Default::default(),
            advice_pause: Default::default(),
            layout: Default::default(),
        }
    }

    /// The cell's layout as it stands (`None` while no resource has answered its part):
    /// the first call starts following it and waits for the first answers (at most a
    /// few seconds).
    pub async fn layout(&self) -> Option<Arc<schemas::layout::CellLayout>> {
        let follower = self
            .layout
            .0
            .get_or_init(|| async {
                let mut follower = holon::layout::Follower::start(&self.session, &self.keys);
                if !follower.first(Duration::from_secs(3)).await {
                    warn!("no resource answered its part of the cell's layout yet");
                }
                follower
            })
            .await;
        follower.latest()
    }

    /// The epoch at which this node holds its leader key, on etcd (`None` on SQLite).
    pub fn epoch(&self) -> Option<u64> {
        let epoch = self.journal.as_ref()?.epoch()?;
        u64::try_from(epoch).ok()
    }

    /// Writes the order's progress; the order acts on a change only once it is written.
    pub fn save(&self, progress: &OrderProgress) -> Result<(), OrderError> {
        let Some(journal) = &self.journal else {
            return Ok(());
        };
        // A commit may wait for an fsync: with thousands of orders writing at once that
        // would hold every worker thread, and nothing else (SIGTERM, queries) would run.
        // On the multi-thread runtime the worker hands its other tasks over while it waits.
        let written =
            holon::journal::blocking(|| journal.put(ORDER_RECORD, progress.holon.name(), progress));
        match written {
            Ok(()) => {
                if self.journal_failing.swap(false, Ordering::SeqCst) {
                    info!("the journal can be written again: waiting orders resume");
                }
                Ok(())
            }
            Err(e) if e.is_deposed() => {
                // The node's loop stops it (it is deposed); nothing was written.
                self.journal_failing.store(true, Ordering::SeqCst);
                Err(OrderError::Journal(format!(
                    "the order-node is deposed, its write refused: {e}"
                )))
            }
            Err(e) => {
                if !self.journal_failing.swap(true, Ordering::SeqCst) {
                    error!(error = %e, "the journal cannot be written: orders wait where they stand (results stay unacknowledged, so resources keep them) and resume once it can (tried every second); new work orders are refused");
                }
                Err(OrderError::Journal(e.to_string()))
            }
        }
    }

    /// Publishes an order's state on `order/<name>/state`.
    pub async fn publish(&self, progress: &Progress) {
        let snapshot = progress.get().snapshot();
        let key = self.keys.state(&snapshot.holon);
        let payload = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
        if let Err(e) = self.session.put(&key, payload).await {
            warn!(holon = %snapshot.holon, error = %e, "cannot publish the order's state; it is published again at the next change");
        }
    }

    /// Applies `change` to an order's progress once it is written: when the journal
    /// cannot write, the progress in memory stays the last one written (a restarted
    /// order task resumes from there, and an unacknowledged result comes again).
    ///
    /// It waits for a permit to wait on the journal ([`JOURNAL_WAITERS`]) before it
    /// reads the progress: from there to the write nothing awaits, as before.
    pub async fn commit(
        &self,
        progress: &Progress,
        change: impl FnOnce(&mut OrderProgress),
    ) -> Result<(), OrderError> {
        let _waiting = match &self.journal {
            Some(_) => Some(
                self.journal_waiters
                    .acquire()
                    .await
                    .expect("the permits are never closed"),
            ),
            None => None,
        };
        let mut next = progress.get().clone();
        change(&mut next);
        if next.status.is_final() && next.finished_at.is_none() {
            next.finished_at = Some(schemas::unix_ms());
        }
        self.save(&next)?;
        progress.0.send_replace(next);
        Ok(())
    }
}

/// Counts one order among the idle ones for as long as it lives.
pub struct IdleOrder {
    idle: Arc<std::sync::atomic::AtomicUsize>,
    /// How many others were idle when it joined them.
    others: usize,
}

impl IdleOrder {
    /// The least pause of this order's next ask: [`IDLE_POLL_SPACING`] per other idle
    /// order, so all of them together ask about once per spacing.
    pub fn spacing(&self) -> Duration {
        IDLE_POLL_SPACING * self.others.min(100_000) as u32
    }

    pub fn count(idle: &Arc<std::sync::atomic::AtomicUsize>) -> IdleOrder {
        IdleOrder {
            idle: idle.clone(),
            others: idle.fetch_add(1, Ordering::SeqCst),
        }
    }
}

impl Drop for IdleOrder {
    fn drop(&mut self) {
        self.idle.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Why an order task stopped before its order ended.
#[derive(Debug, thiserror::Error)]
pub enum OrderError {
    /// The journal could not record a change: the task is restarted after a pause (not
    /// counted as a failure) from the last written progress.
    #[error("the journal cannot record the order's progress: {0}")]
    Journal(String),
    #[error("{0}")]
    Other(String),
}

impl From<String> for OrderError {
    fn from(why: String) -> Self {
        OrderError::Other(why)
    }
}

/// An order's progress as its writer holds it: the running order's task (each run of
/// it a writer of its own), or the node while no task runs (an order it creates, or
/// fails for good). Changed only by [`OrderContext::commit`], once written to the
/// journal; the node reads it through the [`ProgressView`] that follows this writer.
/// Not shared: the task's futures (its attempt, its answers to cancels) borrow it in
/// turn, and a change is whole before the next await.
pub struct Progress(watch::Sender<OrderProgress>);

/// An order's progress as the node sees it: what its writer last committed (kept when
/// the writer ends, as a finished order's last word).
pub type ProgressView = watch::Receiver<OrderProgress>;

impl Progress {
    /// A writer of `progress`, and the node's view of what it writes.
    pub fn new(progress: OrderProgress) -> (Progress, ProgressView) {
        let (writer, view) = watch::channel(progress);
        (Progress(writer), view)
    }

    /// The progress as last committed (not to be held across an await).
    pub fn get(&self) -> watch::Ref<'_, OrderProgress> {
        self.0.borrow()
    }
}

/// How often an order that no resource could take asks again, at most, when nothing
/// woke it (an appearance, a resource ready again, a freed place).
pub const IDLE_POLL: Duration = Duration::from_secs(10);

/// The fallback pause of an idle order grows with the number of idle orders, so that
/// all of them together ask about once per this interval: 5,000 orders waiting for a
/// missing resource ask 10 times a second in all, not 500.
pub const IDLE_POLL_SPACING: Duration = Duration::from_millis(100);

/// Proposal rounds in flight at once on a node: when a resource appears and wakes
/// thousands of waiting orders, they ask in turn (oldest first), not all at once.
pub const MAX_CONCURRENT_ROUNDS: usize = 64;

/// `pause` less up to a quarter, at random: orders that wait together do not retry in
/// lockstep.
pub fn jittered(pause: Duration) -> Duration {
    use std::hash::BuildHasher;
    let random = std::collections::hash_map::RandomState::new().hash_one(std::time::Instant::now());
    pause.mul_f64(1.0 - (random % 1000) as f64 / 4000.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jitter_shortens_by_at_most_a_quarter() {
        for _ in 0..1000 {
            let pause = jittered(Duration::from_millis(1000));
            assert!(
                pause <= Duration::from_millis(1000) && pause >= Duration::from_millis(750),
                "{pause:?}"
            );
        }
    }
}

//! What every order of a node shares: the session, the settings, the presence of the
//! resources, the inboxes, the journal, and the pacing of orders that wait.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use holon::journal::Journal;
use tracing::{error, info, warn};

use crate::config::OrderSettings;
use crate::inbox::Inboxes;
use crate::presence::Presence;
use crate::progress::OrderProgress;

/// What every order of a node shares.
pub struct OrderContext {
    pub session: zenoh::Session,
    pub keys: schemas::CellKeys,
    pub settings: OrderSettings,
    pub presence: Arc<Presence>,
    /// Where results reach the running orders (one queryable for the node).
    pub inboxes: Arc<Inboxes>,
    /// Permits for proposal rounds in flight (see [`MAX_CONCURRENT_ROUNDS`]).
    pub rounds: tokio::sync::Semaphore,
    /// Orders waiting after a round nobody proposed in, or for a plan (see
    /// [`IDLE_POLL_SPACING`]).
    pub idle: Arc<std::sync::atomic::AtomicUsize>,
    pub journal: Option<Arc<Journal>>,
    /// Set while journal writes fail (logged once per fault, not per order).
    pub journal_failing: AtomicBool,
    /// Bookings asked and not answered yet, per resource (see [`BookingsInFlight`]).
    pub bookings_in_flight: BookingsInFlight,
}

/// The bookings this node's orders asked and have no answer to yet, per resource.
///
/// Many orders of one node ask for proposals at once (a batch of work orders, a
/// resource that came back): every round then hears about the same waits, and without
/// care they would all book the same resource while others stay idle. So a round ranks
/// its proposals by the queue as it is when the round ends: the resource's latest
/// published queue (fresher than its proposal), plus the bookings in flight to it, each
/// at the proposal's `duration_ms`. Ranking counts the round's own choice as in flight at
/// once, under one lock ([`BookingsInFlight::rank`]), so rounds that end together see
/// each other's choices; the booking's answer ends it ([`BookingsInFlight::answered`]).
#[derive(Default)]
pub struct BookingsInFlight(Arc<Mutex<InFlightCounts>>);

type InFlightCounts = std::collections::HashMap<schemas::HolonId, u64>;

/// A booking a ranking counted in flight: it ends when dropped (the booking was
/// answered, or the order gave up before asking it).
pub struct InFlight {
    counts: Arc<Mutex<InFlightCounts>>,
    /// The resource it is asked of.
    pub resource: schemas::HolonId,
}

impl Drop for InFlight {
    fn drop(&mut self) {
        let mut counts = self.counts.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = counts.get_mut(&self.resource) {
            *n = n.saturating_sub(1);
        }
    }
}

/// One proposal as a round heard it.
#[derive(Debug, Clone)]
pub struct Offer {
    /// The resource failed this step before: tried last.
    pub avoided: bool,
    pub expected_wait_ms: u64,
    pub queue_position: u64,
    /// The service's nominal duration on that resource.
    pub duration_ms: u64,
    pub provider: schemas::HolonId,
}

impl BookingsInFlight {
    fn counts(&self) -> std::sync::MutexGuard<'_, InFlightCounts> {
        self.0.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The round's offers, best first: not avoided; then the shortest expected wait,
    /// then queue, as they are now (`published`: a resource's latest published queue,
    /// if any); ties at random. The best is counted in flight (its order books it next)
    /// until the returned [`InFlight`] is dropped.
    pub fn rank(
        &self,
        offers: Vec<Offer>,
        published: impl Fn(&schemas::HolonId) -> Option<u64>,
    ) -> (Vec<schemas::HolonId>, Option<InFlight>) {
        let mut in_flight = self.counts();
        let mut ranked: Vec<(bool, u64, u64, u64, schemas::HolonId)> = offers
            .into_iter()
            .map(|o| {
                let queue = published(&o.provider)
                    .unwrap_or(o.queue_position)
                    .saturating_add(in_flight.get(&o.provider).copied().unwrap_or(0));
                // The proposal's wait, moved by what changed since: its jobs of other
                // service types keep their own durations.
                let wait = if queue >= o.queue_position {
                    o.expected_wait_ms
                        .saturating_add((queue - o.queue_position).saturating_mul(o.duration_ms))
                } else {
                    o.expected_wait_ms
                        .saturating_sub((o.queue_position - queue).saturating_mul(o.duration_ms))
                };
                (o.avoided, wait, queue, tie_break(), o.provider)
            })
            .collect();
        ranked.sort();
        let counted = ranked.first().map(|(_, _, _, _, best)| {
            *in_flight.entry(best.clone()).or_default() += 1;
            InFlight {
                counts: self.0.clone(),
                resource: best.clone(),
            }
        });
        (
            ranked.into_iter().map(|(_, _, _, _, p)| p).collect(),
            counted,
        )
    }
}

/// A random number, to order equal proposals.
fn tie_break() -> u64 {
    use std::hash::BuildHasher;
    std::collections::hash_map::RandomState::new().hash_one(std::time::Instant::now())
}

/// The journal kind of order records.
pub const ORDER_RECORD: &str = "order";

impl OrderContext {
    /// Writes the order's progress; the order acts on a change only once it is written.
    pub fn save(&self, progress: &OrderProgress) -> Result<(), OrderError> {
        let Some(journal) = &self.journal else {
            return Ok(());
        };
        // A commit may wait for an fsync: with thousands of orders writing at once that
        // would hold every worker thread, and nothing else (SIGTERM, queries) would run.
        // On the multi-thread runtime the worker hands its other tasks over while it waits.
        let written = journal_write(|| journal.put(ORDER_RECORD, progress.holon.name(), progress));
        match written {
            Ok(()) => {
                if self.journal_failing.swap(false, Ordering::SeqCst) {
                    info!("the journal can be written again: waiting orders resume");
                }
                Ok(())
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
    pub async fn publish(&self, progress: &Shared) {
        let snapshot = lock(progress).snapshot();
        let key = self.keys.state(&snapshot.holon);
        let payload = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
        if let Err(e) = self.session.put(&key, payload).await {
            warn!(holon = %snapshot.holon, error = %e, "cannot publish the order's state; it is published again at the next change");
        }
    }

    /// Applies `change` to an order's progress once it is written: when the journal
    /// cannot write, the progress in memory stays the last one written (a restarted
    /// order task resumes from there, and an unacknowledged result comes again).
    pub fn commit(
        &self,
        progress: &Shared,
        change: impl FnOnce(&mut OrderProgress),
    ) -> Result<(), OrderError> {
        let mut p = lock(progress);
        let mut next = p.clone();
        change(&mut next);
        if next.status.is_final() && next.finished_at.is_none() {
            next.finished_at = Some(schemas::unix_ms());
        }
        self.save(&next)?;
        *p = next;
        Ok(())
    }
}

/// Runs a journal write, which may wait for an fsync: on the multi-thread runtime the
/// worker hands its other tasks over while it waits (with thousands of orders writing at
/// once, nothing else, SIGTERM or queries, would run otherwise).
pub fn journal_write<R>(write: impl FnOnce() -> R) -> R {
    let multi_thread = tokio::runtime::Handle::try_current()
        .is_ok_and(|h| h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread);
    if multi_thread {
        tokio::task::block_in_place(write)
    } else {
        write()
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

/// An order's progress, shared by its task and its node.
pub type Shared = Arc<Mutex<OrderProgress>>;

/// The progress, even if a task panicked while holding it (it changes only whole).
pub fn lock(progress: &Shared) -> std::sync::MutexGuard<'_, OrderProgress> {
    progress.lock().unwrap_or_else(|e| e.into_inner())
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

    fn offer(name: &str, wait: u64, queue: u64) -> Offer {
        Offer {
            avoided: false,
            expected_wait_ms: wait,
            queue_position: queue,
            duration_ms: 1000,
            provider: schemas::HolonId::resource(name).unwrap(),
        }
    }

    #[test]
    fn rounds_that_end_together_spread_their_bookings() {
        let in_flight = BookingsInFlight::default();
        // Eight rounds heard the same waits, none answered yet: each ranks after the
        // others chose.
        let mut held = Vec::new();
        let mut chosen: Vec<String> = (0..8)
            .map(|_| {
                let offers = vec![
                    offer("robot1", 0, 0),
                    offer("robot2", 0, 0),
                    offer("robot3", 1000, 1),
                ];
                let (ranked, counted) = in_flight.rank(offers, |_| None);
                held.push(counted);
                ranked[0].name().to_string()
            })
            .collect();
        chosen.sort();
        let count = |name: &str| chosen.iter().filter(|c| *c == name).count();
        assert_eq!(
            (count("robot1"), count("robot2"), count("robot3")),
            (3, 3, 2),
            "{chosen:?}"
        );
    }

    #[test]
    fn a_fresher_published_queue_and_answered_bookings_count() {
        let in_flight = BookingsInFlight::default();
        let robot1 = schemas::HolonId::resource("robot1").unwrap();
        // robot1 proposed an empty agenda, but has since published 3 jobs ahead.
        let published = |r: &schemas::HolonId| (r.name() == "robot1").then_some(3);
        let (ranked, counted) = in_flight.rank(
            vec![offer("robot1", 0, 0), offer("robot2", 2000, 2)],
            published,
        );
        assert_eq!(ranked[0].name(), "robot2");
        // In flight, robot2's booking counts; answered, it does not (its queue shows it).
        let both = || vec![offer("robot1", 1000, 1), offer("robot2", 1000, 1)];
        let (ranked, again) = in_flight.rank(both(), |_| None);
        assert_eq!(ranked[0], robot1);
        drop((counted, again));
        let (ranked, _counted) =
            in_flight.rank(both(), |r| if r == &robot1 { Some(2) } else { Some(1) });
        assert_eq!(ranked[0].name(), "robot2");
    }

    #[test]
    fn a_resource_that_failed_the_step_is_ranked_last() {
        let in_flight = BookingsInFlight::default();
        let mut avoided = offer("robot1", 0, 0);
        avoided.avoided = true;
        let (ranked, _) = in_flight.rank(vec![avoided, offer("robot2", 5000, 5)], |_| None);
        assert_eq!(ranked[1].name(), "robot1");
    }

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

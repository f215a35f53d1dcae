//! What an order-node knows of the cell's resources: which are alive, who just left or
//! came, and whose turn it is on each free resource (from their state publications).
//!
//! One task owns it ([`task`]): zenoh's callbacks parse what they hear and put it in
//! the task's bounded mailbox; the task applies each event to the pure
//! [`model::PresenceModel`] and publishes what orders read: an immutable
//! [`PresenceView`] (a `watch`), a broadcast of appearances and departures, a counter
//! of appearances, a wake-up per freed place, and a `watch` of [`Turns`] per resource.
//! [`Presence`] is the orders' handle on what it publishes: it reads, it never writes.

pub mod model;
mod task;

use std::collections::{BTreeSet, HashMap, HashSet};
use std::sync::Arc;

use schemas::HolonId;
use tokio::sync::{broadcast, watch, Notify};

pub use model::{PublishedQueue, Turns};
pub use task::MAILBOX;

/// What the presence's task last published for orders to read: immutable, replaced
/// whole when something in it changes.
#[derive(Debug, Default)]
pub struct PresenceView {
    /// The resources whose token is alive.
    pub alive: HashSet<HolonId>,
    /// Each resource's queue as it last published it.
    pub queues: HashMap<HolonId, PublishedQueue>,
    /// The services each resource offers, as it last published.
    pub services: HashMap<HolonId, Vec<String>>,
    /// The staff holons alive (advisors), by name.
    pub staff: BTreeSet<HolonId>,
    /// The resources whose last state said they are being handed over to a successor
    /// (an upgrade): while away, their bookings are kept for `orders.handover_grace_ms`.
    pub handing_over: HashSet<HolonId>,
    /// Per resource heard of, the channel of its [`Turns`]: an order booked there
    /// waits on its own resource's channel only, so a state change wakes the orders it
    /// concerns, not all of them.
    pub turns: HashMap<HolonId, watch::Receiver<Turns>>,
}

/// Which resources are alive, who just left or came, and whose turn it is on each
/// free resource: the orders' handle on what the presence's task publishes.
pub struct Presence {
    /// The task's latest view; dropping the last handle ends the task.
    view: watch::Receiver<Arc<PresenceView>>,
    /// Appearances (true) and departures (false), resubscribed for each order.
    changes: broadcast::Receiver<(HolonId, bool)>,
    /// Moves whenever a resource appears or becomes ready: orders that found no
    /// resource try again.
    appeared: watch::Receiver<u64>,
    /// One waiting order is woken per booking that leaves an agenda (started or
    /// cancelled), so a freed place goes to one order, not to a stampede of them.
    room: Arc<Notify>,
    /// Moves whenever places free up (on an agenda or at a location): the line at the
    /// stations sweeps ([`crate::station_line`]).
    freed: watch::Receiver<u64>,
    /// The events lost to a full mailbox, counted.
    overflow: Arc<task::Overflow>,
}

impl Presence {
    /// Follows `alive/resource/*`, `alive/staff/*` and `resource/*/state` for as long
    /// as the handle lives. The resources' tokens are queried before it returns: a
    /// resource missing from the set counts as vanished.
    pub async fn follow(
        session: &zenoh::Session,
        keys: &schemas::CellKeys,
    ) -> Result<Arc<Presence>, zenoh::Error> {
        task::start(session, keys, MAILBOX).await.map(Arc::new)
    }

    /// The jobs ahead of a new booking of `priority` on `resource`, as it last
    /// published, if it did.
    pub fn queue(&self, resource: &HolonId, priority: i32) -> Option<u64> {
        self.view
            .borrow()
            .queues
            .get(resource)
            .map(|queue| queue.ahead_of(priority))
    }

    /// The services `resource` offers, as it last published (none if it never did).
    pub fn services_of(&self, resource: &HolonId) -> Vec<String> {
        let view = self.view.borrow();
        view.services.get(resource).cloned().unwrap_or_default()
    }

    /// Whether a resource alive other than `except` that offers `service` runs a job,
    /// as it last published: it will free a place for the service when that job ends.
    pub fn working_for(&self, service: &str, except: &HolonId) -> bool {
        let view = self.view.borrow();
        view.services.iter().any(|(resource, services)| {
            resource != except
                && view.alive.contains(resource)
                && services.iter().any(|s| s == service)
                && view.queues.get(resource).is_some_and(|q| q.running)
        })
    }

    /// The staff holon to ask for advice, if one is alive (the first by name).
    pub fn staff(&self) -> Option<HolonId> {
        self.view.borrow().staff.first().cloned()
    }

    /// Whether `resource` said it is being handed over to a successor (and has not
    /// come back since).
    pub fn handing_over(&self, resource: &HolonId) -> bool {
        self.view.borrow().handing_over.contains(resource)
    }

    /// Whether `resource` was heard of as fenced: a holder of it that vanished may
    /// still run its steps (cut from the cell, not from its controller), so a step
    /// that may run there is not given up when it vanishes.
    /// (Its last state carried an epoch: the same knowledge as [`Presence::epoch`].)
    pub fn fenced(&self, resource: &HolonId) -> bool {
        self.epoch(resource).is_some()
    }

    /// Whether `holon`'s token is alive, as the task last published.
    pub fn is_alive(&self, holon: &HolonId) -> bool {
        self.view.borrow().alive.contains(holon)
    }

    /// How many events zenoh reported found the task's mailbox full (each led to a
    /// resynchronisation).
    pub fn lost_events(&self) -> u64 {
        self.overflow.lost()
    }

    /// Appearances (true) and departures (false) from now on.
    pub fn changes(&self) -> broadcast::Receiver<(HolonId, bool)> {
        self.changes.resubscribe()
    }

    /// Completes when `resource` publishes that the job of `conversation_id` runs
    /// (it began on its turn: also when its last publication already said so), or next
    /// publishes that it is free with `conversation_id` first on its agenda (a turn
    /// published before this call does not count: it may be stale).
    pub async fn turn(&self, resource: &HolonId, conversation_id: &str) -> TurnNews {
        let known = self.view.borrow().turns.get(resource).cloned();
        let (mut turns, fresh) = match known {
            Some(turns) => (turns, false),
            // Not heard of yet: whatever its channel says once it has one was
            // published after this call.
            None => (self.turns_when_heard(resource).await, true),
        };
        let news = |now: &Turns, turn_counts: bool| {
            if now.running.as_deref() == Some(conversation_id) {
                Some(TurnNews::Began)
            } else if turn_counts && now.turn.as_deref() == Some(conversation_id) {
                Some(TurnNews::Turn)
            } else {
                None
            }
        };
        if let Some(news) = news(&turns.borrow_and_update(), fresh) {
            return news;
        }
        while turns.changed().await.is_ok() {
            if let Some(news) = news(&turns.borrow_and_update(), true) {
                return news;
            }
        }
        std::future::pending().await
    }

    /// The epoch of the holder whose state `resource` last published (a fenced
    /// resource), if one was heard.
    pub fn epoch(&self, resource: &HolonId) -> Option<u64> {
        self.view
            .borrow()
            .turns
            .get(resource)
            .and_then(|turns| turns.borrow().epoch)
    }

    /// Completes when `resource` publishes a state from a holder of a higher epoch than
    /// `seen` (when `seen` is `None`, than the first epoch heard from now on): a new
    /// holder serves it, which may know nothing of what the last one ran. Pending for
    /// a resource that is not fenced.
    pub async fn new_holder(&self, resource: &HolonId, seen: Option<u64>) {
        let known = self.view.borrow().turns.get(resource).cloned();
        let mut turns = match known {
            Some(turns) => turns,
            None => self.turns_when_heard(resource).await,
        };
        let mut baseline = seen;
        loop {
            match (baseline, turns.borrow_and_update().epoch) {
                (Some(seen), Some(now)) if now > seen => return,
                (None, Some(now)) => baseline = Some(now),
                _ => {}
            }
            if turns.changed().await.is_err() {
                return std::future::pending().await;
            }
        }
    }

    /// The channel of `resource`'s turns, once the task heard of it (its token or its
    /// state); pending until then.
    async fn turns_when_heard(&self, resource: &HolonId) -> watch::Receiver<Turns> {
        let mut view = self.view.clone();
        loop {
            if let Some(turns) = view.borrow_and_update().turns.get(resource) {
                return turns.clone();
            }
            if view.changed().await.is_err() {
                return std::future::pending().await;
            }
        }
    }

    /// Appearances from now on: pass it to [`Presence::appeared_or_room`] after a look
    /// for resources, so one that appears during the look is not missed.
    pub fn appearances(&self) -> watch::Receiver<u64> {
        let mut appearances = self.appeared.clone();
        appearances.mark_unchanged();
        appearances
    }

    /// The news the line at the stations sweeps on: places freed, and resources
    /// appeared or ready.
    pub fn room_news(&self) -> (watch::Receiver<u64>, watch::Receiver<u64>) {
        (self.freed.clone(), self.appeared.clone())
    }

    /// Completes when a resource appeared (or became ready) since `appearances` was
    /// taken, or when a booking left an agenda and this is the order woken for the place.
    pub async fn appeared_or_room(&self, appearances: &mut watch::Receiver<u64>) {
        let appeared = async {
            if appearances.changed().await.is_err() {
                // The task ended: only freed places are news.
                std::future::pending::<()>().await;
            }
        };
        tokio::select! {
            _ = appeared => {}
            _ = self.room.notified() => {}
        }
    }
}

/// What [`Presence::turn`] saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TurnNews {
    /// It is the conversation's turn: its requester asks the resource to start.
    Turn,
    /// Its job runs (the resource began it on its turn).
    Began,
}

#[cfg(test)]
mod tests;

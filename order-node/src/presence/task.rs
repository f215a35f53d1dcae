//! The presence's owner: one task that handles, one at a time, what zenoh reports of
//! the resources and staff, applies it to the [`PresenceModel`] and performs its
//! notices.
//!
//! | event | what the task does |
//! |---|---|
//! | a resource's token put | alive; orders told (`changes`), orders that found none woken |
//! | a resource's token deleted | gone (planned if it was handing over); orders told |
//! | a resource's state | its queue and hand-over kept; its turn published on its channel; a freed place wakes one waiting order; readiness wakes those that found none |
//! | a staff token put or deleted | the advisors' set |
//! | a query of the tokens (the seed, a resynchronisation) | the alive set becomes what it found |
//!
//! Zenoh's callbacks only parse and `try_send` into the mailbox of [`MAILBOX`] events.
//! The overflow rule: an event that finds the mailbox full is counted, never waited
//! for; the task then logs how many were lost and resynchronises: it queries the
//! resources' and staff's tokens and asks the resources for their state (in a helper
//! task that feeds the replies into the mailbox, at most one at a time), so a lost
//! token delete, a lost turn or a lost freed place is recovered from the cell's
//! present state. Events lost while it resynchronises lead to one more
//! resynchronisation when it is done.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use schemas::{CellKeys, HolonId, HolonKind, ResourceSnapshot};
use tokio::sync::{broadcast, mpsc, watch, Notify};
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};
use zenoh::sample::SampleKind;

use super::model::{Event, Notice, PresenceModel, Turns};
use super::{Presence, PresenceView};

/// How many events may wait for the presence's task.
pub const MAILBOX: usize = 1024;

/// How long a query of tokens or states waits for replies, and how long the
/// resynchronisation waits for room in the mailbox for each reply.
const QUERY_TIMEOUT: Duration = Duration::from_secs(2);

/// The events lost to a full mailbox: counted by the callbacks, read by the task.
#[derive(Default)]
pub(super) struct Overflow {
    /// How many events found the mailbox full since the start (only grows).
    lost: AtomicU64,
    /// Wakes the task when one was lost.
    wake: Notify,
}

impl Overflow {
    /// How many events found the mailbox full since the start.
    pub(super) fn lost(&self) -> u64 {
        self.lost.load(Ordering::Relaxed)
    }

    fn lost_one(&self) {
        self.lost.fetch_add(1, Ordering::Relaxed);
        self.wake.notify_one();
    }
}

/// The callbacks' way into the mailbox: never waits.
#[derive(Clone)]
struct Post {
    /// The mailbox.
    mail: mpsc::Sender<Event>,
    /// Where a lost event is counted.
    overflow: Arc<Overflow>,
}

impl Post {
    fn event(&self, event: Event) {
        match self.mail.try_send(event) {
            Ok(()) | Err(mpsc::error::TrySendError::Closed(_)) => {}
            Err(mpsc::error::TrySendError::Full(_)) => self.overflow.lost_one(),
        }
    }
}

/// The task's state: the model and what it publishes.
struct Owner {
    /// The pure state.
    model: PresenceModel,
    /// The view orders read; its receivers all gone ends the task.
    view: watch::Sender<Arc<PresenceView>>,
    /// The model's version the view was made of.
    view_version: u64,
    /// Per resource heard of, the channel of its turns.
    turns: HashMap<HolonId, watch::Sender<Turns>>,
    /// Appearances (true) and departures (false).
    changes: broadcast::Sender<(HolonId, bool)>,
    /// Counts appearances and resources become ready.
    appeared: watch::Sender<u64>,
    /// Moves whenever places free up (see [`Presence::room_news`]).
    freed: watch::Sender<u64>,
    /// One wake-up per freed place.
    room: Arc<Notify>,
    /// Where the callbacks count the events lost to a full mailbox.
    overflow: Arc<Overflow>,
    /// `overflow.lost` when the last resynchronisation began.
    lost_answered: u64,
    /// The mailbox's bound, for the log.
    capacity: usize,
    /// The resynchronisation in flight.
    resync: Option<JoinHandle<()>>,
}

/// Subscribes, seeds the alive set from a query of the tokens, and spawns the task.
/// `capacity` is the mailbox's bound ([`MAILBOX`]; smaller in tests).
pub(super) async fn start(
    session: &zenoh::Session,
    keys: &CellKeys,
    capacity: usize,
) -> Result<Presence, zenoh::Error> {
    let (mail, mailbox) = mpsc::channel(capacity);
    let post = Post {
        mail,
        overflow: Arc::default(),
    };
    subscribe(session, keys, &post).await?;
    let (changes, changes_rx) = broadcast::channel(4096);
    let (view, view_rx) = watch::channel(Arc::new(PresenceView::default()));
    let (appeared, appeared_rx) = watch::channel(0);
    let (freed, freed_rx) = watch::channel(0);
    let room = Arc::new(Notify::new());
    let mut owner = Owner {
        model: PresenceModel::default(),
        view,
        view_version: 0,
        turns: HashMap::new(),
        changes,
        appeared,
        freed,
        room: room.clone(),
        overflow: post.overflow.clone(),
        lost_answered: 0,
        capacity,
        resync: None,
    };
    // Seeded before any order looks: the subscriber's history arrives asynchronously,
    // and a resource missing from the set counts as vanished.
    let seed = tokens(session, keys, HolonKind::Resource).await?;
    owner.handle(Event::Tokens(seed));
    let overflow = post.overflow.clone();
    let resync = Resync {
        session: session.clone(),
        keys: keys.clone(),
        post,
    };
    tokio::spawn(owner.run(mailbox, resync));
    Ok(Presence {
        view: view_rx,
        changes: changes_rx,
        appeared: appeared_rx,
        room,
        freed: freed_rx,
        overflow,
    })
}

/// Declares the three subscribers; their callbacks parse and post.
async fn subscribe(
    session: &zenoh::Session,
    keys: &CellKeys,
    post: &Post,
) -> Result<(), zenoh::Error> {
    let (resources, resource_keys) = (post.clone(), keys.clone());
    session
        .liveliness()
        .declare_subscriber(keys.alive_kind(HolonKind::Resource))
        .history(true)
        .callback(move |sample| {
            if let Some(holon) = resource_keys.holon_from_alive(sample.key_expr().as_str()) {
                let alive = sample.kind() == SampleKind::Put;
                resources.event(Event::Token { holon, alive });
            }
        })
        .background()
        .await?;
    let states = post.clone();
    session
        .declare_subscriber(keys.resource_states())
        .callback(move |sample| {
            if let Some(snapshot) = read_snapshot(&sample.payload().to_bytes()) {
                states.event(Event::Snapshot(snapshot));
            }
        })
        .background()
        .await?;
    let (staff, staff_keys) = (post.clone(), keys.clone());
    session
        .liveliness()
        .declare_subscriber(keys.alive_kind(HolonKind::Staff))
        .history(true)
        .callback(move |sample| {
            if let Some(holon) = staff_keys.holon_from_alive(sample.key_expr().as_str()) {
                let alive = sample.kind() == SampleKind::Put;
                staff.event(Event::Staff { holon, alive });
            }
        })
        .background()
        .await
}

fn read_snapshot(payload: &[u8]) -> Option<Box<ResourceSnapshot>> {
    serde_json::from_slice(payload).ok().map(Box::new)
}

/// The holons of `kind` whose token a query found.
async fn tokens(
    session: &zenoh::Session,
    keys: &CellKeys,
    kind: HolonKind,
) -> Result<Vec<HolonId>, zenoh::Error> {
    let found = holon::presence::tokens(session, &keys.alive_kind(kind), QUERY_TIMEOUT).await?;
    Ok(found
        .iter()
        .filter_map(|key| keys.holon_from_alive(key))
        .collect())
}

/// What a resynchronisation needs.
struct Resync {
    /// The node's session.
    session: zenoh::Session,
    /// The cell's keys.
    keys: CellKeys,
    /// Where it posts what it found.
    post: Post,
}

impl Owner {
    /// Handles the mailbox's events one at a time until no order-node reads the view.
    async fn run(mut self, mut mailbox: mpsc::Receiver<Event>, resync: Resync) {
        loop {
            tokio::select! {
                _ = self.view.closed() => break,
                event = mailbox.recv() => match event {
                    Some(event) => self.handle(event),
                    None => break,
                },
                _ = resynced(&mut self.resync) => {
                    self.resync = None;
                    self.resync_if_lost(&resync);
                }
                _ = self.overflow.wake.notified() => self.resync_if_lost(&resync),
            }
        }
        if let Some(resync) = self.resync.take() {
            resync.abort();
        }
        debug!("the presence's task ends: no order-node reads it");
    }

    /// Applies one event, publishes the view if what orders read changed (before
    /// telling them, so an order told reads the news), then performs the notices.
    fn handle(&mut self, event: Event) {
        let notices = self.model.apply(event);
        for notice in &notices {
            if let Notice::Appeared(resource) | Notice::Turn { resource, .. } = notice {
                self.turns_of(resource);
            }
        }
        self.publish();
        for notice in notices {
            self.perform(notice);
        }
    }

    /// Publishes a new view when the model or the set of turn channels changed.
    fn publish(&mut self) {
        let version = self.model.version();
        let channels_changed = self.view.borrow().turns.len() != self.turns.len();
        if version == self.view_version && !channels_changed {
            return;
        }
        self.view_version = version;
        self.view.send_replace(Arc::new(PresenceView {
            alive: self.model.alive().clone(),
            queues: self.model.queues().clone(),
            services: self.model.services().clone(),
            staff: self.model.staff().clone(),
            handing_over: self.model.handing_over().clone(),
            turns: self
                .turns
                .iter()
                .map(|(resource, turns)| (resource.clone(), turns.subscribe()))
                .collect(),
        }));
    }

    /// `resource`'s turn channel, made the first time it is heard of.
    fn turns_of(&mut self, resource: &HolonId) -> &watch::Sender<Turns> {
        self.turns
            .entry(resource.clone())
            .or_insert_with(|| watch::channel(Turns::default()).0)
    }

    fn perform(&mut self, notice: Notice) {
        match notice {
            Notice::Appeared(holon) => {
                info!(%holon, "resource appeared");
                // An error means no order listens: nobody to tell.
                self.changes.send((holon, true)).ok();
                self.appeared.send_modify(|n| *n += 1);
            }
            Notice::Vanished { holon, handover } => {
                if handover {
                    info!(%holon, "resource away for a planned hand-over (an upgrade): its bookings are kept");
                } else {
                    warn!(%holon, "resource vanished");
                }
                self.changes.send((holon, false)).ok();
            }
            Notice::BecameReady(holon) => {
                debug!(%holon, "resource ready: orders that found none try again");
                self.appeared.send_modify(|n| *n += 1);
            }
            Notice::PlacesFreed { places, .. } => {
                for _ in 0..places {
                    self.room.notify_one();
                }
                self.freed.send_modify(|n| *n += places as u64);
            }
            Notice::Turn { resource, turns } => {
                self.turns_of(&resource).send_replace(turns);
            }
            Notice::StaffChanged { holon, alive: true } => {
                info!(%holon, "staff appeared: orders ask it for advice");
            }
            Notice::StaffChanged {
                holon,
                alive: false,
            } => {
                warn!(%holon, "staff vanished: orders go by contract net alone");
            }
        }
    }

    /// Starts a resynchronisation when events were lost since the last one began and
    /// none is in flight.
    fn resync_if_lost(&mut self, resync: &Resync) {
        let lost = self.overflow.lost();
        if self.resync.is_some() || lost == self.lost_answered {
            return;
        }
        warn!(
            lost = lost - self.lost_answered,
            lost_in_all = lost,
            capacity = self.capacity,
            "the presence's mailbox was full: events lost; resynchronising from the tokens and states"
        );
        self.lost_answered = lost;
        self.resync = Some(tokio::spawn(resynchronise(
            resync.session.clone(),
            resync.keys.clone(),
            resync.post.clone(),
        )));
    }
}

/// Queries the resources' and staff's tokens and the resources' states, and posts what
/// it found, waiting at most [`QUERY_TIMEOUT`] for room for each (an event that finds
/// none is counted as lost: one more resynchronisation follows).
async fn resynchronise(session: zenoh::Session, keys: CellKeys, post: Post) {
    let send = |event: Event| {
        let post = post.clone();
        async move {
            if post.mail.send_timeout(event, QUERY_TIMEOUT).await.is_err() {
                post.overflow.lost_one();
            }
        }
    };
    for (kind, tokens_found) in [
        (
            HolonKind::Resource,
            Event::Tokens as fn(Vec<HolonId>) -> Event,
        ),
        (HolonKind::Staff, Event::StaffTokens),
    ] {
        match tokens(&session, &keys, kind).await {
            Ok(found) => send(tokens_found(found)).await,
            Err(e) => warn!(?kind, error = %e, "cannot query the tokens; the next change tells"),
        }
    }
    match session
        .get(keys.resource_states())
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(QUERY_TIMEOUT)
        .with(holon::query::replies())
        .await
    {
        Ok(mut replies) => {
            // The query's timeout ends the replies.
            while let Some(reply) = replies.recv().await {
                let Ok(sample) = reply.result() else { continue };
                if let Some(snapshot) = read_snapshot(&sample.payload().to_bytes()) {
                    send(Event::Snapshot(snapshot)).await;
                }
            }
        }
        Err(e) => {
            warn!(error = %e, "cannot ask the resources for their state; their next one tells")
        }
    }
    info!("presence resynchronised");
}

/// Completes when the resynchronisation in flight is done; pending while none is.
async fn resynced(resync: &mut Option<JoinHandle<()>>) {
    match resync {
        Some(resync) => {
            if let Err(e) = resync.await {
                warn!(error = %e, "the presence's resynchronisation failed");
            }
        }
        None => std::future::pending().await,
    }
}

//! What an order-node knows of the cell's resources: which are alive, who just left or
//! came, and whose turn it is on each free resource (from their state publications).
//! Shared by every order of the node; fed by two subscriber callbacks.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::{HolonId, ResourceState};
use tokio::sync::{broadcast, watch, Notify};
use tracing::{info, warn};

/// Which resources are alive, who just left or came, and whose turn it is on each
/// free resource.
pub struct Presence {
    alive: Mutex<HashSet<HolonId>>,
    changes: broadcast::Sender<(HolonId, bool)>,
    /// Woken whenever a resource appears or becomes ready: orders that found no
    /// resource try again.
    appeared: watch::Sender<u64>,
    /// One waiting order is woken per booking that leaves an agenda (started or
    /// cancelled), so a freed place goes to one order, not to a stampede of them.
    room: Notify,
    /// The agenda length and whether it could take work (state not `init`), as each
    /// resource last published.
    published: Mutex<HashMap<HolonId, (usize, bool)>>,
    /// Per resource, as it last published: whether it runs a job, and the priority of
    /// each waiting booking in agenda order. Fresher than a proposal heard during a
    /// round.
    queues: Mutex<HashMap<HolonId, PublishedQueue>>,
    /// Per resource, from its state publications: whose turn it is and whose job runs.
    /// An order booked there waits on its own resource's channel only, so a state
    /// change wakes the orders it concerns, not all of them.
    turns: Mutex<HashMap<HolonId, watch::Sender<Turns>>>,
    /// The staff holons alive (advisors), by name.
    staff: Mutex<std::collections::BTreeSet<HolonId>>,
    /// The resources whose last state said they are being handed over to a successor
    /// (an upgrade): while away, their bookings are kept for `orders.handover_grace_ms`.
    handing_over: Mutex<HashSet<HolonId>>,
}

impl Presence {
    /// Follows `alive/resource/*` and `resource/*/state` for as long as the session lives.
    pub async fn follow(
        session: &zenoh::Session,
        keys: &schemas::CellKeys,
    ) -> Result<Arc<Presence>, zenoh::Error> {
        let (changes, _) = broadcast::channel(4096);
        let presence = Arc::new(Presence {
            alive: Mutex::new(HashSet::new()),
            changes,
            appeared: watch::channel(0).0,
            room: Notify::new(),
            published: Mutex::new(HashMap::new()),
            queues: Mutex::new(HashMap::new()),
            turns: Mutex::new(HashMap::new()),
            staff: Mutex::new(Default::default()),
            handing_over: Mutex::new(HashSet::new()),
        });
        let keys_for_callback = keys.clone();
        let weak = Arc::downgrade(&presence);
        session
            .liveliness()
            .declare_subscriber(keys.alive_kind(schemas::HolonKind::Resource))
            .history(true)
            .callback(move |sample| {
                let Some(presence) = weak.upgrade() else {
                    return;
                };
                let Some(holon) = keys_for_callback.holon_from_alive(sample.key_expr().as_str())
                else {
                    return;
                };
                let mut alive = presence.alive.lock().unwrap_or_else(|e| e.into_inner());
                match sample.kind() {
                    zenoh::sample::SampleKind::Put => {
                        presence.set_handing_over(&holon, false);
                        if alive.insert(holon.clone()) {
                            info!(holon = %holon, "resource appeared");
                            // An error means no order listens: nobody to tell.
                            presence.changes.send((holon, true)).ok();
                            presence.appeared.send_modify(|n| *n += 1);
                        }
                    }
                    zenoh::sample::SampleKind::Delete => {
                        alive.remove(&holon);
                        if presence.handing_over(&holon) {
                            info!(holon = %holon, "resource away for a planned hand-over (an upgrade): its bookings are kept");
                        } else {
                            warn!(holon = %holon, "resource vanished");
                        }
                        presence.changes.send((holon, false)).ok();
                    }
                }
            })
            .background()
            .await?;
        let weak = Arc::downgrade(&presence);
        session
            .declare_subscriber(keys.resource_states())
            .callback(move |sample| {
                let Some(presence) = weak.upgrade() else {
                    return;
                };
                let Ok(snapshot) = serde_json::from_slice::<schemas::ResourceSnapshot>(
                    &sample.payload().to_bytes(),
                ) else {
                    return;
                };
                let news = {
                    let mut published =
                        presence.published.lock().unwrap_or_else(|e| e.into_inner());
                    let previous = published.get(&snapshot.holon).copied();
                    let (news, now) = read_state(previous, &snapshot);
                    published.insert(snapshot.holon.clone(), now);
                    news
                };
                presence
                    .queues
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .insert(
                        snapshot.holon.clone(),
                        PublishedQueue {
                            running: snapshot.current.is_some(),
                            waiting: snapshot.agenda.iter().map(|b| b.priority).collect(),
                        },
                    );
                presence.set_handing_over(&snapshot.holon, snapshot.handing_over);
                presence.turn_channel(&snapshot.holon).send_replace(Turns {
                    turn: news.turn,
                    running: snapshot.current.as_ref().map(|c| c.conversation_id.clone()),
                });
                if news.became_ready {
                    // Back from a fault or first ready: as good as a new resource.
                    presence.appeared.send_modify(|n| *n += 1);
                }
                for _ in 0..news.places_freed {
                    presence.room.notify_one();
                }
            })
            .background()
            .await?;
        let weak = Arc::downgrade(&presence);
        let keys_for_staff = keys.clone();
        session
            .liveliness()
            .declare_subscriber(keys.alive_kind(schemas::HolonKind::Staff))
            .history(true)
            .callback(move |sample| {
                let Some(presence) = weak.upgrade() else {
                    return;
                };
                let Some(holon) = keys_for_staff.holon_from_alive(sample.key_expr().as_str())
                else {
                    return;
                };
                let mut staff = presence.staff.lock().unwrap_or_else(|e| e.into_inner());
                match sample.kind() {
                    zenoh::sample::SampleKind::Put => {
                        if staff.insert(holon.clone()) {
                            info!(holon = %holon, "staff appeared: orders ask it for advice");
                        }
                    }
                    zenoh::sample::SampleKind::Delete => {
                        if staff.remove(&holon) {
                            warn!(holon = %holon, "staff vanished: orders go by contract net alone");
                        }
                    }
                }
            })
            .background()
            .await?;
        // Seed the set before any order looks at it: the subscriber's history arrives
        // asynchronously, and a resource missing from the set counts as vanished.
        let alive = holon::presence::tokens(
            session,
            &keys.alive_kind(schemas::HolonKind::Resource),
            Duration::from_secs(2),
        )
        .await?;
        presence
            .alive
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .extend(alive.iter().filter_map(|key| keys.holon_from_alive(key)));
        Ok(presence)
    }

    /// The jobs ahead of a new booking of `priority` on `resource`, as it last
    /// published, if it did.
    pub fn queue(&self, resource: &HolonId, priority: i32) -> Option<u64> {
        self.queues
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(resource)
            .map(|queue| queue.ahead_of(priority))
    }

    /// The staff holon to ask for advice, if one is alive (the first by name).
    pub fn staff(&self) -> Option<HolonId> {
        self.staff
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .first()
            .cloned()
    }

    /// Whether `resource` said it is being handed over to a successor (and has not
    /// come back since).
    pub fn handing_over(&self, resource: &HolonId) -> bool {
        self.handing_over
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(resource)
    }

    fn set_handing_over(&self, resource: &HolonId, handing_over: bool) {
        let mut set = self.handing_over.lock().unwrap_or_else(|e| e.into_inner());
        if handing_over {
            set.insert(resource.clone());
        } else {
            set.remove(resource);
        }
    }

    pub fn is_alive(&self, holon: &HolonId) -> bool {
        self.alive
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(holon)
    }

    /// Appearances (true) and departures (false) from now on.
    pub fn changes(&self) -> broadcast::Receiver<(HolonId, bool)> {
        self.changes.subscribe()
    }

    fn turn_channel(&self, resource: &HolonId) -> watch::Sender<Turns> {
        self.turns
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(resource.clone())
            .or_insert_with(|| watch::channel(Turns::default()).0)
            .clone()
    }

    /// Completes when `resource` publishes that the job of `conversation_id` runs
    /// (it began on its turn: also when its last publication already said so), or next
    /// publishes that it is free with `conversation_id` first on its agenda (a turn
    /// published before this call does not count: it may be stale).
    pub async fn turn(&self, resource: &HolonId, conversation_id: &str) -> TurnNews {
        let mut turns = self.turn_channel(resource).subscribe();
        if turns.borrow_and_update().running.as_deref() == Some(conversation_id) {
            return TurnNews::Began;
        }
        while turns.changed().await.is_ok() {
            let now = turns.borrow_and_update();
            if now.running.as_deref() == Some(conversation_id) {
                return TurnNews::Began;
            }
            if now.turn.as_deref() == Some(conversation_id) {
                return TurnNews::Turn;
            }
        }
        std::future::pending().await
    }

    /// Appearances from now on: pass it to [`Presence::appeared_or_room`] after a look
    /// for resources, so one that appears during the look is not missed.
    pub fn appearances(&self) -> watch::Receiver<u64> {
        self.appeared.subscribe()
    }

    /// Completes when a resource appeared (or became ready) since `appearances` was
    /// taken, or when a booking left an agenda and this is the order woken for the place.
    pub async fn appeared_or_room(&self, appearances: &mut watch::Receiver<u64>) {
        tokio::select! {
            _ = appearances.changed() => {}
            _ = self.room.notified() => {}
        }
    }
}

/// What one state publication of a resource tells the orders waiting on it.
#[derive(Debug, PartialEq, Eq)]
struct StateNews {
    /// The conversation whose turn it is: the resource is free and it is first on the
    /// agenda.
    turn: Option<String>,
    /// The resource has just become able to take work (or is seen ready the first time).
    became_ready: bool,
    /// Places freed on its agenda since its previous publication.
    places_freed: usize,
}

/// What a resource's last publication said of the bookings on it.
#[derive(Debug, Clone, Default, PartialEq)]
struct Turns {
    /// The conversation first on its agenda while it is free and taking orders' work
    /// (`None` while it is busy, has no booking, or is out of Execute).
    turn: Option<String>,
    /// The conversation whose job runs.
    running: Option<String>,
}

/// What [`Presence::turn`] saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TurnNews {
    /// It is the conversation's turn: its requester asks the resource to start.
    Turn,
    /// Its job runs (the resource began it on its turn).
    Began,
}

/// Reads a snapshot against what the resource published before (its agenda length and
/// whether it was ready): the news, and what to remember for the next one.
fn read_state(
    previous: Option<(usize, bool)>,
    snapshot: &schemas::ResourceSnapshot,
) -> (StateNews, (usize, bool)) {
    let (length_before, ready_before) = previous.unwrap_or((0, false));
    // A resource out of PackML Execute or Production (held, stopped, aborted, in
    // maintenance) takes no orders' work: nobody's turn, and not ready (its return to
    // Execute is news, so waiting orders ask at once).
    let takes_orders = snapshot.packml.as_ref().is_none_or(|p| {
        p.state == schemas::PackmlState::Execute && p.mode == schemas::UnitMode::Production
    });
    let ready =
        snapshot.state != ResourceState::Init && snapshot.controller.is_ready() && takes_orders;
    let news = StateNews {
        turn: (snapshot.state == ResourceState::Free && takes_orders)
            .then(|| snapshot.agenda.first().map(|b| b.conversation_id.clone()))
            .flatten(),
        became_ready: ready && !ready_before,
        places_freed: length_before.saturating_sub(snapshot.agenda.len()),
    };
    (news, (snapshot.agenda.len(), ready))
}

/// A resource's queue as it last published it.
#[derive(Debug, Clone, Default, PartialEq)]
struct PublishedQueue {
    /// It runs a job.
    running: bool,
    /// The priority of each waiting booking, in agenda order.
    waiting: Vec<i32>,
}

impl PublishedQueue {
    /// The jobs ahead of a new booking of `priority`: the running one and the waiting
    /// bookings up to the last of equal or higher priority (the agenda's rule; an
    /// estimate, since the resource may also stop it behind a booking passed too often).
    fn ahead_of(&self, priority: i32) -> u64 {
        let waiting_ahead = self
            .waiting
            .iter()
            .rposition(|p| *p >= priority)
            .map_or(0, |last| last + 1);
        (waiting_ahead + usize::from(self.running)) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::{BookingView, ResourceSnapshot};

    fn snapshot(state: &str, controller: &str, agenda: &[&str]) -> ResourceSnapshot {
        ResourceSnapshot {
            holon: HolonId::resource("robot1").unwrap(),
            state: serde_json::from_value(state.into()).expect("a resource state"),
            controller: serde_json::from_value(controller.into()).expect("a controller status"),
            agenda: agenda
                .iter()
                .map(|c| BookingView {
                    requester: HolonId::new(schemas::HolonKind::Order, "o-1").unwrap(),
                    conversation_id: c.to_string(),
                    service_type: "pick_n_place".into(),
                    requester_absent_since: None,
                    priority: 0,
                    due: None,
                    overtaken: 0,
                    program: None,
                })
                .collect(),
            current: None,
            undelivered: 0,
            services: vec!["pick_n_place".into()],
            nominal_ms: Default::default(),
            journal_fault: None,
            delivery_retries: 0,
            handing_over: false,
            packml: None,
            host: None,
            version: None,
            v: 0,
            at: 0,
        }
    }

    #[test]
    fn a_free_resource_gives_the_turn_to_the_first_booking() {
        let (news, now) = read_state(
            Some((2, true)),
            &snapshot("free", "ready", &["a/1/1", "b/1/1"]),
        );
        assert_eq!(news.turn.as_deref(), Some("a/1/1"));
        assert!(!news.became_ready);
        assert_eq!(news.places_freed, 0);
        assert_eq!(now, (2, true));
    }

    #[test]
    fn a_busy_or_empty_resource_gives_no_turn() {
        let (busy, _) = read_state(Some((1, true)), &snapshot("busy", "ready", &["a/1/1"]));
        assert_eq!(busy.turn, None);
        let (empty, _) = read_state(Some((0, true)), &snapshot("free", "ready", &[]));
        assert_eq!(empty.turn, None);
    }

    #[test]
    fn bookings_leaving_the_agenda_free_places() {
        let (news, now) = read_state(Some((3, true)), &snapshot("busy", "ready", &["c/1/1"]));
        assert_eq!(news.places_freed, 2);
        assert_eq!(now, (1, true));
        let (grew, _) = read_state(
            Some((1, true)),
            &snapshot("busy", "ready", &["c/1/1", "d/1/1"]),
        );
        assert_eq!(grew.places_freed, 0);
    }

    #[test]
    fn readiness_is_news_once() {
        let (first, now) = read_state(None, &snapshot("free", "ready", &[]));
        assert!(first.became_ready, "a resource seen ready the first time");
        let (again, _) = read_state(Some(now), &snapshot("free", "ready", &[]));
        assert!(!again.became_ready);
        let (fault, now) = read_state(Some(now), &snapshot("init", "fault", &[]));
        assert!(!fault.became_ready);
        assert_eq!(fault.turn, None);
        let (back, _) = read_state(Some(now), &snapshot("free", "ready", &[]));
        assert!(back.became_ready, "back from a fault");
    }

    #[test]
    fn a_held_resource_gives_no_turn_and_its_unhold_is_news() {
        let mut held = snapshot("free", "ready", &["a/1/1"]);
        let mut unit = packml(schemas::PackmlState::Held);
        held.packml = Some(unit.clone());
        let (news, now) = read_state(Some((1, true)), &held);
        assert_eq!(news.turn, None, "nobody's turn on a held resource");
        assert!(!news.became_ready);
        unit.state = schemas::PackmlState::Execute;
        let mut back = snapshot("free", "ready", &["a/1/1"]);
        back.packml = Some(unit.clone());
        let (news, _) = read_state(Some(now), &back);
        assert_eq!(news.turn.as_deref(), Some("a/1/1"));
        assert!(news.became_ready, "the unhold is news");
        unit.mode = schemas::UnitMode::Maintenance;
        back.packml = Some(unit);
        let (news, _) = read_state(Some(now), &back);
        assert_eq!(news.turn, None, "maintenance takes no orders");
    }

    /// A resource's PackML figures in `state`, in Production.
    fn packml(state: schemas::PackmlState) -> schemas::PackmlStatus {
        schemas::PackmlStatus {
            state,
            state_number: state.number(),
            state_requested: state,
            mode: schemas::UnitMode::Production,
            processed: 0,
            defective: 0,
            stop_reason: None,
            since: 0,
            cumulative_ms: Default::default(),
            commands: vec![],
            operator_job: None,
        }
    }

    #[test]
    fn a_new_booking_counts_the_jobs_of_its_priority_or_higher_ahead() {
        let queue = PublishedQueue {
            running: true,
            waiting: vec![100, 100, 0, 0, -5],
        };
        assert_eq!(queue.ahead_of(0), 5, "behind the running job and c1..c4");
        assert_eq!(queue.ahead_of(100), 3);
        assert_eq!(queue.ahead_of(1000), 1);
        assert_eq!(queue.ahead_of(-1000), 6);
        assert_eq!(PublishedQueue::default().ahead_of(0), 0);
    }
}

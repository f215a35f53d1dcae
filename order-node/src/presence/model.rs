//! What an order-node knows of the cell's resources and staff: the pure part.
//!
//! The presence's owner task feeds it, one at a time, what zenoh reports (a token put
//! or deleted, a resource's state snapshot, a query of the tokens) and performs the
//! notices it returns (tell the orders, wake one for a freed place, publish a turn).
//! Nothing here does I/O, reads a clock or knows of tokio.

use std::collections::{BTreeSet, HashMap, HashSet};

use schemas::{HolonId, ResourceSnapshot, ResourceState};

/// What the presence's owner task hears.
#[derive(Debug)]
pub enum Event {
    /// A resource's liveliness token was declared (`true`) or withdrawn (`false`).
    Token {
        /// The resource.
        holon: HolonId,
        /// Declared, or withdrawn.
        alive: bool,
    },
    /// A query of the resources' tokens found these (the seed at start, or a
    /// resynchronisation): the others are gone.
    Tokens(Vec<HolonId>),
    /// A resource published its state. Boxed: a snapshot is large, the others small.
    Snapshot(Box<ResourceSnapshot>),
    /// A staff holon's token was declared (`true`) or withdrawn (`false`).
    Staff {
        /// The staff holon.
        holon: HolonId,
        /// Declared, or withdrawn.
        alive: bool,
    },
    /// A query of the staff's tokens found these: the others are gone.
    StaffTokens(Vec<HolonId>),
}

/// What the owner task is to do after an event.
#[derive(Debug, Clone, PartialEq)]
pub enum Notice {
    /// A resource came (its token): orders that found none try again.
    Appeared(HolonId),
    /// A resource's token is gone: orders booked there start their grace.
    Vanished {
        /// The resource.
        holon: HolonId,
        /// Its last state said it is being handed over to a successor (an upgrade):
        /// its bookings are kept for `orders.handover_grace_ms`.
        handover: bool,
    },
    /// A resource became able to take work (first seen ready, or back from a fault or
    /// a hold): as good as a new resource for orders that found none.
    BecameReady(HolonId),
    /// Bookings left a resource's agenda: one waiting order is woken per place.
    PlacesFreed {
        /// The resource.
        resource: HolonId,
        /// How many places.
        places: usize,
    },
    /// What a resource's publication says of the bookings on it. Given for every
    /// publication, also when equal to the last: an order that began to wait after the
    /// previous one counts only a turn published since.
    Turn {
        /// The resource.
        resource: HolonId,
        /// Whose turn it is and whose job runs.
        turns: Turns,
    },
    /// A staff holon came (`true`) or went (`false`).
    StaffChanged {
        /// The staff holon.
        holon: HolonId,
        /// Came, or went.
        alive: bool,
    },
}

/// What a resource's last publication said of the bookings on it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Turns {
    /// The conversation first on its agenda while it is free and taking orders' work
    /// (`None` while it is busy, has no booking, or is out of Execute).
    pub turn: Option<String>,
    /// The conversation whose job runs.
    pub running: Option<String>,
    /// The epoch of the holder that published (a fenced resource): one higher than an
    /// order saw when its step began means a new holder serves, which may not know
    /// the step.
    pub epoch: Option<u64>,
}

/// A resource's queue as it last published it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct PublishedQueue {
    /// It runs a job.
    pub running: bool,
    /// The priority of each waiting booking, in agenda order.
    pub waiting: Vec<i32>,
}

impl PublishedQueue {
    /// The jobs ahead of a new booking of `priority`: the running one and the waiting
    /// bookings up to the last of equal or higher priority (the agenda's rule; an
    /// estimate, since the resource may also stop it behind a booking passed too often).
    pub fn ahead_of(&self, priority: i32) -> u64 {
        let waiting_ahead = self
            .waiting
            .iter()
            .rposition(|p| *p >= priority)
            .map_or(0, |last| last + 1);
        (waiting_ahead + usize::from(self.running)) as u64
    }
}

/// What a resource's previous publication said that the next one is read against.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Published {
    /// Its agenda's length.
    pub length: usize,
    /// The places held at its locations, in all (docs/material-flow.md).
    pub held: usize,
    /// A conveyor's carriers out of service: one put back is room for a part waiting
    /// for a home (docs/material-flow.md, "Carriers out of service").
    pub carriers_out: usize,
    /// It could take orders' work.
    pub ready: bool,
}

/// What the order-node knows of the cell's resources and staff.
#[derive(Debug, Default)]
pub struct PresenceModel {
    /// The resources whose token is alive.
    alive: HashSet<HolonId>,
    /// What each resource last published, read against its next publication.
    published: HashMap<HolonId, Published>,
    /// Each resource's queue as it last published it: fresher than a proposal heard
    /// during a round.
    queues: HashMap<HolonId, PublishedQueue>,
    /// The services each resource offers, as it last published.
    services: HashMap<HolonId, Vec<String>>,
    /// The staff holons alive (advisors), by name.
    staff: BTreeSet<HolonId>,
    /// The resources whose last state said they are being handed over to a successor
    /// (an upgrade), until their token comes back.
    handing_over: HashSet<HolonId>,
    /// Counts the changes of what orders read (alive, queues, staff, hand-overs): the
    /// owner publishes a new view when it moved.
    version: u64,
    /// The fenced resources' highest epochs: a deposed holder's states are not read.
    epochs: schemas::Epochs,
}

impl PresenceModel {
    /// Handles one event: what to do about it.
    pub fn apply(&mut self, event: Event) -> Vec<Notice> {
        match event {
            Event::Token { holon, alive: true } => self.appeared(holon).into_iter().collect(),
            Event::Token {
                holon,
                alive: false,
            } => vec![self.vanished(holon)],
            Event::Tokens(holons) => self.tokens(holons),
            Event::Snapshot(snapshot) => self.published(&snapshot),
            Event::Staff { holon, alive } => self.staff_token(holon, alive).into_iter().collect(),
            Event::StaffTokens(holons) => self.staff_tokens(holons),
        }
    }

    /// Whether `resource`'s token is alive.
    pub fn is_alive(&self, resource: &HolonId) -> bool {
        self.alive.contains(resource)
    }

    /// The resources alive.
    pub fn alive(&self) -> &HashSet<HolonId> {
        &self.alive
    }

    /// Each resource's queue, as it last published it.
    pub fn queues(&self) -> &HashMap<HolonId, PublishedQueue> {
        &self.queues
    }

    /// The services each resource offers, as it last published.
    pub fn services(&self) -> &HashMap<HolonId, Vec<String>> {
        &self.services
    }

    /// The staff holons alive, by name.
    pub fn staff(&self) -> &BTreeSet<HolonId> {
        &self.staff
    }

    /// The resources being handed over to a successor.
    pub fn handing_over(&self) -> &HashSet<HolonId> {
        &self.handing_over
    }

    /// Moves whenever something orders read changed.
    pub fn version(&self) -> u64 {
        self.version
    }

    fn appeared(&mut self, holon: HolonId) -> Option<Notice> {
        if self.handing_over.remove(&holon) {
            self.version += 1;
        }
        if !self.alive.insert(holon.clone()) {
            return None;
        }
        self.version += 1;
        Some(Notice::Appeared(holon))
    }

    /// Told also for a resource not known alive (as it always was): an order that
    /// booked it before its token was seen starts its grace.
    fn vanished(&mut self, holon: HolonId) -> Notice {
        if self.alive.remove(&holon) {
            self.version += 1;
        }
        Notice::Vanished {
            handover: self.handing_over.contains(&holon),
            holon,
        }
    }

    fn tokens(&mut self, holons: Vec<HolonId>) -> Vec<Notice> {
        let found: HashSet<HolonId> = holons.into_iter().collect();
        let mut gone: Vec<HolonId> = self.alive.difference(&found).cloned().collect();
        gone.sort();
        let mut came: Vec<HolonId> = found.into_iter().collect();
        came.sort();
        let mut notices: Vec<Notice> = gone.into_iter().map(|h| self.vanished(h)).collect();
        notices.extend(came.into_iter().filter_map(|h| self.appeared(h)));
        notices
    }

    fn published(&mut self, snapshot: &ResourceSnapshot) -> Vec<Notice> {
        if !self.epochs.current(snapshot) {
            // A deposed holder's: its turns and queue are not the resource's.
            return Vec::new();
        }
        let resource = &snapshot.holon;
        let previous = self.published.get(resource).copied();
        let (news, now) = read_state(previous, snapshot);
        self.published.insert(resource.clone(), now);
        let queue = PublishedQueue {
            running: snapshot.current.is_some(),
            waiting: snapshot.agenda.iter().map(|b| b.priority).collect(),
        };
        if self.queues.get(resource) != Some(&queue) {
            self.queues.insert(resource.clone(), queue);
            self.version += 1;
        }
        if self.services.get(resource) != Some(&snapshot.services) {
            self.services
                .insert(resource.clone(), snapshot.services.clone());
            self.version += 1;
        }
        let handing_over_changed = if snapshot.handing_over {
            self.handing_over.insert(resource.clone())
        } else {
            self.handing_over.remove(resource)
        };
        if handing_over_changed {
            self.version += 1;
        }
        let mut notices = vec![Notice::Turn {
            resource: resource.clone(),
            turns: Turns {
                turn: news.turn,
                running: snapshot.current.as_ref().map(|c| c.conversation_id.clone()),
                epoch: snapshot.epoch,
            },
        }];
        if news.became_ready {
            notices.push(Notice::BecameReady(resource.clone()));
        }
        if news.places_freed > 0 {
            notices.push(Notice::PlacesFreed {
                resource: resource.clone(),
                places: news.places_freed,
            });
        }
        notices
    }

    fn staff_token(&mut self, holon: HolonId, alive: bool) -> Option<Notice> {
        let changed = if alive {
            self.staff.insert(holon.clone())
        } else {
            self.staff.remove(&holon)
        };
        changed.then(|| {
            self.version += 1;
            Notice::StaffChanged { holon, alive }
        })
    }

    fn staff_tokens(&mut self, holons: Vec<HolonId>) -> Vec<Notice> {
        let found: BTreeSet<HolonId> = holons.into_iter().collect();
        let gone: Vec<HolonId> = self.staff.difference(&found).cloned().collect();
        let mut notices: Vec<Notice> = gone
            .into_iter()
            .filter_map(|h| self.staff_token(h, false))
            .collect();
        notices.extend(found.into_iter().filter_map(|h| self.staff_token(h, true)));
        notices
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
    /// Places freed since its previous publication: on its agenda, or at its locations.
    places_freed: usize,
}

/// Reads a snapshot against what the resource published before (its agenda length and
/// whether it was ready): the news, and what to remember for the next one.
fn read_state(previous: Option<Published>, snapshot: &ResourceSnapshot) -> (StateNews, Published) {
    let before = previous.unwrap_or_default();
    // A resource out of PackML Execute or Production (held, stopped, aborted, in
    // maintenance) takes no orders' work: nobody's turn, and not ready (its return to
    // Execute is news, so waiting orders ask at once).
    let takes_orders = snapshot.packml.as_ref().is_none_or(|p| {
        p.state == schemas::PackmlState::Execute && p.mode == schemas::UnitMode::Production
    });
    let ready =
        snapshot.state != ResourceState::Init && snapshot.controller.is_ready() && takes_orders;
    let held = snapshot.places.values().map(Vec::len).sum();
    let news = StateNews {
        turn: (snapshot.state == ResourceState::Free && takes_orders)
            .then(|| snapshot.agenda.first().map(|b| b.conversation_id.clone()))
            .flatten(),
        became_ready: ready && !before.ready,
        // A booking gone from the agenda, a place released at a location, or a
        // carrier back in service: each may be what a waiting order needs.
        places_freed: before.length.saturating_sub(snapshot.agenda.len())
            + before.held.saturating_sub(held)
            + before
                .carriers_out
                .saturating_sub(snapshot.carriers_out.len()),
    };
    let now = Published {
        length: snapshot.agenda.len(),
        held,
        carriers_out: snapshot.carriers_out.len(),
        ready,
    };
    (news, now)
}

#[cfg(test)]
pub(super) mod tests;

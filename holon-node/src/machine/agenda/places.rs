//! The places at this resource's own locations (docs/material-flow.md, "Reservations"):
//! a booking of [`schemas::PLACE_SERVICE`] reserves one for a part, its `booking_cancel`
//! releases it. A place is physical: it is not a job, takes no room on the agenda,
//! starts nothing, and outlasts its requester's absence, a withdrawal, a PackML stop
//! and a restart (it is journalled with the agenda). Only its requester releases it.
//!
//! | request | condition, in order | outcome |
//! |---|---|---|
//! | `booking_req` `place` | the requester is a resource | refused `not_a_requester` |
//! | | `info.location` is not one of this resource's locations, or `info.part` is missing | refused `invalid_info` |
//! | | the part holds a place there already | true again (no second place); held now under this request's conversation, so that a late `booking_cancel` of an earlier one releases nothing |
//! | | every place there is held | refused `no_place`, naming who holds them |
//! | | a buffer of a conveyor with no carrier in service left for one more home ([`super::carriers`]) | refused `no_place`, saying so |
//! | | otherwise | true; the place is held for the part |
//! | `booking_cancel` (no booking of the conversation) | the conversation holds a place | true; released |

use std::collections::{BTreeMap, BTreeSet};

use schemas::layout::{LayoutPart, LocationId, LocationRole};
use schemas::{info_key, HolonId, HolonKind, Reason, Service};

use super::{AgendaAction, AgendaMachine};

/// A place held at a location for a part.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PlaceHold {
    /// The part, by its order's name.
    pub part: String,
    /// Who reserved it (the order).
    pub requester: HolonId,
    /// The reservation's conversation: its `booking_cancel` releases it.
    pub conversation_id: String,
    /// When it was reserved (Unix ms).
    pub since: u64,
}

/// This resource's locations and the places held at each.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Places {
    /// Each of its own locations and how many parts it holds at once.
    capacity: BTreeMap<LocationId, u32>,
    /// Those of its locations that are buffers: a place held there is a part's home.
    buffers: BTreeSet<LocationId>,
    /// The places held, by location.
    pub(super) held: BTreeMap<LocationId, Vec<PlaceHold>>,
}

impl Places {
    /// The locations of `part` (the resource's own part of the layout), none held.
    pub fn of(part: Option<&LayoutPart>) -> Places {
        let capacity = part
            .map(|p| {
                p.locations
                    .iter()
                    .map(|l| (l.id.clone(), l.capacity))
                    .collect()
            })
            .unwrap_or_default();
        let buffers = part
            .map(|p| {
                p.locations
                    .iter()
                    .filter(|l| l.role == LocationRole::Buffer)
                    .map(|l| l.id.clone())
                    .collect()
            })
            .unwrap_or_default();
        Places {
            capacity,
            buffers,
            held: BTreeMap::new(),
        }
    }

    /// How many homes are held: places at its buffers.
    pub fn homes_held(&self) -> usize {
        self.buffers
            .iter()
            .filter_map(|b| self.held.get(b))
            .map(Vec::len)
            .sum()
    }

    /// The places held, by location (for the journal and the snapshot).
    pub fn held(&self) -> &BTreeMap<LocationId, Vec<PlaceHold>> {
        &self.held
    }

    /// The places held as the journal had them.
    pub fn restore(&mut self, held: BTreeMap<LocationId, Vec<PlaceHold>>) {
        self.held = held;
    }
}

impl AgendaMachine {
    /// A `booking_req` of a place: the rows of the table above.
    pub(super) fn hold_place(&mut self, request: &Service, now: u64) -> Vec<AgendaAction> {
        if request.requester.kind() == HolonKind::Resource {
            return self.refuse(request, Reason::NotARequester, None);
        }
        let text = |key: &str| request.info.get(key).and_then(|v| v.as_str());
        let location = text(info_key::LOCATION)
            .and_then(|id| LocationId::try_from(id.to_string()).ok())
            .filter(|id| self.places.capacity.contains_key(id));
        let (Some(location), Some(part)) = (location, text(info_key::PART)) else {
            let detail = format!(
                "a place is booked with info.part and info.location, one of {}'s locations ({})",
                self.holon.name(),
                self.places
                    .capacity
                    .keys()
                    .map(LocationId::as_str)
                    .collect::<Vec<_>>()
                    .join(", ")
            );
            return self.refuse(request, Reason::InvalidInfo, Some(detail));
        };
        let capacity = self.places.capacity[&location] as usize;
        let holds = self.places.held.entry(location.clone()).or_default();
        if let Some(hold) = holds.iter_mut().find(|h| h.part == part) {
            let mut actions = vec![AgendaAction::Reply(request.accepted(&self.holon))];
            if hold.conversation_id != request.conversation_id {
                // Reserved again (its order's newer reservation): a cancel of the
                // earlier one, late, finds nothing to release.
                hold.conversation_id = request.conversation_id.clone();
                hold.requester = request.requester.clone();
                actions.push(AgendaAction::StateChanged);
            }
            return actions;
        }
        if holds.len() >= capacity {
            let holders: Vec<&str> = holds.iter().map(|h| h.part.as_str()).collect();
            let detail = format!(
                "{location} is full: its {capacity} place(s) held for {}",
                holders.join(", ")
            );
            return self.refuse(request, Reason::NoPlace, Some(detail));
        }
        if self.places.buffers.contains(&location)
            && !self.carriers.room_for_home(self.places.homes_held())
        {
            let detail = format!(
                "no carrier left for one more part: {} of {}'s carriers in service ({} out: {}), {} homes held",
                self.carriers.in_service(),
                self.holon.name(),
                self.carriers.out().len(),
                self.carriers.out().iter().cloned().collect::<Vec<_>>().join(", "),
                self.places.homes_held()
            );
            return self.refuse(request, Reason::NoPlace, Some(detail));
        }
        let holds = self.places.held.entry(location.clone()).or_default();
        holds.push(PlaceHold {
            part: part.to_string(),
            requester: request.requester.clone(),
            conversation_id: request.conversation_id.clone(),
            since: now,
        });
        tracing::info!(holon = %self.holon, %location, part, conversation_id = %request.conversation_id, "place held");
        vec![
            AgendaAction::Reply(request.accepted(&self.holon)),
            AgendaAction::StateChanged,
        ]
    }

    /// A `booking_cancel` of a conversation that holds a place: released. `None` when
    /// it holds none.
    pub(super) fn release_place(&mut self, request: &Service) -> Option<Vec<AgendaAction>> {
        let (location, holds) = self.places.held.iter_mut().find(|(_, holds)| {
            holds.iter().any(|h| {
                h.requester == request.requester && h.conversation_id == request.conversation_id
            })
        })?;
        holds.retain(|h| {
            h.requester != request.requester || h.conversation_id != request.conversation_id
        });
        tracing::info!(holon = %self.holon, %location, conversation_id = %request.conversation_id, "place released");
        if holds.is_empty() {
            let location = location.clone();
            self.places.held.remove(&location);
        }
        Some(vec![
            AgendaAction::Reply(request.accepted(&self.holon)),
            AgendaAction::StateChanged,
        ])
    }
}

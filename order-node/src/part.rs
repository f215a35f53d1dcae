//! An order's part, as its order knows it (docs/material-flow.md, "Parts and
//! carriers"): where it is, the places held for it, the move under way, and the end the
//! order waits to record until the part has left the cell. Pure: the order's task
//! ([`crate::order`]) decides with it and journals it with the order's progress before
//! acting on it.
//!
//! | event | part | next |
//! |---|---|---|
//! | a move begins (its phase recorded `started`) | at `from` | in transit on the transporter from `from` to `to` |
//! | the transporter says the move has left `from` (`departed`, this move's conversation, its transporter) | in transit | in transit, the move marked left; the place at `from` released unless it is the part's home (or not held) |
//! | a move marked left ends unattempted (its controller refused it after all), or its transporter says it never reached the controller | in transit / lost | lost (the order's decision, `order/material.rs`): the part left `from`, only an operator can say it is there |
//! | the move is done | in transit | at `to` (shipped at an exit); the place at `from` released unless it is the part's home (or released at departure) |
//! | the move ended unattempted (refused, lost before it began, `not_begun`, no transporter) | at `from` | at `from` (the place reserved at `to` released) |
//! | the move failed, or its transporter vanished while it may have run | in transit | lost: in transit on the transporter, last seen at `from`, until it or an operator says |
//! | the transporter says the lost move was done / never reached the controller | lost | at `to` / at `from` |
//! | an operator says the lost part is at `to` / at `from` (recorded with who said it; at a `from` released at departure, only once the order's task has reserved it again: [`PartProgress::needs_origin_again`]) | lost | at `to` / at `from` |
//! | the order's end is decided while the part is in the cell | at a location | the end waits; the part leaves by an exit first |
//!
//! A departure releases the origin's place at most once: it is taken off `held`, so a
//! second `departed` or the move's `done` finds nothing more to release there
//! (docs/material-flow.md, "Departure"). A `departed` for another move, from another
//! transporter, or before the move's start is recorded changes nothing (the place is
//! then released at `done`, as when the transporter never says it departed). The
//! released reservation is kept with the move ([`Move::departed`]) until it ends, so
//! that an order-node restarted between journalling the departure and sending its
//! `booking_cancel` sends it again ([`PartProgress::released_at_departure`]).

use std::collections::BTreeMap;

use schemas::layout::LocationId;
use schemas::{HolonId, OrderStatus, PartFound, PartPlace};

use crate::phase::Phase;

/// The service a move is booked as: what transporters offer by convention.
pub const TRANSPORT_SERVICE: &str = "transport";

/// What a move is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MoveGoal {
    /// To the station where the next step is worked (its place reserved there).
    Station,
    /// Back to the part's home: no station had a place for it.
    Home,
    /// Out of the cell, by an exit: the order's end waits for it.
    Exit,
}

/// A move of the part, booked on a transporter like a step.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Move {
    /// Its conversation: `<order>/m<n>/<attempt>`.
    pub conversation_id: String,
    pub from: LocationId,
    pub to: LocationId,
    pub goal: MoveGoal,
    /// Where its attempt stands with a transporter.
    pub phase: Phase,
    /// The reservation's conversation of the place at `from` released when the
    /// transporter said the move had left it (`departed`); `None` while it has not said
    /// so, or when nothing was released then (the part's home, a place not held).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub departed: Option<String>,
    /// Whether its transporter said the move had left `from` (`departed`), whether or
    /// not a place was released then: from then on the part is not at `from` on the
    /// transporter's word alone (a refusal or "never reached" after it leaves the part
    /// lost, for an operator to say where it is).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub left: bool,
}

/// An order's part.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PartProgress {
    /// Where the part is.
    pub place: PartPlace,
    /// Its home: a buffer place held for it from its entry until it leaves the cell, to
    /// which it can always go back (why the cell cannot deadlock).
    pub home: Option<LocationId>,
    /// The places held for it, each at the resource that states its location, by the
    /// conversation that reserved it (its `booking_cancel` releases it).
    pub held: BTreeMap<LocationId, String>,
    /// The move under way, if any.
    pub moving: Option<Move>,
    /// Moves begun so far: each one's conversation is numbered by it.
    pub moves: u32,
    /// Places reserved so far: each reservation's conversation is numbered by it, so
    /// that a late `booking_cancel` of an earlier reservation of a location never
    /// releases a later one.
    #[serde(default)]
    pub reservations: u32,
    /// The order's end, decided while the part was in the cell: recorded once the part
    /// has left it.
    pub leaving: Option<(OrderStatus, Option<String>)>,
    /// Operators' words on where the part was while it was lost, oldest first: the
    /// order's audit trail of them (at most [`schemas::MAX_ATTEMPT_HISTORY`]).
    #[serde(default)]
    pub found: Vec<PartFound>,
}

impl Default for PartProgress {
    fn default() -> Self {
        PartProgress {
            place: PartPlace::Outside,
            home: None,
            held: BTreeMap::new(),
            moving: None,
            moves: 0,
            reservations: 0,
            leaving: None,
            found: Vec::new(),
        }
    }
}

/// How a move's attempt ended, as the part sees it.
#[derive(Debug, Clone, PartialEq)]
pub enum MoveEnd {
    /// The transporter reported it done.
    Done,
    /// Nothing of it ran (refused, lost before it began, no transporter).
    Unattempted,
    /// It may have moved the part: the transporter failed it or vanished with it.
    Unknown { why: String },
}

impl PartProgress {
    /// Whether the part is in the cell (entered, not shipped).
    pub fn in_cell(&self) -> bool {
        !matches!(self.place, PartPlace::Outside | PartPlace::Shipped { .. })
    }

    /// The reservation's conversation for a place at `location`.
    pub fn place_conversation(&mut self, order: &HolonId, location: &LocationId) -> String {
        self.reservations += 1;
        format!("{}/place/{location}/{}", order.name(), self.reservations)
    }

    /// A move of the part begins to be booked.
    pub fn begin_move(
        &mut self,
        order: &HolonId,
        from: LocationId,
        to: LocationId,
        goal: MoveGoal,
    ) {
        self.moves += 1;
        self.moving = Some(Move {
            conversation_id: format!("{}/m{}/1", order.name(), self.moves),
            from,
            to,
            goal,
            phase: Phase::Proposing,
            departed: None,
            left: false,
        });
    }

    /// The move's attempt is at `phase`: once started, the part is in transit.
    pub fn move_phase(&mut self, phase: Phase) {
        let Some(moving) = &mut self.moving else {
            return;
        };
        if let Phase::Started(transporter) = &phase {
            self.place = PartPlace::InTransit {
                transporter: transporter.clone(),
                from: moving.from.clone(),
                to: moving.to.clone(),
            };
        }
        moving.phase = phase;
    }

    /// The move's transporter says the move `conversation_id` has left its origin: the
    /// place held at `from` is released, unless it is the part's home or not held (any
    /// more). Returns it (the location with its reservation's conversation), taken off
    /// `held`, or `None` when nothing is to be released: a second `departed`, one for
    /// another move or from another transporter than the one the part rides, or one
    /// before the move's start is recorded (the place is then released at `done`).
    pub fn departed(
        &mut self,
        conversation_id: &str,
        transporter: &HolonId,
    ) -> Option<(LocationId, String)> {
        let moving = self.moving.as_mut()?;
        if moving.conversation_id != conversation_id {
            return None;
        }
        match &self.place {
            PartPlace::InTransit {
                transporter: riding,
                from,
                ..
            } if riding == transporter && from == &moving.from => {}
            _ => return None,
        }
        moving.left = true;
        if self.home.as_ref() == Some(&moving.from) {
            return None;
        }
        let released = self.held.remove_entry(&moving.from)?;
        moving.departed = Some(released.1.clone());
        Some(released)
    }

    /// Whether the move under way has left its origin, on its transporter's word.
    pub fn has_left(&self) -> bool {
        self.moving.as_ref().is_some_and(|m| m.left)
    }

    /// The place released when the move under way departed (its location and
    /// reservation's conversation), if it was: a restarted order-node sends its
    /// `booking_cancel` again, as the crash may have come between the journal and the
    /// cancel (a second cancel of a released place is answered `not_booked`, harmless).
    pub fn released_at_departure(&self) -> Option<(LocationId, String)> {
        let moving = self.moving.as_ref()?;
        let conversation = moving.departed.clone()?;
        Some((moving.from.clone(), conversation))
    }

    /// The move ended: where the part is, and the places to release (each location
    /// with the conversation that holds it), taken off `held`.
    pub fn end_move(
        &mut self,
        end: MoveEnd,
        transporter: Option<HolonId>,
    ) -> Vec<(LocationId, String)> {
        let Some(moving) = self.moving.take() else {
            return vec![];
        };
        let release = |held: &mut BTreeMap<LocationId, String>, at: &LocationId| {
            held.remove_entry(at).into_iter().collect::<Vec<_>>()
        };
        match end {
            MoveEnd::Done => {
                // A move to an exit was begun as one (its goal), whatever the layout
                // says now: the transporter that states the exit may be away while its
                // move's end is learnt (restarted mid-move), and the part has left.
                let exit = moving.goal == MoveGoal::Exit;
                let mut released = Vec::new();
                // Not held any more when the move's departure released it: nothing
                // released twice.
                if self.home.as_ref() != Some(&moving.from) {
                    released.extend(release(&mut self.held, &moving.from));
                }
                if exit {
                    self.place = PartPlace::Shipped { exit: moving.to };
                    // Out of the cell: every place it held is free.
                    self.home = None;
                    released.extend(std::mem::take(&mut self.held));
                } else {
                    self.place = PartPlace::At {
                        location: moving.to,
                    };
                }
                released
            }
            MoveEnd::Unattempted => {
                self.place = match &self.place {
                    PartPlace::Outside => PartPlace::Outside,
                    _ => PartPlace::At {
                        location: moving.from.clone(),
                    },
                };
                if moving.goal == MoveGoal::Station {
                    release(&mut self.held, &moving.to)
                } else {
                    vec![]
                }
            }
            MoveEnd::Unknown { why } => {
                self.place = PartPlace::Lost {
                    transporter: transporter
                        .unwrap_or_else(|| HolonId::resource("unknown").expect("a valid name")),
                    from: moving.from.clone(),
                    to: moving.to.clone(),
                    why,
                };
                // Kept to be asked about again.
                self.moving = Some(moving);
                vec![]
            }
        }
    }

    /// The transporter (or an operator) said where the lost part is: `arrived` at the
    /// move's destination, or still where it was. Returns the places to release.
    pub fn found(&mut self, arrived: bool) -> Vec<(LocationId, String)> {
        let end = if arrived {
            MoveEnd::Done
        } else {
            MoveEnd::Unattempted
        };
        let transporter = match &self.place {
            PartPlace::Lost { transporter, .. } => Some(transporter.clone()),
            _ => None,
        };
        self.end_move(end, transporter)
    }

    /// Whether an operator's word that the lost part is at `location` needs its place
    /// there reserved again before it is recorded: `location` is the lost move's origin,
    /// whose place was released when the transporter said the move had left it
    /// (docs/material-flow.md, "Departure"). Asked even when `held` has it again: a
    /// reservation journalled before it was asked may not have been granted (the
    /// process died, or its refusal's removal failed), and asking again is harmless
    /// (a part that holds the place is answered true again). Its home is never
    /// released that way.
    pub fn needs_origin_again(&self, location: &LocationId) -> bool {
        let (PartPlace::Lost { from, .. }, Some(moving)) = (&self.place, &self.moving) else {
            return false;
        };
        location == from && moving.departed.is_some()
    }

    /// An operator said where the lost part is: `location`, the lost move's origin or
    /// its destination (checked before: [`crate::part_word::check`]). Recorded with who
    /// said it and when; returns the places to release. Nothing changes when the part
    /// is not lost or the location is neither end of its move.
    pub fn found_by_operator(
        &mut self,
        location: &LocationId,
        by: &str,
        at: u64,
    ) -> Vec<(LocationId, String)> {
        let (
            PartPlace::Lost {
                transporter,
                from,
                to,
                ..
            },
            Some(moving),
        ) = (&self.place, &self.moving)
        else {
            return vec![];
        };
        if location != from && location != to {
            return vec![];
        }
        let word = PartFound {
            conversation_id: moving.conversation_id.clone(),
            transporter: transporter.clone(),
            location: location.clone(),
            by: by.to_string(),
            at,
        };
        let arrived = location == to;
        if self.found.len() >= schemas::MAX_ATTEMPT_HISTORY {
            self.found.remove(0);
        }
        self.found.push(word);
        self.found(arrived)
    }
}

#[cfg(test)]
mod tests;

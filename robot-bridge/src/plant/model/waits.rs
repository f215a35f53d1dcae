//! What waits in the plant, on what and since when; and whether it is deadlocked (some
//! pallets waiting only on one another).

use std::collections::{BTreeMap, BTreeSet};

use schemas::layout::{Dock, LocationId};
use serde::Serialize;

use super::{Place, Plant};

/// What a waiting pallet waits for.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Blocker {
    /// A location without a place: its parts, the pallets docking into it and the
    /// transfers on their way hold its places.
    Location(LocationId),
    /// A full track (index: the stopper it ends at): its first pallet must go on
    /// before another comes.
    Track { conveyor: String, track: usize },
    /// A jammed track: only clearing it frees it.
    Jammed(Dock),
    /// The spot at a stopper, where its location's pallets come back onto the loop:
    /// held by the pallet stopped there.
    Stopper { conveyor: String, stopper: usize },
    /// The pallet ahead on the same track.
    Behind(String),
}

/// A pallet and where it is, as the state file shows it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PalletView {
    /// `parked` (free, off the loop), `docked` (in `location`), `docking` (into
    /// `location`), `track` (on the track that ends at stopper `track`) or `retired`
    /// (taken out of service: `retire`).
    pub at: &'static str,
    /// The location it is docked in or docking into.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub location: Option<String>,
    /// The stopper whose track it is on (`s2`: the track that ends at stopper s2).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub track: Option<String>,
    /// Its place in that track's queue: 0 is first, at the stopper.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub queue_position: Option<usize>,
    /// On a track, still riding to its stopper or to the queue's back.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub riding: bool,
    /// The part it carries.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part: Option<String>,
    /// Where it takes its part, while a move is under way.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub to: Option<String>,
    /// Stopped where it is by an aborted move.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub stopped: bool,
    /// What it waits for (`robot2.port full`, `track s3 full`, `track s3 jammed`,
    /// `stopper s2 taken by conveyor1/p1`, `behind conveyor1/p1`), if it waits.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub waits: Option<String>,
    /// Since when it waits, in ms since the plant started.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub waits_since_ms: Option<u64>,
}

/// A pallet that waits, as the control port's `waits` answers.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct WaitView {
    /// The pallet.
    pub pallet: String,
    /// What it waits for.
    pub waits: String,
    /// Since when, in ms since the plant started.
    pub since_ms: u64,
    /// For how long so far, in ms.
    pub for_ms: u64,
}

impl Plant {
    /// What `pallet` waits for now, if it waits.
    fn blocker(&self, pallet: &str) -> Option<Blocker> {
        let p = self.pallets.get(pallet).filter(|p| !p.stopped)?;
        let conveyor = p.conveyor.as_str();
        let n = self.loops[conveyor].tracks.len();
        match &p.place {
            Place::Docked(at) if p.bound.is_some() => {
                let stopper = self.stopper_of(conveyor, at)?;
                if self.spot_taken(conveyor, stopper) {
                    return Some(Blocker::Stopper {
                        conveyor: conveyor.into(),
                        stopper,
                    });
                }
                self.track_blocker(conveyor, (stopper + 1) % n)
            }
            Place::Track { track, due } if *due <= self.clock => {
                let queue = &self.loops[conveyor].tracks[*track];
                let position = queue.iter().position(|id| id == pallet)?;
                if position > 0 {
                    return Some(Blocker::Behind(queue[position - 1].clone()));
                }
                if self.is_jammed(conveyor, *track) {
                    return Some(Blocker::Jammed(self.dock(conveyor, *track)));
                }
                let bound = p.bound.as_ref()?;
                if bound.stopper == *track {
                    return (!self.has_place(&bound.to))
                        .then(|| Blocker::Location(bound.to.clone()));
                }
                self.track_blocker(conveyor, (track + 1) % n)
            }
            _ => None,
        }
    }

    /// What stops a pallet entering `track`, if anything does.
    fn track_blocker(&self, conveyor: &str, track: usize) -> Option<Blocker> {
        if self.is_jammed(conveyor, track) {
            return Some(Blocker::Jammed(self.dock(conveyor, track)));
        }
        (!self.has_room(conveyor, track)).then(|| Blocker::Track {
            conveyor: conveyor.into(),
            track,
        })
    }

    fn dock(&self, conveyor: &str, stopper: usize) -> Dock {
        Dock {
            conveyor: conveyor.into(),
            stopper: self.loops[conveyor].spec.stoppers[stopper].name.clone(),
        }
    }

    fn describe(&self, blocker: &Blocker) -> String {
        let stopper = |c: &str, i: usize| self.loops[c].spec.stoppers[i].name.clone();
        match blocker {
            Blocker::Location(at) => format!("{at} full"),
            Blocker::Track { conveyor, track } => {
                format!("track {} full", stopper(conveyor, *track))
            }
            Blocker::Jammed(dock) => format!("track {} jammed", dock.stopper),
            Blocker::Stopper {
                conveyor,
                stopper: s,
            } => {
                let head = self.loops[conveyor].tracks[*s].front().cloned();
                format!(
                    "stopper {} taken by {}",
                    stopper(conveyor, *s),
                    head.unwrap_or_default()
                )
            }
            Blocker::Behind(pallet) => format!("behind {pallet}"),
        }
    }

    /// What `pallet` waits for, in words, if it waits.
    pub fn waits_for(&self, pallet: &str) -> Option<String> {
        self.blocker(pallet).map(|b| self.describe(&b))
    }

    /// Who holds what `blocker` stands for: pallets, or None for anything the pallets
    /// do not decide (a part at rest in a location, a pallet docking, a transfer on its
    /// way, a jam).
    fn holders(&self, blocker: &Blocker) -> Vec<Option<String>> {
        let mut holders = match blocker {
            Blocker::Location(at) => {
                let mut holders: Vec<Option<String>> = self.held[at]
                    .iter()
                    .map(|load| {
                        load.carrier.clone().filter(|c| {
                            self.pallets.get(c).is_some_and(|p| {
                                p.bound.is_some() && p.place == Place::Docked(at.clone())
                            })
                        })
                    })
                    .collect();
                let others = self.occupancy(at) - self.held[at].len();
                holders.extend(std::iter::repeat_n(None, others));
                holders
            }
            Blocker::Track { conveyor, track } => {
                vec![self.loops[conveyor].tracks[*track].front().cloned()]
            }
            Blocker::Stopper { conveyor, stopper } => {
                vec![self.loops[conveyor].tracks[*stopper].front().cloned()]
            }
            Blocker::Behind(pallet) => vec![Some(pallet.clone())],
            Blocker::Jammed(_) => vec![None],
        };
        if holders.is_empty() {
            holders.push(None);
        }
        holders
    }

    /// The pallets that wait only on one another, none of which can go on unless another
    /// does: a cycle in the wait-for graph (pallet X waits at robot2.port's stopper for
    /// a place, held by pallet Y, which waits to leave for the stopper's spot, held by
    /// X). Empty: the plant is not deadlocked (pallets may still wait, on what the
    /// control or an operator decides: a part at rest in a port, a jam).
    pub fn deadlock(&self) -> Vec<String> {
        let waiting: BTreeMap<&String, Vec<Option<String>>> = self
            .pallets
            .keys()
            .filter_map(|id| Some((id, self.holders(&self.blocker(id)?))))
            .collect();
        let mut stuck: BTreeSet<&String> = waiting.keys().copied().collect();
        loop {
            let free: Vec<&String> = stuck
                .iter()
                .copied()
                .filter(|id| {
                    waiting[*id]
                        .iter()
                        .any(|h| h.as_ref().is_none_or(|h| !stuck.contains(h)))
                })
                .collect();
            if free.is_empty() {
                break;
            }
            for id in free {
                stuck.remove(id);
            }
        }
        stuck.into_iter().cloned().collect()
    }

    /// Every pallet that waits now: what for, since when.
    pub fn waits(&self) -> Vec<WaitView> {
        self.pallets
            .iter()
            .filter_map(|(id, p)| {
                let since = p.waiting_since?;
                Some(WaitView {
                    pallet: id.clone(),
                    waits: self.waits_for(id)?,
                    since_ms: since,
                    for_ms: self.clock.saturating_sub(since),
                })
            })
            .collect()
    }

    /// The longest any pallet has waited, or waits now, in ms.
    pub(super) fn longest_wait_ms(&self) -> u64 {
        self.pallets
            .values()
            .filter_map(|p| p.waiting_since)
            .map(|since| self.clock.saturating_sub(since))
            .chain([self.longest_wait_ms])
            .max()
            .unwrap_or(0)
    }

    pub(super) fn pallet_views(&self) -> BTreeMap<String, PalletView> {
        self.pallets
            .iter()
            .map(|(id, p)| {
                let mut view = PalletView {
                    at: "parked",
                    location: None,
                    track: None,
                    queue_position: None,
                    riding: false,
                    part: p.part.clone(),
                    to: p.bound.as_ref().map(|b| b.to.to_string()),
                    stopped: p.stopped,
                    waits: p.waiting_since.and_then(|_| self.waits_for(id)),
                    waits_since_ms: p.waiting_since,
                };
                match &p.place {
                    Place::Parked => {}
                    Place::Docked(at) => {
                        view.at = "docked";
                        view.location = Some(at.to_string());
                    }
                    Place::Docking { at, .. } => {
                        view.at = "docking";
                        view.location = Some(at.to_string());
                    }
                    Place::Track { track, due } => {
                        let lp = &self.loops[&p.conveyor];
                        view.at = "track";
                        view.track = Some(lp.spec.stoppers[*track].name.clone());
                        view.queue_position = lp.tracks[*track].iter().position(|q| q == id);
                        view.riding = *due > self.clock;
                    }
                    Place::Retired => view.at = "retired",
                }
                (id.clone(), view)
            })
            .collect()
    }
}

//! How the plant goes on as time passes (the table at the top of [`super`]): pallets
//! leave their location, ride their tracks, pass stoppers, wait and dock; transfers
//! arrive. Pure: the time comes in as an argument.

use schemas::layout::{ConveyorSpec, Dock, LocationId};

use super::{Happening, Load, Place, Plant};

/// How long a pallet rides `mm` at the conveyor's speed, in ms (as the layout times a
/// move: rounded down).
fn ride_ms(spec: &ConveyorSpec, mm: u64) -> u64 {
    mm * 1000 / u64::from(spec.speed_mm_s.max(1))
}

/// The length of the track that ends at stopper `track`, in mm (the whole loop when it
/// has one stopper).
fn track_mm(spec: &ConveyorSpec, track: usize) -> u64 {
    let n = spec.stoppers.len();
    let length = u64::from(spec.length_mm);
    if n <= 1 {
        return length;
    }
    let end = u64::from(spec.stoppers[track].at_mm);
    let start = u64::from(spec.stoppers[(track + n - 1) % n].at_mm);
    (end + length - start) % length
}

impl Plant {
    /// Advances the plant to `now` (ms since it started; an earlier time is taken as the
    /// plant's own): everything due by then happens at its own time, in order, and
    /// whatever that allows at once (a pallet behind another moving up, a pallet waiting
    /// for the place just freed). Returns what happened since the last call.
    pub fn advance(&mut self, now: u64) -> Vec<Happening> {
        let now = now.max(self.clock);
        loop {
            self.settle();
            match self.next_due() {
                Some(due) if due <= now => self.clock = due,
                _ => break,
            }
        }
        self.clock = now;
        self.settle();
        std::mem::take(&mut self.happened)
    }

    /// When (plant ms) the next thing is due, if anything is: a pallet reaching the end
    /// of its track or docked, a transfer arriving. A pallet that waits is not due: it
    /// goes on when something else happens.
    pub fn next_due(&self) -> Option<u64> {
        let pallets = self
            .pallets
            .values()
            .filter(|p| !p.stopped && !self.estopped.contains_key(&p.conveyor))
            .filter_map(|p| match p.place {
                Place::Track { due, .. } | Place::Docking { due, .. } => Some(due),
                _ => None,
            });
        let transfers = self
            .transit
            .values()
            .filter(|t| !t.stopped && !self.estopped.contains_key(&t.transporter))
            .filter_map(|t| t.arrives_ms);
        pallets
            .chain(transfers)
            .filter(|due| *due > self.clock && *due != u64::MAX)
            .min()
    }

    /// Everything that can happen at the plant's time, until nothing more can; then
    /// which pallets wait, since when.
    pub(super) fn settle(&mut self) {
        self.transfers_arrive();
        self.pallets_found();
        let conveyors: Vec<String> = self
            .loops
            .keys()
            .filter(|c| !self.estopped.contains_key(*c))
            .cloned()
            .collect();
        for conveyor in &conveyors {
            // Non-short-circuit `|`: each kind of step gets its turn every round.
            while self.dockings_end(conveyor) | self.stoppers(conveyor) | self.departures(conveyor)
            {
                // A pallet freed on the way (a part shipped) takes a waiting part.
                self.pallets_found();
            }
        }
        self.note_waits();
    }

    fn transfers_arrive(&mut self) {
        let due: Vec<String> = self
            .transit
            .iter()
            .filter(|(_, t)| {
                !t.stopped
                    && !self.estopped.contains_key(&t.transporter)
                    && t.arrives_ms.is_some_and(|due| due <= self.clock)
            })
            .map(|(part, _)| part.clone())
            .collect();
        for part in due {
            let transit = self.transit.remove(&part).expect("found above");
            self.note_arrival(&transit);
            self.put(transit.load, &transit.to, &transit.transporter);
        }
    }

    /// `load` arrives at `at`: held there, or at an exit shipped (its pallet parked).
    fn put(&mut self, load: Load, at: &LocationId, transporter: &str) {
        let part = load.part.clone();
        if self.is_exit(at) {
            self.park(load.carrier);
            self.shipped += 1;
            self.happened.push(Happening::Shipped {
                part,
                at: at.clone(),
            });
            return;
        }
        self.held
            .get_mut(at)
            .expect("a location of the layout")
            .push(load);
        self.happened.push(Happening::Arrived {
            part,
            at: at.clone(),
            transporter: transporter.into(),
        });
    }

    /// The pallets of `conveyor` whose docking is over: their part is there.
    fn dockings_end(&mut self, conveyor: &str) -> bool {
        let clock = self.clock;
        let done: Vec<(String, LocationId)> = self
            .pallets
            .iter()
            .filter(|(_, p)| p.conveyor == conveyor && !p.stopped)
            .filter_map(|(id, p)| match &p.place {
                Place::Docking { at, due } if *due <= clock => Some((id.clone(), at.clone())),
                _ => None,
            })
            .collect();
        for (pallet, at) in &done {
            let p = self.pallets.get_mut(pallet).expect("a pallet of the plant");
            p.place = Place::Docked(at.clone());
            p.bound = None;
            let Some(part) = p.part.clone() else { continue };
            if let Some(transit) = self.transit.remove(&part) {
                self.note_arrival(&transit);
            }
            let load = Load {
                part,
                carrier: Some(pallet.clone()),
            };
            self.put(load, at, conveyor);
        }
        !done.is_empty()
    }

    /// The first pallet of each of `conveyor`'s tracks, at its stopper: it docks, passes
    /// or waits.
    fn stoppers(&mut self, conveyor: &str) -> bool {
        let tracks = self.loops[conveyor].tracks.len();
        let mut moved = false;
        for track in 0..tracks {
            moved |= self.at_stopper(conveyor, track);
        }
        moved
    }

    fn at_stopper(&mut self, conveyor: &str, track: usize) -> bool {
        let lp = &self.loops[conveyor];
        let Some(head) = lp.tracks[track].front().cloned() else {
            return false;
        };
        let (n, stopper) = (lp.tracks.len(), lp.spec.stoppers[track].name.clone());
        let dock_ms = lp.spec.dock_ms;
        let p = &self.pallets[&head];
        let there = matches!(p.place, Place::Track { due, .. } if due <= self.clock);
        let Some(bound) = p.bound.clone().filter(|_| there && !p.stopped) else {
            return false;
        };
        if self.is_jammed(conveyor, track) {
            return false;
        }
        if bound.stopper == track {
            if !self.has_place(&bound.to) {
                return false;
            }
            self.track_mut(conveyor, track).pop_front();
            let due = self.clock + dock_ms;
            let p = self.pallets.get_mut(&head).expect("a pallet of the plant");
            p.place = Place::Docking {
                at: bound.to.clone(),
                due,
            };
            self.happened.push(Happening::Docking {
                pallet: head,
                at: bound.to,
            });
            return true;
        }
        let next = (track + 1) % n;
        if !self.has_room(conveyor, next) {
            return false;
        }
        self.track_mut(conveyor, track).pop_front();
        self.enter(conveyor, &head, next, 0);
        self.happened.push(Happening::Passed {
            pallet: head,
            stopper,
        });
        true
    }

    /// The pallets of `conveyor` docked with a move under way: each leaves onto the
    /// track after its stopper if nothing waits at the stopper and that track has room.
    fn departures(&mut self, conveyor: &str) -> bool {
        let leaving: Vec<(String, LocationId)> = self
            .pallets
            .iter()
            .filter(|(_, p)| p.conveyor == conveyor && !p.stopped && p.bound.is_some())
            .filter_map(|(id, p)| match &p.place {
                Place::Docked(at) => Some((id.clone(), at.clone())),
                _ => None,
            })
            .collect();
        let (n, dock_ms) = {
            let lp = &self.loops[conveyor];
            (lp.tracks.len(), lp.spec.dock_ms)
        };
        let mut moved = false;
        for (pallet, from) in leaving {
            let Some(stopper) = self.stopper_of(conveyor, &from) else {
                continue;
            };
            let next = (stopper + 1) % n;
            if self.spot_taken(conveyor, stopper) || !self.has_room(conveyor, next) {
                continue;
            }
            let part = self.pallets[&pallet].part.clone();
            if let Some(loads) = self.held.get_mut(&from) {
                loads.retain(|l| Some(&l.part) != part.as_ref());
            }
            self.enter(conveyor, &pallet, next, dock_ms);
            self.happened.push(Happening::Left { pallet, from });
            moved = true;
        }
        moved
    }

    /// `pallet` enters the back of `track`, to ride it (after `extra_ms`: coming back
    /// onto the loop).
    fn enter(&mut self, conveyor: &str, pallet: &str, track: usize, extra_ms: u64) {
        let spec = &self.loops[conveyor].spec;
        let mm = track_mm(spec, track);
        let p = self.pallets.get_mut(pallet).expect("a pallet of the plant");
        let ridden = p.bound.as_ref().map_or(0, |b| b.ridden_mm);
        let ride = ride_ms(spec, ridden + mm) - ride_ms(spec, ridden);
        if let Some(bound) = p.bound.as_mut() {
            bound.ridden_mm += mm;
        }
        p.place = Place::Track {
            track,
            due: self.clock + extra_ms + ride,
        };
        self.track_mut(conveyor, track)
            .push_back(pallet.to_string());
    }

    fn track_mut(
        &mut self,
        conveyor: &str,
        track: usize,
    ) -> &mut std::collections::VecDeque<String> {
        &mut self
            .loops
            .get_mut(conveyor)
            .expect("a conveyor of the plant")
            .tracks[track]
    }

    /// Whether the track that ends at stopper `track` is jammed.
    pub(super) fn is_jammed(&self, conveyor: &str, track: usize) -> bool {
        let stopper = &self.loops[conveyor].spec.stoppers[track].name;
        self.jammed.contains(&Dock {
            conveyor: conveyor.into(),
            stopper: stopper.clone(),
        })
    }

    /// Whether the track that ends at stopper `track` takes one more pallet: fewer than
    /// its queue on it, and not jammed.
    pub(super) fn has_room(&self, conveyor: &str, track: usize) -> bool {
        let lp = &self.loops[conveyor];
        !self.is_jammed(conveyor, track)
            && lp.tracks[track].len() < lp.spec.stoppers[track].queue as usize
    }

    /// Whether a pallet stands at stopper `stopper` (first on its track, there): where
    /// the pallets docked at that stopper come back onto the loop.
    pub(super) fn spot_taken(&self, conveyor: &str, stopper: usize) -> bool {
        self.loops[conveyor].tracks[stopper]
            .front()
            .is_some_and(|head| {
                matches!(self.pallets[head].place, Place::Track { due, .. } if due <= self.clock)
            })
    }

    /// How many places of `at` are taken: the parts there, the pallets docking into
    /// it, the transfers on their way to it.
    pub(super) fn occupancy(&self, at: &LocationId) -> usize {
        let docking = self
            .pallets
            .values()
            .filter(|p| matches!(&p.place, Place::Docking { at: a, .. } if a == at))
            .count();
        let transfers = self
            .transit
            .values()
            .filter(|t| &t.to == at && !t.stopped && t.arrives_ms.is_some())
            .count();
        self.held[at].len() + docking + transfers
    }

    /// Whether a pallet can dock into `at` now: an exit always takes one (its part
    /// leaves the plant), anywhere else below its capacity.
    pub(super) fn has_place(&self, at: &LocationId) -> bool {
        let capacity = self.layout.location(at).map_or(0, |l| l.capacity) as usize;
        self.is_exit(at) || self.occupancy(at) < capacity
    }

    /// Which pallets wait now, since when; a wait that is over counts towards the
    /// longest.
    fn note_waits(&mut self) {
        let clock = self.clock;
        let ids: Vec<String> = self.pallets.keys().cloned().collect();
        for id in ids {
            let p = &self.pallets[&id];
            if self.estopped.contains_key(&p.conveyor) {
                continue;
            }
            let waiting = !p.stopped
                && match &p.place {
                    Place::Track { due, .. } => *due <= clock,
                    Place::Docked(_) => p.bound.is_some(),
                    _ => false,
                };
            match (waiting, p.waiting_since) {
                (true, None) => {
                    let what = self.waits_for(&id).unwrap_or_default();
                    let p = self.pallets.get_mut(&id).expect("a pallet of the plant");
                    p.waiting_since = Some(clock);
                    self.happened.push(Happening::Waits { pallet: id, what });
                }
                (false, Some(since)) => {
                    self.longest_wait_ms = self.longest_wait_ms.max(clock - since);
                    let p = self.pallets.get_mut(&id).expect("a pallet of the plant");
                    p.waiting_since = None;
                }
                _ => {}
            }
        }
    }
}

//! The line at the stations, as a pure machine: which waiting part has the turn to look
//! for a station place, per service: the highest priority first, then the oldest
//! ("ahead" below). No I/O and no clock: the times come with the events, the task
//! ([`super`]) performs the actions.
//!
//! | state of the service's line | event | actions, next state |
//! |---|---|---|
//! | idle, nobody ahead waits (parts ahead that are away do not count) | `Wait` of a part new to the line | `Turn` to it (a sweep that began with it) |
//! | idle | `Wait` (blocking) of a part that missed a room | `Turn` to it (a sweep that began with it) |
//! | sweeping, past its place | `Wait` (blocking) of a part that missed a room | swept again from the first once this sweep ends |
//! | anything else | `Wait { now_only }` | `NotNow` to it; it keeps its place |
//! | anything else | `Wait` (blocking) | it waits for a sweep to reach it |
//! | any | `Room` | every part in line not waiting for its turn (away, or looking) missed it |
//! | idle, parts wait | `Room` | `Turn` to the first waiting: a sweep begins |
//! | sweeping, past the newcomer's place | `Wait` of a part new to the line, of a higher priority | swept again from the first once this sweep ends |
//! | sweeping | `Room` | swept again from the first once this sweep ends |
//! | the part has the turn | `Tried` / `Left` | `Turn` to the next waiting part behind it, or the sweep ends (and begins again if a room came meanwhile) |
//!
//! A freed place reaches the rush orders' parts first, and among parts of one priority
//! the part that has waited longest for a station of its service before any younger
//! one; a part that has just finished a step at a station's port and finds parts ahead
//! of it waiting goes home rather than take the place they wait for
//! (docs/material-flow.md, "Orders arrange their moves").
//!
//! A room is news only to the parts waiting when it comes. A part in line that was not
//! waiting (riding home, or looking already, or between a look and its next wait)
//! *missed* it, and looks as soon as it waits again if no sweep is under way: the parts
//! that waited have looked since. Without that, a part that reached its home just after
//! the place it went home for freed waited for the next room anywhere in the cell, or
//! the fallback's sweep (seconds of wall time, a minute of plant time at 20x).

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, HashMap};

use schemas::HolonId;
use tokio::time::Instant;

/// A part's place in its line: its order's priority (the highest first), since when
/// it waits, and its order (so two parts that joined at the same instant are still
/// ordered).
type Place = (Reverse<i32>, Instant, HolonId);

/// What happens to the lines.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Event {
    /// `order`'s part looks for a place at a station of `service`, waiting since
    /// `since` with its order's `priority` if it is new to the line (a part in line
    /// keeps its place). `now_only`:
    /// it takes a turn only if it can have one at once (a part at a port, which goes
    /// home rather than block the port).
    Wait {
        order: HolonId,
        service: String,
        since: Instant,
        priority: i32,
        now_only: bool,
    },
    /// A place freed up, a resource appeared or became ready, or the fallback's time
    /// came: every line with parts waiting is swept from its oldest.
    Room,
    /// The part that had the turn looked; `placed`: it has a place and leaves the line.
    Tried { order: HolonId, placed: bool },
    /// The order no longer waits for a station (its part is at one, it ended, or its
    /// task stopped).
    Left { order: HolonId },
}

/// What the task does.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action {
    /// It is `order`'s turn to look for a place.
    Turn(HolonId),
    /// `order` asked for a turn at once and has none: older parts wait.
    NotNow(HolonId),
}

/// One service's line.
#[derive(Debug, Default)]
struct Line {
    /// The parts in line, oldest first; true while the part waits for its turn (false
    /// while it has the turn, or does something else, such as going home).
    waiting: BTreeMap<Place, bool>,
    /// The part that has the turn now.
    holder: Option<Place>,
    /// The sweep under way: the last part it gave the turn to.
    sweep: Option<Place>,
    /// A room came during the sweep: sweep again from the oldest when it ends.
    again: bool,
    /// The parts in line that were not waiting for their turn when a room came (away,
    /// or looking): each looks as soon as it waits again, unless a sweep reaches it.
    missed: BTreeSet<Place>,
}

/// Every service's line on a node.
#[derive(Debug, Default)]
pub struct Lines {
    /// The lines, by service type.
    lines: BTreeMap<String, Line>,
    /// Where each order stands: its service and its place.
    of: HashMap<HolonId, (String, Place)>,
}

impl Lines {
    /// Whether any part waits for its turn (the fallback's sweeps are needed).
    pub fn any_waiting(&self) -> bool {
        self.lines.values().any(|l| l.waiting.values().any(|w| *w))
    }

    /// How many parts stand in line, all services together.
    pub fn len(&self) -> usize {
        self.of.len()
    }

    /// Whether nobody stands in line.
    pub fn is_empty(&self) -> bool {
        self.of.is_empty()
    }

    /// Whether `order`'s part stands in the line for a station of `service`.
    pub fn in_line_for(&self, order: &HolonId, service: &str) -> bool {
        self.of.get(order).is_some_and(|(s, _)| s == service)
    }

    /// How many parts other than `order`'s stand in line for a station of `service`.
    pub fn waiting_for(&self, service: &str, order: &HolonId) -> usize {
        self.lines.get(service).map_or(0, |line| {
            line.waiting.keys().filter(|(_, _, o)| o != order).count()
        })
    }

    pub fn handle(&mut self, event: Event) -> Vec<Action> {
        match event {
            Event::Wait {
                order,
                service,
                since,
                priority,
                now_only,
            } => self.wait(order, service, (Reverse(priority), since), now_only),
            Event::Room => self.room(),
            Event::Tried { order, placed } => self.tried(&order, placed),
            Event::Left { order } => self.leave(&order),
        }
    }

    fn wait(
        &mut self,
        order: HolonId,
        service: String,
        (priority, since): (Reverse<i32>, Instant),
        now_only: bool,
    ) -> Vec<Action> {
        let mut actions = Vec::new();
        // A part that now looks for another service leaves its former line.
        if self.of.get(&order).is_some_and(|(s, _)| *s != service) {
            actions.extend(self.leave(&order));
        }
        let new = !self.of.contains_key(&order);
        let place = match self.of.get(&order) {
            Some((_, place)) => place.clone(),
            None => {
                let place = (priority, since, order.clone());
                self.of
                    .insert(order.clone(), (service.clone(), place.clone()));
                place
            }
        };
        let line = self.lines.entry(service).or_default();
        if line.holder.as_ref() == Some(&place) {
            // It has the turn already (asked again after a wake of its own).
            actions.push(Action::Turn(order));
            return actions;
        }
        let idle = line.holder.is_none() && line.sweep.is_none();
        // Parts ahead that are away (riding home, looking elsewhere) do not hold a
        // newcomer back: each looks when it waits again.
        let oldest = !line.waiting.range(..place.clone()).any(|(_, waits)| *waits);
        let missed = line.missed.contains(&place);
        line.waiting.insert(place.clone(), !now_only);
        let passed = line.sweep.as_ref().is_some_and(|at| place < *at);
        if idle && ((new && oldest) || (missed && (oldest || !now_only))) {
            actions.push(line.give(place));
            return actions;
        }
        if now_only {
            // It keeps its place (and what it missed) and goes home.
            actions.push(Action::NotNow(order));
            return actions;
        }
        // A newcomer of a higher priority than the part a sweep under way has reached,
        // or a part that missed a room the sweep has passed it by, has the line swept
        // again from its head once this sweep ends.
        if passed && (new || missed) {
            line.again = true;
        }
        line.missed.remove(&place);
        // Else it waits: a sweep under way reaches it if it has not passed it yet (a
        // newcomer is the youngest of its priority); a part it passed (it looked and
        // found no place) waits for the next room, which is news it could use.
        actions
    }

    fn room(&mut self) -> Vec<Action> {
        let mut actions = Vec::new();
        for line in self.lines.values_mut() {
            line.note_missed();
            if line.holder.is_some() || line.sweep.is_some() {
                line.again = true;
            } else if let Some(next) = line.next_after(None) {
                actions.push(line.give(next));
            }
        }
        actions
    }

    fn tried(&mut self, order: &HolonId, placed: bool) -> Vec<Action> {
        if placed {
            return self.leave(order);
        }
        let Some((service, place)) = self.of.get(order).cloned() else {
            return Vec::new();
        };
        let line = self
            .lines
            .get_mut(&service)
            .expect("an order's line exists");
        if line.holder.as_ref() != Some(&place) {
            return Vec::new();
        }
        line.holder = None;
        line.pass().into_iter().collect()
    }

    fn leave(&mut self, order: &HolonId) -> Vec<Action> {
        let Some((service, place)) = self.of.remove(order) else {
            return Vec::new();
        };
        let line = self
            .lines
            .get_mut(&service)
            .expect("an order's line exists");
        line.waiting.remove(&place);
        line.missed.remove(&place);
        let mut actions = Vec::new();
        if line.holder.as_ref() == Some(&place) {
            line.holder = None;
            actions.extend(line.pass());
        }
        if line.waiting.is_empty() && line.holder.is_none() {
            self.lines.remove(&service);
        }
        actions
    }
}

impl Line {
    /// The first part waiting for its turn after `after` (from the oldest with `None`).
    fn next_after(&self, after: Option<&Place>) -> Option<Place> {
        self.waiting
            .iter()
            .filter(|(place, waits)| **waits && after.is_none_or(|after| *place > after))
            .map(|(place, _)| place.clone())
            .next()
    }

    /// Every part in line that does not wait for its turn now (away, or looking: the
    /// holder) misses the room that has just come.
    fn note_missed(&mut self) {
        let not_waiting: Vec<Place> = self
            .waiting
            .iter()
            .filter(|(_, waits)| !**waits)
            .map(|(place, _)| place.clone())
            .collect();
        self.missed.extend(not_waiting);
    }

    /// Gives the turn to `place`'s part: it looks now, so it has missed nothing.
    fn give(&mut self, place: Place) -> Action {
        self.missed.remove(&place);
        self.waiting.insert(place.clone(), false);
        self.holder = Some(place.clone());
        self.sweep = Some(place.clone());
        Action::Turn(place.2)
    }

    /// The turn goes on to the next younger part waiting; at the end of the line the
    /// sweep ends, and begins again from the oldest if a room came meanwhile.
    fn pass(&mut self) -> Option<Action> {
        if let Some(next) = self.next_after(self.sweep.as_ref()) {
            return Some(self.give(next));
        }
        self.sweep = None;
        if std::mem::take(&mut self.again) {
            if let Some(next) = self.next_after(None) {
                return Some(self.give(next));
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn order(n: u32) -> HolonId {
        HolonId::order(&format!("orders1-{n}")).unwrap()
    }

    fn wait(lines: &mut Lines, n: u32, at: Instant, now_only: bool) -> Vec<Action> {
        wait_with(lines, n, at, 0, now_only)
    }

    fn wait_with(
        lines: &mut Lines,
        n: u32,
        at: Instant,
        priority: i32,
        now_only: bool,
    ) -> Vec<Action> {
        lines.handle(Event::Wait {
            order: order(n),
            service: "inspect".into(),
            since: at,
            priority,
            now_only,
        })
    }

    fn tried(lines: &mut Lines, n: u32, placed: bool) -> Vec<Action> {
        lines.handle(Event::Tried {
            order: order(n),
            placed,
        })
    }

    /// Part `n` alone in line looks, finds no place, and waits again.
    fn looked_and_waits(lines: &mut Lines, n: u32, at: Instant) {
        assert_eq!(wait(lines, n, at, false), vec![Action::Turn(order(n))]);
        assert_eq!(tried(lines, n, false), vec![]);
        assert_eq!(wait(lines, n, at, false), vec![]);
    }

    #[test]
    fn a_part_alone_has_its_turn_at_once_and_again_only_after_a_room() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        assert_eq!(wait(&mut lines, 1, t0, false), vec![Action::Turn(order(1))]);
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        // Waiting again: no place has freed since it looked.
        assert_eq!(wait(&mut lines, 1, t0, false), vec![]);
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(1))]);
        assert_eq!(tried(&mut lines, 1, true), vec![]);
        assert!(lines.is_empty());
    }

    #[test]
    fn a_rush_part_has_its_turn_before_older_parts_of_lower_priority() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        looked_and_waits(&mut lines, 1, t0);
        wait(&mut lines, 2, t0 + Duration::from_secs(1), false);
        // A rush order's part comes later: ahead of both, it looks at once, then the
        // turn goes on to the others.
        let t1 = t0 + Duration::from_secs(5);
        assert_eq!(
            wait_with(&mut lines, 3, t1, 10, false),
            vec![Action::Turn(order(3))]
        );
        assert_eq!(tried(&mut lines, 3, false), vec![Action::Turn(order(1))]);
        // One that comes while the sweep is past its place has the line swept again
        // from its head when the sweep ends, before the parts of lower priority.
        assert_eq!(wait_with(&mut lines, 4, t1, 10, false), vec![]);
        assert_eq!(tried(&mut lines, 1, false), vec![Action::Turn(order(2))]);
        assert_eq!(tried(&mut lines, 2, false), vec![Action::Turn(order(4))]);
        // A place frees with all four waiting: the rush parts look first.
        assert_eq!(tried(&mut lines, 4, false), vec![]);
        for n in 1..=2 {
            wait(&mut lines, n, t0, false);
        }
        for n in 3..=4 {
            wait_with(&mut lines, n, t1, 10, false);
        }
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(3))]);
        assert_eq!(tried(&mut lines, 3, false), vec![Action::Turn(order(4))]);
        assert_eq!(tried(&mut lines, 4, false), vec![Action::Turn(order(1))]);
    }

    #[test]
    fn the_parts_waiting_for_a_service_are_counted_without_the_asker() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        assert_eq!(lines.waiting_for("inspect", &order(1)), 0);
        looked_and_waits(&mut lines, 1, t0);
        wait(&mut lines, 2, t0 + Duration::from_secs(1), false);
        assert_eq!(lines.waiting_for("inspect", &order(1)), 1);
        assert_eq!(lines.waiting_for("inspect", &order(3)), 2);
        assert_eq!(lines.waiting_for("drill", &order(3)), 0);
        lines.handle(Event::Left { order: order(2) });
        assert_eq!(lines.waiting_for("inspect", &order(3)), 1);
    }

    #[test]
    fn a_room_goes_to_the_oldest_part_first_however_often_the_young_look() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        // The oldest looked and found no place.
        assert_eq!(
            wait(&mut lines, 15, t0, false),
            vec![Action::Turn(order(15))]
        );
        assert_eq!(tried(&mut lines, 15, false), vec![]);
        wait(&mut lines, 15, t0, false);
        // A younger part off a station's port asks for a turn at once: none.
        let t1 = t0 + Duration::from_secs(3);
        assert_eq!(
            wait(&mut lines, 16, t1, true),
            vec![Action::NotNow(order(16))]
        );
        // It went home and waits there.
        assert_eq!(wait(&mut lines, 16, t1, false), vec![]);
        // A place frees: the oldest looks first, then the younger.
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(15))]);
        assert_eq!(tried(&mut lines, 15, false), vec![Action::Turn(order(16))]);
        assert_eq!(tried(&mut lines, 16, true), vec![]);
        assert_eq!(lines.len(), 1);
    }

    #[test]
    fn a_room_during_a_sweep_sweeps_again_from_the_oldest() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        looked_and_waits(&mut lines, 1, t0);
        wait(&mut lines, 2, t0 + Duration::from_secs(1), false);
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(1))]);
        assert_eq!(lines.handle(Event::Room), vec![]);
        // 1 looked and waits again before the sweep ends.
        assert_eq!(tried(&mut lines, 1, false), vec![Action::Turn(order(2))]);
        wait(&mut lines, 1, t0, false);
        assert_eq!(tried(&mut lines, 2, false), vec![Action::Turn(order(1))]);
    }

    #[test]
    fn a_holder_that_leaves_passes_the_turn_on() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        looked_and_waits(&mut lines, 1, t0);
        wait(&mut lines, 2, t0 + Duration::from_secs(1), false);
        lines.handle(Event::Room);
        assert_eq!(
            lines.handle(Event::Left { order: order(1) }),
            vec![Action::Turn(order(2))]
        );
        assert_eq!(lines.handle(Event::Left { order: order(2) }), vec![]);
        assert!(lines.is_empty() && !lines.any_waiting());
    }

    #[test]
    fn a_part_that_looks_for_another_service_leaves_its_line() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        wait(&mut lines, 1, t0, false);
        let actions = lines.handle(Event::Wait {
            order: order(1),
            service: "pick_n_place".into(),
            since: t0 + Duration::from_secs(5),
            priority: 0,
            now_only: false,
        });
        assert_eq!(actions, vec![Action::Turn(order(1))]);
        assert_eq!(lines.len(), 1);
    }

    #[test]
    fn a_newcomer_waits_behind_older_parts_even_when_the_line_is_idle() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        looked_and_waits(&mut lines, 1, t0);
        assert_eq!(
            wait(&mut lines, 2, t0 + Duration::from_secs(1), false),
            vec![]
        );
        assert!(lines.any_waiting());
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(1))]);
    }

    #[test]
    fn a_part_back_at_its_home_looks_at_once_for_a_room_that_came_while_it_rode() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        // Worked at a port, it looks, finds no place and rides home.
        assert_eq!(wait(&mut lines, 1, t0, true), vec![Action::Turn(order(1))]);
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        // The place it wanted frees while it rides: nobody waits for a turn.
        assert_eq!(lines.handle(Event::Room), vec![]);
        // Home, it waits: the room is news to it.
        assert_eq!(wait(&mut lines, 1, t0, false), vec![Action::Turn(order(1))]);
        // Looked at, the news is spent: it waits for the next room.
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        assert_eq!(wait(&mut lines, 1, t0, false), vec![]);
    }

    #[test]
    fn a_room_that_comes_while_a_part_looks_is_looked_at_again() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        assert_eq!(wait(&mut lines, 1, t0, false), vec![Action::Turn(order(1))]);
        // A place frees while it looks (it may have asked that station before).
        assert_eq!(lines.handle(Event::Room), vec![]);
        // Its look ends before it waits again: the sweep again finds nobody waiting.
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        assert_eq!(wait(&mut lines, 1, t0, false), vec![Action::Turn(order(1))]);
    }

    #[test]
    fn a_part_that_missed_a_room_a_sweep_has_passed_has_the_line_swept_again() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        // 1, the oldest, looked at a port and rides home; 2 and 3 wait at home.
        assert_eq!(wait(&mut lines, 1, t0, true), vec![Action::Turn(order(1))]);
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        looked_and_waits(&mut lines, 2, t0 + Duration::from_secs(1));
        assert_eq!(
            wait(&mut lines, 3, t0 + Duration::from_secs(2), false),
            vec![]
        );
        // A room: the sweep gives 2 and then 3 the turn; 1, away, missed it.
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(2))]);
        assert_eq!(tried(&mut lines, 2, false), vec![Action::Turn(order(3))]);
        // 1 is home while 3 looks: the sweep is past it, and 1 does not jump it.
        assert_eq!(wait(&mut lines, 1, t0, false), vec![]);
        // When 3's look ends, the line is swept again from 1.
        assert_eq!(tried(&mut lines, 3, false), vec![Action::Turn(order(1))]);
    }

    #[test]
    fn a_part_off_a_port_that_missed_a_room_still_waits_behind_older_parts() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        looked_and_waits(&mut lines, 1, t0);
        // 2 looked once at a port and went on with its work there.
        let t1 = t0 + Duration::from_secs(1);
        assert_eq!(
            wait(&mut lines, 2, t1, true),
            vec![Action::NotNow(order(2))]
        );
        // A room: 1 looks and finds nothing; 2 missed it.
        assert_eq!(lines.handle(Event::Room), vec![Action::Turn(order(1))]);
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        wait(&mut lines, 1, t0, false);
        // 2, worked, asks at once: 1 waits ahead of it, so it goes home...
        assert_eq!(
            wait(&mut lines, 2, t1, true),
            vec![Action::NotNow(order(2))]
        );
        // ...and once home it looks, since it missed the room 1 has looked at.
        assert_eq!(wait(&mut lines, 2, t1, false), vec![Action::Turn(order(2))]);
    }

    #[test]
    fn a_newcomer_looks_at_once_when_the_parts_ahead_are_away() {
        let t0 = Instant::now();
        let mut lines = Lines::default();
        // 1 looked at a port, found no place and rides home.
        assert_eq!(wait(&mut lines, 1, t0, true), vec![Action::Turn(order(1))]);
        assert_eq!(tried(&mut lines, 1, false), vec![]);
        // 2, just worked at a port, asks at once: nobody ahead waits.
        let t1 = t0 + Duration::from_secs(1);
        assert_eq!(wait(&mut lines, 2, t1, true), vec![Action::Turn(order(2))]);
        assert_eq!(tried(&mut lines, 2, true), vec![]);
        // 1, home, waits for the next room.
        assert_eq!(wait(&mut lines, 1, t0, false), vec![]);
    }
}

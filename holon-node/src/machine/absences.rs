//! Who of the cell is present, and since when each absent holon has been absent: the
//! pure part of the booking lifetime (see [`crate::component::requesters`]). A booking
//! lasts while its requester is in the cell, or absent no longer than the grace.

use std::collections::{HashMap, HashSet};
use std::time::Duration;

use schemas::HolonId;
use tokio::time::Instant;

/// A moment, both for measuring (monotonic) and for showing (Unix milliseconds).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Moment {
    pub at: Instant,
    pub unix_ms: u64,
}

impl Moment {
    pub fn now() -> Moment {
        Moment {
            at: Instant::now(),
            unix_ms: schemas::unix_ms(),
        }
    }
}

/// Who is present, and since when each absent holon has been absent.
#[derive(Debug, Clone)]
pub struct Absences {
    /// Holons whose liveliness token is visible.
    present: HashSet<HolonId>,
    /// Holons seen leaving, and when.
    left: HashMap<HolonId, Moment>,
    /// When watching began: a holon never seen has been absent at least since then.
    since: Moment,
}

impl Absences {
    pub fn new(since: Moment) -> Absences {
        Absences {
            present: HashSet::new(),
            left: HashMap::new(),
            since,
        }
    }

    /// `holon`'s token appeared; true if that is news.
    pub fn appeared(&mut self, holon: HolonId) -> bool {
        self.left.remove(&holon);
        self.present.insert(holon)
    }

    /// `holon`'s token vanished; true if that is news.
    pub fn vanished(&mut self, holon: HolonId, now: Moment) -> bool {
        let news = self.present.remove(&holon);
        self.left.entry(holon).or_insert(now);
        news
    }

    /// Since when `holon` is absent; `None` while it is present.
    pub fn absent_since(&self, holon: &HolonId) -> Option<Moment> {
        if self.present.contains(holon) {
            return None;
        }
        Some(self.left.get(holon).copied().unwrap_or(self.since))
    }

    /// The requesters among `booked` absent for longer than `grace` at `now`.
    pub fn expired<'a>(
        &self,
        booked: impl IntoIterator<Item = &'a HolonId>,
        now: Instant,
        grace: Duration,
    ) -> Vec<HolonId> {
        let mut expired: Vec<HolonId> = booked
            .into_iter()
            .filter(|r| {
                self.absent_since(r)
                    .is_some_and(|since| now.saturating_duration_since(since.at) > grace)
            })
            .cloned()
            .collect();
        expired.sort();
        expired.dedup();
        expired
    }

    /// Forgets holons that left long ago and hold nothing here (keeps the map small).
    pub fn forget_except(&mut self, booked: &HashSet<HolonId>) {
        self.left.retain(|holon, _| booked.contains(holon));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn order(name: &str) -> HolonId {
        HolonId::order(name).unwrap()
    }

    #[tokio::test(start_paused = true)]
    async fn a_requester_expires_after_the_grace_unless_it_comes_back() {
        let grace = Duration::from_secs(10);
        let mut a = Absences::new(Moment::now());
        assert!(a.appeared(order("o-1")));
        assert!(!a.appeared(order("o-1")), "a repeat is no news");
        let booked = [order("o-1"), order("o-2")];
        // o-2 was never seen: absent since watching began.
        tokio::time::advance(Duration::from_secs(11)).await;
        assert_eq!(
            a.expired(&booked, Instant::now(), grace),
            vec![order("o-2")]
        );
        assert!(a.vanished(order("o-1"), Moment::now()));
        assert!(a.absent_since(&order("o-1")).is_some());
        tokio::time::advance(Duration::from_secs(5)).await;
        assert_eq!(
            a.expired(&booked, Instant::now(), grace),
            vec![order("o-2")]
        );
        // Back within the grace: kept.
        a.appeared(order("o-1"));
        tokio::time::advance(Duration::from_secs(20)).await;
        assert_eq!(a.absent_since(&order("o-1")), None);
        assert_eq!(
            a.expired(&booked, Instant::now(), grace),
            vec![order("o-2")]
        );
        // Gone for good.
        a.vanished(order("o-1"), Moment::now());
        tokio::time::advance(Duration::from_secs(11)).await;
        assert_eq!(
            a.expired(&booked, Instant::now(), grace),
            vec![order("o-1"), order("o-2")]
        );
    }
}

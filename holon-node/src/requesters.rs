//! Booking lifetime: a booking lasts while its requester is in the cell.
//!
//! Every holon that books (an order) holds a liveliness token at
//! `holarchy/<cell>/alive/<kind>/<name>` while it wants its bookings. The requesters
//! component watches those tokens; when the requester of a booking has been absent longer
//! than `agenda.requester_grace_ms` (its order ended, was faked, or its order-node is gone
//! for good), the agenda manager releases its bookings, so they no longer block the
//! resource or lengthen its offers. The grace covers an order-node restart and a short
//! network cut; the snapshot shows since when a booked requester is absent.
//!
//! [`Absences`] is the pure part (what is known of presence, and which requesters have
//! outstayed the grace); [`run`] is the component that feeds it liveliness samples and
//! a tick, and sends the agenda manager a `RequesterGone` per expired requester.

use std::collections::{HashMap, HashSet};
use std::sync::Arc;
use std::time::Duration;

use holon::ChildError;
use schemas::HolonId;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::agenda::AgendaEvent;
use crate::node::Node;

/// How often booked requesters are checked against the grace.
const CHECK_EVERY: Duration = Duration::from_secs(1);

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

/// The requesters component: watches every liveliness token of the cell and releases
/// the bookings of requesters absent longer than the grace.
pub async fn run(node: Arc<Node>, token: CancellationToken) -> Result<(), ChildError> {
    let holon = node.config.holon.clone();
    let keys = node.config.keys.clone();
    let grace = node.config.requester_grace;
    // A restarted component starts a fresh watch: absences count from now (the grace
    // is restarted, never shortened).
    node.set_absences(Absences::new(Moment::now()));
    let subscriber = node
        .session
        .liveliness()
        .declare_subscriber(keys.alive_all())
        .history(true)
        .await
        .map_err(|e| format!("cannot watch the cell's liveliness tokens: {e}"))?;
    let mut tick = tokio::time::interval(CHECK_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = token.cancelled() => return Ok(()),
            sample = subscriber.recv_async() => {
                let sample = sample.map_err(|e| format!("liveliness subscriber closed: {e}"))?;
                let Some(other) = keys.holon_from_alive(sample.key_expr().as_str()) else {
                    continue;
                };
                let booked = node.booked_requesters().contains(&other);
                let news = match sample.kind() {
                    zenoh::sample::SampleKind::Put => node.update_absences(|a| a.appeared(other.clone())),
                    zenoh::sample::SampleKind::Delete => node.update_absences(|a| a.vanished(other.clone(), Moment::now())),
                };
                if news && booked {
                    match sample.kind() {
                        zenoh::sample::SampleKind::Put => info!(%holon, requester = %other, "requester of a booking is back"),
                        zenoh::sample::SampleKind::Delete => warn!(%holon, requester = %other, grace = ?grace, "requester of a booking left the cell; its bookings end unless it is back within the grace"),
                    }
                    node.state_changed().await;
                }
            }
            _ = tick.tick() => {
                let booked = node.booked_requesters();
                let expired = node.update_absences(|a| {
                    a.forget_except(&booked);
                    a.expired(&booked, Instant::now(), grace)
                });
                for requester in expired {
                    warn!(%holon, %requester, grace = ?grace, "requester absent longer than the grace: its bookings are released");
                    crate::node::send_agenda(&node, AgendaEvent::RequesterGone { requester }).await?;
                }
            }
        }
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

//! Ranking a proposal round's offers, with the node's bookings in flight counted: the
//! rule that keeps many orders of one node from all booking the same resource.

use tokio::sync::watch;

/// The bookings this node's orders asked and have no answer to yet, per resource.
///
/// Many orders of one node ask for proposals at once (a batch of work orders, a
/// resource that came back): every round then hears about the same waits, and without
/// care they would all book the same resource while others stay idle. So a round ranks
/// its proposals by the queue as it is when the round ends: the resource's latest
/// published queue (fresher than its proposal), plus the bookings in flight to it, each
/// at the proposal's `duration_ms`. Ranking counts the round's own choice as in flight at
/// in the same change of the counts as it reads them ([`BookingsInFlight::rank`]), so
/// rounds that end together see each other's choices; the booking's answer ends it
/// (its [`InFlight`] is dropped). The counts are changed in place by the order tasks,
/// one change at a time.
pub struct BookingsInFlight(watch::Sender<InFlightCounts>);

impl Default for BookingsInFlight {
    fn default() -> BookingsInFlight {
        BookingsInFlight(watch::Sender::new(InFlightCounts::new()))
    }
}

type InFlightCounts = std::collections::HashMap<schemas::HolonId, u64>;

/// A booking a ranking counted in flight: it ends when dropped (the booking was
/// answered, or the order gave up before asking it).
pub struct InFlight {
    /// The counts it is counted in.
    counts: watch::Sender<InFlightCounts>,
    /// The resource it is asked of.
    pub resource: schemas::HolonId,
}

impl Drop for InFlight {
    fn drop(&mut self) {
        self.counts.send_modify(|counts| {
            if let Some(n) = counts.get_mut(&self.resource) {
                *n = n.saturating_sub(1);
            }
        });
    }
}

/// One proposal as a round heard it.
#[derive(Debug, Clone)]
pub struct Offer {
    /// The resource failed this step before: tried last.
    pub avoided: bool,
    /// How long the step would wait there, as the resource proposed.
    pub expected_wait_ms: u64,
    /// Where the booking would go in its queue, as proposed.
    pub queue_position: u64,
    /// The service's nominal duration on that resource.
    pub duration_ms: u64,
    /// The resource that proposed.
    pub provider: schemas::HolonId,
}

impl BookingsInFlight {
    /// The round's offers, best first: not avoided; then the resource a staff holon
    /// advised (`advised`), if it proposed; then the shortest expected wait, then
    /// queue, as they are now (`published`: a resource's latest published queue, if
    /// any); ties at random. The best is counted in flight (its order books it next)
    /// until the returned [`InFlight`] is dropped.
    pub fn rank(
        &self,
        offers: Vec<Offer>,
        published: impl Fn(&schemas::HolonId) -> Option<u64>,
        advised: Option<&schemas::HolonId>,
    ) -> (Vec<schemas::HolonId>, Option<InFlight>) {
        let mut ranked: Vec<(bool, bool, u64, u64, u64, schemas::HolonId)> = Vec::new();
        // Read and counted in one change: a round that ends at the same time sees this
        // choice, or this round sees its.
        self.0.send_modify(|in_flight| {
            ranked = offers
                .into_iter()
                .map(|o| {
                    let queue = published(&o.provider)
                        .unwrap_or(o.queue_position)
                        .saturating_add(in_flight.get(&o.provider).copied().unwrap_or(0));
                    // The proposal's wait, moved by what changed since: its jobs of other
                    // service types keep their own durations.
                    let wait = if queue >= o.queue_position {
                        o.expected_wait_ms.saturating_add(
                            (queue - o.queue_position).saturating_mul(o.duration_ms),
                        )
                    } else {
                        o.expected_wait_ms.saturating_sub(
                            (o.queue_position - queue).saturating_mul(o.duration_ms),
                        )
                    };
                    let not_advised = advised != Some(&o.provider);
                    (o.avoided, not_advised, wait, queue, tie_break(), o.provider)
                })
                .collect();
            ranked.sort();
            if let Some((.., best)) = ranked.first() {
                *in_flight.entry(best.clone()).or_default() += 1;
            }
        });
        let counted = ranked.first().map(|(.., best)| InFlight {
            counts: self.0.clone(),
            resource: best.clone(),
        });
        (ranked.into_iter().map(|(.., p)| p).collect(), counted)
    }
}

/// A random number, to order equal proposals.
fn tie_break() -> u64 {
    use std::hash::BuildHasher;
    std::collections::hash_map::RandomState::new().hash_one(std::time::Instant::now())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn offer(name: &str, wait: u64, queue: u64) -> Offer {
        Offer {
            avoided: false,
            expected_wait_ms: wait,
            queue_position: queue,
            duration_ms: 1000,
            provider: schemas::HolonId::resource(name).unwrap(),
        }
    }

    #[test]
    fn rounds_that_end_together_spread_their_bookings() {
        let in_flight = BookingsInFlight::default();
        // Eight rounds heard the same waits, none answered yet: each ranks after the
        // others chose.
        let mut held = Vec::new();
        let mut chosen: Vec<String> = (0..8)
            .map(|_| {
                let offers = vec![
                    offer("robot1", 0, 0),
                    offer("robot2", 0, 0),
                    offer("robot3", 1000, 1),
                ];
                let (ranked, counted) = in_flight.rank(offers, |_| None, None);
                held.push(counted);
                ranked[0].name().to_string()
            })
            .collect();
        chosen.sort();
        let count = |name: &str| chosen.iter().filter(|c| *c == name).count();
        assert_eq!(
            (count("robot1"), count("robot2"), count("robot3")),
            (3, 3, 2),
            "{chosen:?}"
        );
    }

    #[test]
    fn a_fresher_published_queue_and_answered_bookings_count() {
        let in_flight = BookingsInFlight::default();
        let robot1 = schemas::HolonId::resource("robot1").unwrap();
        // robot1 proposed an empty agenda, but has since published 3 jobs ahead.
        let published = |r: &schemas::HolonId| (r.name() == "robot1").then_some(3);
        let (ranked, counted) = in_flight.rank(
            vec![offer("robot1", 0, 0), offer("robot2", 2000, 2)],
            published,
            None,
        );
        assert_eq!(ranked[0].name(), "robot2");
        // In flight, robot2's booking counts; answered, it does not (its queue shows it).
        let both = || vec![offer("robot1", 1000, 1), offer("robot2", 1000, 1)];
        let (ranked, again) = in_flight.rank(both(), |_| None, None);
        assert_eq!(ranked[0], robot1);
        drop((counted, again));
        let (ranked, _counted) = in_flight.rank(
            both(),
            |r| if r == &robot1 { Some(2) } else { Some(1) },
            None,
        );
        assert_eq!(ranked[0].name(), "robot2");
    }

    #[test]
    fn a_resource_that_failed_the_step_is_ranked_last() {
        let in_flight = BookingsInFlight::default();
        let mut avoided = offer("robot1", 0, 0);
        avoided.avoided = true;
        let (ranked, _) = in_flight.rank(vec![avoided, offer("robot2", 5000, 5)], |_| None, None);
        assert_eq!(ranked[1].name(), "robot1");
    }

    #[test]
    fn the_advised_resource_goes_first_if_it_proposed_and_never_before_an_avoided_one() {
        let in_flight = BookingsInFlight::default();
        let slow = schemas::HolonId::resource("slow").unwrap();
        let offers = || vec![offer("fast", 0, 0), offer("slow", 3000, 3)];
        let (ranked, counted) = in_flight.rank(offers(), |_| None, Some(&slow));
        assert_eq!(ranked[0], slow);
        assert_eq!(
            counted.as_ref().map(|c| &c.resource),
            Some(&slow),
            "counted in flight"
        );
        let gone = schemas::HolonId::resource("gone").unwrap();
        let (ranked, _) = in_flight.rank(offers(), |_| None, Some(&gone));
        assert_eq!(
            ranked[0].name(),
            "fast",
            "advice for one that did not propose"
        );
        let mut avoided = offer("slow", 0, 0);
        avoided.avoided = true;
        let (ranked, _) =
            in_flight.rank(vec![avoided, offer("fast", 9000, 9)], |_| None, Some(&slow));
        assert_eq!(ranked[0].name(), "fast");
    }
}

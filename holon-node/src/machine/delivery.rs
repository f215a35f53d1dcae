//! The delivery of results, as a pure machine: each `done` / `failed` is sent to its
//! `reply_to` again and again, with a doubling pause, until the requester acknowledges
//! it.
//!
//! [`DeliveryMachine`] belongs to the agenda manager, the one owner of the undelivered
//! results (they are part of the agenda and journalled with it): it feeds the machine
//! every result the agenda hands out, the moment the resource serves, the ticks of its
//! timer and each attempt's end, and carries out the actions: an [`Attempt`] goes out as
//! a future the agenda manager owns ([`crate::component::agenda_manager::courier`]), an
//! [`Acknowledged`] becomes the agenda's `ResultAcknowledged`. No task waits on another
//! for a result or its acknowledgement.
//!
//! | state of a result | event | actions | next |
//! |---|---|---|---|
//! | (none) | result | `Attempt` when serving | in flight (serving) or due |
//! | any | result (a repeat) | | same |
//! | due, not serving | serving | `Attempt` | in flight |
//! | waiting its pause | tick past its time (serving) | `Attempt` | in flight |
//! | in flight | acknowledged | `Acknowledged` | (none) |
//! | in flight | unanswered or refused | `Retry` (the pause) | waiting its pause |
//! | in flight | lost (the owner restarted) | | due |
//!
//! Time comes in with each event (`now`): the machine reads no clock.
//!
//! [`Attempt`]: DeliveryAction::Attempt
//! [`Acknowledged`]: DeliveryAction::Acknowledged

use std::collections::BTreeMap;
use std::time::Duration;

use holon::Backoff;
use schemas::{MessageType, Service};
use tokio::time::Instant;

use crate::config::DeliverySettings;

/// How one attempt ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AttemptOutcome {
    /// The requester acknowledged the result.
    Acknowledged,
    /// Nobody acknowledged it within the attempt's timeout.
    Unanswered,
    /// The requester refused it, and why (malformed, not booked, ...).
    Refused(String),
}

/// What happens to the deliveries.
#[derive(Debug, Clone, PartialEq)]
pub enum DeliveryEvent {
    /// A result to deliver; a repeat of one pending changes nothing.
    Result(Service),
    /// The resource serves (a fenced one holds its controller): attempts may go out.
    Serving,
    /// The owner's timer: attempts whose pause is over go out.
    Tick,
    /// An attempt ended.
    AttemptEnded {
        /// The result's conversation.
        conversation_id: String,
        /// How it ended.
        outcome: AttemptOutcome,
    },
}

/// What the owner carries out.
#[derive(Debug, Clone, PartialEq)]
pub enum DeliveryAction {
    /// Send this result to its `reply_to` once, and report the end as
    /// [`DeliveryEvent::AttemptEnded`].
    Attempt {
        /// The `done` / `failed` message.
        message: Service,
        /// Which attempt of this result it is (1 for the first).
        attempt: u32,
    },
    /// The result was acknowledged and is no longer delivered: the agenda removes it.
    Acknowledged {
        /// The result's conversation.
        conversation_id: String,
        /// `done` or `failed`.
        message_type: MessageType,
        /// How many attempts it took.
        attempts: u32,
    },
    /// The attempt was not acknowledged: the result goes out again after `pause`.
    Retry {
        /// The result's conversation.
        conversation_id: String,
        /// The attempt that was not acknowledged.
        attempt: u32,
        /// Why, when the requester refused it.
        refused: Option<String>,
        /// The pause before the next attempt.
        pause: Duration,
    },
}

/// A result waiting for its acknowledgement.
#[derive(Debug)]
struct Delivery {
    /// The `done` / `failed` message.
    message: Service,
    /// When the next attempt may go out.
    next_attempt: Instant,
    /// The pauses between attempts.
    backoff: Backoff,
    /// Attempts made so far.
    attempts: u32,
    /// Whether an attempt is out and not yet ended.
    in_flight: bool,
}

/// Every result not yet acknowledged, by `conversation_id`.
#[derive(Debug)]
pub struct DeliveryMachine {
    /// The pauses between attempts.
    settings: DeliverySettings,
    /// The results waiting for their acknowledgement.
    pending: BTreeMap<String, Delivery>,
    /// Whether attempts may go out (the resource serves).
    serving: bool,
    /// Attempts after a result's first, since the process started (a requester away or
    /// slow to acknowledge); published in the state for the dashboard's metrics.
    retries: u64,
}

impl DeliveryMachine {
    /// No result yet, not serving; `retries` counted so far in this process (a
    /// restarted owner goes on counting).
    pub fn new(settings: DeliverySettings, retries: u64) -> DeliveryMachine {
        DeliveryMachine {
            settings,
            pending: BTreeMap::new(),
            serving: false,
            retries,
        }
    }

    /// One event at `now`: the actions to carry out.
    pub fn handle(&mut self, event: DeliveryEvent, now: Instant) -> Vec<DeliveryAction> {
        match event {
            DeliveryEvent::Result(message) => {
                let backoff = Backoff::new(self.settings.retry_initial, self.settings.retry_max);
                self.pending
                    .entry(message.conversation_id.clone())
                    .or_insert(Delivery {
                        message,
                        next_attempt: now,
                        backoff,
                        attempts: 0,
                        in_flight: false,
                    });
                self.due(now)
            }
            DeliveryEvent::Serving => {
                self.serving = true;
                self.due(now)
            }
            DeliveryEvent::Tick => self.due(now),
            DeliveryEvent::AttemptEnded {
                conversation_id,
                outcome,
            } => self.ended(conversation_id, outcome, now),
        }
    }

    /// Attempts after a result's first, since the process started.
    pub fn retries(&self) -> u64 {
        self.retries
    }

    /// When the owner's timer is to tick next: the earliest attempt waiting its pause
    /// (none while not serving, or while every result is in flight).
    pub fn next_due(&self) -> Option<Instant> {
        if !self.serving {
            return None;
        }
        self.pending
            .values()
            .filter(|d| !d.in_flight)
            .map(|d| d.next_attempt)
            .min()
    }

    /// How many results wait for their acknowledgement.
    pub fn len(&self) -> usize {
        self.pending.len()
    }

    /// Whether no result waits.
    pub fn is_empty(&self) -> bool {
        self.pending.is_empty()
    }

    /// An attempt for every result whose time has come, if serving.
    fn due(&mut self, now: Instant) -> Vec<DeliveryAction> {
        if !self.serving {
            return vec![];
        }
        let mut actions = Vec::new();
        for delivery in self.pending.values_mut() {
            if delivery.in_flight || delivery.next_attempt > now {
                continue;
            }
            delivery.in_flight = true;
            delivery.attempts += 1;
            if delivery.attempts > 1 {
                self.retries += 1;
            }
            actions.push(DeliveryAction::Attempt {
                message: delivery.message.clone(),
                attempt: delivery.attempts,
            });
        }
        actions
    }

    fn ended(
        &mut self,
        conversation_id: String,
        outcome: AttemptOutcome,
        now: Instant,
    ) -> Vec<DeliveryAction> {
        let Some(delivery) = self.pending.get_mut(&conversation_id) else {
            return vec![];
        };
        delivery.in_flight = false;
        let attempt = delivery.attempts;
        let refused = match outcome {
            AttemptOutcome::Acknowledged => {
                let delivery = self
                    .pending
                    .remove(&conversation_id)
                    .expect("the delivery is pending");
                return vec![DeliveryAction::Acknowledged {
                    conversation_id,
                    message_type: delivery.message.message_type,
                    attempts: attempt,
                }];
            }
            AttemptOutcome::Unanswered => None,
            AttemptOutcome::Refused(why) => Some(why),
        };
        let pause = delivery.backoff.next_pause();
        delivery.next_attempt = now + pause;
        vec![DeliveryAction::Retry {
            conversation_id,
            attempt,
            refused,
            pause,
        }]
    }
}

/// Whether the `attempt`th try of the same delivery is logged above debug: the first,
/// then every tenth (a requester that stays away does not fill the log).
pub fn repeat_worth_logging(attempt: u32) -> bool {
    attempt == 1 || attempt.is_multiple_of(10)
}

#[cfg(test)]
mod tests {
    use schemas::HolonId;

    use super::*;

    fn settings() -> DeliverySettings {
        DeliverySettings {
            retry_initial: Duration::from_millis(20),
            retry_max: Duration::from_millis(80),
            attempt_timeout: Duration::from_millis(500),
        }
    }

    fn done(conversation: &str) -> Service {
        Service::request(
            MessageType::Done,
            "pick_n_place",
            conversation,
            HolonId::order("o-1").unwrap(),
        )
        .with_reply_to("holarchy/test/inbox/o-1")
    }

    fn serving() -> (DeliveryMachine, Instant) {
        let mut deliveries = DeliveryMachine::new(settings(), 0);
        let now = Instant::now();
        assert_eq!(deliveries.handle(DeliveryEvent::Serving, now), vec![]);
        (deliveries, now)
    }

    fn ended(conversation: &str, outcome: AttemptOutcome) -> DeliveryEvent {
        DeliveryEvent::AttemptEnded {
            conversation_id: conversation.into(),
            outcome,
        }
    }

    fn attempts(actions: &[DeliveryAction]) -> Vec<(String, u32)> {
        actions
            .iter()
            .filter_map(|a| match a {
                DeliveryAction::Attempt { message, attempt } => {
                    Some((message.conversation_id.clone(), *attempt))
                }
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_result_goes_out_at_once_and_a_repeat_changes_nothing() {
        let (mut d, now) = serving();
        let first = d.handle(DeliveryEvent::Result(done("c1")), now);
        assert_eq!(attempts(&first), vec![("c1".into(), 1)]);
        assert_eq!(d.handle(DeliveryEvent::Result(done("c1")), now), vec![]);
        assert_eq!(d.len(), 1);
        assert_eq!(d.next_due(), None, "in flight: nothing waits its pause");
    }

    #[test]
    fn an_acknowledged_result_is_removed_and_reported() {
        let (mut d, now) = serving();
        d.handle(DeliveryEvent::Result(done("c1")), now);
        let actions = d.handle(ended("c1", AttemptOutcome::Acknowledged), now);
        assert_eq!(
            actions,
            vec![DeliveryAction::Acknowledged {
                conversation_id: "c1".into(),
                message_type: MessageType::Done,
                attempts: 1
            }]
        );
        assert!(d.is_empty());
        assert_eq!(d.next_due(), None);
        assert_eq!(d.retries(), 0);
        // A late end of the same conversation changes nothing.
        assert_eq!(
            d.handle(ended("c1", AttemptOutcome::Unanswered), now),
            vec![]
        );
    }

    #[test]
    fn an_unacknowledged_result_goes_out_again_after_a_doubling_pause() {
        let (mut d, now) = serving();
        d.handle(DeliveryEvent::Result(done("c1")), now);
        let retry = d.handle(
            ended("c1", AttemptOutcome::Refused("not booked".into())),
            now,
        );
        assert_eq!(
            retry,
            vec![DeliveryAction::Retry {
                conversation_id: "c1".into(),
                attempt: 1,
                refused: Some("not booked".into()),
                pause: Duration::from_millis(20)
            }]
        );
        assert_eq!(d.next_due(), Some(now + Duration::from_millis(20)));
        // Not yet due: nothing goes out.
        assert_eq!(
            d.handle(DeliveryEvent::Tick, now + Duration::from_millis(10)),
            vec![]
        );
        let later = now + Duration::from_millis(20);
        assert_eq!(
            attempts(&d.handle(DeliveryEvent::Tick, later)),
            vec![("c1".into(), 2)]
        );
        assert_eq!(d.retries(), 1);
        let again = d.handle(ended("c1", AttemptOutcome::Unanswered), later);
        assert!(
            matches!(&again[..], [DeliveryAction::Retry { pause, refused: None, attempt: 2, .. }] if *pause == Duration::from_millis(40)),
            "{again:?}"
        );
    }

    #[test]
    fn nothing_goes_out_before_the_resource_serves() {
        let mut d = DeliveryMachine::new(settings(), 7);
        let now = Instant::now();
        assert_eq!(d.handle(DeliveryEvent::Result(done("c1")), now), vec![]);
        assert_eq!(d.handle(DeliveryEvent::Result(done("c2")), now), vec![]);
        assert_eq!(d.handle(DeliveryEvent::Tick, now), vec![]);
        assert_eq!(d.next_due(), None, "no timer while not serving");
        let out = d.handle(DeliveryEvent::Serving, now);
        assert_eq!(attempts(&out), vec![("c1".into(), 1), ("c2".into(), 1)]);
        assert_eq!(d.retries(), 7, "a restarted owner goes on counting");
    }

    #[test]
    fn each_result_keeps_its_own_pause() {
        let (mut d, now) = serving();
        d.handle(DeliveryEvent::Result(done("c1")), now);
        d.handle(DeliveryEvent::Result(done("c2")), now);
        d.handle(ended("c1", AttemptOutcome::Unanswered), now);
        assert_eq!(d.next_due(), Some(now + Duration::from_millis(20)));
        d.handle(ended("c2", AttemptOutcome::Acknowledged), now);
        assert_eq!(d.len(), 1);
        let later = now + Duration::from_millis(25);
        assert_eq!(
            attempts(&d.handle(DeliveryEvent::Tick, later)),
            vec![("c1".into(), 2)]
        );
    }

    #[test]
    fn the_first_and_every_tenth_attempt_are_worth_logging() {
        let logged: Vec<u32> = (1..=30).filter(|a| repeat_worth_logging(*a)).collect();
        assert_eq!(logged, vec![1, 10, 20, 30]);
    }
}

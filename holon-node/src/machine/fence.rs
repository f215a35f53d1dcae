//! A fenced resource's claim on its controller, as a pure machine
//! (docs/reliability.md, "Standby resources").
//!
//! | state | event | actions | next |
//! |---|---|---|---|
//! | claiming | claim granted, epoch e | serve with e | holding e |
//! | claiming | held by another session (epoch h) | standby (once per holder), retry | claiming |
//! | claiming | the controller cannot fence | refuse, with the reason | claiming |
//! | claiming | no connection, a timeout, another refusal | retry (its reason once) | claiming |
//! | holding e | deposed (`stale_epoch`) or lost, for e | step down | claiming |
//! | holding e | deposed or lost for another epoch (late) | nothing | holding e |
//! | claiming | deposed or lost (late) | nothing | claiming |
//!
//! The node's fence loop ([`crate::node`]) carries the actions out: it asks again
//! [`CLAIM_RETRY`] after a retry, declares the name's token and serves only after a
//! grant, and withdraws (token, offers, bookings) on a step-down.

use std::time::Duration;

use robot_bridge::client::{ClaimError, Epoch, FenceEvent};

/// How long a standby waits between two claims.
pub const CLAIM_RETRY: Duration = Duration::from_millis(200);

/// What the claim machine reacts to.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ClaimEvent {
    /// The controller's answer to a claim.
    Answer(Result<Epoch, ClaimError>),
    /// What the controller client says of the fence.
    Fence(FenceEvent),
}

/// What the fence loop must do.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ClaimAction {
    /// The claim is ours: learn what was in flight, then declare the token and serve.
    Serve(Epoch),
    /// Another session holds the controller with this epoch: wait as a standby (said
    /// once per holder).
    Standby(Epoch),
    /// Ask again after [`CLAIM_RETRY`]; the reason, when it is new, for the log.
    Retry(Option<String>),
    /// The controller cannot fence: standby is refused, with this reason.
    Refuse(String),
    /// A newer holder exists, or the claim went with the connection: withdraw.
    StepDown {
        /// The epoch this resource held.
        epoch: Epoch,
        /// Why, for the log.
        why: String,
    },
}

/// The claim's state.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Claim {
    /// Asking for the claim.
    Claiming {
        /// The holder's epoch last said (standby logged for it).
        holder: Option<Epoch>,
        /// The last reason for a retry that was said.
        reason: Option<String>,
    },
    /// Holding the claim with this epoch: serving.
    Holding(Epoch),
}

impl Default for Claim {
    fn default() -> Self {
        Claim::Claiming {
            holder: None,
            reason: None,
        }
    }
}

impl Claim {
    /// The epoch held, if any.
    pub fn epoch(&self) -> Option<Epoch> {
        match self {
            Claim::Holding(epoch) => Some(*epoch),
            Claim::Claiming { .. } => None,
        }
    }

    pub fn handle(&mut self, event: ClaimEvent) -> Vec<ClaimAction> {
        match (&mut *self, event) {
            (Claim::Claiming { .. }, ClaimEvent::Answer(Ok(epoch))) => {
                *self = Claim::Holding(epoch);
                vec![ClaimAction::Serve(epoch)]
            }
            (Claim::Claiming { holder, reason }, ClaimEvent::Answer(Err(error))) => match error {
                ClaimError::Held(epoch) => {
                    *reason = None;
                    let new = *holder != Some(epoch);
                    *holder = Some(epoch);
                    let mut actions = Vec::new();
                    if new {
                        actions.push(ClaimAction::Standby(epoch));
                    }
                    actions.push(ClaimAction::Retry(None));
                    actions
                }
                ClaimError::NotSupported(why) => vec![ClaimAction::Refuse(why)],
                other => {
                    let why = other.to_string();
                    let new = reason.as_deref() != Some(why.as_str());
                    *reason = Some(why.clone());
                    vec![ClaimAction::Retry(new.then_some(why))]
                }
            },
            (Claim::Holding(held), ClaimEvent::Fence(event)) => {
                let (epoch, why) = match event {
                    FenceEvent::Deposed { epoch, current } => (
                        epoch,
                        match current {
                            Some(current) => {
                                format!("the controller refused epoch {epoch}: epoch {current} holds it")
                            }
                            None => format!("the controller refused epoch {epoch}"),
                        },
                    ),
                    FenceEvent::Lost { epoch } => (
                        epoch,
                        format!(
                            "the connection that held epoch {epoch} ended, and the claim with it"
                        ),
                    ),
                };
                if epoch != *held {
                    return vec![];
                }
                *self = Claim::default();
                vec![ClaimAction::StepDown { epoch, why }]
            }
            // A grant answered twice, or a late event of a claim already given up.
            (Claim::Holding(_), ClaimEvent::Answer(_))
            | (Claim::Claiming { .. }, ClaimEvent::Fence(_)) => {
                vec![]
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn held(epoch: u64) -> ClaimEvent {
        ClaimEvent::Answer(Err(ClaimError::Held(Epoch(epoch))))
    }

    #[test]
    fn a_standby_says_so_once_per_holder_and_retries() {
        let mut claim = Claim::default();
        assert_eq!(
            claim.handle(held(1)),
            vec![ClaimAction::Standby(Epoch(1)), ClaimAction::Retry(None)]
        );
        assert_eq!(claim.handle(held(1)), vec![ClaimAction::Retry(None)]);
        assert_eq!(
            claim.handle(held(2)),
            vec![ClaimAction::Standby(Epoch(2)), ClaimAction::Retry(None)]
        );
        assert_eq!(claim.epoch(), None);
    }

    #[test]
    fn a_grant_serves_and_a_deposition_of_that_epoch_steps_down() {
        let mut claim = Claim::default();
        assert_eq!(
            claim.handle(ClaimEvent::Answer(Ok(Epoch(2)))),
            vec![ClaimAction::Serve(Epoch(2))]
        );
        assert_eq!(claim.epoch(), Some(Epoch(2)));
        // A late event of an older epoch changes nothing.
        assert_eq!(
            claim.handle(ClaimEvent::Fence(FenceEvent::Lost { epoch: Epoch(1) })),
            vec![]
        );
        let actions = claim.handle(ClaimEvent::Fence(FenceEvent::Deposed {
            epoch: Epoch(2),
            current: Some(Epoch(3)),
        }));
        assert!(
            matches!(&actions[..], [ClaimAction::StepDown { epoch: Epoch(2), why }] if why.contains("epoch 3")),
            "{actions:?}"
        );
        assert_eq!(claim, Claim::default());
    }

    #[test]
    fn a_lost_connection_steps_down() {
        let mut claim = Claim::Holding(Epoch(1));
        let actions = claim.handle(ClaimEvent::Fence(FenceEvent::Lost { epoch: Epoch(1) }));
        assert!(matches!(
            &actions[..],
            [ClaimAction::StepDown {
                epoch: Epoch(1),
                ..
            }]
        ));
    }

    #[test]
    fn a_controller_that_cannot_fence_refuses_standby() {
        let mut claim = Claim::default();
        assert_eq!(
            claim.handle(ClaimEvent::Answer(Err(ClaimError::NotSupported(
                "not_fenced".into()
            )))),
            vec![ClaimAction::Refuse("not_fenced".into())]
        );
    }

    #[test]
    fn other_failures_retry_and_say_each_new_reason_once() {
        let mut claim = Claim::default();
        let not_connected = ClaimEvent::Answer(Err(ClaimError::NotConnected));
        assert!(matches!(
            &claim.handle(not_connected.clone())[..],
            [ClaimAction::Retry(Some(_))]
        ));
        assert_eq!(claim.handle(not_connected), vec![ClaimAction::Retry(None)]);
    }
}

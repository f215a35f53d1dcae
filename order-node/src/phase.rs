//! Where an order's attempt of a step stands with its resource: journalled with the
//! order's progress ([`crate::progress`]) and a move's ([`crate::part`]), so that a
//! restarted order asks the resource what became of its booking instead of booking
//! again.

use schemas::HolonId;

/// Where the current attempt stands with its resource. Recorded in the journal before
/// each request that depends on it, so a restarted order-node resumes the conversation
/// instead of starting it again (booking and start are idempotent per conversation).
#[derive(Debug, Clone, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Looking for a resource.
    #[default]
    Proposing,
    /// A booking request to this resource may have been sent.
    Booking(HolonId),
    /// Booked on this resource, not started.
    Booked(HolonId),
    /// Started on this resource: waiting for its result.
    Started(HolonId),
}

impl Phase {
    pub fn resource(&self) -> Option<&HolonId> {
        match self {
            Phase::Proposing => None,
            Phase::Booking(r) | Phase::Booked(r) | Phase::Started(r) => Some(r),
        }
    }
}

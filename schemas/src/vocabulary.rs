//! The words holons answer with: why a Service was refused or failed ([`Reason`]) and
//! why a request could not be taken at all ([`ErrorCode`]).
//!
//! Both travel as the same strings as before (`"busy"`, `"unavailable"`, ...), so the
//! wire does not change; in the code they are enums, matched rather than compared as
//! text. A word this version does not know (a newer holon's, or a third party's free
//! text) is kept as `Other` with its text, never refused.

use std::fmt;

use serde::{Deserialize, Deserializer, Serialize, Serializer};

/// Declares a string enum: its variants with their wire words, `Other(String)` for any
/// other word, `as_str`, `Display`, serde as a plain string.
macro_rules! words {
    ($(#[$meta:meta])* $name:ident { $($(#[$vmeta:meta])* $variant:ident = $word:literal,)* }) => {
        $(#[$meta])*
        #[derive(Debug, Clone, PartialEq, Eq, Hash)]
        pub enum $name {
            $($(#[$vmeta])* $variant,)*
            /// A word this version does not know, as received.
            Other(String),
        }

        impl $name {
            /// The word on the wire.
            pub fn as_str(&self) -> &str {
                match self {
                    $($name::$variant => $word,)*
                    $name::Other(word) => word,
                }
            }

            /// The variant of `word` (`Other` for a word not listed).
            pub fn from_word(word: &str) -> $name {
                match word {
                    $($word => $name::$variant,)*
                    other => $name::Other(other.to_string()),
                }
            }
        }

        impl AsRef<str> for $name {
            fn as_ref(&self) -> &str {
                self.as_str()
            }
        }

        impl From<&str> for $name {
            fn from(word: &str) -> $name {
                $name::from_word(word)
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.as_str())
            }
        }

        impl Serialize for $name {
            fn serialize<S: Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
                serializer.serialize_str(self.as_str())
            }
        }

        impl<'de> Deserialize<'de> for $name {
            fn deserialize<D: Deserializer<'de>>(deserializer: D) -> Result<$name, D::Error> {
                let word = std::borrow::Cow::<'de, str>::deserialize(deserializer)?;
                Ok($name::from_word(&word))
            }
        }
    };
}

words! {
    /// Why a holon answered a Service with `result` false, or why a step failed (details
    /// go in `info.detail`).
    Reason {
        /// `start` or `booking_cancel` from a requester that holds no such booking.
        NotBooked = "not_booked",
        /// `start` while the resource executes another service.
        Busy = "busy",
        /// The resource cannot execute now: its controller is disconnected, in fault or
        /// estop.
        Unavailable = "unavailable",
        /// The resource does not offer this service type.
        UnknownService = "unknown_service",
        /// The agenda is full (`agenda_capacity`).
        AgendaFull = "agenda_full",
        /// `info` lacks what the service's steps need (e.g. a pose).
        InvalidInfo = "invalid_info",
        /// `booking_req` whose requester is a resource: orders, products and staff book
        /// resources; a resource does not (its absence is not watched, so nothing would
        /// release its bookings).
        NotARequester = "not_a_requester",
        /// The controller answered a command with `error` (its message is in
        /// `info.detail`).
        ControllerError = "controller_error",
        /// The connection to the controller broke during the step.
        ControllerDisconnected = "controller_disconnected",
        /// The connection to the controller broke before it began the job's first step,
        /// and its fenced controller says it never had it: nothing of the job ran, it
        /// is safe to book again (a part the job would have moved has not moved).
        NotBegun = "not_begun",
        /// The controller did not answer a command within its timeout.
        ControllerTimeout = "controller_timeout",
        /// The controller sent something that is not the protocol.
        ControllerProtocol = "controller_protocol_error",
        /// The controller answered with a result the step does not expect.
        UnexpectedResult = "unexpected_result",
        /// The controller reported `fault` or `estop` during the step.
        ControllerFault = "controller_fault",
        /// The resource is shutting down and hands the booking back (sent as `failed`
        /// for a booking that never started): book elsewhere.
        Withdrawn = "withdrawn",
        /// The resource holon stopped (crashed, was killed) while the step ran; it was
        /// not completed and is never re-executed by the resource: the order decides.
        Interrupted = "interrupted",
        /// The resource was aborted (PackML Abort, by an operator) while the step ran:
        /// the controller was told to stop, the step did not complete.
        Aborted = "aborted",
        /// A `booking_req`, `start` or `booking_cancel` whose `info.epoch` is lower than
        /// one the booking was already asked at: it comes from a deposed holder of an
        /// order-node on etcd, and a newer holder has the order.
        StaleEpoch = "stale_epoch",
        /// A `booking_req` for a place ([`crate::PLACE_SERVICE`]) at a location whose
        /// places are all held by other parts (`info.detail` names them).
        NoPlace = "no_place",
    }
}

words! {
    /// Why a request was answered with an error reply (`reply_err`): it could not be
    /// decoded, or is not allowed now. The holon changed nothing.
    ErrorCode {
        /// The payload cannot be read.
        Malformed = "malformed",
        /// It speaks another schema version.
        UnsupportedVersion = "unsupported_version",
        /// A field is wrong.
        Invalid = "invalid",
        /// The message was sent to a key that is not its own.
        WrongKey = "wrong_key",
        /// The holon failed inside.
        Internal = "internal",
        /// Not now (e.g. the holon is handed over to its successor): ask again, after
        /// `retry_after_ms` when given.
        Unavailable = "unavailable",
        /// A result or cancel for a booking the holon does not hold.
        NotBooked = "not_booked",
        /// Asked too early (the holon is not ready for it yet).
        NotYet = "not_yet",
        /// Over a limit of the node (`orders.max_orders_per_submit`,
        /// `orders.max_unfinished_orders`).
        Quota = "quota",
        /// No such order on this node.
        UnknownOrder = "unknown_order",
        /// No product holon of that name is alive.
        UnknownProduct = "unknown_product",
    }
}

impl Reason {
    /// Whether a step whose result is `failed` for this reason never reached its
    /// controller, so that nothing of it ran and it may be booked again at no risk (a
    /// part it would have moved is where it was): `not_begun` (its fenced controller
    /// says it never had it), `unavailable` (its turn came while the controller was not
    /// ready: it was never sent), `busy` (another job still ran), `withdrawn` (the
    /// resource handed the booking back before it began). Not a refusal's meaning: a
    /// `booking_req` refused `unavailable` is another answer. Whoever sends these
    /// words must be sure: `not_begun` only for a job's first step (a later step's
    /// unknown state is `controller_disconnected`), `unavailable` and `busy` only from
    /// a holder that cannot have begun the job (a fenced resource, whose controller an
    /// earlier holder may have driven, says `controller_disconnected` instead).
    pub fn never_reached_controller(&self) -> bool {
        matches!(
            self,
            Reason::NotBegun | Reason::Unavailable | Reason::Busy | Reason::Withdrawn
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failure_that_never_reached_the_controller_is_named_by_its_reason() {
        for never in ["not_begun", "unavailable", "busy", "withdrawn"] {
            assert!(
                Reason::from_word(never).never_reached_controller(),
                "{never}"
            );
        }
        for may_have_run in [
            "controller_error",
            "controller_disconnected",
            "controller_timeout",
            "controller_fault",
            "interrupted",
            "aborted",
            "gripper jammed",
        ] {
            assert!(
                !Reason::from_word(may_have_run).never_reached_controller(),
                "{may_have_run}"
            );
        }
    }

    #[test]
    fn the_words_on_the_wire_are_the_old_strings_and_unknown_ones_are_kept() {
        assert_eq!(serde_json::to_string(&Reason::Busy).unwrap(), "\"busy\"");
        assert_eq!(
            serde_json::to_string(&Reason::ControllerProtocol).unwrap(),
            "\"controller_protocol_error\""
        );
        let read: Reason = serde_json::from_str("\"not_booked\"").unwrap();
        assert_eq!(read, Reason::NotBooked);
        let other: Reason = serde_json::from_str("\"gripper jammed\"").unwrap();
        assert_eq!(other, Reason::Other("gripper jammed".into()));
        assert_eq!(serde_json::to_string(&other).unwrap(), "\"gripper jammed\"");
        assert_eq!(ErrorCode::from_word("quota"), ErrorCode::Quota);
        assert_eq!(ErrorCode::UnknownOrder.to_string(), "unknown_order");
    }
}

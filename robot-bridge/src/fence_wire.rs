//! What both ends of the fence share (`docs/controller-protocol.md`, "Fencing
//! (standby)"): the refusal reasons, the step states, and the rule for holon names and
//! step ids. The controller's side is [`crate::sim::fence`], the holon's
//! [`crate::client::fence`].

/// A refusal's `{reason}`: another live session holds the claim.
pub const REASON_HELD: &str = "held";
/// The controller was started without the fence: standby is refused.
pub const REASON_NOT_FENCED: &str = "not_fenced";
/// The epoch is not the live holder's (or the session holds no claim).
pub const REASON_STALE_EPOCH: &str = "stale_epoch";
/// A name, epoch or step id that is not one.
pub const REASON_INVALID: &str = "invalid";

/// A step's `{step_state}`: it ran, with `{result}`.
pub const STEP_DONE: &str = "done";
/// It ended failed, with `{message}`.
pub const STEP_FAILED: &str = "failed";
/// It runs now.
pub const STEP_RUNNING: &str = "running";
/// Never begun, or forgotten.
pub const STEP_UNKNOWN: &str = "unknown";

/// The longest holon name, in bytes.
pub const MAX_NAME_BYTES: usize = 64;
/// The longest step id, in bytes.
pub const MAX_STEP_BYTES: usize = 128;

/// Whether `text` is a valid holon name or step id: 1 to `max` printable ASCII bytes,
/// no space, none of `<>&'"` (so it is written and read back as is, in any framing).
pub fn valid_token(text: &str, max: usize) -> bool {
    !text.is_empty()
        && text.len() <= max
        && text
            .bytes()
            .all(|b| b.is_ascii_graphic() && !b"<>&'\"".contains(&b))
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn tokens_are_bounded_and_printable() {
        assert!(valid_token("orders1-3/2/1#2", MAX_STEP_BYTES));
        assert!(!valid_token("", MAX_STEP_BYTES));
        assert!(!valid_token("a b", MAX_STEP_BYTES));
        assert!(!valid_token("<x>", MAX_STEP_BYTES));
        assert!(!valid_token(
            &"x".repeat(MAX_STEP_BYTES + 1),
            MAX_STEP_BYTES
        ));
    }

    proptest! {
        /// A valid token needs no escaping and is within its bound.
        #[test]
        fn a_valid_token_is_bounded_and_needs_no_escaping(text in ".{0,200}") {
            if valid_token(&text, MAX_STEP_BYTES) {
                prop_assert!(text.len() <= MAX_STEP_BYTES);
                let escaped = quick_xml::escape::escape(text.as_str());
                prop_assert_eq!(escaped.as_ref(), text.as_str());
            }
        }
    }
}

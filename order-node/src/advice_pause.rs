//! When a staff holon stops answering, the node stops asking it for a while.
//!
//! An order waits at most `orders.advice_timeout_ms` for advice, so a staff that does
//! not answer costs each order that much per step. A killed staff's token vanishes at
//! once and orders stop asking; a frozen one (a stopped process, a host that lost its
//! network) keeps its token until its link lease ends, seconds later. So after
//! [`FAILURES_BEFORE_PAUSE`] asks in a row went unanswered, the node's orders go by
//! contract net without asking for [`PAUSE`]; then one order asks again, and an answer
//! ends the pause.

use std::time::Duration;

use tokio::sync::watch;
use tokio::time::Instant;

/// Unanswered asks in a row before the node stops asking.
pub const FAILURES_BEFORE_PAUSE: u32 = 3;

/// How long the node does not ask after that.
pub const PAUSE: Duration = Duration::from_secs(5);

/// The node's record of how its asks for advice went: changed in place by the order
/// that learnt how its ask went, read by every order before it asks.
#[derive(Debug)]
pub struct AdvicePause(watch::Sender<Record>);

impl Default for AdvicePause {
    fn default() -> AdvicePause {
        AdvicePause(watch::Sender::new(Record::default()))
    }
}

/// How the asks went lately.
#[derive(Debug, Default)]
struct Record {
    /// Asks in a row that went unanswered.
    failures: u32,
    /// No ask before this.
    paused_until: Option<Instant>,
}

impl AdvicePause {
    /// Whether an order may ask now.
    pub fn may_ask(&self, now: Instant) -> bool {
        self.0
            .borrow()
            .paused_until
            .is_none_or(|until| now >= until)
    }

    /// An ask was answered (usable or not, the staff is there): asking goes on.
    pub fn answered(&self) {
        self.0.send_if_modified(|record| {
            let news = record.failures != 0 || record.paused_until.is_some();
            record.failures = 0;
            record.paused_until = None;
            news
        });
    }

    /// An ask went unanswered within the timeout. True when this starts a pause.
    pub fn unanswered(&self, now: Instant) -> bool {
        let mut paused = false;
        self.0.send_modify(|record| {
            record.failures += 1;
            if record.failures >= FAILURES_BEFORE_PAUSE {
                record.failures = 0;
                record.paused_until = Some(now + PAUSE);
                paused = true;
            }
        });
        paused
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn three_unanswered_asks_pause_asking_and_an_answer_ends_it() {
        let pause = AdvicePause::default();
        let t = Instant::now();
        assert!(pause.may_ask(t));
        assert!(!pause.unanswered(t));
        pause.answered();
        assert!(!pause.unanswered(t));
        assert!(!pause.unanswered(t));
        assert!(pause.may_ask(t), "two in a row do not pause");
        assert!(pause.unanswered(t), "the third does");
        assert!(!pause.may_ask(t + Duration::from_secs(1)));
        assert!(pause.may_ask(t + PAUSE), "one asks again after the pause");
        assert!(
            !pause.unanswered(t + PAUSE),
            "one more failure starts counting anew"
        );
        pause.answered();
        assert!(pause.may_ask(t + PAUSE));
    }
}

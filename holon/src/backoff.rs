//! The one doubling backoff of the project: how long to wait before trying again.
//!
//! The first pause is `initial`; each further pause is twice the one before, up to
//! `max`. [`Backoff::reset`] starts over after a success. Used for result deliveries,
//! an order's retries, and `cell up`'s process restarts.

use std::time::Duration;

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Backoff {
    /// The first pause, and the pause after a reset.
    initial: Duration,
    /// No pause is longer (if `max` is below `initial`, pauses stay at `initial`).
    max: Duration,
    /// The pause the next call to [`Backoff::next_pause`] returns.
    next: Duration,
}

impl Backoff {
    pub fn new(initial: Duration, max: Duration) -> Backoff {
        Backoff {
            initial,
            max: max.max(initial),
            next: initial,
        }
    }

    /// The pause before the next attempt; the one after it doubles, up to `max`.
    pub fn next_pause(&mut self) -> Duration {
        let pause = self.next;
        self.next = self.next.saturating_mul(2).min(self.max);
        pause
    }

    /// The pause [`Backoff::next_pause`] would return, without taking it.
    pub fn peek(&self) -> Duration {
        self.next
    }

    /// Starts over at `initial` (after a success).
    pub fn reset(&mut self) {
        self.next = self.initial;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pauses_double_up_to_the_max_and_start_over_after_a_reset() {
        let ms = Duration::from_millis;
        let mut backoff = Backoff::new(ms(100), ms(500));
        let pauses: Vec<_> = (0..5).map(|_| backoff.next_pause()).collect();
        assert_eq!(pauses, [ms(100), ms(200), ms(400), ms(500), ms(500)]);
        backoff.reset();
        assert_eq!(backoff.peek(), ms(100));
        assert_eq!(backoff.next_pause(), ms(100));
    }

    #[test]
    fn a_max_below_the_initial_pause_keeps_the_initial_pause() {
        let ms = Duration::from_millis;
        let mut backoff = Backoff::new(ms(300), ms(100));
        assert_eq!(backoff.next_pause(), ms(300));
        assert_eq!(backoff.next_pause(), ms(300));
    }
}

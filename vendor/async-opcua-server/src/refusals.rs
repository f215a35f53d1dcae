//! (holarchy) Refusals of clients that did not authenticate, logged without letting a
//! stranger flood the log: the first refusal of a kind is logged at once, later ones of
//! that kind at most once per [`EVERY`], with how many were left out since.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// The shortest time between two lines of one kind of refusal.
pub(crate) const EVERY: Duration = Duration::from_secs(10);

/// When each kind was last logged, and how many of it were not logged since.
static LOGGED: Mutex<Option<HashMap<&'static str, (Instant, u64)>>> = Mutex::new(None);

/// Whether a refusal of `kind` is to be logged now: `Some(left out since the last
/// line)`, or `None` (counted, not logged).
pub(crate) fn log_now(kind: &'static str) -> Option<u64> {
    let now = Instant::now();
    let mut logged = LOGGED.lock().unwrap_or_else(|e| e.into_inner());
    let entry = logged
        .get_or_insert_with(HashMap::new)
        .entry(kind)
        .or_insert((now - EVERY - Duration::from_millis(1), 0));
    if now.duration_since(entry.0) > EVERY {
        let left_out = entry.1;
        *entry = (now, 0);
        Some(left_out)
    } else {
        entry.1 += 1;
        None
    }
}

/// Logs a refusal of `kind` at warn, or counts it (see the module).
macro_rules! refused {
    ($kind:expr, $($arg:tt)+) => {
        if let Some(left_out) = $crate::refusals::log_now($kind) {
            tracing::warn!(left_out_since_last_line = left_out, $($arg)+);
        }
    };
}
pub(crate) use refused;

#[cfg(test)]
mod tests {
    #[test]
    fn a_flood_is_one_line_then_a_count() {
        assert_eq!(super::log_now("test"), Some(0));
        for _ in 0..100 {
            assert_eq!(super::log_now("test"), None);
        }
        assert_eq!(super::log_now("other"), Some(0));
    }
}

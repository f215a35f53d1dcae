//! Failed logins, slowed and counted: the policy of every door ([`super::Logins`]).
//!
//! - Every refused login is answered only after [`FAILED_LOGIN_DELAY`] (1 s): a guesser
//!   gets one try per second per connection at most, and a right name costs no more
//!   time than a wrong one.
//! - After [`FREE_FAILURES`] (5) refused logins in a row for one user name, or from one
//!   address, that name (or address) is locked out: every login for it is refused
//!   without looking at the password (429, with `Retry-After`) for 30 s, doubling with
//!   every further failure after the lock-out to at most 15 min. A successful login
//!   clears the name's and the address's count.
//! - Every refusal goes to the audit trail, and is counted: the dashboard's `/metrics`
//!   (`holarchy_dashboard_logins_failed_total`), the OPC UA server's
//!   `Cell/Security/LoginsRefused`.
//!
//! Locking out by name lets anybody lock a known user out for a while by guessing
//! wrong; that is the price of stopping a slow guesser spread over many addresses, and
//! a locked-out operator can use a client certificate on the dashboard meanwhile
//! (docs/security.md).

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

/// How long a refused login's answer waits.
pub const FAILED_LOGIN_DELAY: Duration = Duration::from_secs(1);

/// Refused logins in a row before a lock-out.
pub const FREE_FAILURES: u32 = 5;

/// The first lock-out.
const FIRST_LOCK: Duration = Duration::from_secs(30);

/// The longest lock-out.
const LONGEST_LOCK: Duration = Duration::from_secs(15 * 60);

/// The most names or addresses remembered (beyond it, those without a lock are
/// forgotten first).
const MOST_REMEMBERED: usize = 10_000;

/// What is remembered of one name or address.
#[derive(Debug, Clone, Copy, Default)]
struct Failures {
    /// Refused logins in a row.
    in_a_row: u32,
    /// Until when logins are refused outright.
    locked_until: Option<Instant>,
}

impl Failures {
    fn locked(&self, now: Instant) -> Option<Duration> {
        self.locked_until
            .filter(|until| *until > now)
            .map(|until| until - now)
    }

    fn fail(&mut self, now: Instant) {
        self.in_a_row += 1;
        if self.in_a_row >= FREE_FAILURES {
            let doublings = (self.in_a_row - FREE_FAILURES).min(10);
            let lock = (FIRST_LOCK * 2u32.pow(doublings)).min(LONGEST_LOCK);
            self.locked_until = Some(now + lock);
        }
    }
}

/// A login that may not even be tried.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LockedOut {
    /// What is locked: `user anna` or `address 10.0.0.9`.
    pub what: String,
    /// For how much longer.
    pub retry_after: Duration,
}

/// The failed logins of one dashboard.
#[derive(Debug, Default)]
pub struct Throttle {
    /// By user name.
    names: HashMap<String, Failures>,
    /// By client address.
    addresses: HashMap<IpAddr, Failures>,
    /// Every refused login since the start.
    pub refused_total: u64,
}

impl Throttle {
    /// Whether a login of `name` from `from` may be tried at `now`.
    pub fn check(&self, name: &str, from: IpAddr, now: Instant) -> Result<(), LockedOut> {
        if let Some(retry_after) = self.names.get(name).and_then(|f| f.locked(now)) {
            return Err(LockedOut {
                what: format!("user {name}"),
                retry_after,
            });
        }
        if let Some(retry_after) = self.addresses.get(&from).and_then(|f| f.locked(now)) {
            return Err(LockedOut {
                what: format!("address {from}"),
                retry_after,
            });
        }
        Ok(())
    }

    /// A login of `name` from `from` was refused: a wrong password or an unknown name
    /// (a login refused by a lock-out is only counted, [`Throttle::refused_during_lock`],
    /// and does not make the lock longer).
    pub fn failed(&mut self, name: &str, from: IpAddr, now: Instant) {
        self.refused_total += 1;
        if self.names.len() >= MOST_REMEMBERED {
            self.names.retain(|_, f| f.locked(now).is_some());
        }
        if self.addresses.len() >= MOST_REMEMBERED {
            self.addresses.retain(|_, f| f.locked(now).is_some());
        }
        self.names.entry(name.to_string()).or_default().fail(now);
        self.addresses.entry(from).or_default().fail(now);
    }

    /// A login was refused by a lock-out, without looking at the password.
    pub fn refused_during_lock(&mut self) {
        self.refused_total += 1;
    }

    /// A login of `name` from `from` succeeded: their counts start again.
    pub fn succeeded(&mut self, name: &str, from: IpAddr) {
        self.names.remove(name);
        self.addresses.remove(&from);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 9));
    const B: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 10));

    #[test]
    fn five_failures_lock_the_name_out_for_longer_each_time() {
        let mut throttle = Throttle::default();
        let now = Instant::now();
        for _ in 0..FREE_FAILURES - 1 {
            assert!(throttle.check("anna", A, now).is_ok());
            throttle.failed("anna", A, now);
        }
        assert!(throttle.check("anna", A, now).is_ok());
        throttle.failed("anna", A, now);
        let locked = throttle.check("anna", B, now).unwrap_err();
        assert_eq!(locked.what, "user anna");
        assert_eq!(locked.retry_after, FIRST_LOCK);
        // The address is locked too, for any name.
        assert_eq!(
            throttle.check("bert", A, now).unwrap_err().what,
            "address 10.0.0.9"
        );
        // Once the lock is over, one more failure locks for twice as long.
        let later = now + FIRST_LOCK;
        assert!(throttle.check("anna", B, later).is_ok());
        throttle.failed("anna", B, later);
        assert_eq!(
            throttle.check("anna", B, later).unwrap_err().retry_after,
            FIRST_LOCK * 2
        );
        // Never longer than the longest.
        for _ in 0..20 {
            throttle.failed("anna", B, later);
        }
        assert_eq!(
            throttle.check("anna", B, later).unwrap_err().retry_after,
            LONGEST_LOCK
        );
        assert_eq!(throttle.refused_total, 5 + 1 + 20);
    }

    #[test]
    fn a_success_starts_the_count_again() {
        let mut throttle = Throttle::default();
        let now = Instant::now();
        for _ in 0..FREE_FAILURES - 1 {
            throttle.failed("anna", A, now);
        }
        throttle.succeeded("anna", A);
        throttle.failed("anna", A, now);
        assert!(throttle.check("anna", A, now).is_ok());
    }
}

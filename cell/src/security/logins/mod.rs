//! Password logins, one policy for every door of the cell (the dashboard's login page
//! and the OPC UA server's ActivateSession): a guesser is slowed and locked out
//! ([`throttle`]), and checking passwords never takes more memory than a bound, whatever
//! an attacker does.
//!
//! A check is an argon2id hash of 19 MiB and tens of milliseconds of CPU
//! ([`crate::security::users::password`]). At most [`CHECKS_AT_ONCE`] run at a time, on tokio's
//! blocking threads, each in working memory kept from one check to the next (about
//! 40 MiB in all, allocated at the first logins and never again); a login waits at most [`LONGEST_WAIT`]
//! for its turn and is refused as busy after that (not counted against the name or the
//! address: the server was busy, nobody guessed wrong). The waiting logins hold only
//! their name and password.
//!
//! | refused | when | answered after |
//! |---|---|---|
//! | locked out | the name or the address is locked ([`throttle`]) | [`FAILED_LOGIN_DELAY`], without a check |
//! | wrong | no such user, or not their password | [`FAILED_LOGIN_DELAY`] |
//! | busy | no turn within [`LONGEST_WAIT`] | at once |

pub mod throttle;

use std::net::IpAddr;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use tokio::sync::Semaphore;

use crate::security::users::password::Memory;
use crate::security::users::{User, Users};
use throttle::Throttle;
pub use throttle::{LockedOut, FAILED_LOGIN_DELAY, FREE_FAILURES};

/// Password checks running at once, in one process (each holds 19 MiB while it runs).
pub const CHECKS_AT_ONCE: usize = 2;

/// How long a login waits for its turn to be checked before it is refused as busy.
pub const LONGEST_WAIT: Duration = Duration::from_secs(5);

/// Why a login was refused.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Refused {
    /// Too many failures for the name or the address: not even tried.
    LockedOut(LockedOut),
    /// No such user, or not their password (which of the two is not told).
    Wrong,
    /// Too many logins were being checked: try again.
    Busy,
    /// The check itself failed (a panic in the hash): nothing was decided.
    Broken(String),
}

impl Refused {
    /// What the person is told (and the audit trail records).
    pub fn why(&self) -> String {
        match self {
            Refused::LockedOut(locked) => format!(
                "too many failed logins for {}: try again in {} s",
                locked.what,
                locked.retry_after.as_secs().max(1)
            ),
            Refused::Wrong => "wrong user name or password".into(),
            Refused::Busy => format!(
                "too many logins are being checked at once (more than {CHECKS_AT_ONCE} for {} s): try again",
                LONGEST_WAIT.as_secs()
            ),
            Refused::Broken(e) => format!("the password could not be checked: {e}"),
        }
    }
}

/// The logins of one door: its failures and its password checks.
#[derive(Debug)]
pub struct Logins {
    /// The failed logins, by name and by address.
    throttle: Mutex<Throttle>,
    /// The turns to check a password.
    checks: Arc<Semaphore>,
    /// The working memory of the checks, one per turn (a turn takes one).
    memories: Arc<Mutex<Vec<Memory>>>,
    /// Logins waiting for a turn or being checked now.
    in_check: AtomicUsize,
    /// Logins refused as busy since the start.
    busy_total: AtomicU64,
}

impl Default for Logins {
    fn default() -> Self {
        Logins {
            throttle: Mutex::new(Throttle::default()),
            checks: Arc::new(Semaphore::new(CHECKS_AT_ONCE)),
            memories: Arc::new(Mutex::new(
                (0..CHECKS_AT_ONCE).map(|_| Memory::default()).collect(),
            )),
            in_check: AtomicUsize::new(0),
            busy_total: AtomicU64::new(0),
        }
    }
}

impl Logins {
    fn throttle(&self) -> std::sync::MutexGuard<'_, Throttle> {
        self.throttle.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Checks `name`'s `password` for a login from `from`: the user, or why not. A
    /// refusal other than busy is answered only after [`FAILED_LOGIN_DELAY`].
    pub async fn check(
        &self,
        users: &Arc<Users>,
        name: &str,
        password: String,
        from: IpAddr,
    ) -> Result<User, Refused> {
        let locked = self.throttle().check(name, from, Instant::now());
        if let Err(locked) = locked {
            self.throttle().refused_during_lock();
            tokio::time::sleep(FAILED_LOGIN_DELAY).await;
            return Err(Refused::LockedOut(locked));
        }
        let verified = {
            let _counted = InCheck::new(&self.in_check);
            let permit =
                match tokio::time::timeout(LONGEST_WAIT, self.checks.clone().acquire_owned()).await
                {
                    Ok(Ok(permit)) => permit,
                    Ok(Err(_closed)) => {
                        return Err(Refused::Broken("the checks were closed".into()))
                    }
                    Err(_late) => {
                        self.busy_total.fetch_add(1, Ordering::Relaxed);
                        return Err(Refused::Busy);
                    }
                };
            let (users, name, memories) = (users.clone(), name.to_string(), self.memories.clone());
            tokio::task::spawn_blocking(move || {
                let _permit = permit;
                // A turn's memory (there is one per turn; a new one only if a check
                // panicked with one).
                let mut memory = memories
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .pop()
                    .unwrap_or_default();
                let user = users.verify_in(&name, &password, &mut memory).cloned();
                memories
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .push(memory);
                user
            })
            .await
        };
        match verified {
            Ok(Some(user)) => {
                self.throttle().succeeded(name, from);
                Ok(user)
            }
            Ok(None) => {
                self.throttle().failed(name, from, Instant::now());
                tokio::time::sleep(FAILED_LOGIN_DELAY).await;
                Err(Refused::Wrong)
            }
            Err(e) => Err(Refused::Broken(e.to_string())),
        }
    }

    /// Logins refused since the start (wrong, locked out and busy).
    pub fn refused_total(&self) -> u64 {
        self.throttle().refused_total + self.busy_total.load(Ordering::Relaxed)
    }

    /// Logins waiting for their turn or being checked now.
    pub fn in_check(&self) -> usize {
        self.in_check.load(Ordering::Relaxed)
    }
}

/// Counts a login in check for as long as it lives.
struct InCheck<'a>(&'a AtomicUsize);

impl<'a> InCheck<'a> {
    fn new(count: &'a AtomicUsize) -> InCheck<'a> {
        count.fetch_add(1, Ordering::Relaxed);
        InCheck(count)
    }
}

impl Drop for InCheck<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::security::users::Role;

    const A: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 0, 9));

    #[tokio::test(flavor = "multi_thread")]
    async fn a_guesser_is_locked_out_and_the_right_password_then_waits_too() {
        let mut users = Users::default();
        users
            .add("anna", Role::Operator, "anna-password-1")
            .unwrap();
        let users = Arc::new(users);
        let logins = Logins::default();
        for _ in 0..FREE_FAILURES {
            assert_eq!(
                logins.check(&users, "anna", "guess".into(), A).await,
                Err(Refused::Wrong)
            );
        }
        let locked = logins
            .check(&users, "anna", "anna-password-1".into(), A)
            .await
            .unwrap_err();
        assert!(matches!(locked, Refused::LockedOut(_)), "{locked:?}");
        assert_eq!(logins.refused_total(), u64::from(FREE_FAILURES) + 1);
        assert_eq!(logins.in_check(), 0);
    }

    #[tokio::test(flavor = "multi_thread")]
    async fn parallel_logins_take_turns_and_give_them_back() {
        let mut users = Users::default();
        users
            .add("anna", Role::Operator, "anna-password-1")
            .unwrap();
        let users = Arc::new(users);
        let logins = Arc::new(Logins::default());
        let mut tasks = Vec::new();
        for i in 0..8u8 {
            let (logins, users) = (logins.clone(), users.clone());
            let from = IpAddr::V4(std::net::Ipv4Addr::new(10, 0, 1, i));
            tasks.push(tokio::spawn(async move {
                logins
                    .check(&users, "anna", "anna-password-1".into(), from)
                    .await
            }));
        }
        for task in tasks {
            assert!(task.await.unwrap().is_ok());
        }
        assert_eq!(logins.checks.available_permits(), CHECKS_AT_ONCE);
        assert_eq!(logins.in_check(), 0);
        assert_eq!(logins.refused_total(), 0);
    }
}

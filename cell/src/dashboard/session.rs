//! The dashboard's login sessions: who holds which session cookie, until when.
//!
//! A session begins at a password login (a client certificate needs none: it logs in
//! with every request) and ends at the first of:
//! - logout;
//! - [`SessionLimits::idle`] without a request (default 15 min);
//! - [`SessionLimits::absolute`] after the login, however busy (default 8 h);
//! - its user's removal, or a change of the user's password or role in the users file
//!   (the session remembers what the user was, and is dropped when that changed);
//! - the dashboard's restart (sessions live in memory only: everybody logs in again).
//!
//! A session's token is 32 random bytes from the system's source, sent as an
//! `HttpOnly`, `SameSite=Strict` cookie (and `Secure` over HTTPS): a script on the page
//! cannot read it and another site's request never carries it. The store does no I/O;
//! the web server's handlers call it under a lock held for a map lookup.

use std::collections::HashMap;
use std::net::IpAddr;
use std::time::{Duration, Instant};

use crate::security::users::Role;

/// The session cookie's name.
pub const COOKIE: &str = "holarchy_session";

/// The most sessions held at once; the oldest is dropped for a new one beyond it.
const MOST_SESSIONS: usize = 10_000;

/// How long a session that ended by a limit is remembered, so that every later request
/// with its cookie is told why (the page's own request may be the first to notice).
const ENDED_KEPT: Duration = Duration::from_secs(3600);

/// How long a session lives.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SessionLimits {
    /// Without a request for this long, a session ends.
    pub idle: Duration,
    /// This long after its login, a session ends.
    pub absolute: Duration,
}

impl Default for SessionLimits {
    fn default() -> SessionLimits {
        SessionLimits {
            idle: Duration::from_secs(15 * 60),
            absolute: Duration::from_secs(8 * 3600),
        }
    }
}

/// Who a session is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Login {
    /// The user's name as the audit trail shows it: a user of the users file (`anna`),
    /// or a client certificate's identity (`cert:operator.anna`).
    pub who: String,
    /// What the user may do.
    pub role: Role,
    /// What the user was in the users file when logging in (the password hash and the
    /// role): a change there ends the session. Empty for a certificate.
    pub fingerprint: String,
}

/// One session.
#[derive(Debug, Clone)]
struct Session {
    /// Who.
    login: Login,
    /// From where it logged in.
    from: IpAddr,
    /// When it logged in.
    began: Instant,
    /// Its last request.
    seen: Instant,
}

/// Why a cookie does not name a live session.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ended {
    /// No session has that token (never, or logged out, or the dashboard restarted).
    Unknown,
    /// Idle too long.
    Idle,
    /// Past its absolute limit.
    Expired,
}

impl Ended {
    /// What the login page tells the user.
    pub fn explain(self) -> &'static str {
        match self {
            Ended::Unknown => "please log in",
            Ended::Idle => "your session ended after a time without use: please log in again",
            Ended::Expired => "your session reached its time limit: please log in again",
        }
    }
}

/// The sessions of one dashboard.
#[derive(Debug)]
pub struct Sessions {
    /// How long they live.
    limits: SessionLimits,
    /// By token.
    live: HashMap<String, Session>,
    /// Sessions that ended by a limit, by token: why, and when that was noticed.
    ended: HashMap<String, (Ended, Instant)>,
}

impl Sessions {
    pub fn new(limits: SessionLimits) -> Sessions {
        Sessions {
            limits,
            live: HashMap::new(),
            ended: HashMap::new(),
        }
    }

    /// The limits sessions live by.
    pub fn limits(&self) -> SessionLimits {
        self.limits
    }

    /// Opens a session for `login` from `from`: its token.
    pub fn open(&mut self, login: Login, from: IpAddr, now: Instant) -> String {
        self.forget_ended(now);
        if self.live.len() >= MOST_SESSIONS {
            if let Some(oldest) = self
                .live
                .iter()
                .min_by_key(|(_, s)| s.seen)
                .map(|(t, _)| t.clone())
            {
                self.live.remove(&oldest);
            }
        }
        let token = new_token();
        self.live.insert(
            token.clone(),
            Session {
                login,
                from,
                began: now,
                seen: now,
            },
        );
        token
    }

    /// The session of `token` at `now`, marked as used; an ended one is forgotten.
    /// A session that ended by a limit keeps saying so to every later request with its
    /// cookie (for [`ENDED_KEPT`]).
    pub fn check(&mut self, token: &str, now: Instant) -> Result<Login, Ended> {
        let Some(session) = self.live.get_mut(token) else {
            return Err(self
                .ended
                .get(token)
                .filter(|(_, at)| now.duration_since(*at) < ENDED_KEPT)
                .map_or(Ended::Unknown, |(why, _)| *why));
        };
        let ended = ended_by(&self.limits, session, now);
        if let Some(ended) = ended {
            self.live.remove(token);
            self.remember_ended(token.to_string(), ended, now);
            return Err(ended);
        }
        session.seen = now;
        Ok(session.login.clone())
    }

    /// Remembers why the session of `token` ended, forgetting the oldest such memories
    /// past [`ENDED_KEPT`] or [`MOST_SESSIONS`].
    fn remember_ended(&mut self, token: String, why: Ended, now: Instant) {
        self.ended
            .retain(|_, (_, at)| now.duration_since(*at) < ENDED_KEPT);
        if self.ended.len() >= MOST_SESSIONS {
            if let Some(oldest) = self
                .ended
                .iter()
                .min_by_key(|(_, (_, at))| *at)
                .map(|(t, _)| t.clone())
            {
                self.ended.remove(&oldest);
            }
        }
        self.ended.insert(token, (why, now));
    }

    /// Who holds the session of `token`, if it is still live at `now`, without counting
    /// this as its use (a page's open stream of updates does not keep a session alive).
    pub fn peek(&self, token: &str, now: Instant) -> Option<Login> {
        self.live
            .get(token)
            .filter(|s| self.live_at(s, now))
            .map(|s| s.login.clone())
    }

    fn live_at(&self, session: &Session, now: Instant) -> bool {
        now.duration_since(session.began) < self.limits.absolute
            && now.duration_since(session.seen) < self.limits.idle
    }

    /// Ends the session of `token` (logout): who it was.
    pub fn close(&mut self, token: &str) -> Option<Login> {
        self.live.remove(token).map(|s| s.login)
    }

    /// Ends every session of `who` (the user was removed, or changed).
    pub fn close_all_of(&mut self, who: &str) -> usize {
        let before = self.live.len();
        self.live.retain(|_, s| s.login.who != who);
        before - self.live.len()
    }

    /// When the session of `token` ends at the latest if unused (for the page), and
    /// where it logged in from.
    pub fn ends(&self, token: &str) -> Option<(Instant, IpAddr)> {
        let s = self.live.get(token)?;
        let idle_end = s.seen + self.limits.idle;
        let absolute_end = s.began + self.limits.absolute;
        Some((idle_end.min(absolute_end), s.from))
    }

    /// How many sessions are live at `now`.
    pub fn count(&self, now: Instant) -> usize {
        self.live.values().filter(|s| self.live_at(s, now)).count()
    }

    fn forget_ended(&mut self, now: Instant) {
        let limits = self.limits;
        let ended: Vec<(String, Ended)> = self
            .live
            .iter()
            .filter_map(|(token, s)| ended_by(&limits, s, now).map(|why| (token.clone(), why)))
            .collect();
        for (token, why) in ended {
            self.live.remove(&token);
            self.remember_ended(token, why, now);
        }
    }
}

/// Whether `session` has ended by a limit at `now`, and which.
fn ended_by(limits: &SessionLimits, session: &Session, now: Instant) -> Option<Ended> {
    if now.duration_since(session.began) >= limits.absolute {
        Some(Ended::Expired)
    } else if now.duration_since(session.seen) >= limits.idle {
        Some(Ended::Idle)
    } else {
        None
    }
}

/// 32 random bytes, as hex.
fn new_token() -> String {
    use ring::rand::SecureRandom;
    let mut bytes = [0u8; 32];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .expect("the system's random source works");
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The value of the session cookie in a `Cookie` header, if any.
pub fn token_in(cookie_header: &str) -> Option<&str> {
    cookie_header
        .split(';')
        .filter_map(|pair| pair.trim().split_once('='))
        .find(|(name, _)| *name == COOKIE)
        .map(|(_, value)| value.trim())
        .filter(|v| !v.is_empty())
}

/// The `Set-Cookie` value that hands out `token` (`secure`: over HTTPS).
pub fn set_cookie(token: &str, secure: bool) -> String {
    format!(
        "{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict{}",
        if secure { "; Secure" } else { "" }
    )
}

/// The `Set-Cookie` value that removes the cookie.
pub fn clear_cookie(secure: bool) -> String {
    format!(
        "{COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0{}",
        if secure { "; Secure" } else { "" }
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn anna() -> Login {
        Login {
            who: "anna".into(),
            role: Role::Operator,
            fingerprint: "h1".into(),
        }
    }

    const HERE: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);

    #[test]
    fn a_session_ends_when_idle_or_at_its_absolute_limit() {
        let limits = SessionLimits {
            idle: Duration::from_secs(60),
            absolute: Duration::from_secs(300),
        };
        let mut sessions = Sessions::new(limits);
        let t0 = Instant::now();
        let token = sessions.open(anna(), HERE, t0);
        assert_eq!(token.len(), 64);
        // Used every 50 s: alive until the absolute limit.
        let mut now = t0;
        for _ in 0..5 {
            now += Duration::from_secs(50);
            assert_eq!(sessions.check(&token, now), Ok(anna()));
        }
        now += Duration::from_secs(50);
        assert_eq!(sessions.check(&token, now), Err(Ended::Expired));
        // Every later request with its cookie is told why, not just the first.
        assert_eq!(sessions.check(&token, now), Err(Ended::Expired));
        assert_eq!(
            sessions.check(&token, now + ENDED_KEPT / 2),
            Err(Ended::Expired)
        );
        // Idle for a minute: gone.
        let token = sessions.open(anna(), HERE, t0);
        assert_eq!(
            sessions.check(&token, t0 + Duration::from_secs(60)),
            Err(Ended::Idle)
        );
        assert_eq!(
            sessions.check(&token, t0 + Duration::from_secs(61)),
            Err(Ended::Idle)
        );
        // Swept when another logs in: still told why.
        let quiet = sessions.open(anna(), HERE, t0);
        let later = t0 + Duration::from_secs(70);
        sessions.open(anna(), HERE, later);
        assert_eq!(sessions.check(&quiet, later), Err(Ended::Idle));
        // Forgotten after ENDED_KEPT.
        let much_later = later + ENDED_KEPT + Duration::from_secs(1);
        sessions.open(anna(), HERE, much_later);
        assert_eq!(sessions.check(&quiet, much_later), Err(Ended::Unknown));
    }

    #[test]
    fn logout_and_a_changed_user_end_sessions() {
        let mut sessions = Sessions::new(SessionLimits::default());
        let now = Instant::now();
        let one = sessions.open(anna(), HERE, now);
        let two = sessions.open(anna(), HERE, now);
        assert_ne!(one, two);
        assert_eq!(sessions.close(&one).map(|l| l.who), Some("anna".into()));
        assert_eq!(sessions.check(&one, now), Err(Ended::Unknown));
        assert_eq!(sessions.close_all_of("anna"), 1);
        assert_eq!(sessions.check(&two, now), Err(Ended::Unknown));
    }

    #[test]
    fn cookies() {
        assert_eq!(token_in("a=1; holarchy_session=abc ; b=2"), Some("abc"));
        assert_eq!(token_in("holarchy_session="), None);
        assert_eq!(token_in("other=1"), None);
        let set = set_cookie("abc", true);
        for part in ["HttpOnly", "SameSite=Strict", "Secure", "Path=/"] {
            assert!(set.contains(part), "{set}");
        }
        assert!(!set_cookie("abc", false).contains("Secure"));
    }
}

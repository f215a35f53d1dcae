//! Who is asking: the dashboard's logins.
//!
//! Every request but the login page's own passes [`authenticate`], which finds who
//! sends it and hands the handlers a [`Who`], or turns it away (the page to `/login`,
//! an API call with 401). Who a request is, in order:
//! 1. a dashboard without login (no users file, loopback only): everybody is `local`,
//!    an operator or an observer as the dashboard was started;
//! 2. the holder of a live session cookie ([`super::session`]), whose user still is
//!    what it was at login in the users file;
//! 3. over HTTPS in a secure cell, the holder of a client certificate of the cell CA
//!    with an `operator.*` or `observer.*` identity (`cert:operator.anna`), for each
//!    request; its first request after a quiet spell is recorded as a login.
//!
//! | role | may |
//! |---|---|
//! | observer | read everything (page, API, events, metrics) |
//! | operator | also submit and cancel orders, acknowledge alarms, command resources (PackML), read the audit trail |
//! | admin | also manage the users |
//!
//! A user's role works only as far as the dashboard's own identity in the cell goes:
//! a dashboard that joined as an observer lets nobody operate.

use std::net::{IpAddr, SocketAddr};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Redirect, Response};
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};
use tracing::{error, info, warn};

use super::listener::Peer;
use super::session::{self, Ended, Login, SessionLimits, Sessions};
use crate::security::audit::{AuditAction, AuditDoor, AuditOutcome, AuditRecord, AuditTrail};
use crate::security::logins::{Logins, Refused};
use crate::security::users::{fingerprint, CurrentUsers, Role, Users};

/// How the dashboard lets people in.
#[derive(Debug, Clone)]
pub struct GateConfig {
    /// The users file (`None`: no passwords; then only certificates, or nobody logs in).
    pub users: Option<PathBuf>,
    /// Whether client certificates of the cell CA log in (a secure cell over HTTPS).
    pub certificates: bool,
    /// How long sessions live.
    pub limits: SessionLimits,
    /// Without login (a loopback dashboard without users file), the role everybody
    /// has; `None`: everybody logs in.
    pub without_login: Option<Role>,
}

/// Who sends a request, for the handlers.
#[derive(Debug, Clone)]
pub struct Who {
    /// The name the audit trail gives: `anna`, `cert:operator.anna`, `local`.
    pub who: String,
    /// What they may do.
    pub role: Role,
    /// Their address.
    pub from: SocketAddr,
    /// Whether the request came over HTTPS.
    pub tls: bool,
    /// Their session's token (a password login).
    pub token: Option<String>,
}

/// The dashboard's door: sessions, failed logins, the users file and the audit trail.
#[derive(Debug)]
pub struct Gate {
    /// How it lets people in.
    pub config: GateConfig,
    /// The live sessions.
    sessions: Mutex<Sessions>,
    /// The password logins: failures, lock-outs, the checks' bound.
    logins: Logins,
    /// The users file, re-read when it changes (`cell users` may change it any time).
    users: CurrentUsers,
    /// When each certificate identity was last seen (its login is recorded after a
    /// quiet spell of the sessions' idle limit).
    certificates_seen: Mutex<std::collections::HashMap<String, Instant>>,
    /// Where every action is recorded (`None`: this dashboard keeps no trail).
    pub audit: Option<AuditTrail>,
}

fn lock<T>(mutex: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    mutex
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

impl Gate {
    pub fn new(config: GateConfig, audit: Option<AuditTrail>) -> Gate {
        Gate {
            sessions: Mutex::new(Sessions::new(config.limits)),
            logins: Logins::default(),
            users: match &config.users {
                Some(path) => CurrentUsers::file(path.clone()),
                None => CurrentUsers::fixed(Users::default()),
            },
            certificates_seen: Mutex::new(Default::default()),
            config,
            audit,
        }
    }

    /// Whether people log in at all.
    pub fn login_required(&self) -> bool {
        self.config.without_login.is_none()
    }

    /// Records `record` in the trail (as done through the dashboard), if the dashboard
    /// keeps one.
    pub fn record(&self, record: AuditRecord) {
        if let Some(trail) = &self.audit {
            trail.record(&record.through(AuditDoor::Dashboard));
        }
    }

    /// Logins refused since the start.
    pub fn logins_refused(&self) -> u64 {
        self.logins.refused_total()
    }

    /// Live sessions.
    pub fn sessions_live(&self) -> usize {
        lock(&self.sessions).count(Instant::now())
    }

    /// The users file's users, read again if it changed since.
    pub fn users(&self) -> Arc<Users> {
        self.users.get()
    }

    /// Whether `who` may still be served an open stream: a session still live (not
    /// marked as used) whose user is still what it was at login (`cell users` may have
    /// changed it), or a login that needs no session.
    pub fn still_in(&self, who: &Who) -> bool {
        let Some(token) = &who.token else {
            return true;
        };
        let login = lock(&self.sessions).peek(token, Instant::now());
        match login {
            Some(login) if self.still_the_same(&login) => true,
            Some(login) => {
                self.end_sessions_of(&login.who);
                false
            }
            None => false,
        }
    }

    /// Ends every session of `who` (the user changed or went).
    pub fn end_sessions_of(&self, who: &str) {
        let ended = lock(&self.sessions).close_all_of(who);
        if ended > 0 {
            info!(
                user = who,
                sessions = ended,
                "sessions ended: the user changed"
            );
        }
    }

    /// Who a request is, or why it is not let in.
    fn identify(&self, peer: &Peer, headers: &HeaderMap) -> Result<Who, Ended> {
        let who = |name: String, role: Role, token: Option<String>| Who {
            who: name,
            role,
            from: peer.address,
            tls: peer.tls,
            token,
        };
        if let Some(role) = self.config.without_login {
            return Ok(who("local".into(), role, None));
        }
        let token = headers
            .get_all(header::COOKIE)
            .iter()
            .filter_map(|v| v.to_str().ok())
            .find_map(session::token_in)
            .map(str::to_string);
        let mut ended = Ended::Unknown;
        if let Some(token) = token {
            let checked = lock(&self.sessions).check(&token, Instant::now());
            match checked {
                Ok(login) if self.still_the_same(&login) => {
                    return Ok(who(login.who, login.role, Some(token)));
                }
                Ok(login) => self.end_sessions_of(&login.who),
                Err(why) => ended = why,
            }
        }
        if let Some(identity) = self.certificate_login(peer) {
            return Ok(who(identity.0, identity.1, None));
        }
        Err(ended)
    }

    /// Whether the user of `login` is still in the users file as at login.
    fn still_the_same(&self, login: &Login) -> bool {
        if login.fingerprint.is_empty() {
            return true;
        }
        self.users()
            .get(&login.who)
            .is_some_and(|user| fingerprint(user) == login.fingerprint)
    }

    /// The client certificate's login, if the request brings one that logs in.
    fn certificate_login(&self, peer: &Peer) -> Option<(String, Role)> {
        if !self.config.certificates || !peer.tls {
            return None;
        }
        let identity = peer.certificate_identity.as_deref()?;
        let role = match crate::security::access::parse_identity(identity).ok()?.0 {
            crate::security::access::Role::Operator => Role::Operator,
            crate::security::access::Role::Observer => Role::Observer,
            _ => return None,
        };
        let who = format!("cert:{identity}");
        let now = Instant::now();
        let quiet = {
            let mut seen = lock(&self.certificates_seen);
            let last = seen.insert(identity.to_string(), now);
            last.is_none_or(|last| now.duration_since(last) >= self.config.limits.idle)
        };
        if quiet {
            info!(user = %who, from = %peer.address, "logged in with a client certificate");
            self.record(
                AuditRecord::now(
                    &who,
                    &peer.address.to_string(),
                    AuditAction::Login,
                    AuditOutcome::Done,
                )
                .with(serde_json::json!({ "with": "certificate", "role": role.as_str() })),
            );
        }
        Some((who, role))
    }
}

/// The paths open without login: the login page and the login itself.
fn open_path(path: &str) -> bool {
    matches!(path, "/login" | "/api/login")
}

/// The middleware: a [`Who`] for the handlers, or the way to the login page.
pub async fn authenticate(
    State(gate): State<Arc<Gate>>,
    ConnectInfo(peer): ConnectInfo<Peer>,
    mut request: Request,
    next: Next,
) -> Response {
    let path = request.uri().path().to_string();
    match gate.identify(&peer, request.headers()) {
        Ok(who) => {
            request.extensions_mut().insert(who);
            next.run(request).await
        }
        Err(_) if open_path(&path) => next.run(request).await,
        Err(ended) if path.starts_with("/api/") || path == "/events" || path == "/metrics" => (
            StatusCode::UNAUTHORIZED,
            Json(serde_json::json!({ "error": ended.explain(), "login": "/login" })),
        )
            .into_response(),
        Err(ended) => Redirect::to(&format!("/login?why={}", ended_code(ended))).into_response(),
    }
}

fn ended_code(ended: Ended) -> &'static str {
    match ended {
        Ended::Unknown => "login",
        Ended::Idle => "idle",
        Ended::Expired => "expired",
    }
}

/// The login page (no script of another origin, no asset).
pub const LOGIN_PAGE: &str = include_str!("login.html");

/// `GET /login`.
pub async fn login_page() -> axum::response::Html<&'static str> {
    axum::response::Html(LOGIN_PAGE)
}

/// `POST /api/login`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Credentials {
    pub name: String,
    pub password: String,
}

/// Who is logged in, for the page.
#[derive(Debug, Serialize)]
pub struct Me {
    /// Who.
    pub who: String,
    /// Their role.
    pub role: Role,
    /// Whether this dashboard has people log in (false: loopback without login).
    pub login_required: bool,
    /// Whether they may submit, cancel, acknowledge and command.
    pub may_operate: bool,
    /// Whether they may manage users.
    pub may_manage_users: bool,
    /// Whether they may read the audit trail.
    pub may_read_audit: bool,
    /// Whether the dashboard keeps an audit trail.
    pub audit: bool,
    /// Whether the page came over HTTPS.
    pub tls: bool,
    /// Seconds until the session ends if unused (a password login).
    pub session_ends_in_s: Option<u64>,
    /// Whether the user logged in with a certificate (logout does not end it).
    pub certificate: bool,
}

/// `POST /api/login`: a session for a right name and password.
pub async fn login(
    Extension(gate): Extension<Arc<Gate>>,
    ConnectInfo(peer): ConnectInfo<Peer>,
    Json(credentials): Json<Credentials>,
) -> Response {
    let from = peer.address.to_string();
    let ip: IpAddr = peer.address.ip();
    let refuse = |status: StatusCode, why: String| {
        (status, Json(serde_json::json!({ "error": why }))).into_response()
    };
    if gate.config.users.is_none() {
        return refuse(
            StatusCode::NOT_FOUND,
            "this dashboard has no users file: there is no password to log in with".into(),
        );
    }
    let name = credentials.name.trim().to_string();
    let failed = |why: String| {
        warn!(user = %name, %from, reason = %why, "login refused");
        gate.record(
            AuditRecord::now(
                &name,
                &from,
                AuditAction::LoginFailed,
                AuditOutcome::Refused(why),
            )
            .on(name.clone()),
        );
    };
    let users = gate.users();
    let user = match gate
        .logins
        .check(&users, &name, credentials.password, ip)
        .await
    {
        Ok(user) => user,
        Err(refusal) => {
            let why = refusal.why();
            failed(why.clone());
            return match refusal {
                Refused::LockedOut(locked) => {
                    let mut response = refuse(StatusCode::TOO_MANY_REQUESTS, why);
                    response.headers_mut().insert(
                        header::RETRY_AFTER,
                        locked.retry_after.as_secs().max(1).into(),
                    );
                    response
                }
                Refused::Wrong => refuse(StatusCode::UNAUTHORIZED, why),
                Refused::Busy => {
                    let mut response = refuse(StatusCode::SERVICE_UNAVAILABLE, why);
                    response
                        .headers_mut()
                        .insert(header::RETRY_AFTER, 1u64.into());
                    response
                }
                Refused::Broken(e) => {
                    error!(error = %e, "the password check ended abnormally");
                    refuse(StatusCode::INTERNAL_SERVER_ERROR, why)
                }
            };
        }
    };
    let login = Login {
        who: user.name.clone(),
        role: user.role,
        fingerprint: fingerprint(&user),
    };
    let token = lock(&gate.sessions).open(login, ip, Instant::now());
    info!(user = %user.name, role = user.role.as_str(), %from, "logged in");
    gate.record(
        AuditRecord::now(&user.name, &from, AuditAction::Login, AuditOutcome::Done)
            .with(serde_json::json!({ "with": "password", "role": user.role.as_str() })),
    );
    let mut response =
        Json(serde_json::json!({ "who": user.name, "role": user.role })).into_response();
    match session::set_cookie(&token, peer.tls).parse() {
        Ok(cookie) => {
            response.headers_mut().insert(header::SET_COOKIE, cookie);
        }
        Err(e) => error!(error = %e, "cannot set the session cookie"),
    }
    response
}

/// `POST /api/logout`: ends the session.
pub async fn logout(
    Extension(gate): Extension<Arc<Gate>>,
    Extension(who): Extension<Who>,
) -> Response {
    if let Some(token) = &who.token {
        if let Some(login) = lock(&gate.sessions).close(token) {
            info!(user = %login.who, from = %who.from, "logged out");
            gate.record(AuditRecord::now(
                &login.who,
                &who.from.to_string(),
                AuditAction::Logout,
                AuditOutcome::Done,
            ));
        }
    }
    let mut response = StatusCode::NO_CONTENT.into_response();
    if let Ok(cookie) = session::clear_cookie(who.tls).parse() {
        response.headers_mut().insert(header::SET_COOKIE, cookie);
    }
    response
}

/// `GET /api/me`: who is logged in and what they may do (`operating`: whether the
/// dashboard's own identity may operate the cell).
pub fn me(gate: &Gate, who: &Who, operating: bool) -> Me {
    let ends = who
        .token
        .as_ref()
        .and_then(|t| lock(&gate.sessions).ends(t))
        .map(|(at, _)| at.saturating_duration_since(Instant::now()).as_secs());
    Me {
        who: who.who.clone(),
        role: who.role,
        login_required: gate.login_required(),
        may_operate: operating && who.role.may_operate(),
        may_manage_users: gate.config.users.is_some() && who.role.may_manage_users(),
        may_read_audit: gate.audit.is_some() && who.role.may_operate(),
        audit: gate.audit.is_some(),
        tls: who.tls,
        session_ends_in_s: ends,
        certificate: who.who.starts_with("cert:"),
    }
}

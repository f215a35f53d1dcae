//! Who may use `cell opcua`: the server's [`AuthManager`] on the cell's users file
//! ([`crate::security::users`], docs/opcua.md "Users"), and the operator/observer split.
//!
//! An observer may browse, read and subscribe; an operator or an admin may also call
//! methods. The password never reaches the server in clear on the wire: the secure
//! endpoints encrypt it, and async-opcua hands it to us decrypted. Checking it is the
//! cell's one login policy ([`crate::security::logins`]): slowed, locked out per name and per
//! address, never more than a few checks at once, as on the dashboard.
//!
//! The users file is read again when it changes ([`CurrentUsers`]): a user added with
//! `cell users` logs in at once. A session's token carries its user's fingerprint
//! (`user:anna#<fingerprint>`): once the user is removed, demoted or given a new
//! password, the session may do nothing more, and [`CellAuth::ended_sessions`] closes
//! it (the server checks every [`USERS_CHECKED_EVERY`]).
//!
//! Every login, failed login and method call goes to the audit trail ([`CellAuth::record`]).

use std::net::{IpAddr, Ipv4Addr, SocketAddr};
use std::time::Duration;

use async_trait::async_trait;
use opcua::crypto::{SecurityPolicy, Thumbprint};
use opcua::types::{
    ByteString, Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType,
};
use opcua_server::address_space::AccessLevel;
use opcua_server::authenticator::{user_pass_security_policy_id, AuthManager, Password, UserToken};
use opcua_server::ServerEndpoint;
use tracing::{info, warn};

use crate::security::audit::{AuditAction, AuditDoor, AuditOutcome, AuditRecord, AuditTrail};
use crate::security::logins::{Logins, Refused};
use crate::security::users::{fingerprint, CurrentUsers};

/// How often the server looks at the users file for users whose sessions must end.
pub const USERS_CHECKED_EVERY: Duration = Duration::from_millis(500);

/// What a session may do in the OPC UA server.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Browse, read, subscribe and call methods (an operator or an admin of the users
    /// file, or an anonymous session of a plain cell).
    Operator,
    /// Browse, read and subscribe; every method call is refused (BadUserAccessDenied).
    Observer,
}

impl From<crate::security::users::Role> for Role {
    fn from(role: crate::security::users::Role) -> Role {
        if role.may_operate() {
            Role::Operator
        } else {
            Role::Observer
        }
    }
}

/// The prefix of a user-name session's token; then the user's name, `#` and the
/// user's fingerprint at login.
const USER_PREFIX: &str = "user:";

/// The server's authenticator: anonymous (plain cell only, as an operator) and user
/// names with passwords (secure cell).
#[derive(Debug)]
pub struct CellAuth {
    /// Whether anonymous sessions are allowed (on None endpoints only): a plain cell.
    pub anonymous: bool,
    /// The users of the users file, as it changes (none in a plain cell).
    pub users: CurrentUsers,
    /// The password logins: failures, lock-outs, the checks' bound.
    pub logins: Logins,
    /// Where logins and method calls are recorded (`None`: a plain cell keeps no trail).
    pub audit: Option<AuditTrail>,
}

/// A user-name token's name and fingerprint.
fn token_user(token: &UserToken) -> Option<(&str, &str)> {
    token.0.strip_prefix(USER_PREFIX)?.split_once('#')
}

/// The address to count a login against when the server does not know the client's
/// (never, over TCP).
const UNKNOWN_ADDRESS: IpAddr = IpAddr::V4(Ipv4Addr::UNSPECIFIED);

/// A client address as the audit trail writes it.
fn shown(peer: Option<SocketAddr>) -> String {
    peer.map(|a| a.to_string())
        .unwrap_or_else(|| "unknown".into())
}

impl CellAuth {
    /// A plain cell's: anonymous operators, no users, no trail.
    pub fn anonymous() -> CellAuth {
        CellAuth {
            anonymous: true,
            users: CurrentUsers::fixed(Default::default()),
            logins: Logins::default(),
            audit: None,
        }
    }

    /// The role of a session's user now (`None`: no one we know, or a user who changed
    /// since the session logged in).
    pub fn role_of(&self, token: &UserToken) -> Option<Role> {
        if token.is_anonymous() {
            return self.anonymous.then_some(Role::Operator);
        }
        let (name, at_login) = token_user(token)?;
        let users = self.users.get();
        let user = users.get(name)?;
        (fingerprint(user) == at_login).then(|| user.role.into())
    }

    /// Who a session is, for a PackML request's `by` and the log: `opcua:anna`,
    /// `opcua:anonymous`.
    pub fn who(token: &UserToken) -> String {
        match token_user(token) {
            Some((name, _)) => format!("opcua:{name}"),
            None => "opcua:anonymous".to_string(),
        }
    }

    /// The user a session is, as the audit trail names people: `anna`, `anonymous`.
    pub fn user_name(token: &UserToken) -> &str {
        match token_user(token) {
            Some((name, _)) => name,
            None => "anonymous",
        }
    }

    /// Records `record` (as done through the OPC UA server) in the trail, if there is one.
    pub fn record(&self, record: AuditRecord) {
        if let Some(trail) = &self.audit {
            trail.record(&record.through(AuditDoor::Opcua));
        }
    }

    /// Whether a session of `token` must end: its user was removed or changed.
    pub fn ended(&self, token: &UserToken) -> bool {
        !token.is_anonymous() && self.role_of(token).is_none()
    }

    /// A refused login: logged, recorded, answered with `status`.
    fn refuse(
        &self,
        who: &str,
        peer: Option<SocketAddr>,
        why: String,
        status: StatusCode,
    ) -> Error {
        warn!(user = %who, client = %shown(peer), reason = %why, %status, "OPC UA login refused");
        self.record(
            AuditRecord::now(
                who,
                &shown(peer),
                AuditAction::LoginFailed,
                AuditOutcome::Refused(why.clone()),
            )
            .on(who),
        );
        Error::new(status, why)
    }
}

#[async_trait]
impl AuthManager for CellAuth {
    async fn authenticate_anonymous_token_from(
        &self,
        endpoint: &ServerEndpoint,
        peer: Option<SocketAddr>,
    ) -> Result<(), Error> {
        if self.anonymous && endpoint.security_policy() == SecurityPolicy::None {
            Ok(())
        } else {
            Err(self.refuse(
                "anonymous",
                peer,
                "anonymous sessions are not allowed: this cell's server wants a user name and password".into(),
                StatusCode::BadIdentityTokenRejected,
            ))
        }
    }

    async fn authenticate_username_identity_token_from(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
        peer: Option<SocketAddr>,
    ) -> Result<UserToken, Error> {
        let users = self.users.get();
        let from = peer.map(|a| a.ip()).unwrap_or(UNKNOWN_ADDRESS);
        match self
            .logins
            .check(&users, username, password.get().to_string(), from)
            .await
        {
            Ok(user) => {
                info!(user = %user.name, role = %user.role, client = %shown(peer), "OPC UA user logged in");
                self.record(
                    AuditRecord::now(
                        &user.name,
                        &shown(peer),
                        AuditAction::Login,
                        AuditOutcome::Done,
                    )
                    .with(serde_json::json!({ "with": "password", "role": user.role.as_str() })),
                );
                Ok(UserToken(format!(
                    "{USER_PREFIX}{}#{}",
                    user.name,
                    fingerprint(&user)
                )))
            }
            Err(refused) => {
                let status = match refused {
                    Refused::Busy => StatusCode::BadTooManyOperations,
                    Refused::Broken(_) => StatusCode::BadInternalError,
                    Refused::LockedOut(_) | Refused::Wrong => StatusCode::BadUserAccessDenied,
                };
                Err(self.refuse(username, peer, refused.why(), status))
            }
        }
    }

    async fn authenticate_x509_identity_token_from(
        &self,
        _endpoint: &ServerEndpoint,
        _signing_thumbprint: &Thumbprint,
        peer: Option<SocketAddr>,
    ) -> Result<UserToken, Error> {
        Err(self.refuse(
            "x509",
            peer,
            "X509 user tokens are not accepted: log in with a user name and password".into(),
            StatusCode::BadIdentityTokenRejected,
        ))
    }

    async fn authenticate_issued_identity_token_from(
        &self,
        _endpoint: &ServerEndpoint,
        _token: &ByteString,
        peer: Option<SocketAddr>,
    ) -> Result<UserToken, Error> {
        Err(self.refuse(
            "issued",
            peer,
            "issued user tokens are not accepted: log in with a user name and password".into(),
            StatusCode::BadIdentityTokenRejected,
        ))
    }

    fn user_token_policies(&self, endpoint: &ServerEndpoint) -> Vec<UserTokenPolicy> {
        let mut policies = Vec::new();
        if self.anonymous && endpoint.security_policy() == SecurityPolicy::None {
            policies.push(UserTokenPolicy {
                // async-opcua's POLICY_ID_ANONYMOUS.
                policy_id: "anonymous".into(),
                token_type: UserTokenType::Anonymous,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        if self.users.path().is_some() {
            policies.push(UserTokenPolicy {
                policy_id: user_pass_security_policy_id(endpoint),
                token_type: UserTokenType::UserName,
                issued_token_type: UAString::null(),
                issuer_endpoint_url: UAString::null(),
                security_policy_uri: UAString::null(),
            });
        }
        policies
    }

    /// Every user we know may reach a method: the call itself refuses an observer
    /// (BadUserAccessDenied) and logs it (`methods.rs`). async-opcua asks this both for
    /// a call and for a read of the UserExecutable attribute, so refusing here would
    /// leave refused calls unlogged, or log every attribute read of an observer's
    /// client. UserExecutable therefore reads true for observers too.
    fn is_user_executable(&self, token: &UserToken, _method_id: &NodeId) -> bool {
        self.role_of(token).is_some()
    }

    fn effective_user_access_level(
        &self,
        token: &UserToken,
        user_access_level: AccessLevel,
        _node_id: &NodeId,
    ) -> AccessLevel {
        match self.role_of(token) {
            Some(_) => user_access_level & AccessLevel::CURRENT_READ,
            None => AccessLevel::empty(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::security::users::{Role as UserRole, Users};

    #[test]
    fn observers_watch_and_operators_and_admins_operate() {
        assert_eq!(Role::from(UserRole::Observer), Role::Observer);
        assert_eq!(Role::from(UserRole::Operator), Role::Operator);
        assert_eq!(Role::from(UserRole::Admin), Role::Operator);
    }

    #[test]
    fn a_session_is_its_users_role() {
        let mut users = Users::default();
        users.add("anna", UserRole::Admin, "anna-password").unwrap();
        users
            .add("wall", UserRole::Observer, "wall-password")
            .unwrap();
        let token = |name: &str| {
            UserToken(format!(
                "user:{name}#{}",
                fingerprint(users.get(name).unwrap())
            ))
        };
        let (anna, wall) = (token("anna"), token("wall"));
        let auth = CellAuth {
            anonymous: false,
            users: CurrentUsers::fixed(users),
            logins: Logins::default(),
            audit: None,
        };
        assert_eq!(auth.role_of(&anna), Some(Role::Operator));
        assert_eq!(auth.role_of(&wall), Some(Role::Observer));
        assert_eq!(auth.role_of(&UserToken("user:bert#0".into())), None);
        // A token of anna before a change of her password or role: no role any more.
        assert_eq!(auth.role_of(&UserToken("user:anna#0".into())), None);
        assert!(auth.ended(&UserToken("user:anna#0".into())));
        assert!(!auth.ended(&anna));
        assert_eq!(CellAuth::who(&anna), "opcua:anna");
    }
}

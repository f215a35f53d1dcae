//! Who may use `cell opcua`: the server's [`AuthManager`] on the cell's users file
//! ([`crate::users`], docs/opcua.md "Users"), and the operator/observer split.
//!
//! An observer may browse, read and subscribe; an operator or an admin may also call
//! methods. The password never reaches the server in clear on the wire: the secure
//! endpoints encrypt it, and async-opcua hands it to us decrypted. Verifying it (argon2id,
//! tens of ms of CPU) runs on tokio's blocking threads, never on the server's.

use std::sync::Arc;

use async_trait::async_trait;
use opcua::crypto::SecurityPolicy;
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};
use opcua_server::address_space::AccessLevel;
use opcua_server::authenticator::{user_pass_security_policy_id, AuthManager, Password, UserToken};
use opcua_server::ServerEndpoint;
use tracing::{info, warn};

use crate::users::Users;

/// What a session may do in the OPC UA server.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// Browse, read, subscribe and call methods (an operator or an admin of the users
    /// file, or an anonymous session of a plain cell).
    Operator,
    /// Browse, read and subscribe; every method call is refused (BadUserAccessDenied).
    Observer,
}

impl From<crate::users::Role> for Role {
    fn from(role: crate::users::Role) -> Role {
        if role.may_operate() {
            Role::Operator
        } else {
            Role::Observer
        }
    }
}

/// The prefix of a user-name session's token; the rest is the user's name.
const USER_PREFIX: &str = "user:";

/// The server's authenticator: anonymous (plain cell only, as an operator) and user
/// names with passwords (secure cell).
#[derive(Debug)]
pub struct CellAuth {
    /// Whether anonymous sessions are allowed (on None endpoints only): a plain cell.
    pub anonymous: bool,
    /// The users of the users file (empty in a plain cell).
    pub users: Arc<Users>,
}

impl CellAuth {
    /// The role of a session's user (`None`: no one we know).
    pub fn role_of(&self, token: &UserToken) -> Option<Role> {
        if token.is_anonymous() {
            return self.anonymous.then_some(Role::Operator);
        }
        let name = token.0.strip_prefix(USER_PREFIX)?;
        self.users.get(name).map(|u| u.role.into())
    }

    /// Who a session is, for a PackML request's `by` and the log: `opcua:anna`,
    /// `opcua:anonymous`.
    pub fn who(token: &UserToken) -> String {
        match token.0.strip_prefix(USER_PREFIX) {
            Some(name) => format!("opcua:{name}"),
            None => "opcua:anonymous".to_string(),
        }
    }
}

#[async_trait]
impl AuthManager for CellAuth {
    async fn authenticate_anonymous_token(&self, endpoint: &ServerEndpoint) -> Result<(), Error> {
        if self.anonymous && endpoint.security_policy() == SecurityPolicy::None {
            Ok(())
        } else {
            warn!(endpoint = %endpoint.path, "anonymous session refused: this cell's server wants a user name and password");
            Err(Error::new(
                StatusCode::BadIdentityTokenRejected,
                "anonymous sessions are not allowed",
            ))
        }
    }

    async fn authenticate_username_identity_token(
        &self,
        _endpoint: &ServerEndpoint,
        username: &str,
        password: &Password,
    ) -> Result<UserToken, Error> {
        let users = self.users.clone();
        let (name, password) = (username.to_string(), password.get().to_string());
        let role =
            tokio::task::spawn_blocking(move || users.verify(&name, &password).map(|u| u.role))
                .await
                .map_err(|e| {
                    Error::new(
                        StatusCode::BadInternalError,
                        format!("the password check failed: {e}"),
                    )
                })?;
        match role {
            Some(role) => {
                info!(user = username, role = %role, "OPC UA user authenticated");
                Ok(UserToken(format!("{USER_PREFIX}{username}")))
            }
            None if self.users.get(username).is_some() => {
                warn!(
                    user = username,
                    "OPC UA login refused: wrong password (BadUserAccessDenied)"
                );
                Err(Error::new(
                    StatusCode::BadUserAccessDenied,
                    "wrong password",
                ))
            }
            None => {
                warn!(
                    user = username,
                    "OPC UA login refused: no such user in the users file (BadUserAccessDenied)"
                );
                Err(Error::new(StatusCode::BadUserAccessDenied, "unknown user"))
            }
        }
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
        if !self.users.is_empty() {
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
    use crate::users::Role as UserRole;

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
        let auth = CellAuth {
            anonymous: false,
            users: Arc::new(users),
        };
        assert_eq!(
            auth.role_of(&UserToken("user:anna".into())),
            Some(Role::Operator)
        );
        assert_eq!(
            auth.role_of(&UserToken("user:wall".into())),
            Some(Role::Observer)
        );
        assert_eq!(auth.role_of(&UserToken("user:bert".into())), None);
        assert_eq!(CellAuth::who(&UserToken("user:anna".into())), "opcua:anna");
    }
}

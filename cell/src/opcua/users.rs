//! Who may use `cell opcua`: the users file, password hashes, and the server's
//! [`AuthManager`] (authentication, and the operator/observer split).
//!
//! The users file is TOML (docs/opcua.md):
//!
//! ```toml
//! [[user]]
//! name = "anna"
//! role = "operator"            # operator | observer
//! password = "pbkdf2-sha256$100000$<salt hex>$<hash hex>"   # cell opcua --hash-password
//! ```
//!
//! A hash is PBKDF2-HMAC-SHA256 over the password with a 16-byte random salt. The
//! password never reaches the server in clear on the wire: the secure endpoints encrypt
//! it, and async-opcua hands it to us decrypted.

use std::collections::HashMap;
use std::num::NonZeroU32;
use std::path::Path;

use async_trait::async_trait;
use opcua::crypto::SecurityPolicy;
use opcua::types::{Error, NodeId, StatusCode, UAString, UserTokenPolicy, UserTokenType};
use opcua_server::address_space::AccessLevel;
use opcua_server::authenticator::{user_pass_security_policy_id, AuthManager, Password, UserToken};
use opcua_server::ServerEndpoint;
use serde::Deserialize;
use tracing::{info, warn};

/// The PBKDF2 rounds of a new hash (a login costs a few ms of one core).
pub const ROUNDS: u32 = 100_000;

/// The longest user name, so that `opcua:<name>` fits a PackML request's `by`.
pub const MAX_NAME: usize = 64;

/// What a user may do.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Browse, read, subscribe and call methods.
    Operator,
    /// Browse, read and subscribe; every method call is refused (BadUserAccessDenied).
    Observer,
}

/// A users file's problems.
#[derive(Debug, thiserror::Error)]
pub enum UsersError {
    #[error("cannot read the users file {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("the users file {path} is not valid: {message}")]
    Invalid { path: String, message: String },
    #[error("the users file {path} is readable by other users (mode {mode:o}); it holds password hashes: chmod 600 {path}")]
    Open { path: String, mode: u32 },
}

/// The users file as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct UsersFile {
    /// One entry per user.
    #[serde(default)]
    user: Vec<UserEntry>,
}

/// One user as written in the file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct UserEntry {
    /// The user name the client sends.
    name: String,
    /// operator or observer.
    role: Role,
    /// `pbkdf2-sha256$<rounds>$<salt hex>$<hash hex>`, from `cell opcua --hash-password`.
    password: String,
}

/// A password hash, parsed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PasswordHash {
    /// PBKDF2 rounds.
    rounds: NonZeroU32,
    /// The salt.
    salt: Vec<u8>,
    /// PBKDF2-HMAC-SHA256(password, salt, rounds), 32 bytes.
    hash: Vec<u8>,
}

impl PasswordHash {
    /// Hashes `password` with a new random salt.
    pub fn new(password: &str) -> PasswordHash {
        use ring::rand::SecureRandom;
        let mut salt = vec![0u8; 16];
        ring::rand::SystemRandom::new()
            .fill(&mut salt)
            .expect("the system's random source works");
        let rounds = NonZeroU32::new(ROUNDS).expect("ROUNDS > 0");
        let mut hash = vec![0u8; 32];
        ring::pbkdf2::derive(
            ring::pbkdf2::PBKDF2_HMAC_SHA256,
            rounds,
            &salt,
            password.as_bytes(),
            &mut hash,
        );
        PasswordHash { rounds, salt, hash }
    }

    /// Parses `pbkdf2-sha256$<rounds>$<salt hex>$<hash hex>`.
    pub fn parse(text: &str) -> Result<PasswordHash, String> {
        let parts: Vec<&str> = text.trim().split('$').collect();
        let [scheme, rounds, salt, hash] = parts.as_slice() else {
            return Err("a password is pbkdf2-sha256$ROUNDS$SALT$HASH (cell opcua --hash-password makes one)".into());
        };
        if *scheme != "pbkdf2-sha256" {
            return Err(format!(
                "unknown password scheme {scheme:?} (pbkdf2-sha256)"
            ));
        }
        let rounds = rounds
            .parse::<u32>()
            .ok()
            .and_then(NonZeroU32::new)
            .ok_or_else(|| format!("bad rounds {rounds:?}"))?;
        let salt = from_hex(salt).ok_or("the salt is not hex")?;
        let hash = from_hex(hash).ok_or("the hash is not hex")?;
        if salt.len() < 8 || hash.len() != 32 {
            return Err("a salt of at least 8 bytes and a hash of 32 bytes".into());
        }
        Ok(PasswordHash { rounds, salt, hash })
    }

    /// Whether `password` is the one hashed (in constant time).
    pub fn verify(&self, password: &str) -> bool {
        ring::pbkdf2::verify(
            ring::pbkdf2::PBKDF2_HMAC_SHA256,
            self.rounds,
            &self.salt,
            password.as_bytes(),
            &self.hash,
        )
        .is_ok()
    }
}

impl std::fmt::Display for PasswordHash {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "pbkdf2-sha256${}${}${}",
            self.rounds,
            to_hex(&self.salt),
            to_hex(&self.hash)
        )
    }
}

fn to_hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn from_hex(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(text.get(i..i + 2)?, 16).ok())
        .collect()
}

/// One user the server knows.
#[derive(Debug, Clone)]
pub struct User {
    /// What the user may do.
    pub role: Role,
    /// The password's hash.
    pub hash: PasswordHash,
}

/// Reads a users file.
pub fn load(path: &Path) -> Result<HashMap<String, User>, UsersError> {
    let shown = path.display().to_string();
    if let Some(mode) = super::security::open_to_others(path) {
        return Err(UsersError::Open { path: shown, mode });
    }
    let text = std::fs::read_to_string(path).map_err(|source| UsersError::Read {
        path: shown.clone(),
        source,
    })?;
    let invalid = |message: String| UsersError::Invalid {
        path: shown.clone(),
        message,
    };
    let file: UsersFile = toml::from_str(&text).map_err(|e| invalid(e.to_string()))?;
    let mut users = HashMap::new();
    for entry in file.user {
        if entry.name.is_empty()
            || entry.name.len() > MAX_NAME
            || entry.name.chars().any(|c| c.is_control())
        {
            return Err(invalid(format!(
                "user name {:?}: 1 to {MAX_NAME} bytes, no control characters",
                entry.name
            )));
        }
        let hash = PasswordHash::parse(&entry.password)
            .map_err(|e| invalid(format!("user {}: {e}", entry.name)))?;
        if users
            .insert(
                entry.name.clone(),
                User {
                    role: entry.role,
                    hash,
                },
            )
            .is_some()
        {
            return Err(invalid(format!("user {} appears twice", entry.name)));
        }
    }
    Ok(users)
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
    pub users: HashMap<String, User>,
}

impl CellAuth {
    /// The role of a session's user (`None`: no one we know).
    pub fn role_of(&self, token: &UserToken) -> Option<Role> {
        if token.is_anonymous() {
            return self.anonymous.then_some(Role::Operator);
        }
        let name = token.0.strip_prefix(USER_PREFIX)?;
        self.users.get(name).map(|u| u.role)
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
        match self.users.get(username) {
            Some(user) if user.hash.verify(password.get()) => {
                info!(user = username, role = ?user.role, "OPC UA user authenticated");
                Ok(UserToken(format!("{USER_PREFIX}{username}")))
            }
            Some(_) => {
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

    #[test]
    fn a_hash_verifies_its_password_only() {
        let hash = PasswordHash::new("s3cret");
        let text = hash.to_string();
        let parsed = PasswordHash::parse(&text).unwrap();
        assert_eq!(parsed, hash);
        assert!(parsed.verify("s3cret"));
        assert!(!parsed.verify("s3cret "));
        assert!(!parsed.verify(""));
        // A new salt every time.
        assert_ne!(PasswordHash::new("s3cret").to_string(), text);
        assert!(PasswordHash::parse("sha1$1$00$00").is_err());
        assert!(PasswordHash::parse("pbkdf2-sha256$0$0011223344556677$00").is_err());
    }

    #[test]
    fn a_users_file_names_each_user_once_with_a_role() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("users.toml");
        // Written 0600, as a users file must be (the test's umask would make it 0644).
        let write = |text: String| {
            std::fs::write(&path, text).unwrap();
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o600)).unwrap();
        };
        let hash = PasswordHash::new("pw").to_string();
        write(format!("[[user]]\nname = \"anna\"\nrole = \"operator\"\npassword = \"{hash}\"\n[[user]]\nname = \"wall\"\nrole = \"observer\"\npassword = \"{hash}\"\n"));
        let users = load(&path).unwrap();
        assert_eq!(users["anna"].role, Role::Operator);
        assert_eq!(users["wall"].role, Role::Observer);
        write(format!(
            "[[user]]\nname = \"anna\"\nrole = \"admin\"\npassword = \"{hash}\"\n"
        ));
        assert!(load(&path).is_err());
        write(format!("[[user]]\nname = \"a\"\nrole = \"operator\"\npassword = \"{hash}\"\n[[user]]\nname = \"a\"\nrole = \"observer\"\npassword = \"{hash}\"\n"));
        assert!(load(&path).unwrap_err().to_string().contains("twice"));
        // Readable by others: refused, naming the fix.
        write(format!(
            "[[user]]\nname = \"anna\"\nrole = \"operator\"\npassword = \"{hash}\"\n"
        ));
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).unwrap();
        assert!(load(&path).unwrap_err().to_string().contains("chmod 600"));
    }
}

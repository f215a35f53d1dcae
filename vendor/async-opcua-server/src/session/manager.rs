use std::{
    collections::HashMap,
    net::SocketAddr,
    sync::{
        atomic::{AtomicU32, Ordering},
        Arc,
    },
    time::{Duration, Instant},
};

use opcua_core::{comms::secure_channel::SecureChannel, trace_read_lock, trace_write_lock};
use opcua_crypto::{random, CertificateStore, SecurityPolicy};
use parking_lot::RwLock;
use tokio::sync::Notify;
use tracing::{error, info, warn};

use crate::{identity_token::IdentityToken, info::ServerInfo};
use opcua_types::{
    ActivateSessionRequest, ActivateSessionResponse, CloseSessionRequest, CloseSessionResponse,
    CreateSessionRequest, CreateSessionResponse, Error, NodeId, ResponseHeader, SignatureData,
    StatusCode,
};

use super::{instance::Session, message_handler::MessageHandler};

static NEXT_SESSION_ID: AtomicU32 = AtomicU32::new(1);

pub(super) fn next_session_id() -> (NodeId, u32) {
    // Session id will be a string identifier
    let session_id = NEXT_SESSION_ID.fetch_add(1, Ordering::Relaxed);
    (NodeId::new(1, session_id), session_id)
}

/// Manages all sessions on the server.
pub struct SessionManager {
    sessions: HashMap<NodeId, Arc<RwLock<Session>>>,
    info: Arc<ServerInfo>,
    notify: Arc<Notify>,
}

impl SessionManager {
    pub(crate) fn new(info: Arc<ServerInfo>, notify: Arc<Notify>) -> Self {
        Self {
            sessions: Default::default(),
            info,
            notify,
        }
    }

    /// Get a session by its authentication token.
    pub fn find_by_token(&self, authentication_token: &NodeId) -> Option<Arc<RwLock<Session>>> {
        Self::find_by_token_int(&self.sessions, authentication_token)
    }

    fn find_by_token_int(
        sessions: &HashMap<NodeId, Arc<RwLock<Session>>>,
        authentication_token: &NodeId,
    ) -> Option<Arc<RwLock<Session>>> {
        sessions
            .iter()
            .find(|(_, s)| &s.read().authentication_token == authentication_token)
            .map(|p| p.1.clone())
    }

    /// (holarchy) Closes every session for which `close` says so (a user removed or
    /// changed: its sessions end); their clients get `BadSessionIdInvalid` from then
    /// on. Returns how many were closed.
    pub fn close_sessions_where(&mut self, mut close: impl FnMut(&Session) -> bool) -> usize {
        let closing: Vec<NodeId> = self
            .sessions
            .iter()
            .filter(|(_, session)| close(&session.read()))
            .map(|(id, _)| id.clone())
            .collect();
        for id in &closing {
            if let Some(session) = self.sessions.remove(id) {
                session.write().close();
                info!("Session {id} closed by the server");
            }
        }
        if !closing.is_empty() {
            self.info
                .diagnostics
                .set_current_session_count(self.sessions.len() as u32);
            self.notify.notify_waiters();
        }
        closing.len()
    }

    /// (holarchy) The number of sessions, activated and waiting for activation.
    pub fn counts(&self) -> (usize, usize) {
        let activated = self
            .sessions
            .values()
            .filter(|s| s.read().is_activated())
            .count();
        (activated, self.sessions.len() - activated)
    }

    /// (holarchy) Whether one more session may wait for activation on this channel from
    /// this address: sessions waiting for activation are bounded per channel and per
    /// address, and never take the places of activated sessions. When all the places
    /// for waiting sessions are taken, the oldest waiting session of the address that
    /// holds the most is closed for the newcomer, if that address holds more than the
    /// newcomer's (a stranger holding places cannot keep an operator from logging in).
    fn admit_pending(
        &mut self,
        secure_channel_id: u32,
        peer: Option<SocketAddr>,
    ) -> Result<(), StatusCode> {
        let limits = self.info.config.limits.clone();
        let ip = peer.map(|a| a.ip());
        let mut activated = 0;
        let mut on_channel = 0;
        let mut waiting: Vec<(NodeId, Option<std::net::IpAddr>, Instant)> = Vec::new();
        let mut by_address: HashMap<Option<std::net::IpAddr>, usize> = HashMap::new();
        for (id, session) in &self.sessions {
            let session = session.read();
            if session.is_activated() {
                activated += 1;
                continue;
            }
            if session.secure_channel_id() == secure_channel_id {
                on_channel += 1;
            }
            let address = session.peer_address().map(|a| a.ip());
            *by_address.entry(address).or_default() += 1;
            waiting.push((id.clone(), address, session.created_at()));
        }
        let from_address = by_address.get(&ip).copied().unwrap_or(0);
        let client = peer.map(|a| a.to_string()).unwrap_or_else(|| "?".into());
        let refuse = |why: String| {
            crate::refusals::refused!("too-many-sessions", %client, "CreateSession refused (BadTooManySessions): {why}");
            Err(StatusCode::BadTooManySessions)
        };
        if activated >= limits.max_sessions {
            return refuse(format!(
                "{activated} activated sessions, the most the server holds (max_sessions)"
            ));
        }
        if on_channel >= limits.max_pending_sessions_per_channel {
            return refuse(format!("{on_channel} sessions not yet activated on this channel, the most allowed (max_pending_sessions_per_channel)"));
        }
        if from_address >= limits.max_pending_sessions_per_address {
            return refuse(format!("{from_address} sessions not yet activated from this address, the most allowed (max_pending_sessions_per_address)"));
        }
        if waiting.len() < limits.max_pending_sessions {
            return Ok(());
        }
        // Full: the oldest waiting session of the address holding the most.
        let most = by_address.values().copied().max().unwrap_or(0);
        let victim = waiting
            .iter()
            .filter(|(_, address, _)| by_address.get(address).copied() == Some(most))
            .min_by_key(|(_, _, created)| *created)
            .cloned();
        match victim {
            Some((id, address, _)) if most > from_address => {
                crate::refusals::refused!(
                    "waiting-session-closed",
                    %client,
                    holder = %address.map(|a| a.to_string()).unwrap_or_else(|| "?".into()),
                    "{} sessions wait for activation, the most the server holds (max_pending_sessions): the oldest of the address holding the most ({most}) is closed for a newcomer",
                    waiting.len()
                );
                if let Some(session) = self.sessions.remove(&id) {
                    session.write().close();
                }
                Ok(())
            }
            _ => refuse(format!("{} sessions not yet activated, the most the server holds (max_pending_sessions), none from an address holding more than this one", waiting.len())),
        }
    }

    /// (holarchy) Closes the sessions still waiting for activation on a secure channel
    /// that closed: only that channel could have activated them.
    pub(crate) fn close_pending_of_channel(&mut self, secure_channel_id: u32) -> usize {
        self.close_sessions_where(|session| {
            !session.is_activated() && session.secure_channel_id() == secure_channel_id
        })
    }

    pub(crate) fn create_session(
        &mut self,
        channel: &mut SecureChannel,
        certificate_store: &RwLock<CertificateStore>,
        request: &CreateSessionRequest,
        peer: Option<SocketAddr>,
    ) -> Result<CreateSessionResponse, StatusCode> {
        // (holarchy) A session only on a channel whose security an endpoint offers: a
        // channel of SecurityPolicy None on a server without a None endpoint serves
        // discovery (GetEndpoints, FindServers) and nothing else.
        if !self
            .info
            .offers_channel(channel.security_policy(), channel.security_mode())
        {
            crate::refusals::refused!(
                "session-on-discovery-channel",
                client = %peer.map(|a| a.to_string()).unwrap_or_else(|| "?".into()),
                policy = %channel.security_policy(),
                mode = ?channel.security_mode(),
                "CreateSession refused (BadSecurityPolicyRejected): no endpoint of the server offers this channel's security; it serves discovery only"
            );
            return Err(StatusCode::BadSecurityPolicyRejected);
        }
        self.admit_pending(channel.secure_channel_id(), peer)?;

        // TODO: Auditing and diagnostics.
        let endpoints = self
            .info
            .new_endpoint_descriptions(request.endpoint_url.as_ref());
        // TODO request.endpoint_url should match hostname of server application certificate
        // Find matching end points for this url
        if request.endpoint_url.is_empty() {
            error!("Create session was passed an null endpoint url");
            return Err(StatusCode::BadTcpEndpointUrlInvalid);
        }

        let Some(endpoints) = endpoints else {
            return Err(StatusCode::BadTcpEndpointUrlInvalid);
        };

        let security_policy = channel.security_policy();

        if !matches!(security_policy, SecurityPolicy::None)
            && request.client_nonce.len() < self.info.config.session_nonce_length
        {
            error!("Create session was passed a client nonce that is too short, expected at least {} bytes, got {}", 
                self.info.config.session_nonce_length, request.client_nonce.len()
            );
            return Err(StatusCode::BadNonceInvalid);
        }

        let client_certificate = if security_policy != SecurityPolicy::None {
            let cert = opcua_crypto::X509::from_byte_string(&request.client_certificate)?;
            let store = trace_read_lock!(certificate_store);
            store.validate_or_reject_application_instance_cert(
                &cert,
                security_policy,
                None,
                None,
            )?;
            Some(cert)
        } else {
            None
        };

        let session_timeout = self
            .info
            .config
            .max_session_timeout_ms
            .min(request.requested_session_timeout.floor() as u64);
        let max_request_message_size = self.info.config.limits.max_message_size as u32;

        let server_signature = if let Some(ref pkey) = self.info.server_pkey {
            opcua_crypto::create_signature_data(
                pkey,
                security_policy,
                &request.client_certificate,
                &request.client_nonce,
            )
            .unwrap_or_else(|err| {
                error!(
                    "Cannot create signature data from private key, check log and error {:?}",
                    err
                );
                SignatureData::null()
            })
        } else {
            SignatureData::null()
        };

        let authentication_token = NodeId::new(0, random::byte_string(32));
        let server_nonce = random::byte_string(self.info.config.session_nonce_length);
        let server_certificate = self.info.server_certificate_as_byte_string();
        let server_endpoints = Some(endpoints);

        let session = Session::create(
            &self.info,
            authentication_token.clone(),
            channel.secure_channel_id(),
            session_timeout,
            max_request_message_size,
            request.max_response_message_size,
            request.endpoint_url.clone(),
            security_policy.to_uri().to_string(),
            IdentityToken::None,
            client_certificate,
            server_nonce.clone(),
            request.session_name.clone(),
            request.client_description.clone(),
            channel.security_mode(),
            peer,
        );
        info!("Created new session with ID {}", session.session_id());

        let session_id = session.session_id().clone();
        self.sessions
            .insert(session_id.clone(), Arc::new(RwLock::new(session)));

        // Increment metrics.
        self.info
            .diagnostics
            .set_current_session_count(self.sessions.len() as u32);
        self.info.diagnostics.inc_session_count();

        self.notify.notify_waiters();

        Ok(CreateSessionResponse {
            response_header: ResponseHeader::new_good(&request.request_header),
            session_id,
            authentication_token,
            revised_session_timeout: session_timeout as f64,
            server_nonce,
            server_certificate,
            server_endpoints,
            server_software_certificates: None,
            server_signature,
            max_request_message_size,
        })
    }

    fn verify_client_signature(
        security_policy: SecurityPolicy,
        info: &ServerInfo,
        session: &Session,
        client_signature: &SignatureData,
    ) -> Result<(), Error> {
        if let Some(client_certificate) = session.client_certificate() {
            if let Some(ref server_certificate) = info.server_certificate {
                opcua_crypto::verify_signature_data(
                    client_signature,
                    security_policy,
                    client_certificate,
                    server_certificate,
                    session.session_nonce().as_ref(),
                )?;
                Ok(())
            } else {
                Err(Error::new(
                    StatusCode::BadUnexpectedError,
                    "Client signature verification failed, server has no server certificate",
                ))
            }
        } else {
            Err(Error::new(
                StatusCode::BadUnexpectedError,
                "Client signature verification failed, session has no client certificate",
            ))
        }
    }

    pub(crate) fn expire_session(&mut self, id: &NodeId) {
        let Some(session) = self.sessions.remove(id) else {
            return;
        };
        self.info
            .diagnostics
            .set_current_session_count(self.sessions.len() as u32);
        self.info.diagnostics.inc_session_timeout_count();

        info!("Session {id} has expired, removing it from the session map. Subscriptions will remain until they individually expire");

        let mut session = trace_write_lock!(session);
        session.close();
    }

    pub(crate) fn check_session_expiry(&self) -> (Instant, Vec<NodeId>) {
        let now = Instant::now();
        let mut expired = Vec::new();
        let mut expiry = now + Duration::from_millis(self.info.config.max_session_timeout_ms);
        for (id, session) in &self.sessions {
            let deadline = session.read().deadline();
            if deadline < now {
                expired.push(id.clone());
            } else if deadline < expiry {
                expiry = deadline;
            }
        }

        (expiry, expired)
    }
}

// This is a non-self method to avoid holding the manager
// across an await point.
pub(crate) async fn close_session(
    mgr_lck: &RwLock<SessionManager>,
    channel: &mut SecureChannel,
    handler: &mut MessageHandler,
    request: &CloseSessionRequest,
) -> Result<CloseSessionResponse, StatusCode> {
    let (session, id, token) = {
        let mut mgr = trace_write_lock!(mgr_lck);
        let Some(session) = mgr.find_by_token(&request.request_header.authentication_token) else {
            return Err(StatusCode::BadSessionIdInvalid);
        };
        let (id, token, session_id) = {
            let session = trace_read_lock!(session);
            let id = session.session_id_numeric();
            let token = session.user_token().cloned();

            let secure_channel_id = channel.secure_channel_id();
            if !session.is_activated() && session.secure_channel_id() != secure_channel_id {
                error!("close_session rejected, secure channel id {} for inactive session does not match one used to create session, {}", secure_channel_id, session.secure_channel_id());
                return Err(StatusCode::BadSecureChannelIdInvalid);
            }
            let session_id = session.session_id().clone();
            (id, token, session_id)
        };

        info!("Closed session with ID {}", session_id);
        let session = mgr.sessions.remove(&session_id).unwrap();
        {
            let mut session_lck = trace_write_lock!(session);
            session_lck.close();
        }
        mgr.info
            .diagnostics
            .set_current_session_count(mgr.sessions.len() as u32);
        (session, id, token)
    };

    if request.delete_subscriptions {
        if let Some(token) = token {
            handler
                .delete_session_subscriptions(id, session, token)
                .await;
        }
        // The token might be None if the session was never activated. No need to delete subscriptions in that case.
    }

    Ok(CloseSessionResponse {
        response_header: ResponseHeader::new_good(&request.request_header),
    })
}

pub(crate) async fn activate_session(
    mgr_lck: &RwLock<SessionManager>,
    channel: &mut SecureChannel,
    request: &ActivateSessionRequest,
    handler: &mut MessageHandler,
    peer: Option<SocketAddr>,
) -> Result<ActivateSessionResponse, StatusCode> {
    let security_policy = channel.security_policy();
    let security_mode = channel.security_mode();
    let secure_channel_id = channel.secure_channel_id();
    let server_nonce = security_policy.random_nonce();
    let (endpoint_url, session_nonce, session_lck, info) = {
        let mgr = trace_read_lock!(mgr_lck);
        let Some(session_lck) = mgr.find_by_token(&request.request_header.authentication_token)
        else {
            return Err(StatusCode::BadSessionIdInvalid);
        };

        let (endpoint_url, session_nonce) = {
            let session = trace_read_lock!(session_lck);
            session.validate_timed_out()?;

            let endpoint_url = session.endpoint_url().to_string();

            if !mgr
                .info
                .endpoint_exists(&endpoint_url, security_policy, security_mode)
            {
                error!("activate_session, Endpoint dues not exist for requested url & mode {}, {:?} / {:?}",
                endpoint_url, security_policy, security_mode);
                return Err(StatusCode::BadTcpEndpointUrlInvalid);
            }

            if security_policy != SecurityPolicy::None {
                SessionManager::verify_client_signature(
                    security_policy,
                    &mgr.info,
                    &session,
                    &request.client_signature,
                )?;
            }
            (endpoint_url, session.session_nonce().clone())
        };
        (endpoint_url, session_nonce, session_lck, mgr.info.clone())
    };

    let user_token = info
        .authenticate_endpoint(
            request,
            &endpoint_url,
            security_policy,
            security_mode,
            request.user_identity_token.clone(),
            &session_nonce,
            peer,
        )
        .await?;

    // (holarchy) Activated sessions are bounded by max_sessions: the place is taken
    // here, not at CreateSession.
    {
        let mgr = trace_read_lock!(mgr_lck);
        let already = session_lck.read().is_activated();
        let (activated, _) = mgr.counts();
        if !already && activated >= mgr.info.config.limits.max_sessions {
            warn!(
                client = %peer.map(|a| a.to_string()).unwrap_or_else(|| "?".into()),
                "ActivateSession refused (BadTooManySessions): {activated} activated sessions, the most the server holds (max_sessions)"
            );
            return Err(StatusCode::BadTooManySessions);
        }
    }

    let (server_nonce, session_id) = {
        let mut session = trace_write_lock!(session_lck);

        if !session.is_activated() && session.secure_channel_id() != secure_channel_id {
            error!("activate session, rejected secure channel id {} for inactive session does not match one used to create session, {}", secure_channel_id, session.secure_channel_id());
            return Err(StatusCode::BadSecureChannelIdInvalid);
        } else {
            // TODO additional secure channel validation here for client certificate and user identity
            //  token
        }

        // TODO: If the user identity changed here, we need to re-check permissions for any created monitored items.
        // It may be possible to just create a "fake" UserAccessLevel for each monitored item and pass it to the auth manager.
        // The standard also mentions that a server may need to
        // "Tear down connections to an underlying system and re-establish them using the new credentials". We need some way to
        // handle this eventuality, perhaps a dedicated node-manager endpoint that can be called here.
        session.activate(
            secure_channel_id,
            server_nonce,
            IdentityToken::new(request.user_identity_token.clone()),
            request.locale_ids.clone(),
            user_token.clone(),
        );
        (
            session.session_nonce().clone(),
            session.session_id_numeric(),
        )
    };

    let namespaces = handler.get_namespaces_for_user(session_lck.clone(), session_id, user_token);
    {
        channel.set_namespaces(namespaces);
    }

    // TODO: Audit

    Ok(ActivateSessionResponse {
        response_header: ResponseHeader::new_good(&request.request_header),
        server_nonce,
        results: None,
        diagnostic_infos: None,
    })
}

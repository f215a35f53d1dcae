//! The client of etcd's v3 JSON gateway: HTTP/1 POSTs to the members of one cluster,
//! with failover between them, over plain TCP (`http://` endpoints) or mutual TLS
//! (`https://`, [`ClientConfig::tls`]: the member's certificate checked against a given
//! CA and its endpoint's host, this client's certificate presented).
//!
//! A request goes to the member that answered last, and on to the next ones in turn
//! when it fails; every attempt is bounded by [`ClientConfig::request_timeout`] (its
//! connection by [`ClientConfig::connect_timeout`]), so a call takes at most one of each
//! per member. What is retried on another member depends on what the request does:
//! - a read, a lease grant, keep-alive or revoke ([`Retry::Always`]) is tried on the next
//!   member whatever went wrong (repeating it changes nothing that matters);
//! - a write ([`Retry::IfNotSent`]) only when the first member surely did not take it (no
//!   connection, or etcd said it had no raft leader). Once sent, a write that gets no
//!   reply is [`EtcdError::Uncertain`]: etcd may commit it later, so sending it again to
//!   another member could land the two in either order.
//!
//! Connections are kept open and reused (one request at a time on each). A TLS handshake
//! is part of the connection (within [`ClientConfig::connect_timeout`]); a member whose
//! handshake fails (its certificate not trusted, ours refused) has failed like one that
//! refused the connection, and the next is tried.

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper::client::conn::http1::{self, SendRequest};
use hyper_util::rt::TokioIo;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::endpoint::{common_scheme, server_name, Endpoint, Scheme, TlsFiles};
use super::wire;
use super::EtcdError;

/// The most idle connections kept open to one member.
const MAX_IDLE_PER_MEMBER: usize = 16;

/// Where the cluster is and how long to wait for it.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// The members' client URLs, e.g. `http://10.0.0.1:2379` or `https://etcd-a:2379`
    /// (no scheme: http). All share one scheme.
    pub endpoints: Vec<String>,
    /// The longest one attempt on one member may take, connection included.
    pub request_timeout: Duration,
    /// The longest a new connection to one member may take, TLS handshake included.
    pub connect_timeout: Duration,
    /// The files of mutual TLS: required with `https://` endpoints, refused with
    /// `http://` ones.
    pub tls: Option<TlsFiles>,
}

impl ClientConfig {
    /// `endpoints` with the default timeouts (1 s per attempt, 250 ms per connection).
    pub fn new<I, S>(endpoints: I) -> ClientConfig
    where
        I: IntoIterator<Item = S>,
        S: Into<String>,
    {
        ClientConfig {
            endpoints: endpoints.into_iter().map(Into::into).collect(),
            request_timeout: Duration::from_secs(1),
            connect_timeout: Duration::from_millis(250),
            tls: None,
        }
    }
}

/// Which failures a request may be sent again to another member after.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Retry {
    /// Any: the request reads, or repeating it is harmless.
    Always,
    /// Only if the member surely did not take it (see the module's doc).
    IfNotSent,
}

/// One member of the cluster, as a client sees it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MemberStatus {
    /// Its client URL, as configured.
    pub endpoint: String,
    /// Its member id.
    pub member_id: u64,
    /// The raft leader's member id, as this member knows it (0: it knows none).
    pub leader_id: u64,
}

/// A client of one etcd cluster; clones share its connections.
#[derive(Clone)]
pub struct Client {
    /// Shared by the clones.
    inner: Arc<Inner>,
}

struct Inner {
    /// The cluster's members, as configured.
    members: Vec<Member>,
    /// The member that answered last: tried first.
    preferred: AtomicUsize,
    /// See [`ClientConfig::request_timeout`].
    request_timeout: Duration,
    /// See [`ClientConfig::connect_timeout`].
    connect_timeout: Duration,
    /// With `https://` endpoints: the TLS connector of [`ClientConfig::tls`].
    tls: Option<tokio_rustls::TlsConnector>,
}

struct Member {
    /// As configured, for messages.
    endpoint: String,
    /// `host:port`, to connect to and for the Host header.
    authority: String,
    /// The name its certificate must have (with TLS): its endpoint's host.
    server_name: rustls::pki_types::ServerName<'static>,
    /// Open connections, idle.
    idle: Mutex<Vec<SendRequest<Full<Bytes>>>>,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let endpoints: Vec<&str> = self
            .inner
            .members
            .iter()
            .map(|m| m.endpoint.as_str())
            .collect();
        f.debug_struct("Client")
            .field("endpoints", &endpoints)
            .finish()
    }
}

/// How one attempt on one member failed.
enum Failure {
    /// The member surely did not take the request.
    NotSent(String),
    /// The request went out and no usable reply came back.
    NoReply(String),
    /// etcd answered with an error: its message and gRPC code.
    Refused { message: String, code: i32 },
    /// etcd answered something that is not its JSON.
    Malformed(String),
}

impl Client {
    /// A client of the cluster at `config.endpoints`; it connects when first used. With
    /// `https://` endpoints the TLS files are read now: one missing or unusable is an
    /// [`EtcdError::Config`] naming it.
    pub fn new(config: ClientConfig) -> Result<Client, EtcdError> {
        let scheme = common_scheme(&config.endpoints)?;
        let tls = match (scheme, &config.tls) {
            (Scheme::Https, Some(files)) => {
                Some(tokio_rustls::TlsConnector::from(files.client_config()?))
            }
            (Scheme::Https, None) => {
                return Err(EtcdError::Config(format!(
                    "https etcd endpoints ({}) need TLS files: a CA, a certificate and a key",
                    config.endpoints.join(", ")
                )))
            }
            (Scheme::Http, Some(_)) => {
                return Err(EtcdError::Config(format!(
                    "TLS files are given but the etcd endpoints ({}) are http://; write them \
                     https://",
                    config.endpoints.join(", ")
                )))
            }
            (Scheme::Http, None) => None,
        };
        let members = config
            .endpoints
            .iter()
            .map(|endpoint| {
                let parsed = Endpoint::parse(endpoint)?;
                Ok(Member {
                    endpoint: endpoint.clone(),
                    server_name: server_name(&parsed)?,
                    authority: parsed.authority,
                    idle: Mutex::new(Vec::new()),
                })
            })
            .collect::<Result<Vec<_>, EtcdError>>()?;
        Ok(Client {
            inner: Arc::new(Inner {
                members,
                preferred: AtomicUsize::new(0),
                request_timeout: config.request_timeout,
                connect_timeout: config.connect_timeout,
                tls,
            }),
        })
    }

    /// The members' endpoints, as configured.
    pub fn endpoints(&self) -> Vec<String> {
        self.inner
            .members
            .iter()
            .map(|m| m.endpoint.clone())
            .collect()
    }

    /// The longest one attempt on one member may take.
    pub fn request_timeout(&self) -> Duration {
        self.inner.request_timeout
    }

    /// POSTs `request` as JSON to `path` (e.g. `/v3/kv/range`) on the preferred member,
    /// and on the next ones as `retry` allows; the first reply that is not an error is
    /// decoded as `R`.
    pub(crate) async fn call<Q: Serialize, R: DeserializeOwned>(
        &self,
        path: &str,
        request: &Q,
        retry: Retry,
    ) -> Result<R, EtcdError> {
        let body = Bytes::from(serde_json::to_vec(request).expect("etcd requests serialize"));
        let count = self.inner.members.len();
        let first = self.inner.preferred.load(Ordering::Relaxed) % count;
        let mut tried = Vec::new();
        let mut last = String::new();
        for n in 0..count {
            let index = (first + n) % count;
            let member = &self.inner.members[index];
            tried.push(member.endpoint.clone());
            let attempt = tokio::time::timeout(
                self.inner.request_timeout,
                self.attempt(member, path, body.clone()),
            )
            .await
            .unwrap_or_else(|_| {
                Err(Failure::NoReply(format!(
                    "no reply within {:?}",
                    self.inner.request_timeout
                )))
            });
            let failure = match attempt {
                Ok(reply) => {
                    self.inner.preferred.store(index, Ordering::Relaxed);
                    return serde_json::from_slice(&reply).map_err(|e| EtcdError::Malformed {
                        endpoint: member.endpoint.clone(),
                        path: path.to_string(),
                        why: e.to_string(),
                    });
                }
                Err(failure) => failure,
            };
            let endpoint = member.endpoint.clone();
            match failure {
                Failure::NotSent(why) => last = why,
                Failure::NoReply(why) if retry == Retry::Always => last = why,
                Failure::NoReply(why) => return Err(EtcdError::Uncertain { endpoint, why }),
                Failure::Refused { message, code } => {
                    let not_taken = message.contains("no leader");
                    let busy = matches!(code, 4 | 14);
                    if !(not_taken || retry == Retry::Always && busy) {
                        return Err(EtcdError::Refused {
                            endpoint,
                            path: path.to_string(),
                            message,
                            code,
                        });
                    }
                    last = format!("{message} (code {code})");
                }
                Failure::Malformed(why) => {
                    return Err(EtcdError::Malformed {
                        endpoint,
                        path: path.to_string(),
                        why,
                    })
                }
            }
            tracing::debug!(etcd = %member.endpoint, path, why = %last, "etcd member failed; trying the next");
        }
        Err(EtcdError::Unreachable {
            tried: tried.join(", "),
            last,
        })
    }

    /// One POST to one member: the reply's body when its status is 200.
    async fn attempt(&self, member: &Member, path: &str, body: Bytes) -> Result<Bytes, Failure> {
        let (mut sender, mut driver) = match self.idle_connection(member).await {
            Some(sender) => (sender, None),
            None => {
                let (sender, driver) = self.connect(member).await?;
                (sender, Some(driver))
            }
        };
        let request = hyper::Request::builder()
            .method(hyper::Method::POST)
            .uri(path)
            .header(hyper::header::HOST, &member.authority)
            .header(hyper::header::CONTENT_TYPE, "application/json")
            .body(Full::new(body))
            .expect("a POST with a path and two headers is a request");
        let sending = sender.try_send_request(request);
        let sent = match driver.as_mut() {
            None => sending.await,
            // A new connection is driven here until the reply's head: if it ends first
            // (the member refused our certificate), its error says why.
            Some(connection) => {
                tokio::pin!(sending);
                tokio::select! {
                    sent = &mut sending => sent,
                    ended = connection.as_mut() => {
                        let endpoint = &member.endpoint;
                        return Err(match ended {
                            // Unsent if the member refused the handshake: it read nothing.
                            Err(e) => match refused_handshake(&e) {
                                Some(alert) => Failure::NotSent(format!(
                                    "{endpoint}: the member refused this client's TLS certificate ({alert:?})"
                                )),
                                None => Failure::NoReply(format!("{endpoint}: connection closed: {e}")),
                            },
                            Ok(()) => Failure::NoReply(format!(
                                "{endpoint}: connection closed before the reply"
                            )),
                        });
                    }
                }
            }
        };
        if let Some(connection) = driver {
            let endpoint = member.endpoint.clone();
            tokio::spawn(async move {
                if let Err(e) = connection.await {
                    tracing::debug!(etcd = %endpoint, error = %e, "etcd connection ended");
                }
            });
        }
        let response = match sent {
            Ok(response) => response,
            Err(e) if e.message().is_some() => {
                return Err(Failure::NotSent(format!(
                    "{}: connection closed: {}",
                    member.endpoint,
                    e.error()
                )))
            }
            Err(e) => {
                // TLS 1.3: the client's side of the handshake ends before the member has
                // checked our certificate, so its refusal comes as an alert in place of
                // the reply. It never read the request.
                if let Some(alert) = refused_handshake(e.error()) {
                    return Err(Failure::NotSent(format!(
                        "{}: the member refused this client's TLS certificate ({alert:?})",
                        member.endpoint
                    )));
                }
                return Err(Failure::NoReply(format!(
                    "{}: {}",
                    member.endpoint,
                    e.error()
                )));
            }
        };
        let status = response.status();
        let reply = response
            .into_body()
            .collect()
            .await
            .map_err(|e| Failure::NoReply(format!("{}: reply cut: {e}", member.endpoint)))?
            .to_bytes();
        if !sender.is_closed() {
            let mut idle = member.idle.lock().unwrap_or_else(|e| e.into_inner());
            // More than that were open only for a burst: closed (dropped) after it.
            if idle.len() < MAX_IDLE_PER_MEMBER {
                idle.push(sender);
            }
        }
        if status == hyper::StatusCode::OK {
            return Ok(reply);
        }
        match serde_json::from_slice::<wire::ErrorReply>(&reply) {
            Ok(error) => Err(Failure::Refused {
                message: error.message,
                code: error.code,
            }),
            Err(_) => Err(Failure::Malformed(format!(
                "HTTP {status}: {}",
                String::from_utf8_lossy(&reply)
            ))),
        }
    }

    /// An open idle connection to `member`, if it has one. (One just returned may not
    /// say it is ready yet: its driver is told the last reply was read; it is waited
    /// for, within the attempt's timeout.)
    async fn idle_connection(&self, member: &Member) -> Option<SendRequest<Full<Bytes>>> {
        loop {
            let sender = member.idle.lock().unwrap_or_else(|e| e.into_inner()).pop();
            let mut sender = sender?;
            if !sender.is_closed() && sender.ready().await.is_ok() {
                return Some(sender);
            }
        }
    }

    /// A new connection to `member` (TCP, then TLS with https, both within the connect
    /// timeout), and its driver, for the caller to poll or spawn.
    async fn connect(
        &self,
        member: &Member,
    ) -> Result<(SendRequest<Full<Bytes>>, Driver), Failure> {
        let connecting = async {
            let stream = tokio::net::TcpStream::connect(&member.authority)
                .await
                .map_err(|e| format!("{}: {e}", member.endpoint))?;
            if let Err(e) = stream.set_nodelay(true) {
                tracing::debug!(etcd = %member.endpoint, error = %e, "cannot set TCP_NODELAY");
            }
            match &self.inner.tls {
                None => Ok(Stream::Plain(stream)),
                Some(connector) => connector
                    .connect(member.server_name.clone(), stream)
                    .await
                    .map(|tls| Stream::Tls(Box::new(tls)))
                    .map_err(|e| format!("{}: TLS handshake failed: {e}", member.endpoint)),
            }
        };
        let stream = match tokio::time::timeout(self.inner.connect_timeout, connecting).await {
            Ok(Ok(stream)) => stream,
            Ok(Err(why)) => return Err(Failure::NotSent(why)),
            Err(_) => {
                return Err(Failure::NotSent(format!(
                    "{}: no connection within {:?}",
                    member.endpoint, self.inner.connect_timeout
                )))
            }
        };
        let not_sent = |e: hyper::Error| Failure::NotSent(format!("{}: {e}", member.endpoint));
        Ok(match stream {
            Stream::Plain(stream) => {
                let (sender, connection) = http1::handshake(TokioIo::new(stream))
                    .await
                    .map_err(not_sent)?;
                (sender, Box::pin(connection) as Driver)
            }
            Stream::Tls(stream) => {
                let (sender, connection) = http1::handshake(TokioIo::new(*stream))
                    .await
                    .map_err(not_sent)?;
                (sender, Box::pin(connection) as Driver)
            }
        })
    }

    /// Grants a lease of `ttl` whole seconds; its id.
    pub async fn lease_grant(&self, ttl: Duration) -> Result<i64, EtcdError> {
        let request = wire::LeaseGrantRequest {
            ttl: ttl.as_secs().max(1) as i64,
        };
        let reply: wire::LeaseResponse = self
            .call("/v3/lease/grant", &request, Retry::Always)
            .await?;
        Ok(reply.id)
    }

    /// Renews the lease: the seconds it now has left, or `None` when etcd no longer
    /// knows it (it expired or was revoked).
    pub async fn lease_keep_alive(&self, lease: i64) -> Result<Option<Duration>, EtcdError> {
        let reply: wire::KeepAliveResponse = self
            .call(
                "/v3/lease/keepalive",
                &wire::LeaseIdRequest { id: lease },
                Retry::Always,
            )
            .await?;
        match reply.result.ttl {
            ttl if ttl > 0 => Ok(Some(Duration::from_secs(ttl as u64))),
            _ => Ok(None),
        }
    }

    /// Revokes the lease, deleting the keys attached to it; `false` if etcd did not know
    /// it (already expired or revoked).
    pub async fn lease_revoke(&self, lease: i64) -> Result<bool, EtcdError> {
        let revoked: Result<serde_json::Value, _> = self
            .call(
                "/v3/lease/revoke",
                &wire::LeaseIdRequest { id: lease },
                Retry::Always,
            )
            .await;
        match revoked {
            Ok(_) => Ok(true),
            Err(EtcdError::Refused { code: 5, .. }) => Ok(false),
            Err(e) => Err(e),
        }
    }

    /// Each member's view of the cluster (its id and the raft leader's), asked of each
    /// in turn (each within the request timeout); a member that does not answer is left
    /// out.
    pub async fn member_statuses(&self) -> Vec<MemberStatus> {
        const PATH: &str = "/v3/maintenance/status";
        let mut statuses = Vec::new();
        for member in &self.inner.members {
            let attempt = tokio::time::timeout(
                self.inner.request_timeout,
                self.attempt(member, PATH, Bytes::from_static(b"{}")),
            )
            .await;
            let why = match attempt {
                Ok(Ok(reply)) => match serde_json::from_slice::<wire::StatusResponse>(&reply) {
                    Ok(status) => {
                        statuses.push(MemberStatus {
                            endpoint: member.endpoint.clone(),
                            member_id: status.header.member_id,
                            leader_id: status.leader,
                        });
                        continue;
                    }
                    Err(e) => format!("malformed status: {e}"),
                },
                Ok(Err(
                    Failure::NotSent(why) | Failure::NoReply(why) | Failure::Malformed(why),
                )) => why,
                Ok(Err(Failure::Refused { message, code })) => format!("{message} (code {code})"),
                Err(_) => format!("no reply within {:?}", self.inner.request_timeout),
            };
            tracing::debug!(etcd = %member.endpoint, why = %why, "no status");
        }
        statuses
    }
}

/// What drives one connection's I/O: polled by the first request's attempt, then
/// spawned.
type Driver = std::pin::Pin<Box<dyn std::future::Future<Output = Result<(), hyper::Error>> + Send>>;

/// A connection to a member.
enum Stream {
    /// `http://`.
    Plain(tokio::net::TcpStream),
    /// `https://`.
    Tls(Box<tokio_rustls::client::TlsStream<tokio::net::TcpStream>>),
}

/// The alert a member refused our certificate with, if that is what ended `error`: one
/// of the handshake's alerts, received where the reply should have been.
fn refused_handshake(
    error: &(dyn std::error::Error + 'static),
) -> Option<rustls::AlertDescription> {
    use rustls::AlertDescription as A;
    let mut next = Some(error);
    while let Some(error) = next {
        let tls = error.downcast_ref::<rustls::Error>().or_else(|| {
            error
                .downcast_ref::<std::io::Error>()
                .and_then(|io| io.get_ref())
                .and_then(|inner| inner.downcast_ref::<rustls::Error>())
        });
        if let Some(rustls::Error::AlertReceived(alert)) = tls {
            let handshake = matches!(
                alert,
                A::BadCertificate
                    | A::UnsupportedCertificate
                    | A::CertificateRevoked
                    | A::CertificateExpired
                    | A::CertificateUnknown
                    | A::UnknownCA
                    | A::AccessDenied
                    | A::HandshakeFailure
                    | A::CertificateRequired
            );
            return handshake.then_some(*alert);
        }
        next = error.source();
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_client_needs_endpoints_of_one_scheme_and_tls_files_with_https() {
        assert!(Client::new(ClientConfig::new(Vec::<String>::new())).is_err());
        assert!(Client::new(ClientConfig::new(["http://10.0.0.1:2379"])).is_ok());
        let mixed = ["https://10.0.0.1:2379", "http://10.0.0.2:2379"];
        let error = Client::new(ClientConfig::new(mixed)).unwrap_err();
        assert!(matches!(error, EtcdError::Config(_)), "{error}");
        assert!(error.to_string().contains("10.0.0.2"), "{error}");
        let error = Client::new(ClientConfig::new(["https://10.0.0.1:2379"])).unwrap_err();
        assert!(error.to_string().contains("need TLS files"), "{error}");
        let files = TlsFiles {
            ca: "/nonexistent/ca.pem".into(),
            certificate: "/nonexistent/c.pem".into(),
            key: "/nonexistent/c.key".into(),
        };
        let plain = ClientConfig {
            tls: Some(files.clone()),
            ..ClientConfig::new(["http://10.0.0.1:2379"])
        };
        let error = Client::new(plain).unwrap_err();
        assert!(error.to_string().contains("write them https://"), "{error}");
        let secure = ClientConfig {
            tls: Some(files),
            ..ClientConfig::new(["https://10.0.0.1:2379"])
        };
        let error = Client::new(secure).unwrap_err();
        assert!(error.to_string().contains("/nonexistent/ca.pem"), "{error}");
    }

    #[tokio::test]
    async fn a_cluster_nobody_answers_for_is_unreachable() {
        // Two ports nothing listens on (bound, then closed).
        let ports: Vec<u16> = (0..2)
            .map(|_| {
                std::net::TcpListener::bind("127.0.0.1:0")
                    .unwrap()
                    .local_addr()
                    .unwrap()
                    .port()
            })
            .collect();
        let client = Client::new(ClientConfig::new(
            ports.iter().map(|p| format!("http://127.0.0.1:{p}")),
        ))
        .unwrap();
        let error = client
            .lease_grant(Duration::from_secs(2))
            .await
            .unwrap_err();
        assert!(matches!(error, EtcdError::Unreachable { .. }), "{error}");
        assert!(error.is_transient());
        assert!(error.to_string().contains(&ports[1].to_string()), "{error}");
    }
}

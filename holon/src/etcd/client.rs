//! The client of etcd's v3 JSON gateway: plain HTTP/1 POSTs to the members of one
//! cluster, with failover between them.
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
//! Connections are kept open and reused (one request at a time on each).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper::client::conn::http1::{self, SendRequest};
use hyper_util::rt::TokioIo;
use serde::de::DeserializeOwned;
use serde::Serialize;

use super::wire;
use super::EtcdError;

/// The most idle connections kept open to one member.
const MAX_IDLE_PER_MEMBER: usize = 16;

/// Where the cluster is and how long to wait for it.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// The members' client URLs, e.g. `http://10.0.0.1:2379` (the scheme may be left
    /// out; only `http` is spoken).
    pub endpoints: Vec<String>,
    /// The longest one attempt on one member may take, connection included.
    pub request_timeout: Duration,
    /// The longest a new connection to one member may take.
    pub connect_timeout: Duration,
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
}

struct Member {
    /// As configured, for messages.
    endpoint: String,
    /// `host:port`, to connect to and for the Host header.
    authority: String,
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
    /// A client of the cluster at `config.endpoints`; it connects when first used.
    pub fn new(config: ClientConfig) -> Result<Client, EtcdError> {
        if config.endpoints.is_empty() {
            return Err(EtcdError::Config("no etcd endpoint given".into()));
        }
        let members = config
            .endpoints
            .iter()
            .map(|endpoint| {
                let authority = authority_of(endpoint)?;
                Ok(Member {
                    endpoint: endpoint.clone(),
                    authority,
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
        let mut sender = match self.idle_connection(member).await {
            Some(sender) => sender,
            None => self.connect(member).await?,
        };
        let request = hyper::Request::builder()
            .method(hyper::Method::POST)
            .uri(path)
            .header(hyper::header::HOST, &member.authority)
            .header(hyper::header::CONTENT_TYPE, "application/json")
            .body(Full::new(body))
            .expect("a POST with a path and two headers is a request");
        let response = match sender.try_send_request(request).await {
            Ok(response) => response,
            Err(e) if e.message().is_some() => {
                return Err(Failure::NotSent(format!(
                    "{}: connection closed: {}",
                    member.endpoint,
                    e.error()
                )))
            }
            Err(e) => {
                return Err(Failure::NoReply(format!(
                    "{}: {}",
                    member.endpoint,
                    e.error()
                )))
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

    /// A new connection to `member`, its driver spawned.
    async fn connect(&self, member: &Member) -> Result<SendRequest<Full<Bytes>>, Failure> {
        let connecting = tokio::net::TcpStream::connect(&member.authority);
        let stream = match tokio::time::timeout(self.inner.connect_timeout, connecting).await {
            Ok(Ok(stream)) => stream,
            Ok(Err(e)) => return Err(Failure::NotSent(format!("{}: {e}", member.endpoint))),
            Err(_) => {
                return Err(Failure::NotSent(format!(
                    "{}: no connection within {:?}",
                    member.endpoint, self.inner.connect_timeout
                )))
            }
        };
        if let Err(e) = stream.set_nodelay(true) {
            tracing::debug!(etcd = %member.endpoint, error = %e, "cannot set TCP_NODELAY");
        }
        let (sender, connection) = http1::handshake(TokioIo::new(stream))
            .await
            .map_err(|e| Failure::NotSent(format!("{}: {e}", member.endpoint)))?;
        let endpoint = member.endpoint.clone();
        tokio::spawn(async move {
            if let Err(e) = connection.await {
                tracing::debug!(etcd = %endpoint, error = %e, "etcd connection ended");
            }
        });
        Ok(sender)
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
    /// in turn; a member that does not answer is left out.
    pub async fn member_statuses(&self) -> Vec<MemberStatus> {
        let mut statuses = Vec::new();
        for endpoint in self.endpoints() {
            let single = Client::new(ClientConfig {
                endpoints: vec![endpoint.clone()],
                request_timeout: self.inner.request_timeout,
                connect_timeout: self.inner.connect_timeout,
            });
            let Ok(single) = single else { continue };
            let status: Result<wire::StatusResponse, _> = single
                .call(
                    "/v3/maintenance/status",
                    &serde_json::json!({}),
                    Retry::Always,
                )
                .await;
            match status {
                Ok(status) => statuses.push(MemberStatus {
                    endpoint,
                    member_id: status.header.member_id,
                    leader_id: status.leader,
                }),
                Err(e) => tracing::debug!(etcd = %endpoint, error = %e, "no status"),
            }
        }
        statuses
    }
}

/// `host:port` of an endpoint `http://host:port[/]` or `host:port`.
fn authority_of(endpoint: &str) -> Result<String, EtcdError> {
    let rest = match endpoint.split_once("://") {
        Some(("http", rest)) => rest,
        Some((scheme, _)) => {
            return Err(EtcdError::Config(format!(
                "etcd endpoint {endpoint:?}: scheme {scheme} is not spoken (http only)"
            )))
        }
        None => endpoint,
    };
    let authority = rest.trim_end_matches('/');
    match authority.rsplit_once(':') {
        Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok() => {
            Ok(authority.to_string())
        }
        _ => Err(EtcdError::Config(format!(
            "etcd endpoint {endpoint:?} is not http://host:port"
        ))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_host_and_port_over_http() {
        assert_eq!(
            authority_of("http://10.0.0.1:2379").unwrap(),
            "10.0.0.1:2379"
        );
        assert_eq!(authority_of("127.0.0.1:2379/").unwrap(), "127.0.0.1:2379");
        assert!(authority_of("https://10.0.0.1:2379").is_err());
        assert!(authority_of("10.0.0.1").is_err());
        assert!(Client::new(ClientConfig::new(Vec::<String>::new())).is_err());
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

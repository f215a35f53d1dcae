//! The dashboard's listener: HTTPS, with an optional client certificate as a login, and
//! plain HTTP beside it on the same port (issue 29).
//!
//! axum serves from a [`DashboardListener`] (`axum::serve(listener, router
//! .into_make_service_with_connect_info::<Peer>())`); each connection comes with a
//! [`Peer`], the handlers' `ConnectInfo`: the client's address, whether the connection
//! is HTTPS, and the identity of the client certificate it presented, if any.
//!
//! A task accepts the TCP connections (TCP_NODELAY on) and prepares each one in a task
//! of its own, which hands it to [`axum::serve::Listener::accept`] through a bounded
//! channel, so that a slow or silent client never holds up the others. At most
//! [`MAX_PREPARING`] connections are prepared at once; beyond that new connections wait
//! in the kernel's accept backlog (they are not dropped) until one of those is handed
//! over or given up, which takes at most [`FIRST_BYTE_TIMEOUT`] plus
//! [`HANDSHAKE_TIMEOUT`]. Accept errors (EMFILE when out of file descriptors...) are
//! logged and retried after [`ACCEPT_ERROR_PAUSE`], never in a busy loop.
//!
//! With TLS ([`server_config`]) the first byte of each connection decides (waited for at
//! most [`FIRST_BYTE_TIMEOUT`], then the connection is dropped): 0x16, a TLS handshake
//! record, is served HTTPS after a handshake bounded by [`HANDSHAKE_TIMEOUT`]; anything
//! else is served as it is, plain HTTP with `Peer { tls: false, .. }`, which the
//! dashboard answers with a redirect to https. A failed handshake (scanners are common)
//! is logged at debug level with the peer's address, and the connection dropped.
//! Without TLS every connection is plain.
//!
//! When the TLS configuration names a client CA, the server asks for a client
//! certificate but does not require one (a browser without one still connects and logs
//! in with a password); one that is presented must be the CA's, or the handshake fails.
//! [`Peer::certificate_identity`] is then the certificate's common name, the identity
//! `cell certs` issued it for (`operator.anna`, `observer.screen1`).
//!
//! Dropping the listener (axum's graceful shutdown does) stops the accept task and the
//! preparation of the connections not yet handed over.
//!
//! rustls is always given the ring provider explicitly: the process may not have
//! installed a default one.

use std::io;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use rustls::crypto::CryptoProvider;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use rustls::server::WebPkiClientVerifier;
use rustls::RootCertStore;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Semaphore};
use tokio::task::{JoinHandle, JoinSet};
use tokio_rustls::TlsAcceptor;
use tracing::{debug, error, warn};

/// How many connections are prepared (first byte awaited, TLS handshake) at once.
pub const MAX_PREPARING: usize = 256;

/// How long a new connection may stay silent before it is dropped (TLS configured).
pub const FIRST_BYTE_TIMEOUT: Duration = Duration::from_secs(10);

/// How long a TLS handshake may take before the connection is dropped.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// How long the accept task pauses after an accept error other than a connection's own.
pub const ACCEPT_ERROR_PAUSE: Duration = Duration::from_secs(1);

/// How many prepared connections wait for axum to take them.
const READY_QUEUE: usize = 64;

/// The first byte of a TLS connection: a handshake record.
const TLS_HANDSHAKE_RECORD: u8 = 0x16;

/// Who is on the other end of one connection (axum's `ConnectInfo`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Peer {
    /// The client's address.
    pub address: SocketAddr,
    /// Whether the connection is HTTPS.
    pub tls: bool,
    /// The common name of the client certificate the client presented, which rustls
    /// verified against the configured client CA (the cell CA), e.g. `operator.anna`;
    /// `None` without a certificate, on plain HTTP, or without a client CA.
    pub certificate_identity: Option<String>,
}

impl axum::extract::connect_info::Connected<axum::serve::IncomingStream<'_, DashboardListener>>
    for Peer
{
    fn connect_info(stream: axum::serve::IncomingStream<'_, DashboardListener>) -> Self {
        stream.remote_addr().clone()
    }
}

/// Where the HTTPS certificate comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    /// The server's certificate chain, PEM, the server's own certificate first.
    pub certificate: PathBuf,
    /// The server's private key, PEM; must not be readable by group or others.
    pub key: PathBuf,
    /// The CA whose client certificates are accepted as a login, PEM (the cell CA); no
    /// client certificate is asked for when `None`.
    pub client_ca: Option<PathBuf>,
}

/// Why the TLS configuration cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum ListenerError {
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: String,
        /// Why not.
        source: io::Error,
    },
    #[error("{path} is readable by other users (mode {mode:o}); a private key must be 0600 or stricter: chmod 600 {path}")]
    KeyExposed {
        /// The key file.
        path: String,
        /// Its permission bits.
        mode: u32,
    },
    #[error("{path} holds no PEM certificate{}", if message.is_empty() { String::new() } else { format!(": {message}") })]
    NotACertificate {
        /// The file.
        path: String,
        /// What the PEM parser said, if anything.
        message: String,
    },
    #[error("{path} holds no PEM private key{}", if message.is_empty() { String::new() } else { format!(": {message}") })]
    NotAKey {
        /// The file.
        path: String,
        /// What the PEM parser said, if anything.
        message: String,
    },
    #[error("the client CA {path} is not a usable CA certificate: {message}")]
    BadClientCa {
        /// The client CA file.
        path: String,
        /// What rustls said.
        message: String,
    },
    #[error("the certificate {certificate} and the key {key} make no TLS server: {source}")]
    Config {
        /// The certificate file.
        certificate: String,
        /// The key file.
        key: String,
        /// What rustls said (a key that does not match the certificate...).
        source: rustls::Error,
    },
}

fn show(path: &Path) -> String {
    path.display().to_string()
}

fn read(path: &Path) -> Result<Vec<u8>, ListenerError> {
    std::fs::read(path).map_err(|source| ListenerError::Read {
        path: show(path),
        source,
    })
}

fn certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, ListenerError> {
    let pem = read(path)?;
    let not_certificate = |message: String| ListenerError::NotACertificate {
        path: show(path),
        message,
    };
    let chain = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| not_certificate(e.to_string()))?;
    if chain.is_empty() {
        return Err(not_certificate(String::new()));
    }
    Ok(chain)
}

fn private_key(path: &Path) -> Result<PrivateKeyDer<'static>, ListenerError> {
    use std::os::unix::fs::PermissionsExt;
    let metadata = std::fs::metadata(path).map_err(|source| ListenerError::Read {
        path: show(path),
        source,
    })?;
    let mode = metadata.permissions().mode() & 0o777;
    if mode & 0o077 != 0 {
        return Err(ListenerError::KeyExposed {
            path: show(path),
            mode,
        });
    }
    let pem = read(path)?;
    PrivateKeyDer::from_pem_slice(&pem).map_err(|e| ListenerError::NotAKey {
        path: show(path),
        message: match e {
            rustls::pki_types::pem::Error::NoItemsFound => String::new(),
            e => e.to_string(),
        },
    })
}

/// The ring provider, given to rustls explicitly.
fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// The HTTPS configuration from `files`: ALPN http/1.1; with a client CA, a client
/// certificate asked for (not required) and verified against it. Refuses a key readable
/// by group or others, and names the file that is missing or not PEM.
pub fn server_config(files: &TlsFiles) -> Result<Arc<rustls::ServerConfig>, ListenerError> {
    let chain = certificates(&files.certificate)?;
    let key = private_key(&files.key)?;
    let provider = provider();
    let config_error = |source: rustls::Error| ListenerError::Config {
        certificate: show(&files.certificate),
        key: show(&files.key),
        source,
    };
    let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
        .with_safe_default_protocol_versions()
        .map_err(config_error)?;
    let builder = match &files.client_ca {
        None => builder.with_no_client_auth(),
        Some(ca) => {
            let bad_ca = |message: String| ListenerError::BadClientCa {
                path: show(ca),
                message,
            };
            let mut roots = RootCertStore::empty();
            for certificate in certificates(ca)? {
                roots.add(certificate).map_err(|e| bad_ca(e.to_string()))?;
            }
            let verifier = WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                .allow_unauthenticated()
                .build()
                .map_err(|e| bad_ca(e.to_string()))?;
            builder.with_client_cert_verifier(verifier)
        }
    };
    let mut config = builder.with_single_cert(chain, key).map_err(config_error)?;
    config.alpn_protocols = vec![b"http/1.1".to_vec()];
    Ok(Arc::new(config))
}

/// One connection, plain or TLS, as axum reads and writes it.
#[derive(Debug)]
pub enum Connection {
    /// Plain HTTP.
    Plain(TcpStream),
    /// HTTPS, the handshake done.
    Tls(Box<tokio_rustls::server::TlsStream<TcpStream>>),
}

impl AsyncRead for Connection {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Connection::Plain(stream) => Pin::new(stream).poll_read(cx, buf),
            Connection::Tls(stream) => Pin::new(stream.as_mut()).poll_read(cx, buf),
        }
    }
}

impl AsyncWrite for Connection {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Connection::Plain(stream) => Pin::new(stream).poll_write(cx, buf),
            Connection::Tls(stream) => Pin::new(stream.as_mut()).poll_write(cx, buf),
        }
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        match self.get_mut() {
            Connection::Plain(stream) => Pin::new(stream).poll_write_vectored(cx, bufs),
            Connection::Tls(stream) => Pin::new(stream.as_mut()).poll_write_vectored(cx, bufs),
        }
    }

    fn is_write_vectored(&self) -> bool {
        match self {
            Connection::Plain(stream) => stream.is_write_vectored(),
            Connection::Tls(stream) => stream.is_write_vectored(),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Connection::Plain(stream) => Pin::new(stream).poll_flush(cx),
            Connection::Tls(stream) => Pin::new(stream.as_mut()).poll_flush(cx),
        }
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        match self.get_mut() {
            Connection::Plain(stream) => Pin::new(stream).poll_shutdown(cx),
            Connection::Tls(stream) => Pin::new(stream.as_mut()).poll_shutdown(cx),
        }
    }
}

/// The dashboard's listener: TCP, with HTTPS and plain HTTP on the same port when TLS is
/// configured (see the module's doc).
#[derive(Debug)]
pub struct DashboardListener {
    /// The address it is bound to.
    local: SocketAddr,
    /// Whether TLS is configured.
    tls: bool,
    /// The prepared connections, from the accept task.
    ready: mpsc::Receiver<(Connection, Peer)>,
    /// The accept task; aborted when the listener is dropped.
    accepting: JoinHandle<()>,
}

impl DashboardListener {
    /// Binds `address` and starts accepting; `tls` serves HTTPS (and plain HTTP beside
    /// it), `None` plain HTTP only.
    pub async fn bind(
        address: SocketAddr,
        tls: Option<Arc<rustls::ServerConfig>>,
    ) -> io::Result<DashboardListener> {
        let listener = TcpListener::bind(address).await?;
        let local = listener.local_addr()?;
        let (sender, ready) = mpsc::channel(READY_QUEUE);
        let acceptor = tls.map(TlsAcceptor::from);
        let is_tls = acceptor.is_some();
        let accepting = tokio::spawn(accept_loop(listener, acceptor, sender));
        Ok(DashboardListener {
            local,
            tls: is_tls,
            ready,
            accepting,
        })
    }

    /// The address it is bound to (the port chosen when bound to port 0).
    pub fn local_addr(&self) -> io::Result<SocketAddr> {
        Ok(self.local)
    }
}

impl Drop for DashboardListener {
    fn drop(&mut self) {
        self.accepting.abort();
    }
}

impl axum::serve::Listener for DashboardListener {
    type Io = Connection;
    type Addr = Peer;

    async fn accept(&mut self) -> (Self::Io, Self::Addr) {
        match self.ready.recv().await {
            Some(connection) => connection,
            None => {
                // The accept task ends only when this receiver is dropped, or if it
                // panicked: no connection will ever come.
                error!("the dashboard's accept task has stopped; no more connections");
                std::future::pending().await
            }
        }
    }

    fn local_addr(&self) -> io::Result<Self::Addr> {
        Ok(Peer {
            address: self.local,
            tls: self.tls,
            certificate_identity: None,
        })
    }
}

/// Whether an accept error is the connection's own (the next accept may succeed at
/// once) rather than the process's (out of file descriptors...).
fn is_connection_error(e: &io::Error) -> bool {
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::ConnectionReset
    )
}

async fn accept_loop(
    listener: TcpListener,
    tls: Option<TlsAcceptor>,
    ready: mpsc::Sender<(Connection, Peer)>,
) {
    let preparing = Arc::new(Semaphore::new(MAX_PREPARING));
    // Dropped with this task: aborts the preparations under way.
    let mut tasks = JoinSet::new();
    loop {
        while tasks.try_join_next().is_some() {}
        let permit = tokio::select! {
            permit = preparing.clone().acquire_owned() => match permit {
                Ok(permit) => permit,
                Err(_) => return, // never closed
            },
            _ = ready.closed() => return,
        };
        let (stream, address) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) if is_connection_error(&e) => {
                    debug!("dashboard: accept: {e}");
                    continue;
                }
                Err(e) => {
                    warn!("dashboard: accept: {e}; trying again in {ACCEPT_ERROR_PAUSE:?}");
                    tokio::time::sleep(ACCEPT_ERROR_PAUSE).await;
                    continue;
                }
            },
            _ = ready.closed() => return,
        };
        if let Err(e) = stream.set_nodelay(true) {
            debug!(peer = %address, "dashboard: TCP_NODELAY: {e}");
        }
        let tls = tls.clone();
        let ready = ready.clone();
        tasks.spawn(async move {
            if let Some(prepared) = prepare(stream, address, tls).await {
                // Fails only when the listener is gone.
                let _ = ready.send(prepared).await;
            }
            drop(permit);
        });
    }
}

/// A connection as axum gets it: the first byte awaited and the TLS handshake made when
/// TLS is configured; `None` when it is given up.
async fn prepare(
    stream: TcpStream,
    address: SocketAddr,
    tls: Option<TlsAcceptor>,
) -> Option<(Connection, Peer)> {
    let plain = |stream| {
        Some((
            Connection::Plain(stream),
            Peer {
                address,
                tls: false,
                certificate_identity: None,
            },
        ))
    };
    let Some(acceptor) = tls else {
        return plain(stream);
    };
    let mut first = [0u8; 1];
    match tokio::time::timeout(FIRST_BYTE_TIMEOUT, stream.peek(&mut first)).await {
        Err(_) => {
            debug!(peer = %address, "dashboard: nothing sent in {FIRST_BYTE_TIMEOUT:?}; connection dropped");
            return None;
        }
        Ok(Err(e)) => {
            debug!(peer = %address, "dashboard: connection lost: {e}");
            return None;
        }
        Ok(Ok(0)) => return None,
        Ok(Ok(_)) => {}
    }
    if first[0] != TLS_HANDSHAKE_RECORD {
        return plain(stream);
    }
    let stream = match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(stream)).await {
        Err(_) => {
            debug!(peer = %address, "dashboard: TLS handshake not done in {HANDSHAKE_TIMEOUT:?}; connection dropped");
            return None;
        }
        Ok(Err(e)) => {
            debug!(peer = %address, "dashboard: TLS handshake failed: {e}");
            return None;
        }
        Ok(Ok(stream)) => stream,
    };
    // rustls verified a presented certificate against the client CA, or the handshake
    // failed; without a client CA none is asked for.
    let certificate_identity = stream
        .get_ref()
        .1
        .peer_certificates()
        .and_then(|chain| chain.first())
        .and_then(|der| x509_parser::parse_x509_certificate(der.as_ref()).ok())
        .map(|(_, certificate)| holon::tls::common_name(&certificate))
        .filter(|name| !name.is_empty());
    Some((
        Connection::Tls(Box::new(stream)),
        Peer {
            address,
            tls: true,
            certificate_identity,
        },
    ))
}

#[cfg(test)]
mod tests;

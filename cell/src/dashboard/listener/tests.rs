use super::*;
use axum::extract::ConnectInfo;
use axum::routing::get;
use axum::{Json, Router};
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// A CA: its certificate (PEM) and its issuer.
fn new_ca(name: &str) -> (String, Issuer<'static, KeyPair>) {
    let key = KeyPair::generate().unwrap();
    let mut params = CertificateParams::default();
    let mut dn = DistinguishedName::new();
    dn.push(DnType::CommonName, format!("holarchy cell {name} CA"));
    params.distinguished_name = dn;
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    let cert = params.self_signed(&key).unwrap();
    (cert.pem(), Issuer::new(params, key))
}

/// A certificate and its key (PEM), for `identity`, as `cell certs` issues them.
fn issue(identity: &str, issuer: &Issuer<'_, KeyPair>) -> (String, String) {
    let key = KeyPair::generate().unwrap();
    let mut params =
        CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()]).unwrap();
    let mut dn = DistinguishedName::new();
    dn.push(DnType::CommonName, identity);
    params.distinguished_name = dn;
    params.key_usages = vec![
        KeyUsagePurpose::DigitalSignature,
        KeyUsagePurpose::KeyEncipherment,
    ];
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    let cert = params.signed_by(&key, issuer).unwrap();
    (cert.pem(), key.serialize_pem())
}

fn write(path: &Path, text: &str, mode: u32) {
    use std::os::unix::fs::PermissionsExt;
    std::fs::write(path, text).unwrap();
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(mode)).unwrap();
}

/// A cell's PKI in a directory: the CA, the dashboard's certificate, an operator's.
struct Pki {
    dir: tempfile::TempDir,
    ca: String,
    operator: (String, String),
    /// A certificate of another CA, for the same identity.
    stranger: (String, String),
}

fn pki() -> Pki {
    let dir = tempfile::tempdir().unwrap();
    let (ca, issuer) = new_ca("test");
    let (cert, key) = issue("dashboard.test", &issuer);
    write(&dir.path().join("ca.pem"), &ca, 0o644);
    write(&dir.path().join("dashboard.pem"), &cert, 0o644);
    write(&dir.path().join("dashboard.key"), &key, 0o600);
    let operator = issue("operator.anna", &issuer);
    let (_, other) = new_ca("other");
    let stranger = issue("operator.anna", &other);
    Pki {
        dir,
        ca,
        operator,
        stranger,
    }
}

impl Pki {
    fn files(&self) -> TlsFiles {
        TlsFiles {
            certificate: self.dir.path().join("dashboard.pem"),
            key: self.dir.path().join("dashboard.key"),
            client_ca: Some(self.dir.path().join("ca.pem")),
        }
    }
}

async fn echo(ConnectInfo(peer): ConnectInfo<Peer>) -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "address": peer.address.to_string(),
        "tls": peer.tls,
        "identity": peer.certificate_identity,
    }))
}

/// Serves the echo on 127.0.0.1, port chosen; returns the port.
async fn serve(tls: Option<Arc<rustls::ServerConfig>>) -> SocketAddr {
    let listener = DashboardListener::bind("127.0.0.1:0".parse().unwrap(), tls)
        .await
        .unwrap();
    let address = listener.local_addr().unwrap();
    let router = Router::new().route("/peer", get(echo));
    tokio::spawn(async move {
        axum::serve(
            listener,
            router.into_make_service_with_connect_info::<Peer>(),
        )
        .await
        .unwrap();
    });
    address
}

/// One GET /peer over `stream`; the response's body as JSON.
async fn get_peer<S: AsyncRead + AsyncWrite + Unpin>(
    mut stream: S,
) -> io::Result<serde_json::Value> {
    stream
        .write_all(b"GET /peer HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n")
        .await?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).await?;
    let response = String::from_utf8_lossy(&response);
    let (head, body) = response
        .split_once("\r\n\r\n")
        .ok_or_else(|| io::Error::other(format!("no HTTP response: {response:?}")))?;
    if !head.starts_with("HTTP/1.1 200") {
        return Err(io::Error::other(format!("not 200: {head}")));
    }
    serde_json::from_str(body).map_err(io::Error::other)
}

/// An HTTPS GET /peer, with the client certificate `client` if any.
async fn https(
    address: SocketAddr,
    ca: &str,
    client: Option<&(String, String)>,
) -> io::Result<serde_json::Value> {
    let mut roots = RootCertStore::empty();
    for cert in CertificateDer::pem_slice_iter(ca.as_bytes()) {
        roots.add(cert.unwrap()).unwrap();
    }
    let builder = rustls::ClientConfig::builder_with_provider(provider())
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots);
    let config = match client {
        None => builder.with_no_client_auth(),
        Some((cert, key)) => builder
            .with_client_auth_cert(
                CertificateDer::pem_slice_iter(cert.as_bytes())
                    .collect::<Result<Vec<_>, _>>()
                    .unwrap(),
                PrivateKeyDer::from_pem_slice(key.as_bytes()).unwrap(),
            )
            .unwrap(),
    };
    let connector = tokio_rustls::TlsConnector::from(Arc::new(config));
    let tcp = TcpStream::connect(address).await?;
    let name = rustls::pki_types::ServerName::try_from("localhost").unwrap();
    let stream = connector.connect(name, tcp).await?;
    get_peer(stream).await
}

async fn within<T>(future: impl std::future::Future<Output = T>) -> T {
    tokio::time::timeout(Duration::from_secs(5), future)
        .await
        .expect("took more than 5 s")
}

#[tokio::test(flavor = "multi_thread")]
async fn https_with_a_client_certificate_of_the_cell_ca_names_its_identity() {
    let pki = pki();
    let address = serve(Some(server_config(&pki.files()).unwrap())).await;
    let peer = within(https(address, &pki.ca, Some(&pki.operator)))
        .await
        .unwrap();
    assert_eq!(peer["tls"], true);
    assert_eq!(peer["identity"], "operator.anna");
    assert!(peer["address"].as_str().unwrap().starts_with("127.0.0.1:"));
}

#[tokio::test(flavor = "multi_thread")]
async fn https_without_a_client_certificate_has_no_identity() {
    let pki = pki();
    let address = serve(Some(server_config(&pki.files()).unwrap())).await;
    let peer = within(https(address, &pki.ca, None)).await.unwrap();
    assert_eq!(peer["tls"], true);
    assert_eq!(peer["identity"], serde_json::Value::Null);
}

#[tokio::test(flavor = "multi_thread")]
async fn without_a_client_ca_no_certificate_is_asked_for() {
    let pki = pki();
    let files = TlsFiles {
        client_ca: None,
        ..pki.files()
    };
    let address = serve(Some(server_config(&files).unwrap())).await;
    let peer = within(https(address, &pki.ca, Some(&pki.operator)))
        .await
        .unwrap();
    assert_eq!(peer["tls"], true);
    assert_eq!(peer["identity"], serde_json::Value::Null);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_certificate_of_another_ca_is_refused() {
    let pki = pki();
    let address = serve(Some(server_config(&pki.files()).unwrap())).await;
    // With TLS 1.3 the client may finish its side of the handshake before the
    // server refuses the certificate: the refusal then comes on the first read.
    let result = within(https(address, &pki.ca, Some(&pki.stranger))).await;
    let error = result.expect_err("served");
    // A TLS alert (unknown CA), or the connection closed: not a bad HTTP answer.
    assert_ne!(error.kind(), io::ErrorKind::Other, "{error}");
    // The listener still serves the others.
    let peer = within(https(address, &pki.ca, Some(&pki.operator)))
        .await
        .unwrap();
    assert_eq!(peer["identity"], "operator.anna");
}

#[tokio::test(flavor = "multi_thread")]
async fn plain_http_on_the_same_port_is_served_plain() {
    let pki = pki();
    let address = serve(Some(server_config(&pki.files()).unwrap())).await;
    let tcp = TcpStream::connect(address).await.unwrap();
    let peer = within(get_peer(tcp)).await.unwrap();
    assert_eq!(peer["tls"], false);
    assert_eq!(peer["identity"], serde_json::Value::Null);
}

#[tokio::test(flavor = "multi_thread")]
async fn without_tls_every_connection_is_plain() {
    let address = serve(None).await;
    let tcp = TcpStream::connect(address).await.unwrap();
    let peer = within(get_peer(tcp)).await.unwrap();
    assert_eq!(peer["tls"], false);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_silent_client_does_not_hold_up_the_others() {
    let pki = pki();
    let address = serve(Some(server_config(&pki.files()).unwrap())).await;
    let mut silent = Vec::new();
    for _ in 0..8 {
        silent.push(TcpStream::connect(address).await.unwrap());
    }
    // A client that starts a TLS handshake and stops.
    let mut stalled = TcpStream::connect(address).await.unwrap();
    stalled.write_all(&[0x16, 0x03, 0x01]).await.unwrap();
    let peer = within(https(address, &pki.ca, Some(&pki.operator)))
        .await
        .unwrap();
    assert_eq!(peer["identity"], "operator.anna");
    let tcp = TcpStream::connect(address).await.unwrap();
    let peer = within(get_peer(tcp)).await.unwrap();
    assert_eq!(peer["tls"], false);
    drop((silent, stalled));
}

#[tokio::test(flavor = "multi_thread")]
async fn dropping_the_listener_stops_accepting() {
    let listener = DashboardListener::bind("127.0.0.1:0".parse().unwrap(), None)
        .await
        .unwrap();
    let address = listener.local_addr().unwrap();
    drop(listener);
    // The accept task lets go of the socket: connections are refused.
    within(async {
        while TcpStream::connect(address).await.is_ok() {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await;
}

#[test]
fn a_key_readable_by_others_is_refused() {
    let pki = pki();
    let files = pki.files();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&files.key, std::fs::Permissions::from_mode(0o644)).unwrap();
    let error = server_config(&files).unwrap_err();
    assert!(
        matches!(error, ListenerError::KeyExposed { mode: 0o644, .. }),
        "{error}"
    );
    assert!(error.to_string().contains("chmod 600"), "{error}");
    std::fs::set_permissions(&files.key, std::fs::Permissions::from_mode(0o640)).unwrap();
    assert!(server_config(&files).is_err());
}

#[test]
fn missing_and_unparseable_files_are_named() {
    let pki = pki();
    let missing = TlsFiles {
        certificate: pki.dir.path().join("nothing.pem"),
        ..pki.files()
    };
    let error = server_config(&missing).unwrap_err();
    assert!(matches!(error, ListenerError::Read { .. }), "{error}");
    assert!(error.to_string().contains("nothing.pem"), "{error}");

    write(&pki.dir.path().join("junk.pem"), "not PEM\n", 0o600);
    let junk = TlsFiles {
        certificate: pki.dir.path().join("junk.pem"),
        ..pki.files()
    };
    let error = server_config(&junk).unwrap_err();
    assert!(
        matches!(error, ListenerError::NotACertificate { .. }),
        "{error}"
    );
    let junk = TlsFiles {
        key: pki.dir.path().join("junk.pem"),
        ..pki.files()
    };
    let error = server_config(&junk).unwrap_err();
    assert!(matches!(error, ListenerError::NotAKey { .. }), "{error}");

    // A key that is not the certificate's.
    let (_, stranger_key) = &pki.stranger;
    write(&pki.dir.path().join("other.key"), stranger_key, 0o600);
    let mismatched = TlsFiles {
        key: pki.dir.path().join("other.key"),
        ..pki.files()
    };
    assert!(server_config(&mismatched).is_err());
}

//! The members' client URLs (`http://host:port` or `https://host:port`), and the files
//! of mutual TLS to `https://` members: the CA their server certificates must be issued
//! by, and the certificate and key this client presents (etcd's `--client-cert-auth`).

use std::net::IpAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};

use super::EtcdError;

/// How a client speaks to the members of one cluster.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scheme {
    /// Plain HTTP/1 over TCP: anyone who reaches the port reads and writes everything.
    Http,
    /// HTTP/1 over mutual TLS.
    Https,
}

impl Scheme {
    /// `http` or `https`.
    pub fn as_str(self) -> &'static str {
        match self {
            Scheme::Http => "http",
            Scheme::Https => "https",
        }
    }
}

/// One member's client URL, parsed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    /// `http` (also when the URL has no scheme) or `https`.
    pub scheme: Scheme,
    /// The host: a DNS name or an IP address (an IPv6 one without its brackets). With
    /// https the member's certificate must name it.
    pub host: String,
    /// `host:port` as written (IPv6 in brackets), to connect to and for the Host header.
    pub authority: String,
}

impl Endpoint {
    /// Parses `http://host:port[/]`, `https://host:port[/]` or `host:port` (http).
    pub fn parse(endpoint: &str) -> Result<Endpoint, EtcdError> {
        let (scheme, rest) = match endpoint.split_once("://") {
            Some(("http", rest)) => (Scheme::Http, rest),
            Some(("https", rest)) => (Scheme::Https, rest),
            Some((scheme, _)) => {
                return Err(EtcdError::Config(format!(
                    "etcd endpoint {endpoint:?}: scheme {scheme} is not spoken (http or https)"
                )))
            }
            None => (Scheme::Http, endpoint),
        };
        let authority = rest.trim_end_matches('/');
        match authority.rsplit_once(':') {
            Some((host, port)) if !host.is_empty() && port.parse::<u16>().is_ok() => {
                let host = host
                    .strip_prefix('[')
                    .and_then(|h| h.strip_suffix(']'))
                    .unwrap_or(host);
                Ok(Endpoint {
                    scheme,
                    host: host.to_string(),
                    authority: authority.to_string(),
                })
            }
            _ => Err(EtcdError::Config(format!(
                "etcd endpoint {endpoint:?} is not http://host:port or https://host:port"
            ))),
        }
    }

    /// Whether the host is this machine's loopback (`localhost`, `127.0.0.0/8`, `::1`):
    /// nobody on the network reaches it.
    pub fn is_loopback(&self) -> bool {
        self.host == "localhost" || self.host.parse::<IpAddr>().is_ok_and(|ip| ip.is_loopback())
    }
}

/// The scheme every endpoint shares: endpoints of both are refused, naming them.
pub fn common_scheme(endpoints: &[String]) -> Result<Scheme, EtcdError> {
    let parsed = endpoints
        .iter()
        .map(|e| Endpoint::parse(e))
        .collect::<Result<Vec<_>, _>>()?;
    let first = parsed
        .first()
        .ok_or_else(|| EtcdError::Config("no etcd endpoint given".into()))?
        .scheme;
    if parsed.iter().any(|e| e.scheme != first) {
        let of = |scheme: Scheme| {
            endpoints
                .iter()
                .zip(&parsed)
                .filter(|(_, p)| p.scheme == scheme)
                .map(|(e, _)| e.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        };
        return Err(EtcdError::Config(format!(
            "etcd endpoints mix http ({}) and https ({}): every member of one cluster is \
             spoken to the same way",
            of(Scheme::Http),
            of(Scheme::Https)
        )));
    }
    Ok(first)
}

/// The PEM files of mutual TLS to `https://` members.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TlsFiles {
    /// The CA certificate(s): a member's server certificate must be issued by one, and
    /// name the endpoint's host. No other CA is trusted (not the system's).
    pub ca: PathBuf,
    /// The certificate (chain) this client presents; the members' `--trusted-ca-file`
    /// must have issued it.
    pub certificate: PathBuf,
    /// The certificate's private key.
    pub key: PathBuf,
}

fn read(path: &Path) -> Result<Vec<u8>, EtcdError> {
    std::fs::read(path)
        .map_err(|e| EtcdError::Config(format!("etcd TLS: cannot read {}: {e}", path.display())))
}

/// The certificates of a PEM file, at least one.
fn certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>, EtcdError> {
    let pem = read(path)?;
    let certificates = CertificateDer::pem_slice_iter(&pem)
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| {
            EtcdError::Config(format!(
                "etcd TLS: {} is not PEM certificates: {e}",
                path.display()
            ))
        })?;
    if certificates.is_empty() {
        return Err(EtcdError::Config(format!(
            "etcd TLS: {} holds no certificate",
            path.display()
        )));
    }
    Ok(certificates)
}

impl TlsFiles {
    /// Reads the files into a rustls client config (ring, TLS 1.2 and 1.3): the CA as
    /// the only root, the certificate and key as the client's. A file that cannot be
    /// read, or is not what it should be, is [`EtcdError::Config`] naming it.
    pub fn client_config(&self) -> Result<Arc<rustls::ClientConfig>, EtcdError> {
        let tls_error = |what: String| EtcdError::Config(format!("etcd TLS: {what}"));
        let mut roots = rustls::RootCertStore::empty();
        for ca in certificates(&self.ca)? {
            roots
                .add(ca)
                .map_err(|e| tls_error(format!("{} is not a usable CA: {e}", self.ca.display())))?;
        }
        let chain = certificates(&self.certificate)?;
        let key = PrivateKeyDer::from_pem_slice(&read(&self.key)?).map_err(|e| {
            tls_error(format!(
                "{} is not a PEM private key: {e}",
                self.key.display()
            ))
        })?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let config = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .map_err(|e| tls_error(e.to_string()))?
            .with_root_certificates(roots)
            .with_client_auth_cert(chain, key)
            .map_err(|e| {
                tls_error(format!(
                    "the key {} does not go with the certificate {}: {e}",
                    self.key.display(),
                    self.certificate.display()
                ))
            })?;
        Ok(Arc::new(config))
    }
}

/// The name a member's certificate must have: its endpoint's host.
pub(crate) fn server_name(endpoint: &Endpoint) -> Result<ServerName<'static>, EtcdError> {
    ServerName::try_from(endpoint.host.clone()).map_err(|e| {
        EtcdError::Config(format!(
            "etcd endpoint host {:?} is not a DNS name or an IP address: {e}",
            endpoint.host
        ))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_are_a_scheme_a_host_and_a_port() {
        let e = Endpoint::parse("http://10.0.0.1:2379").unwrap();
        assert_eq!(
            (e.scheme, e.host.as_str(), e.authority.as_str()),
            (Scheme::Http, "10.0.0.1", "10.0.0.1:2379")
        );
        let e = Endpoint::parse("127.0.0.1:2379/").unwrap();
        assert_eq!(
            (e.scheme, e.authority.as_str()),
            (Scheme::Http, "127.0.0.1:2379")
        );
        assert!(e.is_loopback());
        let e = Endpoint::parse("https://[::1]:2379").unwrap();
        assert_eq!(
            (e.scheme, e.host.as_str(), e.authority.as_str()),
            (Scheme::Https, "::1", "[::1]:2379")
        );
        assert!(e.is_loopback());
        let e = Endpoint::parse("https://etcd-a.plant:2379").unwrap();
        assert!(!e.is_loopback());
        assert!(server_name(&e).is_ok());
        assert!(Endpoint::parse("unix://x:1").is_err());
        assert!(Endpoint::parse("10.0.0.1").is_err());
        assert!(Endpoint::parse("https://:2379").is_err());
    }

    #[test]
    fn one_cluster_one_scheme() {
        let both = [
            "https://10.0.0.1:2379".to_string(),
            "http://10.0.0.2:2379".to_string(),
        ];
        let error = common_scheme(&both).unwrap_err().to_string();
        assert!(
            error.contains("http (http://10.0.0.2:2379)")
                && error.contains("https (https://10.0.0.1:2379)"),
            "{error}"
        );
        assert_eq!(common_scheme(&both[..1]).unwrap(), Scheme::Https);
        assert!(common_scheme(&[]).is_err());
    }

    #[test]
    fn missing_or_wrong_files_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let junk = dir.path().join("junk.pem");
        std::fs::write(&junk, "not PEM\n").unwrap();
        let files = TlsFiles {
            ca: dir.path().join("nothing.pem"),
            certificate: junk.clone(),
            key: junk.clone(),
        };
        let error = files.client_config().unwrap_err().to_string();
        assert!(error.contains("nothing.pem"), "{error}");
        let files = TlsFiles {
            ca: junk.clone(),
            ..files
        };
        let error = files.client_config().unwrap_err().to_string();
        assert!(error.contains("junk.pem holds no certificate"), "{error}");
    }
}

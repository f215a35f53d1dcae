//! An HTTP/1.1 client for the dashboard's tests, over plain TCP or HTTPS (rustls, with
//! the cell CA as the only root and optionally a client certificate), that keeps the
//! session cookie a login hands out.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};

/// One answer.
#[derive(Debug, Clone)]
pub struct Answer {
    pub status: u16,
    /// The status line and headers, as sent.
    pub head: String,
    pub body: String,
}

impl Answer {
    /// The value of header `name` (case-insensitive), if sent.
    pub fn header(&self, name: &str) -> Option<String> {
        self.head.lines().find_map(|line| {
            let (n, v) = line.split_once(':')?;
            n.trim()
                .eq_ignore_ascii_case(name)
                .then(|| v.trim().to_string())
        })
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {} {}", self.status, self.body))
    }
}

/// A client of one dashboard.
#[derive(Clone)]
pub struct Web {
    /// `IP:PORT`.
    pub address: String,
    /// HTTPS settings (`None`: plain HTTP).
    tls: Option<Arc<rustls::ClientConfig>>,
    /// The session cookie (`name=value`) the last login handed out.
    pub cookie: Option<String>,
}

impl Web {
    /// Plain HTTP to `address`.
    pub fn plain(address: &str) -> Web {
        Web {
            address: address.to_string(),
            tls: None,
            cookie: None,
        }
    }

    /// HTTPS to `address`, trusting only `ca` (PEM), presenting `client` (certificate
    /// and key PEM files) when given.
    pub fn https(address: &str, ca: &Path, client: Option<(&Path, &Path)>) -> Result<Web> {
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let mut roots = rustls::RootCertStore::empty();
        for cert in CertificateDer::pem_file_iter(ca).context("the CA file")? {
            roots.add(cert?)?;
        }
        let builder = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()?
            .with_root_certificates(roots);
        let config = match client {
            Some((cert, key)) => {
                let chain = CertificateDer::pem_file_iter(cert)
                    .context("the client certificate")?
                    .collect::<Result<Vec<_>, _>>()?;
                let key = PrivateKeyDer::from_pem_file(key).context("the client key")?;
                builder.with_client_auth_cert(chain, key)?
            }
            None => builder.with_no_client_auth(),
        };
        Ok(Web {
            address: address.to_string(),
            tls: Some(Arc::new(config)),
            cookie: None,
        })
    }

    /// The page's own origin.
    pub fn origin(&self) -> String {
        let scheme = if self.tls.is_some() { "https" } else { "http" };
        format!("{scheme}://{}", self.address)
    }

    /// A request as the dashboard's own page makes it: its host, its `Origin` and JSON
    /// for a change, and the session cookie.
    pub fn call(&self, method: &str, path: &str, body: &str) -> Answer {
        let origin = self.origin();
        let mut headers = vec![("content-type", "application/json")];
        if method != "GET" {
            headers.push(("origin", origin.as_str()));
        }
        self.raw(method, path, &self.address, &headers, body)
            .unwrap_or_else(|e| panic!("{method} {path}: {e:#}"))
    }

    /// Logs in: keeps the cookie of a successful login.
    pub fn login(&mut self, name: &str, password: &str) -> Answer {
        let body = serde_json::json!({ "name": name, "password": password }).to_string();
        let answer = self.call("POST", "/api/login", &body);
        if answer.status == 200 {
            let set = answer.header("set-cookie").expect("a login sets a cookie");
            self.cookie = set.split(';').next().map(str::to_string);
        }
        answer
    }

    /// One request with `host` and `headers` as given (plus the cookie, if held).
    pub fn raw(
        &self,
        method: &str,
        path: &str,
        host: &str,
        headers: &[(&str, &str)],
        body: &str,
    ) -> Result<Answer> {
        let mut request =
            format!("{method} {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n");
        for (name, value) in headers {
            request.push_str(&format!("{name}: {value}\r\n"));
        }
        if let Some(cookie) = &self.cookie {
            request.push_str(&format!("cookie: {cookie}\r\n"));
        }
        request.push_str(&format!("content-length: {}\r\n\r\n{body}", body.len()));
        let tcp = TcpStream::connect(&self.address)?;
        tcp.set_read_timeout(Some(Duration::from_secs(20)))?;
        let mut bytes = Vec::new();
        match &self.tls {
            None => {
                let mut tcp = tcp;
                tcp.write_all(request.as_bytes())?;
                tcp.read_to_end(&mut bytes)?;
            }
            Some(config) => {
                let ip = self.address.rsplit_once(':').map_or("", |(ip, _)| ip);
                let name = ServerName::try_from(ip.trim_matches(['[', ']']).to_string())?;
                let connection = rustls::ClientConnection::new(config.clone(), name)?;
                let mut stream = rustls::StreamOwned::new(connection, tcp);
                stream.write_all(request.as_bytes())?;
                match stream.read_to_end(&mut bytes) {
                    Ok(_) => {}
                    // A server that closes without close_notify after its answer.
                    Err(e)
                        if e.kind() == std::io::ErrorKind::UnexpectedEof && !bytes.is_empty() => {}
                    Err(e) => return Err(e.into()),
                }
            }
        }
        let text = String::from_utf8_lossy(&bytes).to_string();
        let (head, body) = text
            .split_once("\r\n\r\n")
            .map(|(h, b)| (h.to_string(), b.to_string()))
            .ok_or_else(|| anyhow!("no answer: {text:?}"))?;
        let status = head
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or(0);
        Ok(Answer { status, head, body })
    }
}

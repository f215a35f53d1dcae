//! Mutual TLS for a holon process: which files prove its identity (`[zenoh.tls]` in its
//! config, or `--pki DIR`), and the checks made before zenoh ever reads them.
//!
//! An identity is the common name of a process's certificate, `<role>.<name>`:
//! `resource.robot1`, `product.breaker`, `order-node.orders1`, `router.a`,
//! `operator.alice`, `observer.screen1`. `cell certs` issues one per process of a cell
//! into a PKI directory: `ca.pem`, `<identity>.pem`, `<identity>.key` and
//! `access_control.json5` (the cell's zenoh access control). A process refuses to start
//! when its key cannot be read, is readable by every user, does not match its
//! certificate, or when the certificate is not the cell CA's, has expired, or names
//! another identity.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// `[zenoh.tls]`: turns on mutual TLS (and, for holons and routers, access control).
/// Paths are relative to the config file's directory.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsSettings {
    /// The PKI directory `cell certs` wrote; the defaults of the fields below are in it.
    #[serde(default)]
    pub pki: Option<PathBuf>,
    /// The cell CA's certificate (default `<pki>/ca.pem`): peers must present a
    /// certificate it issued.
    #[serde(default)]
    pub ca: Option<PathBuf>,
    /// This process's certificate (default `<pki>/<identity>.pem`).
    #[serde(default)]
    pub certificate: Option<PathBuf>,
    /// This process's private key (default `<pki>/<identity>.key`); must not be
    /// readable by other users.
    #[serde(default)]
    pub key: Option<PathBuf>,
    /// The cell's access control, a zenoh JSON5 config holding `access_control`
    /// (default `<pki>/access_control.json5`). Enforced on every link of a holon or
    /// router; operator commands, which link only to a router, do not load it.
    #[serde(default)]
    pub access_control: Option<PathBuf>,
}

/// The files of one identity, resolved and checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IdentityFiles {
    /// The identity, `<role>.<name>`: the certificate's common name.
    pub identity: String,
    pub ca: PathBuf,
    pub certificate: PathBuf,
    pub key: PathBuf,
    /// The access-control file, when this process enforces access control.
    pub access_control: Option<PathBuf>,
}

#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    #[error("[zenoh.tls] needs `pki` or all of `ca`, `certificate` and `key`: {0} is not given")]
    Missing(&'static str),
    #[error("cannot read {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("{path} is readable by other users (mode {mode:o}); a private key must be 0600 or stricter: chmod 600 {path}")]
    KeyExposed { path: String, mode: u32 },
    #[error("{path} is not a PEM certificate: {message}")]
    NotACertificate { path: String, message: String },
    #[error("{path} is not a PEM private key: {message}")]
    NotAKey { path: String, message: String },
    #[error("the key {key} does not match the certificate {certificate}")]
    KeyMismatch { key: String, certificate: String },
    #[error("the certificate {certificate} is for {found:?}, not {expected:?} (the common name must be the process's identity)")]
    WrongIdentity {
        certificate: String,
        found: String,
        expected: String,
    },
    #[error("the certificate {certificate} was not issued by the CA {ca}")]
    NotIssuedByCa { certificate: String, ca: String },
    #[error("the certificate {path} is not valid now (valid from {not_before} to {not_after})")]
    Expired {
        path: String,
        not_before: String,
        not_after: String,
    },
    #[error("the access-control file {0} does not exist; `cell certs` writes it")]
    NoAccessControl(String),
}

impl TlsSettings {
    /// Makes relative paths relative to `base` (the config file's directory).
    pub fn resolve_paths(&mut self, base: &Path) {
        for path in [
            &mut self.pki,
            &mut self.ca,
            &mut self.certificate,
            &mut self.key,
            &mut self.access_control,
        ]
        .into_iter()
        .flatten()
        {
            if path.is_relative() {
                *path = base.join(&*path);
            }
        }
    }

    /// The files of `identity`, checked (see the module's doc). `enforce_access` asks for
    /// the access-control file too (holons and routers).
    pub fn identity_files(
        &self,
        identity: &str,
        enforce_access: bool,
    ) -> Result<IdentityFiles, TlsError> {
        let from_pki = |file: String| self.pki.as_ref().map(|dir| dir.join(file));
        let ca = self
            .ca
            .clone()
            .or_else(|| from_pki("ca.pem".into()))
            .ok_or(TlsError::Missing("ca"))?;
        let certificate = self
            .certificate
            .clone()
            .or_else(|| from_pki(format!("{identity}.pem")))
            .ok_or(TlsError::Missing("certificate"))?;
        let key = self
            .key
            .clone()
            .or_else(|| from_pki(format!("{identity}.key")))
            .ok_or(TlsError::Missing("key"))?;
        let access_control = if enforce_access {
            let path = self
                .access_control
                .clone()
                .or_else(|| from_pki("access_control.json5".into()))
                .ok_or(TlsError::Missing("access_control"))?;
            if !path.is_file() {
                return Err(TlsError::NoAccessControl(path.display().to_string()));
            }
            Some(path)
        } else {
            None
        };
        let files = IdentityFiles {
            identity: identity.to_string(),
            ca,
            certificate,
            key,
            access_control,
        };
        files.check()?;
        Ok(files)
    }
}

fn read(path: &Path) -> Result<Vec<u8>, TlsError> {
    std::fs::read(path).map_err(|source| TlsError::Read {
        path: path.display().to_string(),
        source,
    })
}

/// The DER of the first certificate in a PEM file.
fn certificate_der(path: &Path) -> Result<Vec<u8>, TlsError> {
    let pem = read(path)?;
    let not_cert = |message: String| TlsError::NotACertificate {
        path: path.display().to_string(),
        message,
    };
    let (_, pem) = x509_parser::pem::parse_x509_pem(&pem).map_err(|e| not_cert(e.to_string()))?;
    if pem.label != "CERTIFICATE" {
        return Err(not_cert(format!("it holds a {}", pem.label)));
    }
    Ok(pem.contents)
}

fn parse_certificate<'a>(
    path: &Path,
    der: &'a [u8],
) -> Result<x509_parser::certificate::X509Certificate<'a>, TlsError> {
    x509_parser::parse_x509_certificate(der)
        .map(|(_, c)| c)
        .map_err(|e| TlsError::NotACertificate {
            path: path.display().to_string(),
            message: e.to_string(),
        })
}

/// The common name of a certificate's subject.
pub fn common_name(cert: &x509_parser::certificate::X509Certificate<'_>) -> String {
    cert.subject()
        .iter_common_name()
        .next()
        .and_then(|cn| cn.as_str().ok())
        .unwrap_or("")
        .to_string()
}

impl IdentityFiles {
    /// Reads and checks the files: the key private and matching the certificate, the
    /// certificate issued by the CA, valid now and for this identity.
    pub fn check(&self) -> Result<(), TlsError> {
        use std::os::unix::fs::PermissionsExt;
        let show = |p: &Path| p.display().to_string();
        let metadata = std::fs::metadata(&self.key).map_err(|source| TlsError::Read {
            path: show(&self.key),
            source,
        })?;
        let mode = metadata.permissions().mode() & 0o777;
        if mode & 0o007 != 0 {
            return Err(TlsError::KeyExposed {
                path: show(&self.key),
                mode,
            });
        }
        let key_pem = String::from_utf8(read(&self.key)?).map_err(|_| TlsError::NotAKey {
            path: show(&self.key),
            message: "not text".into(),
        })?;
        let key = rcgen::KeyPair::from_pem(&key_pem).map_err(|e| TlsError::NotAKey {
            path: show(&self.key),
            message: e.to_string(),
        })?;
        let ca_der = certificate_der(&self.ca)?;
        let cert_der = certificate_der(&self.certificate)?;
        let ca = parse_certificate(&self.ca, &ca_der)?;
        let cert = parse_certificate(&self.certificate, &cert_der)?;
        if cert.public_key().subject_public_key.data.as_ref() != key.public_key_raw() {
            return Err(TlsError::KeyMismatch {
                key: show(&self.key),
                certificate: show(&self.certificate),
            });
        }
        if cert.verify_signature(Some(ca.public_key())).is_err() {
            return Err(TlsError::NotIssuedByCa {
                certificate: show(&self.certificate),
                ca: show(&self.ca),
            });
        }
        for (path, c) in [(&self.ca, &ca), (&self.certificate, &cert)] {
            if !c.validity().is_valid() {
                return Err(TlsError::Expired {
                    path: show(path),
                    not_before: c.validity().not_before.to_string(),
                    not_after: c.validity().not_after.to_string(),
                });
            }
        }
        let found = common_name(&cert);
        if found != self.identity {
            return Err(TlsError::WrongIdentity {
                certificate: show(&self.certificate),
                found,
                expected: self.identity.clone(),
            });
        }
        Ok(())
    }
}

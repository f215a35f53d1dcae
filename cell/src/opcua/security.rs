//! The OPC UA server's security: which endpoints it offers, its application certificate
//! (issued by the cell CA, `cell certs`), and which client application certificates it
//! trusts (`cell opcua --trust`); and who may log in ([`auth_and_files`]).
//! docs/opcua.md, "Security".

use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use opcua::crypto::{CertificateStore, SecurityPolicy};
use opcua::types::MessageSecurityMode;
use opcua_server::ServerEndpoint;
use tracing::info;

use super::users::CellAuth;
use super::OpcuaConfig;

/// The server certificate's file in the PKI directory (DER).
pub const SERVER_CERT: &str = "opcua-server.der";
/// The server certificate, PEM (for people and clients that want PEM).
pub const SERVER_CERT_PEM: &str = "opcua-server.pem";
/// The server's RSA key (PKCS#8 PEM, 0600).
pub const SERVER_KEY: &str = "opcua-server.key";
/// The old OPC UA users file (PBKDF2 hashes) in the PKI directory: no longer read, looked
/// for only to refuse a PKI that still has it and no `users.toml` (`cell users` makes one).
pub const USERS_FILE: &str = "opcua-users.toml";
/// The server's own certificate store in the PKI directory: `trusted/` (client
/// application certificates it accepts) and `rejected/` (those it refused).
pub const STORE_DIR: &str = "opcua";

/// The OPC UA ApplicationUri of a cell's server (also a URI SAN of its certificate).
pub fn application_uri(cell: &str) -> String {
    format!("urn:holarchy:{cell}:opcua")
}

/// Where the server's files of a PKI directory are.
#[derive(Debug, Clone)]
pub struct ServerFiles {
    /// The certificate (DER).
    pub certificate: PathBuf,
    /// The RSA private key (PEM).
    pub key: PathBuf,
    /// The certificate store (trusted/, rejected/).
    pub store: PathBuf,
}

impl ServerFiles {
    /// The files in `pki` (made absolute: async-opcua joins relative paths onto its
    /// store's directory).
    pub fn in_pki(pki: &Path) -> Result<ServerFiles> {
        let pki = pki
            .canonicalize()
            .with_context(|| format!("the PKI directory {} cannot be read", pki.display()))?;
        Ok(ServerFiles {
            certificate: pki.join(SERVER_CERT),
            key: pki.join(SERVER_KEY),
            store: pki.join(STORE_DIR),
        })
    }

    /// Checks that the certificate and key load and belong together, before the server
    /// starts (async-opcua would otherwise run without encryption, with a log line).
    pub fn check(&self) -> Result<()> {
        let hint = "issue it with `cell certs DIR` (a manifest with a `cell opcua` process) or see docs/opcua.md";
        if let Some(mode) = crate::security::private_file::open_to_others(&self.key) {
            bail!(
                "the OPC UA server key {} is readable by other users (mode {mode:o}); a private key must be 0600 or stricter: chmod 600 {}",
                self.key.display(),
                self.key.display()
            );
        }
        let cert = CertificateStore::read_cert(&self.certificate).map_err(|e| {
            anyhow!(
                "the OPC UA server certificate {}: {e}; {hint}",
                self.certificate.display()
            )
        })?;
        let key = CertificateStore::read_pkey(&self.key)
            .map_err(|e| anyhow!("the OPC UA server key {}: {e}; {hint}", self.key.display()))?;
        let public = cert.public_key().map_err(|e| {
            anyhow!(
                "the OPC UA server certificate {} has no RSA public key: {e}",
                self.certificate.display()
            )
        })?;
        let probe = b"holarchy opcua key check";
        let mut signature = vec![0u8; opcua::crypto::KeySize::size(&key)];
        let signed = key.sign_sha256(probe, &mut signature).map_err(|e| {
            anyhow!(
                "the OPC UA server key {} cannot sign: {e}",
                self.key.display()
            )
        })?;
        if !public
            .verify_sha256(probe, &signature[..signed])
            .unwrap_or(false)
        {
            bail!(
                "the OPC UA server key {} does not belong to the certificate {}",
                self.key.display(),
                self.certificate.display()
            );
        }
        Ok(())
    }
}

/// Whether the server listens on a loopback address only.
pub fn is_loopback(listen: &SocketAddr) -> bool {
    listen.ip().is_loopback()
}

/// The endpoints of a secure cell: SignAndEncrypt with the three current RSA policies.
pub fn secure_endpoints() -> Vec<(&'static str, ServerEndpoint)> {
    [
        ("basic256sha256", SecurityPolicy::Basic256Sha256),
        ("aes128sha256rsaoaep", SecurityPolicy::Aes128Sha256RsaOaep),
        ("aes256sha256rsapss", SecurityPolicy::Aes256Sha256RsaPss),
    ]
    .into_iter()
    .map(|(id, policy)| {
        (
            id,
            ServerEndpoint::new("/", policy, MessageSecurityMode::SignAndEncrypt, &[]),
        )
    })
    .collect()
}

/// Trusts a client application certificate (DER or PEM): copies it into the store's
/// `trusted/` under the name async-opcua looks for (`CN=<cn> [<sha1>].der`) and removes
/// it from `rejected/`. Returns the file written.
pub fn trust(pki: &Path, client: &Path) -> Result<PathBuf> {
    let files = ServerFiles::in_pki(pki)?;
    let cert = CertificateStore::read_cert(client)
        .map_err(|e| anyhow!("{}: not a certificate: {e}", client.display()))?;
    let name = CertificateStore::cert_file_name(&cert);
    let trusted = files.store.join("trusted");
    std::fs::create_dir_all(&trusted)
        .with_context(|| format!("cannot create {}", trusted.display()))?;
    let der = cert
        .to_der()
        .map_err(|_| anyhow!("{}: cannot encode the certificate", client.display()))?;
    let path = trusted.join(&name);
    std::fs::write(&path, der).with_context(|| format!("cannot write {}", path.display()))?;
    let rejected = files.store.join("rejected").join(&name);
    if rejected.exists() {
        std::fs::remove_file(&rejected)
            .with_context(|| format!("cannot remove {}", rejected.display()))?;
    }
    Ok(path)
}

/// Issues the server's application certificate into `pki`: a new 2048-bit RSA key (the
/// OPC UA policies need RSA; the cell CA may stay ECDSA), signed by the cell CA, with
/// the ApplicationUri and `addresses` as subject alternative names.
pub fn issue_server_certificate(
    pki: &Path,
    cell: &str,
    addresses: &[String],
    days: u32,
    issuer: &rcgen::Issuer<'_, rcgen::KeyPair>,
) -> Result<()> {
    use rcgen::{
        CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, KeyUsagePurpose,
        SanType,
    };
    let rsa =
        opcua::crypto::PrivateKey::new(2048).map_err(|e| anyhow!("cannot make an RSA key: {e}"))?;
    let der = rsa
        .to_der()
        .map_err(|e| anyhow!("cannot encode the RSA key: {e}"))?;
    let key = rcgen::KeyPair::from_pkcs8_der_and_sign_algo(
        &der.as_bytes().into(),
        &rcgen::PKCS_RSA_SHA256,
    )?;
    let mut params = CertificateParams::new(addresses.to_vec())?;
    params
        .subject_alt_names
        .push(SanType::URI(application_uri(cell).as_str().try_into()?));
    let mut dn = DistinguishedName::new();
    dn.push(
        DnType::CommonName,
        format!("holarchy cell {cell} OPC UA server"),
    );
    dn.push(DnType::OrganizationName, "holarchy");
    params.distinguished_name = dn;
    params.key_usages = vec![
        KeyUsagePurpose::DigitalSignature,
        KeyUsagePurpose::ContentCommitment,
        KeyUsagePurpose::KeyEncipherment,
        KeyUsagePurpose::DataEncipherment,
    ];
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    let now = time::OffsetDateTime::now_utc();
    params.not_before = now - time::Duration::hours(1);
    params.not_after = now + time::Duration::days(days as i64);
    let cert = params.signed_by(&key, issuer)?;
    crate::security::private_file::write_private(&pki.join(SERVER_KEY), &key.serialize_pem())?;
    std::fs::write(pki.join(SERVER_CERT), cert.der())?;
    std::fs::write(pki.join(SERVER_CERT_PEM), cert.pem())?;
    Ok(())
}

/// Watches the store's `rejected/` until `shutdown` and logs each client certificate
/// that lands there with the command that trusts it (async-opcua's own line does not
/// say how).
pub async fn watch_rejected(
    pki: PathBuf,
    store: PathBuf,
    shutdown: tokio_util::sync::CancellationToken,
) {
    let rejected = store.join("rejected");
    let list = || -> std::collections::BTreeSet<PathBuf> {
        std::fs::read_dir(&rejected)
            .map(|entries| entries.filter_map(|e| e.ok().map(|e| e.path())).collect())
            .unwrap_or_default()
    };
    let mut seen = list();
    for path in &seen {
        tracing::warn!(certificate = %path.display(), "a client certificate waits in rejected/: trust it with `cell opcua --pki {} --trust '{}'`", pki.display(), path.display());
    }
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            _ = tokio::time::sleep(std::time::Duration::from_secs(1)) => {}
        }
        let now = list();
        for path in now.difference(&seen) {
            tracing::warn!(certificate = %path.display(), "an unknown client application certificate was rejected (BadCertificateUntrusted): trust it with `cell opcua --pki {} --trust '{}'`", pki.display(), path.display());
        }
        seen = now;
    }
}

/// Who may log in, and the server's certificate files: anonymous on loopback in a plain
/// cell; the users file, the logins' throttle and the audit trail in a secure one.
pub(super) fn auth_and_files(config: &OpcuaConfig) -> Result<(CellAuth, Option<ServerFiles>)> {
    let Some(pki) = &config.pki else {
        if !is_loopback(&config.listen) {
            bail!(
                "refusing to serve OPC UA without security on {} (not a loopback address): anyone on that network could command the cell's resources; run with --pki DIR (a secure cell, docs/opcua.md) or listen on 127.0.0.1",
                config.listen
            );
        }
        return Ok((CellAuth::anonymous(), None));
    };
    let files = ServerFiles::in_pki(pki)?;
    files.check()?;
    let users_path = match &config.users {
        Some(path) => path.clone(),
        None => default_users_file(pki)?,
    };
    let users = crate::security::users::load(&users_path).with_context(|| {
        format!(
            "a secure cell's OPC UA server needs its users (docs/opcua.md, \"Users\"): add them with `cell users --pki {} add NAME --role observer|operator|admin`",
            pki.display()
        )
    })?;
    if users.is_empty() {
        bail!(
            "the users file {} names no user: no one could log in (`cell users --pki {} add NAME --role operator`)",
            users_path.display(),
            pki.display()
        );
    }
    info!(users = users.len(), file = %users_path.display(), "OPC UA users loaded");
    let audit_path = match &config.audit {
        Some(path) => path.clone(),
        None => users_path
            .parent()
            .unwrap_or(std::path::Path::new("."))
            .join(crate::security::audit::FILE_NAME),
    };
    let audit = crate::security::audit::AuditTrail::open(&audit_path)?;
    let auth = CellAuth {
        anonymous: false,
        users: crate::security::users::CurrentUsers::file(users_path),
        logins: crate::security::logins::Logins::default(),
        audit: Some(audit),
    };
    Ok((auth, Some(files)))
}

/// The users file of a secure cell without `--users`: `<pki>/users.toml`. Refuses a
/// PKI directory that still has only the old OPC UA users file (`opcua-users.toml`,
/// PBKDF2 hashes): its users must be added again.
fn default_users_file(pki: &std::path::Path) -> Result<PathBuf> {
    let path = crate::security::users::default_path(pki);
    let old = pki.join(USERS_FILE);
    if old.exists() && !path.exists() {
        bail!(
            "{} is no longer read: the cell's users now live in {} (one file for the dashboard and the OPC UA server, argon2id hashes); add them again with `cell users --pki {} add NAME --role observer|operator|admin`, then remove {}",
            old.display(),
            path.display(),
            pki.display(),
            old.display()
        );
    }
    Ok(path)
}

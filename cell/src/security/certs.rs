//! `cell certs DIR`: the identities of a cell, from its manifest `DIR/cell.toml`.
//!
//! Writes into the PKI directory (`[pki] dir`, default `DIR/pki`):
//! - `ca.pem`, `ca.key`: the cell CA (made once; replaced only with `--force`);
//! - `<identity>.pem`, `<identity>.key` (0600) for every process with an `identity`,
//!   a router per host (`router.<host>`), the operators, observers and spares of
//!   `[pki]`, and an etcd member per host of `[pki] etcd_hosts` (`etcd.<host>`: the
//!   host's addresses and loopback, for etcd's `--cert-file`/`--key-file` and
//!   `--peer-cert-file`/`--peer-key-file`, with the CA as its trusted CA): issued when
//!   missing, not issued by the current CA, expiring within 30 days, or named by
//!   `--renew`;
//! - `access_control.json5`: the cell's zenoh access control (see `crate::security::access`),
//!   rewritten every time; etcd members are not in it (they are no zenoh clients);
//! - `router-<host>.json5`: a zenohd config per router of the manifest (listen,
//!   connect, TLS, access control), for the stock `zenohd -c` or `cell router --config`;
//! - `opcua-server.der`, `.pem`, `.key` (RSA, 0600): the OPC UA server's application
//!   certificate, when the manifest runs `cell opcua` (docs/opcua.md); issued when
//!   missing, with a new CA, or with `--renew opcua-server`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use rcgen::{
    BasicConstraints, CertificateParams, DistinguishedName, DnType, ExtendedKeyUsagePurpose, IsCa,
    Issuer, KeyPair, KeyUsagePurpose,
};

use crate::security::access;
use crate::up::manifest::Manifest;

#[derive(Debug, Clone, Default)]
pub struct CertsOptions {
    /// Make a new CA (and so reissue every identity) even if one exists.
    pub force: bool,
    /// Reissue these identities (rotation) even if their certificates are good.
    pub renew: Vec<String>,
}

/// One identity of the cell and the addresses its certificate names.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Identity {
    pub name: String,
    /// Subject alternative names: what others may connect to it by.
    pub addresses: Vec<String>,
}

/// The host part of an endpoint such as `tls/10.0.0.5:7447` or `tls/[::1]:7447`.
fn endpoint_host(endpoint: &str) -> Option<String> {
    let address = endpoint.split_once('/')?.1;
    let address = address.split('#').next()?;
    let (host, _port) = address.rsplit_once(':')?;
    let host = host.trim_start_matches('[').trim_end_matches(']');
    (!host.is_empty() && host != "0.0.0.0" && host != "::").then(|| host.to_string())
}

/// Every identity of the manifest, with the addresses of its host.
pub fn identities(manifest: &Manifest) -> Result<Vec<Identity>> {
    let mut host_addresses: BTreeMap<String, Vec<String>> = BTreeMap::new();
    let local = ["localhost", "127.0.0.1", "::1"].map(String::from).to_vec();
    let mut routers = Vec::new();
    if let Some(router) = &manifest.router {
        routers.push(("local".to_string(), router.listen.clone()));
    }
    for (host, section) in &manifest.hosts {
        let mut addresses = section.addresses.clone();
        if let Some(router) = &section.router {
            routers.push((host.clone(), router.listen.clone()));
            addresses.extend(router.listen.iter().filter_map(|e| endpoint_host(e)));
        }
        host_addresses.insert(host.clone(), addresses);
    }
    let addresses_of = |host: &str| {
        let mut all = local.clone();
        all.extend(host_addresses.get(host).cloned().unwrap_or_default());
        all.sort();
        all.dedup();
        all
    };
    let mut out: Vec<Identity> = Vec::new();
    let mut push = |name: String, addresses: Vec<String>| -> Result<()> {
        access::parse_identity(&name)?;
        if out.iter().any(|i| i.name == name) {
            bail!("identity {name} appears twice in the manifest");
        }
        out.push(Identity { name, addresses });
        Ok(())
    };
    for (host, listen) in routers {
        let mut addresses = addresses_of(&host);
        addresses.extend(listen.iter().filter_map(|e| endpoint_host(e)));
        addresses.sort();
        addresses.dedup();
        push(
            holon::role::identity(holon::role::Role::Router, &host),
            addresses,
        )?;
    }
    for process in &manifest.processes {
        if let Some(identity) = &process.identity {
            // A standby runs as the same identity on its own host.
            let mut addresses = addresses_of(&process.host);
            if let Some(standby_on) = &process.standby_on {
                addresses.extend(addresses_of(standby_on));
                addresses.sort();
                addresses.dedup();
            }
            push(identity.clone(), addresses)?;
        }
    }
    for spare in &manifest.pki.spares {
        push(spare.clone(), addresses_of("local"))?;
    }
    for host in &manifest.pki.etcd_hosts {
        if host != "local" && !manifest.hosts.contains_key(host) {
            bail!(
                "[pki] etcd_hosts names {host:?}, which is neither \"local\" nor a host of \
                 [hosts]"
            );
        }
        let mut addresses = addresses_of(host);
        if host == "local" {
            // A one-host manifest's addresses are its router's.
            let listen = manifest.router.iter().flat_map(|r| &r.listen);
            addresses.extend(listen.filter_map(|e| endpoint_host(e)));
            addresses.sort();
            addresses.dedup();
        }
        push(
            holon::role::identity(holon::role::Role::Etcd, host),
            addresses,
        )?;
    }
    for operator in &manifest.pki.operators {
        push(
            holon::role::identity(holon::role::Role::Operator, operator),
            local.clone(),
        )?;
    }
    for observer in &manifest.pki.observers {
        push(
            holon::role::identity(holon::role::Role::Observer, observer),
            local.clone(),
        )?;
    }
    // An order-node's orders are `<node>-<n>`: no node may be named like another's orders.
    let nodes: Vec<&str> = out
        .iter()
        .filter_map(|i| i.name.strip_prefix("order-node."))
        .collect();
    for a in &nodes {
        for b in &nodes {
            if a != b && b.starts_with(&format!("{a}-")) {
                bail!("order-nodes {a} and {b}: {b}'s name starts with {a}-, so access control could not tell {a}'s orders from {b}'s; rename one");
            }
        }
    }
    Ok(out)
}

fn validity(days: u32) -> (time::OffsetDateTime, time::OffsetDateTime) {
    let now = time::OffsetDateTime::now_utc();
    (
        now - time::Duration::hours(1),
        now + time::Duration::days(days as i64),
    )
}

fn new_ca(cell: &str) -> Result<(String, KeyPair)> {
    let key = KeyPair::generate()?;
    let mut params = CertificateParams::default();
    let mut dn = DistinguishedName::new();
    dn.push(DnType::CommonName, format!("holarchy cell {cell} CA"));
    params.distinguished_name = dn;
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.key_usages = vec![
        KeyUsagePurpose::KeyCertSign,
        KeyUsagePurpose::CrlSign,
        KeyUsagePurpose::DigitalSignature,
    ];
    (params.not_before, params.not_after) = validity(3650);
    let cert = params.self_signed(&key)?;
    Ok((cert.pem(), key))
}

fn issue(identity: &Identity, days: u32, issuer: &Issuer<'_, KeyPair>) -> Result<(String, String)> {
    let key = KeyPair::generate()?;
    let mut params = CertificateParams::new(identity.addresses.clone())
        .with_context(|| format!("{}: addresses", identity.name))?;
    let mut dn = DistinguishedName::new();
    dn.push(DnType::CommonName, identity.name.clone());
    params.distinguished_name = dn;
    params.key_usages = vec![
        KeyUsagePurpose::DigitalSignature,
        KeyUsagePurpose::KeyEncipherment,
    ];
    params.extended_key_usages = vec![
        ExtendedKeyUsagePurpose::ServerAuth,
        ExtendedKeyUsagePurpose::ClientAuth,
    ];
    (params.not_before, params.not_after) = validity(days);
    let cert = params.signed_by(&key, issuer)?;
    Ok((cert.pem(), key.serialize_pem()))
}

/// Whether the certificate at `path` is good: issued by `ca_pem`'s CA, for this
/// identity, valid for 30 more days, with its key beside it.
fn still_good(dir: &Path, identity: &str) -> bool {
    let files = holon::tls::IdentityFiles {
        identity: identity.to_string(),
        ca: dir.join("ca.pem"),
        certificate: dir.join(format!("{identity}.pem")),
        key: dir.join(format!("{identity}.key")),
        access_control: None,
    };
    if files.check().is_err() {
        return false;
    }
    let Ok(pem) = std::fs::read(&files.certificate) else {
        return false;
    };
    let Ok((_, pem)) = x509_parser::pem::parse_x509_pem(&pem) else {
        return false;
    };
    let Ok((_, cert)) = x509_parser::parse_x509_certificate(&pem.contents) else {
        return false;
    };
    let soon = time::OffsetDateTime::now_utc() + time::Duration::days(30);
    cert.validity().not_after.to_datetime() > soon
}

/// A zenohd config for the router of `host`.
fn router_config(
    manifest: &Manifest,
    host: &str,
    pki: &Path,
    access: &serde_json::Value,
) -> Option<serde_json::Value> {
    let router = if host == "local" {
        manifest.router.as_ref()?
    } else {
        manifest.hosts.get(host)?.router.as_ref()?
    };
    let identity = holon::role::identity(holon::role::Role::Router, host);
    let path = |file: String| pki.join(file).display().to_string();
    let mut config = serde_json::json!({
        "mode": "router",
        "listen": { "endpoints": router.listen },
        "connect": { "endpoints": router.connect },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": { "tls": {
            "root_ca_certificate": path("ca.pem".into()),
            "listen_certificate": path(format!("{identity}.pem")),
            "listen_private_key": path(format!("{identity}.key")),
            "connect_certificate": path(format!("{identity}.pem")),
            "connect_private_key": path(format!("{identity}.key")),
            "enable_mtls": true,
            "verify_name_on_connect": true,
            "close_link_on_expiration": true,
        } } },
        "access_control": access["access_control"],
    });
    if let Some(lease) = router.lease_ms {
        config["transport"]["link"]["tx"] = serde_json::json!({ "lease": lease });
    }
    Some(config)
}

/// Issues what is missing; returns the lines to print.
pub fn run(dir: &Path, options: &CertsOptions) -> Result<Vec<String>> {
    let manifest = Manifest::load(dir)?;
    let identities = identities(&manifest)?;
    for renew in &options.renew {
        let known = identities.iter().any(|i| &i.name == renew)
            || (renew == OPCUA_SERVER && opcua_server(&manifest).is_some());
        if !known {
            bail!(
                "--renew {renew}: no such identity in {}",
                dir.join("cell.toml").display()
            );
        }
    }
    let pki = dir.join(&manifest.pki.dir);
    std::fs::create_dir_all(&pki).with_context(|| format!("cannot create {}", pki.display()))?;
    let pki = pki
        .canonicalize()
        .with_context(|| format!("cannot resolve {}", pki.display()))?;
    let mut said = Vec::new();
    let ca_pem_path = pki.join("ca.pem");
    let ca_key_path = pki.join("ca.key");
    let made_ca = if options.force || !ca_pem_path.exists() {
        if ca_key_path.exists() && !options.force {
            bail!(
                "{} exists without {}; restore the CA certificate or use --force for a new CA",
                ca_key_path.display(),
                ca_pem_path.display()
            );
        }
        let (pem, key) = new_ca(&manifest.cell)?;
        crate::security::private_file::write_private(&ca_key_path, &key.serialize_pem())?;
        std::fs::write(&ca_pem_path, pem)?;
        said.push(format!("new cell CA {}", ca_pem_path.display()));
        true
    } else {
        said.push(format!("using the cell CA {}", ca_pem_path.display()));
        false
    };
    let ca_pem = std::fs::read_to_string(&ca_pem_path)?;
    let ca_key_pem = std::fs::read_to_string(&ca_key_path).with_context(|| {
        format!(
            "cannot read the CA key {} (it is needed to issue identities)",
            ca_key_path.display()
        )
    })?;
    let ca_key =
        KeyPair::from_pem(&ca_key_pem).map_err(|e| anyhow!("{}: {e}", ca_key_path.display()))?;
    let issuer = Issuer::from_ca_cert_pem(&ca_pem, ca_key)
        .map_err(|e| anyhow!("{}: {e}", ca_pem_path.display()))?;
    for identity in &identities {
        let renew = made_ca || options.renew.contains(&identity.name);
        if !renew && still_good(&pki, &identity.name) {
            continue;
        }
        let (cert, key) = issue(identity, manifest.pki.days, &issuer)?;
        crate::security::private_file::write_private(
            &pki.join(format!("{}.key", identity.name)),
            &key,
        )?;
        std::fs::write(pki.join(format!("{}.pem", identity.name)), cert)?;
        said.push(format!(
            "issued {} ({})",
            identity.name,
            identity.addresses.join(", ")
        ));
    }
    if let Some(server) = opcua_server(&manifest) {
        let fresh = pki.join(crate::opcua::security::SERVER_CERT).exists()
            && pki.join(crate::opcua::security::SERVER_KEY).exists();
        if made_ca || !fresh || options.renew.iter().any(|r| r == OPCUA_SERVER) {
            let addresses = server
                .identity
                .as_ref()
                .and_then(|name| identities.iter().find(|i| &i.name == name))
                .map(|i| i.addresses.clone())
                .unwrap_or_else(|| ["localhost", "127.0.0.1", "::1"].map(String::from).to_vec());
            crate::opcua::security::issue_server_certificate(
                &pki,
                &manifest.cell,
                &addresses,
                manifest.pki.days,
                &issuer,
            )?;
            said.push(format!(
                "issued the OPC UA server's certificate {} (RSA, for `cell opcua`; {})",
                pki.join(crate::opcua::security::SERVER_CERT).display(),
                addresses.join(", ")
            ));
        }
    }
    let names: Vec<String> = identities.iter().map(|i| i.name.clone()).collect();
    let access = access::access_control(&manifest.cell, &names)?;
    let access_path = pki.join("access_control.json5");
    std::fs::write(&access_path, serde_json::to_string_pretty(&access)?)?;
    said.push(format!(
        "access control for {} identities in {}",
        names.len(),
        access_path.display()
    ));
    let hosts: Vec<String> = std::iter::once("local".to_string())
        .chain(manifest.hosts.keys().cloned())
        .collect();
    for host in hosts {
        if let Some(config) = router_config(&manifest, &host, &pki, &access) {
            let path = pki.join(format!("router-{host}.json5"));
            std::fs::write(&path, serde_json::to_string_pretty(&config)?)?;
            said.push(format!(
                "zenohd config of router.{host} in {}",
                path.display()
            ));
        }
    }
    Ok(said)
}

/// The name `--renew` takes for the OPC UA server's application certificate.
pub const OPCUA_SERVER: &str = "opcua-server";

/// The manifest's `cell opcua` process, if it has one: its certificate is issued too.
fn opcua_server(manifest: &Manifest) -> Option<&crate::up::manifest::ProcessSection> {
    manifest.processes.iter().find(|p| {
        Path::new(&p.program).file_name().and_then(|n| n.to_str()) == Some("cell")
            && p.args.first().map(String::as_str) == Some("opcua")
    })
}

/// The PKI directory of a manifest, for the commands that use it.
pub fn pki_dir(dir: &Path, manifest: &Manifest) -> PathBuf {
    dir.join(&manifest.pki.dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoint_hosts() {
        assert_eq!(
            endpoint_host("tls/10.0.0.5:7447").as_deref(),
            Some("10.0.0.5")
        );
        assert_eq!(endpoint_host("tls/[::1]:7447").as_deref(), Some("::1"));
        assert_eq!(endpoint_host("tls/0.0.0.0:7447"), None);
    }

    #[test]
    fn the_secure_cell_has_an_identity_for_every_holon() {
        let dir = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../deploy/cells/secure"
        ));
        let manifest = Manifest::load(dir).unwrap();
        let names: Vec<String> = identities(&manifest)
            .unwrap()
            .into_iter()
            .map(|i| i.name)
            .collect();
        for expected in [
            "router.local",
            "resource.robot1",
            "resource.robot2",
            "resource.inspect1",
            "resource.conveyor1",
            "product.breaker",
            "order-node.orders1",
            "resource.robot3",
            "operator.default",
            "observer.default",
        ] {
            assert!(names.iter().any(|n| n == expected), "{expected}: {names:?}");
        }
        // Every holon process of the manifest has one.
        for process in &manifest.processes {
            let holon = matches!(process.program.as_str(), "holon-node" | "order-node");
            assert_eq!(process.identity.is_some(), holon, "{}", process.name);
        }
    }

    #[test]
    fn a_manifest_running_cell_opcua_gets_its_server_certificate() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("cell.toml"),
            "cell = \"t\"\n[[process]]\nname = \"opcua\"\nprogram = \"cell\"\nargs = [\"opcua\", \"--pki\", \"pki\"]\nidentity = \"operator.opcua\"\n",
        )
        .unwrap();
        let said = run(dir.path(), &CertsOptions::default()).unwrap();
        assert!(said.iter().any(|l| l.contains("OPC UA server")), "{said:?}");
        let pki = dir.path().join("pki");
        let files = crate::opcua::security::ServerFiles::in_pki(&pki).unwrap();
        files.check().unwrap();
        assert!(pki.join("operator.opcua.pem").exists());
        // Kept on a second run; reissued with --renew opcua-server.
        let again = run(dir.path(), &CertsOptions::default()).unwrap();
        assert!(
            !again.iter().any(|l| l.contains("OPC UA server")),
            "{again:?}"
        );
        let before = std::fs::read(&files.certificate).unwrap();
        let renewed = run(
            dir.path(),
            &CertsOptions {
                renew: vec![OPCUA_SERVER.into()],
                ..Default::default()
            },
        )
        .unwrap();
        assert!(
            renewed.iter().any(|l| l.contains("OPC UA server")),
            "{renewed:?}"
        );
        assert_ne!(std::fs::read(&files.certificate).unwrap(), before);
        files.check().unwrap();
        // A key of another certificate is refused.
        std::fs::copy(pki.join("operator.opcua.key"), &files.key).unwrap();
        assert!(files.check().is_err());
    }

    #[test]
    fn etcd_members_get_server_and_client_certificates_and_no_zenoh_rights() {
        let dir = tempfile::tempdir().unwrap();
        let manifest = |etcd_hosts: &str| {
            format!(
                "cell = \"t\"\n[hosts.b]\naddresses = [\"10.0.0.2\", \"etcd-b.plant\"]\n\
                 [hosts.c.router]\nlisten = [\"tls/10.0.0.3:7447\"]\n[pki]\n\
                 etcd_hosts = {etcd_hosts}\n[[process]]\nname = \"o\"\n\
                 program = \"order-node\"\nhost = \"b\"\nidentity = \"order-node.orders1\"\n"
            )
        };
        let path = dir.path().join("cell.toml");
        std::fs::write(&path, manifest("[\"b\", \"c\"]")).unwrap();
        let said = run(dir.path(), &CertsOptions::default()).unwrap();
        assert!(
            said.iter().any(|l| l.starts_with("issued etcd.b")),
            "{said:?}"
        );
        let pki = dir.path().join("pki");
        for (host, address) in [("b", "10.0.0.2"), ("c", "10.0.0.3")] {
            let identity = format!("etcd.{host}");
            let tls = holon::tls::TlsSettings {
                pki: Some(pki.clone()),
                ..Default::default()
            };
            tls.identity_files(&identity, false)
                .unwrap_or_else(|e| panic!("{identity}: {e}"));
            let pem = std::fs::read(pki.join(format!("{identity}.pem"))).unwrap();
            let (_, pem) = x509_parser::pem::parse_x509_pem(&pem).unwrap();
            let (_, cert) = x509_parser::parse_x509_certificate(&pem.contents).unwrap();
            let names: Vec<String> = cert
                .subject_alternative_name()
                .unwrap()
                .unwrap()
                .value
                .general_names
                .iter()
                .map(|n| match n {
                    x509_parser::extensions::GeneralName::DNSName(d) => d.to_string(),
                    x509_parser::extensions::GeneralName::IPAddress(ip) => {
                        let octets: [u8; 4] = (*ip).try_into().unwrap_or([0; 4]);
                        std::net::Ipv4Addr::from(octets).to_string()
                    }
                    other => format!("{other:?}"),
                })
                .collect();
            for expected in [address, "127.0.0.1", "localhost"] {
                assert!(names.iter().any(|n| n == expected), "{identity}: {names:?}");
            }
            let usage = cert.extended_key_usage().unwrap().unwrap().value;
            assert!(usage.server_auth && usage.client_auth, "{identity}");
        }
        // Not in the cell's zenoh access control: no subject, so denied everything.
        let access = std::fs::read_to_string(pki.join("access_control.json5")).unwrap();
        assert!(access.contains("order-node.orders1"), "{access}");
        assert!(!access.contains("etcd."), "{access}");
        // A host the manifest does not know is refused.
        std::fs::write(&path, manifest("[\"d\"]")).unwrap();
        let error = run(dir.path(), &CertsOptions::default()).unwrap_err();
        assert!(error.to_string().contains("\"d\""), "{error}");
    }

    #[test]
    fn order_node_names_must_not_overlap() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("cell.toml"),
            "cell = \"t\"\n[[process]]\nname = \"a\"\nprogram = \"order-node\"\nidentity = \"order-node.orders1\"\n[[process]]\nname = \"b\"\nprogram = \"order-node\"\nidentity = \"order-node.orders1-x\"\n",
        )
        .unwrap();
        let manifest = Manifest::load(dir.path()).unwrap();
        let err = identities(&manifest).unwrap_err();
        assert!(err.to_string().contains("rename one"), "{err}");
    }

    #[test]
    fn issues_a_pki_that_the_holons_accept() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join("cell.toml"),
            r#"
cell = "t"
[router]
listen = ["tls/127.0.0.1:17000"]
[pki]
spares = ["resource.robot9"]
[[process]]
name = "robot1"
program = "holon-node"
identity = "resource.robot1"
"#,
        )
        .unwrap();
        let said = run(dir.path(), &CertsOptions::default()).unwrap();
        assert!(
            said.iter().any(|l| l.starts_with("new cell CA")),
            "{said:?}"
        );
        let pki = dir.path().join("pki");
        for identity in [
            "router.local",
            "resource.robot1",
            "resource.robot9",
            "operator.default",
            "observer.default",
        ] {
            let tls = holon::tls::TlsSettings {
                pki: Some(pki.clone()),
                ..Default::default()
            };
            tls.identity_files(identity, true)
                .unwrap_or_else(|e| panic!("{identity}: {e}"));
        }
        // A second run keeps the CA and issues nothing new.
        let again = run(dir.path(), &CertsOptions::default()).unwrap();
        assert!(!again.iter().any(|l| l.starts_with("issued")), "{again:?}");
        // Renewing one reissues only it.
        let renewed = run(
            dir.path(),
            &CertsOptions {
                renew: vec!["resource.robot1".into()],
                ..Default::default()
            },
        )
        .unwrap();
        let issued: Vec<_> = renewed.iter().filter(|l| l.starts_with("issued")).collect();
        assert_eq!(issued.len(), 1, "{renewed:?}");
        // A key readable by everyone, or another identity's certificate, is refused.
        use std::os::unix::fs::PermissionsExt;
        let key = pki.join("resource.robot1.key");
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).unwrap();
        let tls = holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            ..Default::default()
        };
        let err = tls.identity_files("resource.robot1", true).unwrap_err();
        assert!(err.to_string().contains("readable by other users"), "{err}");
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
        let mismatched = holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            key: Some(pki.join("resource.robot9.key")),
            ..Default::default()
        };
        let err = mismatched
            .identity_files("resource.robot1", true)
            .unwrap_err();
        assert!(err.to_string().contains("does not match"), "{err}");
        let wrong = holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            certificate: Some(pki.join("resource.robot9.pem")),
            key: Some(pki.join("resource.robot9.key")),
            ..Default::default()
        };
        let err = wrong.identity_files("resource.robot1", true).unwrap_err();
        assert!(
            err.to_string().contains("is for \"resource.robot9\""),
            "{err}"
        );
    }
}

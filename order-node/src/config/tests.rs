use super::*;

const DEMO: &str = include_str!("../../../deploy/cells/demo/orders1.toml");

#[test]
fn the_demo_config_loads() {
    let c = OrderNodeConfig::parse(DEMO, "orders1.toml", Overrides::default()).unwrap();
    assert_eq!(c.name, "orders1");
    assert_eq!(c.orders.max_attempts, 3);
}

#[test]
fn the_journal_may_be_on_etcd() {
    let sqlite = OrderNodeConfig::parse(DEMO, "x", Overrides::default()).unwrap();
    assert_eq!(sqlite.etcd, None, "SQLite stays the default");
    let with = |journal: &str| {
        let text = DEMO.replacen("[journal]", &format!("[journal]\n{journal}"), 1);
        let text = text.replace("max_orders_per_submit = 1000\n", "");
        OrderNodeConfig::parse(&text, "x", Overrides::default())
    };
    let c = with("etcd = [\"http://10.0.0.1:2379\", \"http://10.0.0.2:2379\"]").unwrap();
    let etcd = c.etcd.unwrap();
    assert_eq!(etcd.endpoints.len(), 2);
    assert_eq!(etcd.prefix, "holarchy/demo/order-node/orders1");
    assert_eq!(etcd.lease_ttl, Duration::from_secs(2));
    assert_eq!(
        c.orders.max_orders_per_submit, MAX_ORDERS_PER_SUBMIT_ON_ETCD,
        "a work order fits one etcd commit"
    );
    let c = with("etcd = [\"http://e:2379\"]\netcd_prefix = \"plant/o1/\"\nlease_ttl_ms = 3000")
        .unwrap()
        .etcd
        .unwrap();
    assert_eq!(
        (c.prefix.as_str(), c.lease_ttl),
        ("plant/o1", Duration::from_secs(3))
    );
    for refused in [
        "etcd = [\"http://e:2379\"]\ndir = \"/var/lib/holarchy\"",
        "etcd = [\"http://e:2379\"]\nlease_ttl_ms = 1500",
        "etcd = [\"http://e:2379\"]\nlease_ttl_ms = 1000",
        "etcd = [\"\"]",
        "etcd_prefix = \"a\"",
    ] {
        assert!(with(refused).is_err(), "{refused}");
    }
    // The demo's explicit 1000 does not fit one commit.
    let text = DEMO.replacen("[journal]", "[journal]\netcd = [\"http://e:2379\"]", 1);
    let e = OrderNodeConfig::parse(&text, "x", Overrides::default()).unwrap_err();
    assert!(e.to_string().contains("max_orders_per_submit"), "{e}");
    // --data-dir and --take-over are refused with etcd.
    let text = DEMO
        .replacen("[journal]", "[journal]\netcd = [\"http://e:2379\"]", 1)
        .replace("max_orders_per_submit = 1000\n", "");
    for overrides in [
        Overrides {
            data_dir: Some("/tmp/x".into()),
            ..Default::default()
        },
        Overrides {
            take_over: Some(Duration::from_secs(5)),
            ..Default::default()
        },
    ] {
        assert!(OrderNodeConfig::parse(&text, "x", overrides).is_err());
    }
}

/// A PKI directory as `cell certs` writes one: `ca.pem` and `order-node.orders1`'s
/// certificate and key (0600).
fn pki() -> tempfile::TempDir {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let ca_key = rcgen::KeyPair::generate().unwrap();
    let mut ca = rcgen::CertificateParams::default();
    ca.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    ca.distinguished_name
        .push(rcgen::DnType::CommonName, "holarchy cell demo CA");
    let ca_cert = ca.self_signed(&ca_key).unwrap();
    let issuer = rcgen::Issuer::new(ca, ca_key);
    let key = rcgen::KeyPair::generate().unwrap();
    let mut params = rcgen::CertificateParams::new(vec!["localhost".into()]).unwrap();
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "order-node.orders1");
    let cert = params.signed_by(&key, &issuer).unwrap();
    std::fs::write(dir.path().join("ca.pem"), ca_cert.pem()).unwrap();
    std::fs::write(dir.path().join("order-node.orders1.pem"), cert.pem()).unwrap();
    let key_path = dir.path().join("order-node.orders1.key");
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    std::fs::set_permissions(&key_path, std::fs::Permissions::from_mode(0o600)).unwrap();
    dir
}

/// The demo config with `journal` added to `[journal]`, read as `path`, in a
/// secure cell of `pki` when given (its zenoh endpoints then `tls/`).
fn etcd_config(
    journal: &str,
    pki: Option<&Path>,
    path: &str,
) -> Result<OrderNodeConfig, ConfigError> {
    let mut text = DEMO
        .replacen("[journal]", &format!("[journal]\n{journal}"), 1)
        .replace("max_orders_per_submit = 1000\n", "");
    if let Some(pki) = pki {
        text = text
            .replace("tcp/127.0.0.1:7447", "tls/127.0.0.1:7447")
            .replacen(
                "[orders]",
                &format!("[zenoh.tls]\npki = {:?}\n\n[orders]", pki.display()),
                1,
            );
    }
    OrderNodeConfig::parse(&text, path, Overrides::default())
}

/// The TLS files an etcd journal config resolves to (it must have some).
fn etcd_tls(journal: &str, pki: Option<&Path>, path: &str) -> holon::etcd::TlsFiles {
    etcd_config(journal, pki, path)
        .unwrap()
        .etcd
        .unwrap()
        .tls
        .expect("TLS files")
}

#[test]
fn etcd_over_tls_takes_the_cells_pki_or_its_own_files() {
    let pki = pki();
    let dir = pki.path();
    // In a secure cell, https uses the cell CA and the node's identity.
    let tls = etcd_tls("etcd = [\"https://10.0.0.1:2379\"]", Some(dir), "x");
    assert_eq!(tls.ca, dir.join("ca.pem"));
    assert_eq!(tls.certificate, dir.join("order-node.orders1.pem"));
    assert_eq!(tls.key, dir.join("order-node.orders1.key"));
    // Outside one, the files of [journal.etcd_tls], relative to the config file.
    let config_path = dir.join("orders1.toml").display().to_string();
    let own = "etcd = [\"https://etcd-a:2379\", \"https://etcd-b:2379\"]\n\
               etcd_tls = { ca = \"ca.pem\", certificate = \"order-node.orders1.pem\", \
               key = \"order-node.orders1.key\" }";
    let tls = etcd_tls(own, None, &config_path);
    assert_eq!(tls.ca, dir.join("ca.pem"));
    assert_eq!(tls.key, dir.join("order-node.orders1.key"));
    // One field given overrides the cell's, the others stay the cell's.
    let ca_only = format!(
        "etcd = [\"https://10.0.0.1:2379\"]\netcd_tls = {{ ca = {:?} }}",
        dir.join("order-node.orders1.pem").display()
    );
    let tls = etcd_tls(&ca_only, Some(dir), "x");
    assert_eq!(tls.ca, dir.join("order-node.orders1.pem"));
    assert_eq!(tls.certificate, dir.join("order-node.orders1.pem"));
    // http stays plain outside a secure cell, as today.
    let plain = etcd_config("etcd = [\"http://10.0.0.1:2379\"]", None, "x").unwrap();
    assert_eq!(plain.etcd.unwrap().tls, None);
}

#[test]
fn etcd_tls_misconfigurations_say_what_to_set() {
    let pki = pki();
    let dir = pki.path();
    let refused = |journal: &str, pki: Option<&Path>, expected: &str| {
        let error = etcd_config(journal, pki, "x").unwrap_err().to_string();
        assert!(error.contains(expected), "{journal}: {error}");
    };
    // https with no files to take.
    refused(
        "etcd = [\"https://10.0.0.1:2379\"]",
        None,
        "journal.etcd_tls.ca is not set",
    );
    refused(
        "etcd = [\"https://10.0.0.1:2379\"]\netcd_tls = { ca = \"/etc/ca.pem\" }",
        None,
        "journal.etcd_tls.certificate is not set",
    );
    // Files that are not there.
    refused(
        "etcd = [\"https://10.0.0.1:2379\"]\netcd_tls = { ca = \"/nonexistent/ca.pem\" }",
        Some(dir),
        "/nonexistent/ca.pem",
    );
    // One cluster, one scheme.
    refused(
        "etcd = [\"https://10.0.0.1:2379\", \"http://10.0.0.2:2379\"]",
        Some(dir),
        "mix http (http://10.0.0.2:2379) and https (https://10.0.0.1:2379)",
    );
    // A secure cell refuses plain http off loopback, unless told.
    refused(
        "etcd = [\"http://127.0.0.1:2379\", \"http://10.0.0.2:2379\"]",
        Some(dir),
        "plain http (http://10.0.0.2:2379)",
    );
    let accepted = "etcd = [\"http://10.0.0.2:2379\"]\netcd_plain_http = true";
    assert_eq!(
        etcd_config(accepted, Some(dir), "x")
            .unwrap()
            .etcd
            .unwrap()
            .tls,
        None
    );
    let loopback = "etcd = [\"http://127.0.0.1:2379\", \"http://localhost:2380\"]";
    assert!(etcd_config(loopback, Some(dir), "x").is_ok());
    // Contradictions.
    refused(
        "etcd = [\"http://10.0.0.2:2379\"]\netcd_tls = { ca = \"ca.pem\" }",
        Some(dir),
        "write them https://",
    );
    refused(
        "etcd = [\"https://10.0.0.2:2379\"]\netcd_plain_http = true",
        Some(dir),
        "remove one",
    );
    refused(
        "etcd = [\"http://10.0.0.2:2379\"]\netcd_plain_http = true",
        None,
        "is for a secure cell",
    );
    refused(
        "etcd_tls = { ca = \"ca.pem\" }",
        None,
        "without journal.etcd",
    );
}

#[test]
fn bad_configs_are_refused() {
    for (from, to) in [
        ("name = \"orders1\"", "name = \"Orders\""),
        ("max_attempts = 3", "max_attempts = 0"),
        ("[orders]", "[orders]\nspeed = 1"),
        ("advice_timeout_ms = 20", "advice_timeout_ms = 5000"),
        (
            "retry_interval_ms = 50",
            "retry_interval_ms = 50\nretry_max_ms = 10",
        ),
    ] {
        assert!(DEMO.contains(from), "{from}");
        assert!(
            OrderNodeConfig::parse(&DEMO.replacen(from, to, 1), "x", Overrides::default()).is_err(),
            "{to}"
        );
    }
}

//! The servers a demo runs in its own process for its user: the dashboard and the
//! OPC UA server, and in a secure demo the user they log in with.

use anyhow::{anyhow, Result};
use tokio_util::sync::CancellationToken;

use super::Cell;

/// A server the demo runs in a task of its own: what stops it, and the task.
pub(super) type RunningServer = (CancellationToken, tokio::task::JoinHandle<Result<()>>);

/// A secure demo's user for the dashboard and the OPC UA server: `operator` (an
/// operator) in `<pki>/users.toml` (0600), with a new random password each run, printed
/// once. An open demo has none (its dashboard has no login and serves loopback only).
pub(super) fn demo_operator(cell: &Cell) -> Result<()> {
    use ring::rand::SecureRandom;
    let Some(pki) = &cell.pki else {
        return Ok(());
    };
    let mut bytes = [0u8; 9];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .map_err(|_| anyhow!("no random source for the demo's password"))?;
    let password: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    let users = crate::security::users::default_path(pki);
    crate::security::users::change(&users, |users| {
        if users.get("operator").is_some() {
            users.set_password("operator", &password)
        } else {
            users.add(
                "operator",
                crate::security::users::Role::Operator,
                &password,
            )
        }
    })?;
    println!(
        "log in as user operator, password {password} (in {}; add people with `cell users --pki {} add NAME --role operator`)",
        users.display(),
        pki.display()
    );
    Ok(())
}

/// A client session of the demo's router (with the PKI of a secure demo).
fn client_of(cell: &Cell) -> holon::ZenohSettings {
    holon::ZenohSettings {
        mode: holon::Mode::Client,
        connect: vec![cell.endpoint.clone()],
        tls: cell.pki.as_ref().map(|pki| holon::tls::TlsSettings {
            pki: Some(pki.clone()),
            ..holon::tls::TlsSettings::default()
        }),
        ..holon::ZenohSettings::default()
    }
}

/// The cell's dashboard, in this process, as an operator (it prints its address): the
/// token that stops it and its task.
pub(super) async fn start_dashboard(
    cell: &Cell,
    listen: std::net::SocketAddr,
) -> Result<RunningServer> {
    let config = crate::dashboard::DashboardConfig {
        keys: cell.keys.clone(),
        zenoh: client_of(cell),
        identity: "operator.default".into(),
        listen,
        operator: true,
        host_names: Vec::new(),
        // A secure demo's dashboard: HTTPS, people log in with the users file (the
        // demo's operator) or an operator.* certificate, and an audit trail beside it.
        // An open demo's: no login on loopback, its trail in the demo's directory.
        users: cell
            .pki
            .as_deref()
            .map(crate::security::users::default_path),
        audit: Some(
            cell.pki
                .as_deref()
                .unwrap_or(&cell.dir)
                .join(crate::security::audit::FILE_NAME),
        ),
        sessions: Default::default(),
        part_wait_alarm: crate::dashboard::DEFAULT_PART_WAIT_ALARM,
        tls: crate::dashboard::https_files(
            cell.pki.as_deref(),
            "operator.default",
            false,
            false,
            None,
            listen,
        )?,
    };
    let stop = CancellationToken::new();
    let task = tokio::spawn(crate::dashboard::run(config, stop.clone()));
    Ok((stop, task))
}

/// The cell's OPC UA server, in this process (it prints its endpoint): the token that
/// stops it and its task. A secure demo's users log in as [`demo_operator`] says.
pub(super) fn start_opcua(cell: &Cell, listen: std::net::SocketAddr) -> Result<RunningServer> {
    if let Some(pki) = &cell.pki {
        println!(
            "OPC UA: SignAndEncrypt only, as the demo's user; trust your client's certificate with `cell opcua --pki {} --trust CLIENT.der` (docs/opcua.md)",
            pki.display()
        );
    }
    let config = crate::opcua::OpcuaConfig {
        keys: cell.keys.clone(),
        zenoh: client_of(cell),
        identity: "operator.opcua".into(),
        listen,
        pki: cell.pki.clone(),
        users: None,
        audit: None,
    };
    let stop = CancellationToken::new();
    let task = tokio::spawn(crate::opcua::run(config, stop.clone()));
    Ok((stop, task))
}

/// Stops the OPC UA server (within 10 s), then the dashboard, saying how each ended if
/// not well.
pub(super) async fn stop(opcua: Option<RunningServer>, dashboard: Option<RunningServer>) {
    if let Some((stop, task)) = opcua {
        stop.cancel();
        match tokio::time::timeout(std::time::Duration::from_secs(10), task).await {
            Ok(Ok(Ok(()))) => {}
            Ok(Ok(Err(e))) => println!("the OPC UA server stopped with an error: {e:#}"),
            Ok(Err(e)) => println!("the OPC UA server's task ended abnormally: {e}"),
            Err(_) => println!("the OPC UA server did not stop within 10 s"),
        }
    }
    if let Some((stop, task)) = dashboard {
        stop.cancel();
        match task.await {
            Ok(Ok(())) => {}
            Ok(Err(e)) => println!("the dashboard stopped with an error: {e:#}"),
            Err(e) => println!("the dashboard's task ended abnormally: {e}"),
        }
    }
}

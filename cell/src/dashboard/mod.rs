//! `cell dashboard`: a live web page of a running cell, alarms, a JSON API and
//! Prometheus metrics, from what the holons already publish.
//!
//! It joins the cell as a zenoh client and keeps a model of it ([`model`]) from
//! subscriptions: the holons' liveliness tokens (`alive/**`, with their history), the
//! resources' state (`resource/*/state`) and the orders' state (`order/*/state`), each
//! asked for at the start. The holons do nothing for it.
//!
//! A holon publishes its state only when it changes, and zenoh routes a publication
//! only to subscribers the publisher has heard of: a holon that has just joined (or a
//! dashboard that has just subscribed) can publish a change before the subscription
//! reached it, and that change would never arrive (seen: a resource turning `free`
//! 1 ms after its token appeared, shown `init` for good). So the dashboard asks again,
//! once, [`crate::client::states::ASK_NEWCOMER_AGAIN`] after it starts and after each resource's token
//! appears; a snapshot older than the one held changes nothing. One task owns the model;
//! the zenoh callbacks queue what they hear for it (bounded; when full, a sample is
//! dropped and counted: the next snapshot of that holon brings the model up to date),
//! and it publishes a view of the model at most every [`PUBLISH_EVERY`] for the web
//! server ([`http`]), which pushes it to every open page as a server-sent event.

pub mod actions;
pub mod gate;
pub mod guard;
pub mod http;
pub mod listener;
pub mod metrics;
pub mod model;
pub mod people;
pub mod refusal;
pub mod session;
pub mod view;
pub use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use schemas::{CellKeys, HolonKind};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use model::{Input, Model, ProcessId};
pub use view::{OrderRow, Throughput, View, FINISHED_SHOWN};

/// How often, at most, the view is published to the pages.
pub const PUBLISH_EVERY: Duration = Duration::from_millis(250);

/// How often the fenced resources' and the order-nodes on etcd's processes are asked
/// where they stand (holder or standby): their reports are answered by live processes only, so a dead one drops off.
const FENCES_EVERY: Duration = Duration::from_secs(2);

/// How many inputs wait for the model's task.
const INPUT_QUEUE: usize = 8192;

/// What `cell dashboard` runs with.
#[derive(Debug, Clone)]
pub struct DashboardConfig {
    pub keys: CellKeys,
    /// The cell's zenoh session (a client of its routers).
    pub zenoh: holon::ZenohSettings,
    /// The identity to connect with (a secure cell).
    pub identity: String,
    /// Where the web server listens.
    pub listen: SocketAddr,
    /// Whether the page may submit work orders and acknowledge alarms.
    pub operator: bool,
    /// Host names the page is served under besides its IP addresses and localhost
    /// (`--host-name`); requests naming another host are refused.
    pub host_names: Vec<String>,
    /// The users file people log in with (`--users`; `<pki>/users.toml` in a secure
    /// cell). Without it and without client certificates nobody logs in, and the
    /// dashboard may listen on loopback only.
    pub users: Option<std::path::PathBuf>,
    /// The audit trail (`--audit`; `audit.jsonl` beside the users file); `None`: none.
    pub audit: Option<std::path::PathBuf>,
    /// How long login sessions live.
    pub sessions: session::SessionLimits,
    /// HTTPS: the certificate, its key and the CA of client certificates that log in
    /// (`None`: plain HTTP).
    pub tls: Option<listener::TlsFiles>,
    /// A running order's part in the cell that stays where it is longer than this
    /// raises `part_waits` (`--part-wait-alarm-s`).
    pub part_wait_alarm: Duration,
}

/// The `part_waits` bound unless told otherwise.
pub const DEFAULT_PART_WAIT_ALARM: Duration =
    Duration::from_millis(model::DEFAULT_PART_WAIT_BOUND_MS);

impl DashboardConfig {
    /// Who logs in and how, from the users file, HTTPS and the dashboard's own role;
    /// refuses a dashboard without login, or with password logins over plain HTTP,
    /// anywhere but on loopback.
    fn gate(&self) -> Result<gate::GateConfig> {
        let certificates = self.tls.as_ref().is_some_and(|t| t.client_ca.is_some());
        let without_login = (self.users.is_none() && !certificates).then_some(if self.operator {
            crate::security::users::Role::Operator
        } else {
            crate::security::users::Role::Observer
        });
        if without_login.is_some() && !self.listen.ip().is_loopback() {
            return Err(anyhow!(
                "a dashboard without login listens on loopback only, and {} is not: give it a users file (--users FILE, made with `cell users --file FILE add NAME --role admin`) or listen on 127.0.0.1",
                self.listen
            ));
        }
        if self.users.is_some() && self.tls.is_none() && !self.listen.ip().is_loopback() {
            return Err(anyhow!(
                "password logins over plain HTTP on {} would show the passwords to the network: serve HTTPS (--tls-cert FILE --tls-key FILE, or --pki DIR of a secure cell) or listen on loopback behind a reverse proxy that serves HTTPS",
                self.listen
            ));
        }
        Ok(gate::GateConfig {
            users: self.users.clone(),
            certificates,
            limits: self.sessions,
            without_login,
        })
    }
}

/// Who the dashboard connects as, and whether its page may operate (submit work
/// orders, acknowledge alarms), from `--pki`, `--identity` and `--operator`.
///
/// In a secure cell (`secure`) the identity's role decides, since the cell's access
/// control enforces it anyway: an `operator.*` identity gets an operator's page, an
/// `observer.*` identity a read-only one (`--operator` with it is an error, not a page
/// whose buttons the routers would refuse), and no other role may run a dashboard.
/// Without `--identity`, `--operator` picks `operator.default`, else `observer.default`.
/// In an open cell `--operator` alone decides.
pub fn connect_as(secure: bool, identity: Option<&str>, operator: bool) -> Result<(String, bool)> {
    let default = if operator {
        "operator.default"
    } else {
        "observer.default"
    };
    let identity = identity.unwrap_or(default).to_string();
    if !secure {
        return Ok((identity, operator));
    }
    let (role, _) = crate::security::access::parse_identity(&identity)?;
    match role {
        crate::security::access::Role::Operator => Ok((identity, true)),
        crate::security::access::Role::Observer if operator => Err(anyhow!(
            "--operator needs an operator identity: {identity} may only watch the cell (leave out --operator for a read-only page)"
        )),
        crate::security::access::Role::Observer => Ok((identity, false)),
        _ => Err(anyhow!(
            "a dashboard connects as an operator or an observer, not as {identity}"
        )),
    }
}

/// Where the dashboard's HTTPS certificate comes from, from `--pki`, `--tls`,
/// `--no-tls` and `--tls-cert`/`--tls-key` (`given`):
/// - a certificate given is served (HTTPS), in any cell;
/// - a secure cell (`pki`) serves HTTPS by default, with the certificate `cell certs`
///   issued for the dashboard's identity, and takes client certificates of the cell CA
///   as logins; `--no-tls` serves plain HTTP instead, on loopback only (behind a
///   reverse proxy on the same host);
/// - an open cell serves plain HTTP unless `--tls` (which then needs a certificate).
pub fn https_files(
    pki: Option<&std::path::Path>,
    identity: &str,
    tls: bool,
    no_tls: bool,
    given: Option<(std::path::PathBuf, std::path::PathBuf)>,
    listen: SocketAddr,
) -> Result<Option<listener::TlsFiles>> {
    let client_ca = pki.map(|p| p.join("ca.pem"));
    if no_tls {
        return match pki {
            None => Err(anyhow!(
                "--no-tls is for a secure cell (--pki): without --pki the dashboard serves plain HTTP unless --tls"
            )),
            Some(_) if !listen.ip().is_loopback() => Err(anyhow!(
                "--no-tls serves plain HTTP on loopback only (behind a reverse proxy on this host), and {listen} is not loopback"
            )),
            Some(_) => Ok(None),
        };
    }
    match (given, pki) {
        (Some((certificate, key)), _) => Ok(Some(listener::TlsFiles {
            certificate,
            key,
            client_ca,
        })),
        (None, Some(pki)) => Ok(Some(listener::TlsFiles {
            certificate: pki.join(format!("{identity}.pem")),
            key: pki.join(format!("{identity}.key")),
            client_ca,
        })),
        (None, None) if tls => Err(anyhow!(
            "--tls needs a certificate: --tls-cert FILE --tls-key FILE (or --pki DIR of a secure cell)"
        )),
        (None, None) => Ok(None),
    }
}

/// Commands from the pages to the model's owner.
#[derive(Debug)]
pub enum Command {
    /// An alarm acknowledged by a user.
    Acknowledge { id: u64, by: String },
}

/// What the web server shares with the model's task.
pub struct Shared {
    /// Who is let in, and the audit trail.
    pub gate: Arc<gate::Gate>,
    pub view: watch::Receiver<Arc<View>>,
    pub commands: mpsc::Sender<Command>,
    pub session: zenoh::Session,
    pub keys: CellKeys,
    pub operator: bool,
    /// The identity the dashboard joined the cell with: who commands, in a PackML
    /// command's `by`.
    pub identity: String,
}

/// Runs the dashboard until `shutdown`.
pub async fn run(config: DashboardConfig, shutdown: CancellationToken) -> Result<()> {
    // Everything that can be wrong with the settings is found before joining the cell.
    let (gate, tls) = gate_and_tls(&config)?;
    let session = config
        .zenoh
        .open(&config.identity, Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("cannot join the cell: {e}"))?;
    let (inputs, input_rx) = mpsc::channel(INPUT_QUEUE);
    let dropped = Arc::new(AtomicU64::new(0));
    let _subscriptions = subscribe(&session, &config.keys, &inputs, &dropped).await?;
    let every_state = [config.keys.resource_states(), config.keys.order_states()];
    ask_states(&session, &every_state, &inputs, &dropped).await;
    // Once more when the subscriptions surely reached every holon (see the module's
    // doc): a change published before they did is not lost.
    {
        let (session, inputs, dropped) = (session.clone(), inputs.clone(), dropped.clone());
        tokio::spawn(async move {
            tokio::time::sleep(crate::client::states::ASK_NEWCOMER_AGAIN).await;
            ask_states(&session, &every_state, &inputs, &dropped).await;
        });
    }
    tokio::spawn(ask_the_cell_every_while(
        session.clone(),
        config.keys.clone(),
        inputs.clone(),
        dropped.clone(),
        shutdown.clone(),
    ));
    let (view_tx, view_rx) = watch::channel(Arc::new(View::default()));
    let (commands, command_rx) = mpsc::channel(64);
    let owner = tokio::spawn(own_the_model(
        config.clone(),
        session.clone(),
        input_rx,
        command_rx,
        view_tx,
        dropped,
        shutdown.clone(),
    ));
    let shared = Arc::new(Shared {
        gate,
        view: view_rx,
        commands,
        session: session.clone(),
        keys: config.keys.clone(),
        operator: config.operator,
        identity: config.identity.clone(),
    });
    let https = tls.is_some();
    let listener = listener::DashboardListener::bind(config.listen, tls)
        .await
        .with_context(|| format!("cannot listen on {}", config.listen))?;
    let address = listener.local_addr()?;
    let scheme = if https { "https" } else { "http" };
    info!(cell = %config.keys.cell(), %address, %scheme, login = shared.gate.login_required(), "dashboard serving");
    println!(
        "dashboard of cell {} on {scheme}://{address}/",
        config.keys.cell()
    );
    let guard = Arc::new(guard::Guard::new(address, &config.host_names, https));
    let app = http::router(shared, guard).into_make_service_with_connect_info::<listener::Peer>();
    let served = axum::serve(listener, app)
        .with_graceful_shutdown(shutdown.clone().cancelled_owned())
        .await;
    shutdown.cancel();
    if let Err(e) = owner.await {
        warn!(error = %e, "the model's task ended abnormally");
    }
    if let Err(e) = session.close().await {
        warn!(error = %e, "cannot close the zenoh session");
    }
    served.context("the web server stopped")
}

/// The gate (who is let in, the audit trail) and the HTTPS settings, checked before the
/// dashboard joins the cell.
fn gate_and_tls(
    config: &DashboardConfig,
) -> Result<(Arc<gate::Gate>, Option<Arc<rustls::ServerConfig>>)> {
    let gate_config = config.gate()?;
    let tls = config
        .tls
        .as_ref()
        .map(listener::server_config)
        .transpose()
        .map_err(|e| anyhow!("{e}"))?;
    if let Some(users) = &config.users {
        if users.exists() {
            crate::security::users::load(users)?;
        } else {
            warn!(file = %users.display(), "no users file yet: nobody logs in with a password (add users with `cell users`)");
        }
    }
    let audit = config
        .audit
        .as_deref()
        .map(crate::security::audit::AuditTrail::open)
        .transpose()?;
    if gate_config.without_login.is_some() {
        warn!("this dashboard has no login: everybody who reaches it on this machine is `local`");
    }
    Ok((Arc::new(gate::Gate::new(gate_config, audit)), tls))
}

/// Asks the cell every [`FENCES_EVERY`], until `stop`, what it does not publish: where
/// the fenced resources and order-nodes stand, the layout, the order-nodes' counts.
async fn ask_the_cell_every_while(
    session: zenoh::Session,
    keys: CellKeys,
    inputs: mpsc::Sender<Input>,
    dropped: Arc<AtomicU64>,
    stop: CancellationToken,
) {
    let mut every = tokio::time::interval(FENCES_EVERY);
    loop {
        tokio::select! {
            _ = stop.cancelled() => return,
            _ = every.tick() => {}
        }
        // Time passes for the model: what waits too long is alarmed.
        queue(
            &inputs,
            &dropped,
            Input::Tick {
                at: schemas::unix_ms(),
            },
        );
        match crate::client::status::fences(&session, &keys, FENCES_EVERY).await {
            Ok(reports) => queue(
                &inputs,
                &dropped,
                Input::Fences {
                    reports,
                    at: schemas::unix_ms(),
                },
            ),
            Err(e) => warn!(error = %e, "cannot ask the fenced resources where they stand"),
        }
        match crate::client::status::node_fences(&session, &keys, FENCES_EVERY).await {
            Ok(reports) => queue(&inputs, &dropped, Input::NodeFences { reports }),
            Err(e) => {
                warn!(error = %e, "cannot ask the order-nodes on etcd where they stand")
            }
        }
        // Each order-node's counts of its whole history (a listing page of
        // none): the totals the page shows. A node that does not answer keeps
        // its last counts out of the totals until it does.
        match crate::client::layout::live(&session, &keys, FENCES_EVERY).await {
            Ok(layout) => queue(&inputs, &dropped, Input::Layout(Box::new(layout))),
            Err(e) => warn!(error = %e, "cannot ask the resources for the layout"),
        }
        match crate::client::listing::answered_counts(&session, &keys, FENCES_EVERY).await {
            Ok(counts) => queue(&inputs, &dropped, Input::NodeCounts { counts }),
            Err(e) => warn!(error = %e, "cannot ask the order-nodes for their counts"),
        }
    }
}

/// Queues an input for the model from a zenoh callback (which must not block).
fn queue(inputs: &mpsc::Sender<Input>, dropped: &AtomicU64, input: Input) {
    if inputs.try_send(input).is_err() {
        dropped.fetch_add(1, Ordering::Relaxed);
    }
}

/// What the dashboard subscribes to, declared for its life.
struct Subscriptions {
    _alive: zenoh::pubsub::Subscriber<()>,
    _processes: zenoh::pubsub::Subscriber<()>,
    _states: crate::client::states::Following,
}

async fn subscribe(
    session: &zenoh::Session,
    keys: &CellKeys,
    inputs: &mpsc::Sender<Input>,
    dropped: &Arc<AtomicU64>,
) -> Result<Subscriptions> {
    let z = |e: zenoh::Error| anyhow!("{}", holon::zenoh_error::describe(&e));
    let alive = {
        let (inputs, dropped) = (inputs.clone(), dropped.clone());
        let (asked, counter) = (inputs.clone(), dropped.clone());
        crate::client::states::follow_tokens(
            session,
            keys,
            move |holon, appeared| {
                // Orders hold a token only while they book: they show in the orders.
                if holon.kind() == HolonKind::Order {
                    return;
                }
                let at = schemas::unix_ms();
                let input = if appeared {
                    Input::Appeared { holon, at }
                } else {
                    Input::Vanished { holon, at }
                };
                queue(&inputs, &dropped, input);
            },
            move |heard| queue(&asked, &counter, input_of(heard)),
        )
        .await?
    };
    let processes = {
        let (inputs, dropped, keys) = (inputs.clone(), dropped.clone(), keys.clone());
        session
            .liveliness()
            .declare_subscriber(keys.host_all())
            .history(true)
            .callback(move |sample| {
                let Some((program, name)) = keys.process_from_host(sample.key_expr().as_str())
                else {
                    return;
                };
                let process = ProcessId {
                    program: program.to_string(),
                    name: name.to_string(),
                };
                let at = schemas::unix_ms();
                let input = match sample.kind() {
                    zenoh::sample::SampleKind::Put => Input::ProcessAppeared { process, at },
                    zenoh::sample::SampleKind::Delete => Input::ProcessVanished { process, at },
                };
                queue(&inputs, &dropped, input);
            })
            .await
            .map_err(z)?
    };
    let states = {
        let (inputs, dropped) = (inputs.clone(), dropped.clone());
        crate::client::states::follow(
            session,
            keys,
            &[keys.resource_states(), keys.order_states()],
            move |heard| queue(&inputs, &dropped, input_of(heard)),
        )
        .await?
    };
    Ok(Subscriptions {
        _alive: alive,
        _processes: processes,
        _states: states,
    })
}

/// Asks for the states on `keys` (the subscriptions bring the changes from then on).
async fn ask_states(
    session: &zenoh::Session,
    keys: &[String],
    inputs: &mpsc::Sender<Input>,
    dropped: &AtomicU64,
) {
    crate::client::states::ask(session, keys, |heard| {
        queue(inputs, dropped, input_of(heard))
    })
    .await;
}

/// A state heard, as the model's input, stamped now.
fn input_of(heard: crate::client::states::Heard) -> Input {
    let at = schemas::unix_ms();
    match heard {
        crate::client::states::Heard::Resource(snapshot) => Input::Resource { snapshot, at },
        crate::client::states::Heard::Order(snapshot) => Input::Order { snapshot, at },
    }
}

/// The model's one owner: applies every input and command, and publishes the view
/// when it changed, at most every [`PUBLISH_EVERY`].
async fn own_the_model(
    config: DashboardConfig,
    session: zenoh::Session,
    mut inputs: mpsc::Receiver<Input>,
    mut commands: mpsc::Receiver<Command>,
    view: watch::Sender<Arc<View>>,
    dropped: Arc<AtomicU64>,
    shutdown: CancellationToken,
) {
    let mut model = Model::with_part_wait_bound(config.part_wait_alarm.as_millis() as u64);
    let started = schemas::unix_ms();
    let mut changed = true;
    let mut linked_routers = Vec::new();
    let mut tick = tokio::time::interval(PUBLISH_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            Some(input) = inputs.recv() => changed |= model.apply(input),
            Some(command) = commands.recv() => match command {
                Command::Acknowledge { id, by } => {
                    changed |= model.apply(Input::Acknowledge { id, by, at: schemas::unix_ms() });
                }
            },
            _ = tick.tick() => {
                // What zenoh tells of this session's own links (local, no round trip).
                let linked: Vec<String> =
                    session.info().routers_zid().await.map(|zid| zid.to_string()).collect();
                if linked != linked_routers {
                    linked_routers = linked;
                    changed = true;
                }
                if changed {
                    let dropped = dropped.load(Ordering::Relaxed);
                    let mut next = view::view_of(&config, &model, dropped, started);
                    next.linked_routers = linked_routers.clone();
                    view.send_replace(Arc::new(next));
                    changed = false;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::connect_as;

    #[test]
    fn in_a_secure_cell_the_identity_decides_what_the_page_may_do() {
        let is = |secure, identity, operator| connect_as(secure, identity, operator).ok();
        let pair = |identity: &str, operator| Some((identity.to_string(), operator));
        assert_eq!(is(true, None, false), pair("observer.default", false));
        assert_eq!(is(true, None, true), pair("operator.default", true));
        assert_eq!(
            is(true, Some("operator.anna"), false),
            pair("operator.anna", true)
        );
        assert_eq!(
            is(true, Some("observer.wall"), false),
            pair("observer.wall", false)
        );
        let refused = connect_as(true, Some("observer.wall"), true).unwrap_err();
        assert!(refused
            .to_string()
            .contains("--operator needs an operator identity"));
        assert!(connect_as(true, Some("resource.robot1"), false).is_err());
        assert!(connect_as(true, Some("nonsense"), false).is_err());
        // An open cell: the flag decides.
        assert_eq!(is(false, None, true), pair("operator.default", true));
        assert_eq!(is(false, None, false), pair("observer.default", false));
    }
}

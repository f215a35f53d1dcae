//! `cell opcua`: an OPC UA server for the cell (docs/opcua.md).
//!
//! It joins the cell as a zenoh client (an operator identity in a secure cell) and
//! shows every resource holon as a PackML unit after OPC 30050
//! (`Objects/PackMLObjects/<resource>`: Status, Admin, the command methods) and the
//! cell as `Objects/Cell` (order figures, SubmitWorkOrder). The values come from what
//! the holons publish: `resource/*/state` and `order/*/state`, subscribed and asked for
//! at the start (and once more [`crate::client::states::ASK_NEWCOMER_AGAIN`] later, and after each resource's
//! liveliness token appears, as the dashboard does: a change published before the
//! subscription reached its publisher would be lost otherwise). A resource's token
//! appearing adds its object; its token going marks its variables
//! `BadNoCommunication` and removes its object, while clients stay connected. A
//! snapshot is shown only while its resource's token is there (one arriving first
//! waits for the token; a late one of a resource that left is dropped).
//!
//! One task owns the values ([`own_the_values`]); zenoh callbacks queue what they
//! hear for it (bounded; a sample dropped on a full queue is counted and logged, and
//! the holon's next snapshot repairs it). Values are pushed to the address space only
//! when they change, which notifies the OPC UA subscriptions; the server checks its
//! subscriptions every [`TICK_MS`] ms and allows publishing intervals down to that.

pub mod address_space;
pub mod audit;
mod doors;
pub mod methods;
pub mod ns0;
pub mod security;
pub mod users;

use std::collections::{HashMap, HashSet};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use opcua::types::{DataValue, StatusCode, Variant};
use opcua_server::{ServerBuilder, ServerEndpoint, SubscriptionCache};
use schemas::{CellKeys, HolonKind, OrderStatus, ResourceSnapshot};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use methods::CellNodeManager;
use users::CellAuth;

/// The default endpoint's address (OPC UA's registered port, loopback only).
pub const DEFAULT_LISTEN: &str = "127.0.0.1:4840";

/// The server's subscription tick, and the shortest publishing interval it grants (ms):
/// a change reaches a client asking for a 20 ms publishing interval in about 20 ms.
/// Monitored items of the cell's values report every change
/// ([`methods::PUSHED_SAMPLING_MS`]).
pub const TICK_MS: u64 = 10;

/// How many inputs wait for the values' owner.
const INPUT_QUEUE: usize = 8192;

/// What `cell opcua` runs with.
#[derive(Debug, Clone)]
pub struct OpcuaConfig {
    /// The cell's keys.
    pub keys: CellKeys,
    /// The cell's zenoh session settings (a client of its routers; TLS with --pki).
    pub zenoh: holon::ZenohSettings,
    /// The zenoh identity to join with (an operator's in a secure cell).
    pub identity: String,
    /// Where the OPC UA server listens.
    pub listen: SocketAddr,
    /// A secure cell's PKI directory: the server's certificate, its store of trusted
    /// client certificates, and the users file's default place. None: a plain cell.
    pub pki: Option<PathBuf>,
    /// The cell's users file (default `<pki>/users.toml`, [`crate::security::users`]).
    pub users: Option<PathBuf>,
    /// The audit trail (default `audit.jsonl` beside the users file; a secure cell only).
    pub audit: Option<PathBuf>,
}

/// The server's endpoint URL for a listen address.
pub fn endpoint_url(listen: &SocketAddr) -> String {
    format!("opc.tcp://{listen}/")
}

/// What the zenoh callbacks tell the values' owner.
#[derive(Debug)]
enum Input {
    /// A resource's state snapshot.
    Resource(Box<ResourceSnapshot>),
    /// A resource's liveliness token appeared.
    Appeared(String),
    /// A resource's liveliness token went.
    Vanished(String),
    /// The order-nodes' counts of their orders, summed (a listing page of none from
    /// each, [`crate::client::listing::counts`]).
    Counts(schemas::OrderCounts),
    /// The server's door figures ([`address_space::SECURITY_FIGURES`], in their order).
    Doors([u64; 4]),
}

/// How often the order figures are asked of the order-nodes.
const COUNTS_EVERY: Duration = Duration::from_secs(1);

impl Input {
    /// A resource's state as an input; an order's is none (the figures are counted by
    /// the nodes).
    fn heard(heard: crate::client::states::Heard) -> Option<Input> {
        match heard {
            crate::client::states::Heard::Resource(snapshot) => Some(Input::Resource(snapshot)),
            crate::client::states::Heard::Order(_) => None,
        }
    }
}

/// Queues an input from a zenoh callback (which must not block).
fn queue(inputs: &mpsc::Sender<Input>, dropped: &AtomicU64, input: Input) {
    if inputs.try_send(input).is_err() {
        let n = dropped.fetch_add(1, Ordering::Relaxed) + 1;
        warn!(dropped = n, "the OPC UA server's input queue is full: a state sample was dropped (the holon's next snapshot repairs it)");
    }
}

/// Runs the server until `shutdown`.
pub async fn run(config: OpcuaConfig, shutdown: CancellationToken) -> Result<()> {
    let cell = config.keys.cell().to_string();
    let url = endpoint_url(&config.listen);
    // Decide the security first: a bad setup must not join the cell at all.
    let (auth, server_files) = security::auth_and_files(&config)?;
    let auth = Arc::new(auth);
    // Fail early and clearly if the port is taken (async-opcua only logs it).
    drop(
        std::net::TcpListener::bind(config.listen)
            .with_context(|| format!("cannot listen on {}", config.listen))?,
    );

    let session = config
        .zenoh
        .open(&config.identity, Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("cannot join the cell: {e}"))?;

    // Subscribed before the server is built; what arrives waits in the queue.
    let (inputs, input_rx) = mpsc::channel(INPUT_QUEUE);
    let dropped = Arc::new(AtomicU64::new(0));
    let _subscriptions = subscribe(&session, &config.keys, &inputs, &dropped).await?;

    let uri = address_space::namespace_uri(&cell);
    let (server, handle, plain_store) = build_server(
        &config,
        &cell,
        &uri,
        server_files.as_ref(),
        &session,
        auth.clone(),
        shutdown.child_token(),
    )?;
    let owner = start_the_values_owner(&handle, &uri, server_files.is_some(), input_rx, &shutdown)?;
    // No await between the build and the run: the server is not Send until it runs.
    let owner_queue = InputQueue { inputs, dropped };
    spawn_state_asks(&session, &config.keys, &owner_queue);
    spawn_order_counts(&session, &config.keys, &owner_queue, &shutdown);
    tokio::spawn(doors::end_sessions_of_changed_users(
        auth.clone(),
        handle.clone(),
        shutdown.clone(),
    ));
    tokio::spawn(doors::count_the_doors(
        auth.clone(),
        handle.clone(),
        owner_queue.inputs.clone(),
        owner_queue.dropped.clone(),
        shutdown.clone(),
    ));
    announce(&cell, &url, server_files.as_ref());
    if let (Some(files), Some(pki)) = (&server_files, &config.pki) {
        tokio::spawn(security::watch_rejected(
            pki.clone(),
            files.store.clone(),
            shutdown.clone(),
        ));
    }
    println!("opcua server of cell {cell} on {url}");
    let served = server.run().await;
    shutdown.cancel();
    if let Err(e) = owner.await {
        warn!(error = %e, "the values' task ended abnormally");
    }
    close(session, plain_store).await;
    served.map_err(|e| anyhow!("the OPC UA server stopped: {e}"))
}

/// Checks the built server (its certificate loaded in a secure cell, the cell's
/// namespace registered) and spawns the one owner of its values.
fn start_the_values_owner(
    handle: &opcua_server::ServerHandle,
    uri: &str,
    secure: bool,
    input_rx: mpsc::Receiver<Input>,
    shutdown: &CancellationToken,
) -> Result<tokio::task::JoinHandle<()>> {
    if secure && (handle.info().server_certificate.is_none() || handle.info().server_pkey.is_none())
    {
        bail!("the OPC UA server's certificate or key did not load: refusing to run without encryption");
    }
    let ns = handle
        .get_namespace_index(uri)
        .ok_or_else(|| anyhow!("the namespace {uri} was not registered"))?;
    let nodes = handle
        .node_managers()
        .get_of_type::<CellNodeManager>()
        .ok_or_else(|| anyhow!("the cell's node manager is missing"))?;
    let subscriptions = handle.subscriptions().clone();
    Ok(tokio::spawn(own_the_values(
        nodes,
        subscriptions,
        ns,
        input_rx,
        shutdown.clone(),
    )))
}

/// The values' owner's queue, as the tasks and callbacks that feed it hold it.
#[derive(Clone)]
struct InputQueue {
    /// Where inputs wait for the values' owner.
    inputs: mpsc::Sender<Input>,
    /// How many inputs a full queue dropped.
    dropped: Arc<AtomicU64>,
}

/// Asks every resource's state now and once more a little later (a newcomer's first
/// snapshot may be published before the subscription reaches it).
fn spawn_state_asks(session: &zenoh::Session, keys: &CellKeys, owner: &InputQueue) {
    let every_state = [keys.resource_states()];
    let (session, InputQueue { inputs, dropped }) = (session.clone(), owner.clone());
    tokio::spawn(async move {
        ask_states(&session, &every_state, &inputs, &dropped).await;
        tokio::time::sleep(crate::client::states::ASK_NEWCOMER_AGAIN).await;
        ask_states(&session, &every_state, &inputs, &dropped).await;
    });
}

/// Asks the order-nodes for their counts every [`COUNTS_EVERY`] until `shutdown`, and
/// queues their sum.
fn spawn_order_counts(
    session: &zenoh::Session,
    keys: &CellKeys,
    owner: &InputQueue,
    shutdown: &CancellationToken,
) {
    let (session, keys, InputQueue { inputs, dropped }, stop) = (
        session.clone(),
        keys.clone(),
        owner.clone(),
        shutdown.clone(),
    );
    tokio::spawn(async move {
        let mut every = tokio::time::interval(COUNTS_EVERY);
        every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = every.tick() => {}
            }
            match crate::client::listing::answered_counts(&session, &keys, COUNTS_EVERY * 2).await {
                Ok(nodes) => {
                    let mut total = schemas::OrderCounts::default();
                    for counts in nodes.values() {
                        total.merge(counts);
                    }
                    queue(&inputs, &dropped, Input::Counts(total));
                }
                Err(e) => warn!(error = %e, "cannot ask the order-nodes for their counts"),
            }
        }
    });
}

/// Says in the log how the server is secured.
fn announce(cell: &str, url: &str, server_files: Option<&security::ServerFiles>) {
    match server_files {
        None => warn!(
            %cell, endpoint = %url,
            "OPC UA server without security (None/None; anonymous sessions may browse and call methods): allowed because it listens on loopback only; a secure cell uses --pki"
        ),
        Some(files) => info!(
            %cell, endpoint = %url, store = %files.store.display(),
            "OPC UA server, SignAndEncrypt only (Basic256Sha256, Aes128_Sha256_RsaOaep, Aes256_Sha256_RsaPss); user names and passwords; unknown client certificates are rejected into the store's rejected/ (trust one with `cell opcua --trust`)"
        ),
    }
}

/// Leaves the cell (within 5 s) and removes the plain server's certificate store.
async fn close(session: zenoh::Session, plain_store: Option<PathBuf>) {
    match tokio::time::timeout(Duration::from_secs(5), session.close()).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => warn!(error = %e, "cannot close the zenoh session"),
        Err(_) => warn!("the zenoh session did not close within 5 s; leaving anyway"),
    }
    if let Some(store) = plain_store {
        if let Err(e) = std::fs::remove_dir_all(&store) {
            debug!(error = %e, store = %store.display(), "cannot remove the plain server's certificate store");
        }
    }
}

/// Builds the server (a plain function: the builder is not Send, and `run` is awaited
/// in a spawned task by `cell demo`).
fn build_server(
    config: &OpcuaConfig,
    cell: &str,
    uri: &str,
    server_files: Option<&security::ServerFiles>,
    session: &zenoh::Session,
    auth: Arc<CellAuth>,
    token: CancellationToken,
) -> Result<(
    opcua_server::Server,
    opcua_server::ServerHandle,
    Option<PathBuf>,
)> {
    let mut builder = ServerBuilder::new()
        .application_name(format!("holarchy cell {cell}"))
        .application_uri(security::application_uri(cell))
        .product_uri("urn:holarchy")
        .host(config.listen.ip().to_string())
        .port(config.listen.port())
        .discovery_urls(vec!["/".to_string()])
        .create_sample_keypair(false)
        .trust_client_certs(false)
        .subscription_poll_interval_ms(TICK_MS)
        .token(token)
        .with_authenticator(auth.clone())
        .with_node_manager(ns0::mini_core())
        .with_node_manager(methods::cell_nodes(
            uri.to_string(),
            session.clone(),
            config.keys.clone(),
            auth.clone(),
        ));
    builder
        .limits_mut()
        .subscriptions
        .min_publishing_interval_ms = TICK_MS as f64;
    // Values are pushed on change, not sampled (see methods::PUSHED_SAMPLING_MS).
    builder.limits_mut().subscriptions.min_sampling_interval_ms = 0.0;
    let plain_store;
    match server_files {
        Some(files) => {
            builder = builder
                .pki_dir(&files.store)
                .certificate_path(&files.certificate)
                .private_key_path(&files.key);
            for (id, endpoint) in security::secure_endpoints() {
                builder = builder.add_endpoint(id, endpoint);
            }
            plain_store = None;
        }
        None => {
            // async-opcua wants a certificate store even with no security.
            let store = std::env::temp_dir().join(format!("holarchy-opcua-{}", std::process::id()));
            builder = builder
                .pki_dir(&store)
                .add_endpoint("none", ServerEndpoint::new_none("/", &[]));
            plain_store = Some(store);
        }
    }
    let (server, handle) = builder
        .build()
        .map_err(|e| anyhow!("cannot set up the OPC UA server: {e}"))?;
    Ok((server, handle, plain_store))
}

/// What the server subscribes to, declared for its life.
struct Subscriptions {
    /// The holons' liveliness tokens (`alive/**`, with history).
    _alive: zenoh::pubsub::Subscriber<()>,
    /// `resource/*/state` and `order/*/state`.
    _states: crate::client::states::Following,
}

async fn subscribe(
    session: &zenoh::Session,
    keys: &CellKeys,
    inputs: &mpsc::Sender<Input>,
    dropped: &Arc<AtomicU64>,
) -> Result<Subscriptions> {
    let alive = {
        let (inputs, dropped) = (inputs.clone(), dropped.clone());
        let (asked, counter) = (inputs.clone(), dropped.clone());
        crate::client::states::follow_tokens(
            session,
            keys,
            move |holon, appeared| {
                if holon.kind() != HolonKind::Resource {
                    return;
                }
                let name = holon.name().to_string();
                let input = if appeared {
                    Input::Appeared(name)
                } else {
                    Input::Vanished(name)
                };
                queue(&inputs, &dropped, input);
            },
            move |heard| {
                if let Some(input) = Input::heard(heard) {
                    queue(&asked, &counter, input)
                }
            },
        )
        .await?
    };
    let states = {
        let (inputs, dropped) = (inputs.clone(), dropped.clone());
        // The order figures are the nodes' counts (Input::Counts): no order's state
        // is followed.
        crate::client::states::follow(session, keys, &[keys.resource_states()], move |heard| {
            if let Some(input) = Input::heard(heard) {
                queue(&inputs, &dropped, input)
            }
        })
        .await?
    };
    Ok(Subscriptions {
        _alive: alive,
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
        if let Some(input) = Input::heard(heard) {
            queue(inputs, dropped, input)
        }
    })
    .await;
}

/// The one owner of the values: adds and removes resources' objects and pushes the
/// values that changed.
async fn own_the_values(
    nodes: Arc<CellNodeManager>,
    subscriptions: Arc<SubscriptionCache>,
    ns: u16,
    mut inputs: mpsc::Receiver<Input>,
    shutdown: CancellationToken,
) {
    let mut values = Values {
        nodes,
        subscriptions,
        ns,
        pushed: HashMap::new(),
        resources: HashSet::new(),
        waiting: HashMap::new(),
        shown_at: HashMap::new(),
    };
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => return,
            input = inputs.recv() => match input {
                Some(input) => values.apply(input),
                None => return,
            },
        }
    }
}

/// The address space's values as last pushed.
struct Values {
    /// The cell's node manager.
    nodes: Arc<CellNodeManager>,
    /// The server's subscriptions, notified of each push.
    subscriptions: Arc<SubscriptionCache>,
    /// Our namespace's index.
    ns: u16,
    /// Each variable's last pushed value, by NodeId path.
    pushed: HashMap<String, Variant>,
    /// The resources with an object in the address space: those whose liveliness
    /// token is in the cell.
    resources: HashSet<String>,
    /// The last snapshot of a resource whose token has not appeared (yet): applied
    /// when it does. A late snapshot of a resource that left is never shown.
    waiting: HashMap<String, Box<ResourceSnapshot>>,
    /// The `at` of each resource's snapshot shown.
    shown_at: HashMap<String, u64>,
}

impl Values {
    fn apply(&mut self, input: Input) {
        match input {
            Input::Appeared(resource) => {
                self.add(&resource);
                if let Some(snapshot) = self.waiting.remove(&resource) {
                    self.shown_at.insert(resource, snapshot.at);
                    self.push(address_space::snapshot_values(&snapshot));
                }
            }
            Input::Vanished(resource) => {
                self.waiting.remove(&resource);
                self.shown_at.remove(&resource);
                self.remove(&resource);
            }
            Input::Resource(snapshot) => {
                let resource = snapshot.holon.name().to_string();
                // A snapshot older than the one shown (a late answer to an ask) is not
                // shown.
                if self
                    .shown_at
                    .get(&resource)
                    .is_some_and(|at| snapshot.at < *at)
                {
                    debug!(resource, at = snapshot.at, "an older snapshot ignored");
                    return;
                }
                if self.resources.contains(&resource) {
                    self.shown_at.insert(resource, snapshot.at);
                    self.push(address_space::snapshot_values(&snapshot));
                } else {
                    self.waiting.insert(resource, snapshot);
                }
            }
            Input::Doors(figures) => {
                let values = address_space::SECURITY_FIGURES
                    .iter()
                    .zip(figures)
                    .map(|(name, value)| {
                        (
                            format!("{}.{}.{name}", address_space::CELL, address_space::SECURITY),
                            Variant::Int32(i32::try_from(value).unwrap_or(i32::MAX)),
                        )
                    })
                    .collect();
                self.push(values);
            }
            Input::Counts(counts) => {
                let count = |status: OrderStatus| {
                    Variant::Int32(i32::try_from(counts.of(status)).unwrap_or(i32::MAX))
                };
                let figures = vec![
                    (
                        "Cell.OrdersRunning".to_string(),
                        count(OrderStatus::Running),
                    ),
                    ("Cell.OrdersDone".to_string(), count(OrderStatus::Done)),
                    ("Cell.OrdersFailed".to_string(), count(OrderStatus::Failed)),
                ];
                self.push(figures);
            }
        }
    }

    fn add(&mut self, resource: &str) {
        if !self.resources.insert(resource.to_string()) {
            return;
        }
        let added = {
            let mut space = self.nodes.address_space().write();
            address_space::add_resource(&mut space, self.ns, resource)
        };
        if added {
            info!(resource, "resource added to the address space");
        }
        for (path, value) in address_space::values(resource, None) {
            self.pushed.insert(path, value);
        }
    }

    fn remove(&mut self, resource: &str) {
        if !self.resources.remove(resource) {
            return;
        }
        // A monitored item on a deleted node goes quiet: tell the clients first.
        let paths: Vec<String> = address_space::values(resource, None)
            .into_iter()
            .map(|(path, _)| path)
            .collect();
        let ids: Vec<_> = paths
            .iter()
            .map(|p| address_space::id(self.ns, p))
            .collect();
        let gone = ids.iter().map(|id| {
            let mut value = DataValue::null();
            value.status = Some(StatusCode::BadNoCommunication);
            value.source_timestamp = Some(opcua::types::DateTime::now());
            (id, None, value)
        });
        if let Err(status) = self.nodes.set_values(&self.subscriptions, gone) {
            warn!(resource, %status, "cannot mark the resource's variables BadNoCommunication before removing them");
        }
        for path in &paths {
            self.pushed.remove(path);
        }
        let removed = {
            let mut space = self.nodes.address_space().write();
            address_space::remove_resource(&mut space, self.ns, resource)
        };
        if removed {
            info!(resource, "resource left the cell (its liveliness token went): removed from the address space");
        }
    }

    /// Pushes the values that differ from the last pushed ones.
    fn push(&mut self, values: Vec<(String, Variant)>) {
        let changed: Vec<(String, Variant)> = values
            .into_iter()
            .filter(|(path, value)| self.pushed.get(path) != Some(value))
            .collect();
        if changed.is_empty() {
            return;
        }
        let ids: Vec<_> = changed
            .iter()
            .map(|(path, _)| address_space::id(self.ns, path))
            .collect();
        let updates = ids
            .iter()
            .zip(&changed)
            .map(|(id, (_, value))| (id, None, DataValue::new_now(value.clone())));
        match self.nodes.set_values(&self.subscriptions, updates) {
            Ok(()) => {
                debug!(changed = ?changed, "values pushed");
                for (path, value) in changed {
                    self.pushed.insert(path, value);
                }
            }
            Err(status) => {
                warn!(%status, "cannot update the address space; the next snapshot tries again");
            }
        }
    }
}

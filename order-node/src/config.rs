//! The order-node's config file (TOML); `deploy/cells/demo/orders1.toml` documents it.

use std::path::Path;
use std::time::Duration;

use holon::ZenohSettings;
use schemas::CellKeys;
use serde::Deserialize;

pub use holon::config_file::ConfigError;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    cell: String,
    name: String,
    #[serde(default)]
    zenoh: ZenohSettings,
    #[serde(default)]
    orders: OrdersSection,
    #[serde(default)]
    journal: JournalSection,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct JournalSection {
    #[serde(default)]
    dir: Option<std::path::PathBuf>,
    #[serde(default)]
    durability: holon::journal::Durability,
    #[serde(default = "default_keep_finished")]
    keep_finished_ms: u64,
    #[serde(default)]
    etcd: Vec<String>,
    #[serde(default)]
    etcd_prefix: Option<String>,
    #[serde(default = "default_lease_ttl")]
    lease_ttl_ms: u64,
    #[serde(default)]
    etcd_tls: EtcdTlsSection,
    #[serde(default)]
    etcd_plain_http: bool,
}

/// `[journal.etcd_tls]`: the files of mutual TLS to `https://` members; each defaults
/// to the node's own in a secure cell (`[zenoh.tls]` or `--pki`).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct EtcdTlsSection {
    ca: Option<std::path::PathBuf>,
    certificate: Option<std::path::PathBuf>,
    key: Option<std::path::PathBuf>,
}

impl Default for JournalSection {
    fn default() -> Self {
        JournalSection {
            dir: None,
            durability: Default::default(),
            keep_finished_ms: default_keep_finished(),
            etcd: Vec::new(),
            etcd_prefix: None,
            lease_ttl_ms: default_lease_ttl(),
            etcd_tls: EtcdTlsSection::default(),
            etcd_plain_http: false,
        }
    }
}

fn default_lease_ttl() -> u64 {
    2000
}

fn default_keep_finished() -> u64 {
    86_400_000
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct OrdersSection {
    #[serde(default = "default_proposal")]
    proposal_timeout_ms: u64,
    #[serde(default = "default_attempts")]
    max_attempts: u32,
    #[serde(default = "default_no_resource")]
    no_resource_timeout_ms: u64,
    #[serde(default = "default_retry")]
    retry_interval_ms: u64,
    #[serde(default = "default_retry_max")]
    retry_max_ms: u64,
    #[serde(default = "default_step")]
    step_timeout_ms: u64,
    #[serde(default = "default_grace")]
    vanished_grace_ms: u64,
    #[serde(default = "default_handover_grace")]
    handover_grace_ms: u64,
    #[serde(default = "default_request")]
    request_timeout_ms: u64,
    #[serde(default)]
    max_orders_per_submit: Option<u32>,
    #[serde(default = "default_max_unfinished")]
    max_unfinished_orders: usize,
    #[serde(default = "default_start_on_turn")]
    start_on_turn: bool,
    #[serde(default = "default_advice_timeout")]
    advice_timeout_ms: u64,
    #[serde(default = "default_wait_at_port")]
    wait_at_port: bool,
}

fn default_wait_at_port() -> bool {
    true
}

fn default_advice_timeout() -> u64 {
    20
}

fn default_start_on_turn() -> bool {
    true
}

fn default_max_per_submit() -> u32 {
    1000
}

fn default_max_unfinished() -> usize {
    5000
}

fn default_request() -> u64 {
    1000
}

fn default_grace() -> u64 {
    2000
}

fn default_handover_grace() -> u64 {
    30_000
}

fn default_proposal() -> u64 {
    1000
}
fn default_attempts() -> u32 {
    3
}
fn default_no_resource() -> u64 {
    60_000
}
fn default_retry() -> u64 {
    50
}
fn default_retry_max() -> u64 {
    2000
}
fn default_step() -> u64 {
    600_000
}

impl Default for OrdersSection {
    fn default() -> Self {
        OrdersSection {
            proposal_timeout_ms: default_proposal(),
            max_attempts: default_attempts(),
            no_resource_timeout_ms: default_no_resource(),
            retry_interval_ms: default_retry(),
            retry_max_ms: default_retry_max(),
            step_timeout_ms: default_step(),
            vanished_grace_ms: default_grace(),
            handover_grace_ms: default_handover_grace(),
            request_timeout_ms: default_request(),
            max_orders_per_submit: None,
            max_unfinished_orders: default_max_unfinished(),
            start_on_turn: default_start_on_turn(),
            advice_timeout_ms: default_advice_timeout(),
            wait_at_port: default_wait_at_port(),
        }
    }
}

/// How orders negotiate and retry.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OrderSettings {
    /// How long a proposal round waits for replies.
    pub proposal_timeout: Duration,
    /// Failed attempts of one step (on different resources) before the order fails.
    pub max_attempts: u32,
    /// How long a step may find no resource to book before the order fails.
    pub no_resource_timeout: Duration,
    /// First pause before a retry (a `start` refused as busy, an empty proposal round);
    /// it doubles while the retry keeps failing, up to `retry_max`.
    pub retry_interval: Duration,
    /// Longest pause between retries. An order waiting for a busy resource is woken at
    /// once when that resource publishes that it is free and the order is first on its
    /// agenda, and a waiting order is woken when a resource appears: the pauses are the
    /// fallback, not the way work normally resumes.
    pub retry_max: Duration,
    /// Longest wait for a started step's result before the attempt counts as failed.
    pub step_timeout: Duration,
    /// How long a resource that vanished while running a step may take to come back
    /// and report it before the step is booked elsewhere.
    pub vanished_grace: Duration,
    /// How long a resource that said it is being handed over to a successor (an
    /// upgrade) may be away before its bookings are booked elsewhere.
    pub handover_grace: Duration,
    /// Longest wait for a resource's answer to one request (booking, start, cancel).
    pub request_timeout: Duration,
    /// The most orders one work order may create; a larger `count` is refused (`quota`).
    pub max_orders_per_submit: u32,
    /// The most unfinished orders this node hosts; a work order that would pass it is
    /// refused whole (`quota`).
    pub max_unfinished_orders: usize,
    /// Bookings ask the resource to start the step by itself when its turn comes
    /// (`start_on_turn` in the `booking_req`): at once when it is free, else as soon as
    /// the job ahead ends, without a `start` from the order. False: the order sends
    /// `start` itself when the resource says it is its turn (for a cell where the part
    /// must be brought to the resource first).
    pub start_on_turn: bool,
    /// How long an order waits for a staff holon's advice, asked together with the
    /// proposals (the round usually takes longer); `ZERO`: never asks.
    pub advice_timeout: Duration,
    /// A part at a station's port whose next station has no place yet may wait there
    /// rather than go home, while no part of this node waits for a service of the
    /// station it holds: for the time its move home would take, and on while a
    /// station of its next service works, up to four times that
    /// (docs/material-flow.md, "Orders arrange their moves"). False: it goes home at
    /// once.
    pub wait_at_port: bool,
}

#[derive(Debug, Clone)]
pub struct OrderNodeConfig {
    pub keys: CellKeys,
    pub name: String,
    pub zenoh: ZenohSettings,
    pub orders: OrderSettings,
    /// Where the journal lives (`<dir>/order-node-<name>.sqlite`); None: not durable.
    pub data_dir: Option<std::path::PathBuf>,
    pub durability: holon::journal::Durability,
    /// How long a finished order (done, scrapped, failed, cancelled) stays in the
    /// journal and in `cell orders` after it ended; `None`: for ever.
    pub keep_finished: Option<Duration>,
    /// Start as the successor of the running order-node (`--take-over`), waiting this
    /// long at most for it to hand over.
    pub take_over: Option<Duration>,
    /// The journal on etcd (`journal.etcd`), for a primary and standbys of this name on
    /// several hosts; `None`: the SQLite journal in `data_dir`.
    pub etcd: Option<EtcdSettings>,
}

/// Where the order-node's journal lives on etcd, and its leader key's lease.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EtcdSettings {
    /// The members' client URLs (`journal.etcd`).
    pub endpoints: Vec<String>,
    /// The key prefix of this node's leader key and records (`journal.etcd_prefix`,
    /// default `holarchy/<cell>/order-node/<name>`).
    pub prefix: String,
    /// The leader key's lease (`journal.lease_ttl_ms`, whole seconds, at least 2 s): how
    /// long a dead or cut-off primary holds the name before a standby may take it.
    pub lease_ttl: Duration,
    /// With `https://` endpoints: the CA the members' certificates must be issued by,
    /// and the certificate and key this node presents (`[journal.etcd_tls]`, each by
    /// default the cell CA and the node's identity `order-node.<name>` of its secure
    /// cell). `None` with `http://` endpoints.
    pub tls: Option<holon::etcd::TlsFiles>,
}

/// The most records etcd takes in one commit, less the next order number written with
/// a work order's orders: the most orders one work order may create on etcd.
pub const MAX_ORDERS_PER_SUBMIT_ON_ETCD: u32 = holon::etcd::MAX_RECORDS_PER_WRITE as u32 - 1;

/// What the command line may override: cell, name, zenoh endpoints, data directory.
pub type Overrides = holon::session::CommandLine;

impl OrderNodeConfig {
    pub fn load(path: &Path, overrides: Overrides) -> Result<Self, ConfigError> {
        let (text, display) = holon::config_file::read(path)?;
        Self::parse(&text, &display, overrides)
    }

    pub fn parse(text: &str, path: &str, overrides: Overrides) -> Result<Self, ConfigError> {
        let invalid = holon::config_file::invalid(path);
        let mut file: File = holon::config_file::parse(text, path)?;
        let header = holon::config_file::Header {
            cell: file.cell,
            name: file.name,
            zenoh: file.zenoh,
        }
        .check(
            path,
            &overrides,
            &mut file.journal.dir,
            holon::role::Role::OrderNode,
        )
        .map_err(&invalid)?;
        if header.name.len() > 40 {
            return Err(invalid(
                "name: at most 40 bytes (order names append a number)".into(),
            ));
        }
        let base = Path::new(path).parent().unwrap_or(Path::new(""));
        let etcd = etcd_settings(
            &file.journal,
            &header.keys,
            &header.name,
            &header.zenoh,
            base,
            &overrides,
        )
        .map_err(&invalid)?;
        let max_orders_per_submit = match (file.orders.max_orders_per_submit, &etcd) {
            (Some(n), Some(_)) if n > MAX_ORDERS_PER_SUBMIT_ON_ETCD => {
                return Err(invalid(format!(
                    "orders.max_orders_per_submit ({n}) must be at most \
                     {MAX_ORDERS_PER_SUBMIT_ON_ETCD} with journal.etcd: a work order's orders \
                     and the next number go to etcd in one commit, of at most {} records",
                    holon::etcd::MAX_RECORDS_PER_WRITE
                )))
            }
            (Some(n), _) => n,
            (None, Some(_)) => MAX_ORDERS_PER_SUBMIT_ON_ETCD,
            (None, None) => default_max_per_submit(),
        };
        let o = &file.orders;
        for (field, value) in [
            ("orders.proposal_timeout_ms", o.proposal_timeout_ms),
            ("orders.max_attempts", o.max_attempts as u64),
            ("orders.no_resource_timeout_ms", o.no_resource_timeout_ms),
            ("orders.retry_interval_ms", o.retry_interval_ms),
            ("orders.retry_max_ms", o.retry_max_ms),
            ("orders.step_timeout_ms", o.step_timeout_ms),
            ("orders.request_timeout_ms", o.request_timeout_ms),
            ("orders.max_orders_per_submit", max_orders_per_submit as u64),
            (
                "orders.max_unfinished_orders",
                o.max_unfinished_orders as u64,
            ),
        ] {
            if value == 0 {
                return Err(invalid(format!("{field} must be greater than 0")));
            }
        }
        if o.advice_timeout_ms > 1000 {
            return Err(invalid(format!(
                "orders.advice_timeout_ms ({}) must be at most 1000: advice that comes later is no help",
                o.advice_timeout_ms
            )));
        }
        if o.retry_max_ms < o.retry_interval_ms {
            return Err(invalid(format!(
                "orders.retry_max_ms ({}) must be at least orders.retry_interval_ms ({})",
                o.retry_max_ms, o.retry_interval_ms
            )));
        }
        Ok(OrderNodeConfig {
            keys: header.keys,
            name: header.name,
            zenoh: header.zenoh,
            orders: OrderSettings {
                proposal_timeout: Duration::from_millis(o.proposal_timeout_ms),
                max_attempts: o.max_attempts,
                no_resource_timeout: Duration::from_millis(o.no_resource_timeout_ms),
                retry_interval: Duration::from_millis(o.retry_interval_ms),
                retry_max: Duration::from_millis(o.retry_max_ms),
                step_timeout: Duration::from_millis(o.step_timeout_ms),
                vanished_grace: Duration::from_millis(o.vanished_grace_ms),
                handover_grace: Duration::from_millis(o.handover_grace_ms),
                request_timeout: Duration::from_millis(o.request_timeout_ms),
                max_orders_per_submit,
                max_unfinished_orders: o.max_unfinished_orders,
                start_on_turn: o.start_on_turn,
                advice_timeout: Duration::from_millis(o.advice_timeout_ms),
                wait_at_port: o.wait_at_port,
            },
            data_dir: file.journal.dir,
            durability: file.journal.durability,
            keep_finished: (file.journal.keep_finished_ms > 0)
                .then(|| Duration::from_millis(file.journal.keep_finished_ms)),
            take_over: overrides.take_over,
            etcd,
        })
    }
}

/// The etcd settings of `journal`, if it names etcd members. With etcd the journal is
/// not in a data directory: `journal.dir` (or `--data-dir`) beside `journal.etcd` is
/// refused, as is `--take-over` (the leader key decides who serves). TLS: see
/// [`etcd_tls`].
fn etcd_settings(
    journal: &JournalSection,
    keys: &CellKeys,
    name: &str,
    zenoh: &ZenohSettings,
    base: &Path,
    overrides: &Overrides,
) -> Result<Option<EtcdSettings>, String> {
    if journal.etcd.is_empty() {
        if journal.etcd_prefix.is_some() {
            return Err("journal.etcd_prefix is set without journal.etcd".into());
        }
        let tls = &journal.etcd_tls;
        if tls.ca.is_some() || tls.certificate.is_some() || tls.key.is_some() {
            return Err("journal.etcd_tls is set without journal.etcd".into());
        }
        if journal.etcd_plain_http {
            return Err("journal.etcd_plain_http is set without journal.etcd".into());
        }
        return Ok(None);
    }
    if let Some(dir) = &journal.dir {
        return Err(format!(
            "journal.dir (or --data-dir, here {}) and journal.etcd exclude each other: with \
             etcd the orders live in etcd, and nothing is read from or written to a data \
             directory (the orders of a SQLite journal there would not be resumed); remove one",
            dir.display()
        ));
    }
    if overrides.take_over.is_some() {
        return Err(
            "--take-over with journal.etcd: an order-node on etcd is replaced by its \
                    standby (start the new one, then stop the old one: it gives its leader key up)"
                .into(),
        );
    }
    if journal.etcd.iter().any(|e| e.trim().is_empty()) {
        return Err("journal.etcd: an endpoint is empty".into());
    }
    let ttl = journal.lease_ttl_ms;
    if ttl < 2000 || !ttl.is_multiple_of(1000) {
        return Err(format!(
            "journal.lease_ttl_ms ({ttl}) must be a whole number of seconds, at least 2000 \
             (etcd's leases are in seconds, 2 s at least)"
        ));
    }
    let prefix = match &journal.etcd_prefix {
        Some(prefix) => {
            let prefix = prefix.trim_end_matches('/');
            if prefix.is_empty() {
                return Err("journal.etcd_prefix is empty".into());
            }
            prefix.to_string()
        }
        None => format!("holarchy/{}/order-node/{name}", keys.cell()),
    };
    let tls = etcd_tls(journal, name, zenoh, base)?;
    Ok(Some(EtcdSettings {
        endpoints: journal.etcd.clone(),
        prefix,
        lease_ttl: Duration::from_millis(ttl),
        tls,
    }))
}

/// The TLS files for `journal.etcd`: all endpoints `https://` or all `http://`.
/// - https: `[journal.etcd_tls]`'s files (relative to `base`, the config file's
///   directory), each by default the node's own in a secure cell (the cell CA,
///   `order-node.<name>.pem` and `.key`); a file neither gives is an error saying what to
///   set. The files are read now: one that is not usable stops the start.
/// - http: no TLS. In a secure cell (`[zenoh.tls]` or `--pki`) a member off loopback is
///   refused unless `journal.etcd_plain_http` says the operator knows anyone who reaches
///   etcd's port can rewrite the journal.
fn etcd_tls(
    journal: &JournalSection,
    name: &str,
    zenoh: &ZenohSettings,
    base: &Path,
) -> Result<Option<holon::etcd::TlsFiles>, String> {
    use holon::etcd::{common_scheme, Endpoint, Scheme};
    let scheme = common_scheme(&journal.etcd).map_err(|e| format!("journal.etcd: {e}"))?;
    let given = &journal.etcd_tls;
    let secure = zenoh.tls.is_some();
    match scheme {
        Scheme::Http => {
            if given.ca.is_some() || given.certificate.is_some() || given.key.is_some() {
                return Err("journal.etcd_tls is set but journal.etcd's endpoints are \
                            http://: write them https:// (the members must serve TLS)"
                    .into());
            }
            let remote: Vec<&str> = journal
                .etcd
                .iter()
                .filter(|e| Endpoint::parse(e).is_ok_and(|e| !e.is_loopback()))
                .map(String::as_str)
                .collect();
            if secure && !remote.is_empty() && !journal.etcd_plain_http {
                return Err(format!(
                    "journal.etcd: this cell is secure ([zenoh.tls] or --pki) but etcd is \
                     spoken to over plain http ({}): anyone who reaches etcd's port could \
                     rewrite the order journal. Serve etcd's clients over TLS and write the \
                     endpoints https:// (the cell CA and this node's identity are used; \
                     `cell certs` issues etcd.<host> for [pki] etcd_hosts), or set \
                     journal.etcd_plain_http = true to accept the risk",
                    remote.join(", ")
                ));
            }
            if journal.etcd_plain_http && !secure {
                return Err(
                    "journal.etcd_plain_http is for a secure cell ([zenoh.tls] or \
                            --pki); without it the whole cell is plain TCP and http is the \
                            default"
                        .into(),
                );
            }
            Ok(None)
        }
        Scheme::Https => {
            if journal.etcd_plain_http {
                return Err("journal.etcd_plain_http = true with https:// endpoints: \
                            remove one"
                    .into());
            }
            let identity = holon::role::identity(holon::role::Role::OrderNode, name);
            let own = zenoh
                .identity_files(&identity)
                .map_err(|e| format!("zenoh: {e}"))?;
            let pick = |field: &str,
                        set: &Option<std::path::PathBuf>,
                        default: Option<&std::path::PathBuf>| {
                match (set, default) {
                    (Some(path), _) if path.is_relative() => Ok(base.join(path)),
                    (Some(path), _) => Ok(path.clone()),
                    (None, Some(path)) => Ok(path.clone()),
                    (None, None) => Err(format!(
                        "journal.etcd is https:// but journal.etcd_tls.{field} is not set, and \
                         this cell is not secure (no [zenoh.tls] nor --pki) to take it from: \
                         set journal.etcd_tls's ca, certificate and key (the CA that issued \
                         the members' certificates, and this node's certificate and key)"
                    )),
                }
            };
            let files = holon::etcd::TlsFiles {
                ca: pick("ca", &given.ca, own.as_ref().map(|f| &f.ca))?,
                certificate: pick(
                    "certificate",
                    &given.certificate,
                    own.as_ref().map(|f| &f.certificate),
                )?,
                key: pick("key", &given.key, own.as_ref().map(|f| &f.key))?,
            };
            files
                .client_config()
                .map_err(|e| format!("journal.etcd_tls: {e}"))?;
            Ok(Some(files))
        }
    }
}

#[cfg(test)]
mod tests;

//! An order-node whose journal is on etcd (`journal.etcd`): processes of one name on
//! several hosts are a primary and standbys, and the leader key on etcd decides which
//! one serves (docs/reliability.md, "Order-node standby on etcd").
//!
//! Before it declares anything else in the cell, a node declares where it stands
//! ([`crate::fence_report`]) and campaigns for `<prefix>/leader`
//! ([`holon::etcd::Candidate`]). While another holds it, the node is a standby: it
//! logs so, declares no token and no other queryable, and answers nothing else; every
//! [`FOLLOW_EVERY`] it reads the journal's records changed since it last read, applies
//! them to its copy of the orders ([`Recovery`]: the unfinished ones whole, of the
//! finished only number and end), and reports its lag (the cluster's revisions it has
//! not read) or that it cannot reach etcd. Once it wins at epoch E it reads only what
//! changed since its last read (nothing can change after: every write of a deposed
//! holder is refused) and serves with its copy; every write of its orders is fenced on
//! E. Without a whole copy (a record it could not read, etcd slow at the takeover) it
//! reads the journal whole, as a SQLite node reads its journal at start. When it is
//! deposed it stops at once and exits with an error, so that its supervisor starts it
//! again, a standby.

use std::sync::Arc;
use std::time::Duration;

use holon::etcd::{Candidate, Client, ClientConfig, ElectionConfig, Leader};
use holon::life::Leadership;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::config::{EtcdSettings, OrderNodeConfig};
use crate::error::OrderNodeError;
use crate::fence_report::Reporter;
use crate::journal::{OrderJournal, Replicated};
use crate::recovery::{recover, Recovered, Recovery};

/// The orders' journal and what it holds, from the leadership (etcd's), or `None`:
/// the node opens its own.
pub type Grant = Option<(Arc<OrderJournal>, Recovered)>;

/// How long a deposed node asks etcd who deposed it, at most, for its exit message.
const ASK_HOLDER_WITHIN: Duration = Duration::from_secs(2);

/// How long resigning the leader key at shutdown may take before the node goes on (the
/// key then goes with its lease).
const RESIGN_WITHIN: Duration = Duration::from_secs(2);

/// How often a standby reads the journal's changes (and who holds the key).
pub const FOLLOW_EVERY: Duration = Duration::from_millis(500);

/// How long one such read may take before the standby counts etcd as lost.
const FOLLOW_WITHIN: Duration = Duration::from_secs(2);

/// The most records one read of the journal's changes takes (more: the next page at
/// once, and a lag meanwhile).
const FOLLOW_PAGE: usize = 1000;

/// How long the read of what changed since the standby's last read may take once it
/// won, before it reads the journal whole instead.
const CATCH_UP_WITHIN: Duration = Duration::from_secs(2);

/// A node that won its leader key, with its orders read from etcd.
pub struct Elected {
    /// Where this process stands (holder at its epoch), answered while it serves.
    pub report: Reporter,
    /// The holder of the leader key; dropped or resigned when the node stops.
    pub leader: Leader,
    /// The candidate it won as: asked who holds the key once this node is deposed.
    pub candidate: Candidate,
    /// The orders' store, fenced on the leader's epoch.
    pub journal: Arc<OrderJournal>,
    /// What the store held when the node won.
    pub recovered: Recovered,
}

/// The etcd leader key as an order-node's leadership: campaigned for before the node
/// starts (a standby follows the journal meanwhile), lost when etcd says so, given up
/// when the node stops.
pub struct EtcdLeader<'a> {
    /// The node's config.
    config: &'a OrderNodeConfig,
    /// Where its journal and leader key are.
    etcd: &'a EtcdSettings,
    /// The key won, while held.
    elected: Option<Elected>,
}

impl<'a> EtcdLeader<'a> {
    /// A candidate for the node's leader key on `etcd`.
    pub fn new(config: &'a OrderNodeConfig, etcd: &'a EtcdSettings) -> EtcdLeader<'a> {
        EtcdLeader {
            config,
            etcd,
            elected: None,
        }
    }
}

impl<B> Leadership<B> for EtcdLeader<'_>
where
    B: holon::life::Behaviour<Grant = Grant, Error = OrderNodeError>,
{
    /// Stands by until it wins the key; its orders, read from etcd, are the grant.
    async fn win(
        &mut self,
        _life: &holon::life::Life,
        session: &zenoh::Session,
        shutdown: &CancellationToken,
    ) -> Result<Option<Grant>, OrderNodeError> {
        let Some(mut elected) = stand_by(self.config, self.etcd, session, shutdown).await? else {
            return Ok(None);
        };
        let grant = (
            elected.journal.clone(),
            std::mem::take(&mut elected.recovered),
        );
        self.elected = Some(elected);
        Ok(Some(Some(grant)))
    }

    fn refusal(&self) -> Option<String> {
        Some("its journal is on etcd: start the successor beside it (a standby), then stop this one, which gives its leader key up".into())
    }

    async fn serving(&mut self, _life: &holon::life::Life) {
        if let Some(elected) = &self.elected {
            let epoch = elected.leader.epoch();
            info!(node = %self.config.name, epoch, "serving at epoch {epoch}: the order-node's leader key on etcd is this process's");
        }
    }

    async fn lost(&mut self) -> String {
        match &self.elected {
            Some(elected) => deposed(elected).await,
            None => std::future::pending().await,
        }
    }

    /// Stopped: the key is given up, so that a standby serves at once.
    async fn resign(&mut self) {
        if let Some(elected) = self.elected.take() {
            resign(&self.config.name, elected.leader).await;
        }
    }

    /// Deposed: the node ends, naming who holds the key now.
    async fn deposed(&mut self, why: &str) -> Result<(), OrderNodeError> {
        match self.elected.take() {
            Some(elected) => Err(deposed_error(&elected, why.to_string()).await),
            None => Err(OrderNodeError::Deposed {
                epoch: 0,
                by: "an unknown holder".into(),
                why: why.to_string(),
            }),
        }
    }
}

/// Campaigns for the node's leader key until it wins (then reads its orders) or
/// `shutdown` (`Ok(None)`). While another holds the key the node is a standby.
async fn stand_by(
    config: &OrderNodeConfig,
    etcd: &EtcdSettings,
    session: &zenoh::Session,
    shutdown: &CancellationToken,
) -> Result<Option<Elected>, OrderNodeError> {
    let node = &config.name;
    let handle = tokio::runtime::Handle::current();
    if handle.runtime_flavor() != tokio::runtime::RuntimeFlavor::MultiThread {
        // The journal's synchronous calls block on etcd in place: that needs other
        // workers to run the runtime meanwhile.
        return Err(holon::etcd::EtcdError::Config(
            "the order journal on etcd needs tokio's multi-thread runtime".into(),
        )
        .into());
    }
    let client = Client::new(ClientConfig {
        tls: etcd.tls.clone(),
        ..ClientConfig::new(etcd.endpoints.clone())
    })?;
    let me = holon::presence::Holder::this_process(session).to_string();
    let mut election = ElectionConfig::new(etcd.prefix.clone(), me);
    election.ttl = etcd.lease_ttl;
    election.keep_alive_every = etcd.lease_ttl / 4;
    let candidate = Candidate::new(client.clone(), election);
    let report = Reporter::declare(node, &config.keys.node_fence(node), session).await;
    match candidate.holder().await {
        Ok(Some(holder)) => info!(
            %node,
            holder = %holder.candidate,
            epoch = holder.epoch,
            "standby: order-node {node} is held by {} (epoch {}); waiting",
            holder.candidate,
            holder.epoch
        ),
        Ok(None) => {}
        Err(e) => {
            warn!(%node, error = %e, endpoints = ?etcd.endpoints, "cannot ask etcd who holds the order-node; campaigning anyway")
        }
    }
    let mut copy = Followed::new(node);
    let won = tokio::select! {
        won = candidate.campaign(shutdown.cancelled()) => won?,
        never = follow(&client, &candidate, &etcd.prefix, config, &report, &mut copy) => match never {},
    };
    let Some(leader) = won else {
        info!(%node, "told to stop while standing by");
        return Ok(None);
    };
    let epoch = leader.epoch();
    report.holder(u64::try_from(epoch).unwrap_or_default());
    let journal = Arc::new(OrderJournal::Replicated(Replicated {
        store: leader.store(),
        handle,
        deposed: CancellationToken::new(),
    }));
    let read = match catch_up(&client, &etcd.prefix, copy).await {
        Ok((recovered, changes)) => {
            info!(%node, epoch, key = %leader.key(), changes, hosted = recovered.hosted.len(), finished = recovered.finished.len(), submits = recovered.submits.len(), "won the order-node's leader key at epoch {epoch}: serving with the orders it followed, {changes} records read at the takeover");
            Ok(recovered)
        }
        Err(why) => {
            info!(%node, epoch, key = %leader.key(), %why, "won the order-node's leader key at epoch {epoch}: reading its orders from etcd whole");
            recover(&journal, node)
        }
    };
    match read {
        Ok(recovered) => Ok(Some(Elected {
            report,
            leader,
            candidate,
            journal,
            recovered,
        })),
        Err(e) => {
            // Given up at once, so that a standby need not wait for the lease.
            resign(node, leader).await;
            Err(e.into())
        }
    }
}

/// A standby's copy of its holder's orders, and how far it read.
struct Followed {
    /// The orders as the journal holds them, up to `read_to`.
    recovery: Recovery,
    /// Every change of the journal up to this revision is applied.
    read_to: i64,
}

impl Followed {
    fn new(node: &str) -> Followed {
        Followed {
            recovery: Recovery::new(node),
            read_to: 0,
        }
    }

    /// Applies one read of the journal's changes; returns its lag.
    fn apply(&mut self, read: &holon::etcd::JournalRead) -> u64 {
        self.recovery.apply(&read.records);
        self.read_to = read.read_to;
        read.lag()
    }
}

/// A standby follows its holder's journal until the campaign ends (never returns):
/// every [`FOLLOW_EVERY`] (at once while a read was cut after a page), who holds the key
/// and the records changed since it last read (bounded by [`FOLLOW_WITHIN`]), applied
/// to its copy; its report says the holder's epoch and its lag, or that it lost etcd. A
/// change of either is logged once.
async fn follow(
    client: &Client,
    candidate: &Candidate,
    prefix: &str,
    config: &OrderNodeConfig,
    report: &Reporter,
    copy: &mut Followed,
) -> std::convert::Infallible {
    let node = &config.name;
    let mut lost = false;
    let mut behind = false;
    let mut records = 0usize;
    let mut every = tokio::time::interval(FOLLOW_EVERY);
    every.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut page_cut = false;
    loop {
        if !page_cut {
            every.tick().await;
        }
        let read_to = copy.read_to;
        let asked = tokio::time::timeout(FOLLOW_WITHIN, async {
            let holder = candidate.holder().await?;
            let read = holon::etcd::journal_since(client, prefix, read_to, FOLLOW_PAGE).await?;
            Ok::<_, holon::etcd::EtcdError>((holder, read))
        })
        .await;
        page_cut = false;
        match asked {
            Ok(Ok((holder, read))) => {
                if lost {
                    info!(%node, revision = read.revision, "standby: reaches etcd again");
                    lost = false;
                }
                records += read.records.len();
                page_cut = read.records.len() >= FOLLOW_PAGE;
                let lag = copy.apply(&read);
                if let Some(keep) = config.keep_finished {
                    let keep_ms = u64::try_from(keep.as_millis()).unwrap_or(u64::MAX);
                    copy.recovery
                        .forget_finished_before(schemas::unix_ms().saturating_sub(keep_ms));
                }
                if (lag > 0) != behind {
                    behind = lag > 0;
                    if behind {
                        warn!(%node, lag, read_to = copy.read_to, "standby: behind the journal by {lag} revisions");
                    } else {
                        let (hosted, finished) = copy.recovery.counts();
                        info!(%node, read_to = copy.read_to, records, hosted, finished, "standby: caught up with the journal");
                    }
                }
                let holder_epoch = holder.and_then(|h| u64::try_from(h.epoch).ok());
                report.following(holder_epoch, lag);
            }
            failed => {
                let why = match failed {
                    Ok(Err(e)) => e.to_string(),
                    _ => format!("etcd did not answer within {FOLLOW_WITHIN:?}"),
                };
                if !lost {
                    warn!(%node, error = %why, read_to, "standby: store lost, cannot read the journal on etcd (it cannot take over meanwhile)");
                    lost = true;
                }
                report.store_lost();
            }
        }
    }
}

/// Once won: reads what changed since the copy's last read, up to the cluster's
/// revision now, and returns the orders to serve with and how many records it read.
/// Nothing changes the journal after this read: the key is this node's, so every write
/// of the holder before is refused. Fails (the caller reads the journal whole) when the
/// copy has a record it could not read, or etcd does not answer within
/// [`CATCH_UP_WITHIN`].
async fn catch_up(
    client: &Client,
    prefix: &str,
    mut copy: Followed,
) -> Result<(Recovered, usize), String> {
    let mut changes = 0;
    let caught_up = tokio::time::timeout(CATCH_UP_WITHIN, async {
        loop {
            let read = holon::etcd::journal_since(client, prefix, copy.read_to, FOLLOW_PAGE)
                .await
                .map_err(|e| e.to_string())?;
            changes += read.records.len();
            if copy.apply(&read) == 0 {
                return Ok::<_, String>(());
            }
        }
    })
    .await;
    match caught_up {
        Ok(Ok(())) => {}
        Ok(Err(why)) => return Err(format!("cannot read the journal's last changes: {why}")),
        Err(_) => {
            return Err(format!(
                "etcd did not give the journal's last changes within {CATCH_UP_WITHIN:?}"
            ))
        }
    }
    if let Some(record) = copy.recovery.unreadable_record() {
        return Err(format!("a record it followed cannot be read: {record}"));
    }
    Ok((copy.recovery.into_recovered(), changes))
}

/// Waits until the node is deposed: its keep-alive says so, or etcd refused a write.
async fn deposed(elected: &Elected) -> String {
    let refused = elected.journal.deposed().unwrap_or_default();
    tokio::select! {
        why = elected.leader.deposed() => why,
        _ = refused.cancelled() => "etcd refused a write of this epoch".into(),
    }
}

/// The error a deposed node exits with, naming who holds the key now (asked of etcd,
/// bounded).
async fn deposed_error(elected: &Elected, why: String) -> OrderNodeError {
    let by = match tokio::time::timeout(ASK_HOLDER_WITHIN, elected.candidate.holder()).await {
        Ok(Ok(Some(holder))) => format!("epoch {} ({})", holder.epoch, holder.candidate),
        Ok(Ok(None)) => "no holder yet (the key is free)".into(),
        Ok(Err(e)) => format!("an unknown holder (etcd: {e})"),
        Err(_) => format!("an unknown holder (etcd did not answer within {ASK_HOLDER_WITHIN:?})"),
    };
    OrderNodeError::Deposed {
        epoch: elected.leader.epoch(),
        by,
        why,
    }
}

/// Gives the leader key up (bounded): a standby takes over within its next ask.
async fn resign(node: &str, leader: Leader) {
    let epoch = leader.epoch();
    match tokio::time::timeout(RESIGN_WITHIN, leader.resign()).await {
        Ok(Ok(())) => info!(%node, epoch, "gave the leader key up: a standby may serve now"),
        Ok(Err(e)) => {
            warn!(%node, epoch, error = %e, "cannot give the leader key up; a standby takes over when its lease expires")
        }
        Err(_) => {
            warn!(%node, epoch, "etcd did not take the leader key back within {RESIGN_WITHIN:?}; a standby takes over when its lease expires")
        }
    }
}

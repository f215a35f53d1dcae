//! The election of one holder among candidates of one name, on etcd.
//!
//! The holder owns `<prefix>/leader`, a key created under its lease by a txn that
//! succeeds only if the key does not exist; the value is the holder's name. The
//! **epoch** is the key's create_revision: etcd's revisions only grow, so every new
//! holder's epoch is greater than every earlier one's, and it is the fencing token of
//! the holder's writes ([`super::FencedStore`]) and of whatever else it sends.
//!
//! A candidate that loses waits until the key is gone (asking every
//! [`ElectionConfig::retry_every`]) and tries again. The holder renews its lease every
//! [`ElectionConfig::keep_alive_every`] (TTL / 4 by default) and checks that the key is
//! still its own. It is **deposed**, told on [`Leader::watch`], as soon as:
//! - etcd says its lease is gone (expired or revoked: the key went with it), or the key
//!   was deleted or is another holder's; or
//! - no keep-alive was confirmed for long enough that the lease may have expired: a
//!   keep-alive sent at `t` that etcd confirms keeps the lease at least until `t + TTL`,
//!   and the holder gives up at that time, less [`ElectionConfig::step_down_margin`]
//!   for timers that fire late. (A failed keep-alive is tried again at the next tick;
//!   etcd itself extends leases when its raft leader changes, but a holder that cannot
//!   reach a raft leader cannot know it.)
//!
//! The store does not depend on the holder hearing this in time: every write is fenced
//! by etcd on the epoch. The event is for the holder to stop acting at once.

use std::time::Duration;

use tokio::sync::watch;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use super::client::Retry;
use super::wire::{self, Compare, PutRequest, RangeRequest, RequestOp, TxnRequest};
use super::{Client, EtcdError, FencedStore};

/// What an election is about and how fast it goes.
#[derive(Debug, Clone)]
pub struct ElectionConfig {
    /// The key prefix of the holon's state, e.g. `holarchy/<cell>/order-node/<name>`:
    /// the leader key is `<prefix>/leader`.
    pub prefix: String,
    /// This candidate's name, written as the leader key's value (host and process, for
    /// people reading who holds it).
    pub candidate: String,
    /// The lease's time to live, in whole seconds (etcd takes no less than 2 s).
    pub ttl: Duration,
    /// How often the holder renews its lease (and checks its key).
    pub keep_alive_every: Duration,
    /// How often a candidate that lost asks whether the key is gone.
    pub retry_every: Duration,
    /// How long before its lease may have expired a holder with no confirmed keep-alive
    /// steps down.
    pub step_down_margin: Duration,
}

impl ElectionConfig {
    /// The defaults: a 2 s lease renewed every 500 ms, a holder that could not renew it
    /// steps down 200 ms before it may expire; a loser asks every 250 ms.
    pub fn new(prefix: impl Into<String>, candidate: impl Into<String>) -> ElectionConfig {
        let ttl = Duration::from_secs(2);
        ElectionConfig {
            prefix: prefix.into(),
            candidate: candidate.into(),
            ttl,
            keep_alive_every: ttl / 4,
            retry_every: Duration::from_millis(250),
            step_down_margin: Duration::from_millis(200),
        }
    }

    /// `<prefix>/leader`.
    pub fn leader_key(&self) -> String {
        leader_key(&self.prefix)
    }
}

/// `<prefix>/leader`.
pub(crate) fn leader_key(prefix: &str) -> String {
    format!("{prefix}/leader")
}

/// A holder's standing, as its [`Leader::watch`] tells it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Leadership {
    /// It holds the leader key at this epoch.
    Holding {
        /// The leader key's create_revision.
        epoch: i64,
    },
    /// It no longer does, and never will again at this epoch: it must stop acting.
    Deposed {
        /// The epoch it held.
        epoch: i64,
        /// Why it is deposed.
        why: String,
    },
}

/// Who holds a leader key now.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Holder {
    /// The holder's name (the key's value).
    pub candidate: String,
    /// Its epoch (the key's create_revision).
    pub epoch: i64,
}

/// One candidate for one leader key.
#[derive(Debug, Clone)]
pub struct Candidate {
    /// The cluster.
    client: Client,
    /// The election.
    config: ElectionConfig,
}

impl Candidate {
    /// A candidate under `config`, speaking to etcd through `client`.
    pub fn new(client: Client, config: ElectionConfig) -> Candidate {
        Candidate { client, config }
    }

    /// The election's configuration.
    pub fn config(&self) -> &ElectionConfig {
        &self.config
    }

    /// Who holds the leader key now, if anyone (a linearizable read).
    pub async fn holder(&self) -> Result<Option<Holder>, EtcdError> {
        holder_of(&self.client, &self.config.leader_key()).await
    }

    /// Tries until it wins, and returns the holder; `Ok(None)` when `cancelled` ends
    /// first (a holon passes its shutdown token's `cancelled()`). While etcd is
    /// unreachable it keeps trying (saying so); an error that trying again cannot mend
    /// (a refusal, a malformed reply) is returned.
    pub async fn campaign(
        &self,
        cancelled: impl std::future::Future<Output = ()>,
    ) -> Result<Option<Leader>, EtcdError> {
        let cancel = CancellationToken::new();
        // Cancellation is taken at points where nothing is half done (never inside a try).
        let watcher = async {
            cancelled.await;
            cancel.cancel();
            std::future::pending::<()>().await
        };
        tokio::select! {
            outcome = self.campaign_until(&cancel) => outcome,
            _ = watcher => unreachable!("the watcher never ends"),
        }
    }

    async fn campaign_until(
        &self,
        cancel: &CancellationToken,
    ) -> Result<Option<Leader>, EtcdError> {
        let key = self.config.leader_key();
        let mut last_holder: Option<Holder> = None;
        // The last failure to reach etcd, logged once (again only when it changes).
        let mut failing: Option<String> = None;
        loop {
            if cancel.is_cancelled() {
                return Ok(None);
            }
            // Bounded by the client's timeouts; not cut short, so a key won is not left.
            let tried = self.try_once().await;
            if !matches!(&tried, Err(e) if e.is_transient()) && failing.take().is_some() {
                tracing::info!(key = %key, "etcd answers again");
            }
            match tried {
                Ok(Ok(leader)) if cancel.is_cancelled() => {
                    if let Err(e) = leader.resign().await {
                        tracing::warn!(key = %key, error = %e, "won as the campaign was cancelled, and could not resign: the key expires with its lease");
                    }
                    return Ok(None);
                }
                Ok(Ok(leader)) => return Ok(Some(leader)),
                Ok(Err(holder)) => {
                    if last_holder.as_ref() != Some(&holder) {
                        tracing::info!(key = %key, holder = %holder.candidate, epoch = holder.epoch, "leader key held; standing by");
                        last_holder = Some(holder);
                    }
                    // Wait until it is gone.
                    loop {
                        tokio::select! {
                            _ = cancel.cancelled() => return Ok(None),
                            _ = tokio::time::sleep(self.config.retry_every) => {}
                        }
                        match holder_of(&self.client, &key).await {
                            Ok(None) => break,
                            Ok(Some(_)) => {}
                            Err(e) if e.is_transient() => {
                                failed(
                                    &mut failing,
                                    &key,
                                    &e,
                                    "cannot ask etcd who leads; asking again",
                                );
                            }
                            Err(e) => return Err(e),
                        }
                    }
                }
                Err(e) if e.is_transient() => {
                    failed(
                        &mut failing,
                        &key,
                        &e,
                        "cannot campaign on etcd; trying again",
                    );
                    tokio::select! {
                        _ = cancel.cancelled() => return Ok(None),
                        _ = tokio::time::sleep(self.config.retry_every) => {}
                    }
                }
                Err(e) => return Err(e),
            }
        }
    }

    /// One try: a new lease, and the leader key created under it if it does not exist.
    /// `Ok(Ok(leader))` when won, `Ok(Err(holder))` when someone else holds the key.
    pub async fn try_once(&self) -> Result<Result<Leader, Holder>, EtcdError> {
        let key = self.config.leader_key();
        let granted_at = Instant::now();
        let lease = self.client.lease_grant(self.config.ttl).await?;
        let txn = TxnRequest {
            compare: vec![Compare::created_at(key.as_str().into(), 0)],
            success: vec![RequestOp::Put(PutRequest {
                key: key.as_str().into(),
                value: self.config.candidate.as_str().into(),
                lease,
            })],
            failure: vec![RequestOp::Range(RangeRequest {
                key: key.as_str().into(),
                ..Default::default()
            })],
        };
        let reply: Result<wire::TxnResponse, _> =
            self.client.call("/v3/kv/txn", &txn, Retry::IfNotSent).await;
        let outcome = match reply {
            Ok(reply) if reply.succeeded => Ok(reply.header.revision),
            Ok(reply) => Err(holder_in(&reply)),
            // Whether it went in is told by the key: ours if it is under our lease.
            Err(EtcdError::Uncertain { .. }) => match self.key_under(&key, lease).await? {
                Some(epoch) => Ok(epoch),
                None => Err(holder_of(&self.client, &key).await?),
            },
            Err(e) => {
                self.revoke_unused(lease).await;
                return Err(e);
            }
        };
        match outcome {
            Ok(epoch) => {
                tracing::info!(key = %key, epoch, lease, candidate = %self.config.candidate, "won the leader key");
                Ok(Ok(Leader::start(
                    self.client.clone(),
                    self.config.clone(),
                    epoch,
                    lease,
                    granted_at,
                )))
            }
            Err(holder) => {
                self.revoke_unused(lease).await;
                // The key went between the txn and the read: nobody to name, try again.
                Ok(Err(holder.unwrap_or(Holder {
                    candidate: String::new(),
                    epoch: 0,
                })))
            }
        }
    }

    /// The create_revision of `key` if it exists under `lease`.
    async fn key_under(&self, key: &str, lease: i64) -> Result<Option<i64>, EtcdError> {
        let range = RangeRequest {
            key: key.into(),
            ..Default::default()
        };
        let reply: wire::RangeResponse = self
            .client
            .call("/v3/kv/range", &range, Retry::Always)
            .await?;
        Ok(reply
            .kvs
            .first()
            .filter(|kv| kv.lease == lease)
            .map(|kv| kv.create_revision))
    }

    /// Revokes a lease that won nothing (it would expire by itself anyway).
    async fn revoke_unused(&self, lease: i64) {
        if let Err(e) = self.client.lease_revoke(lease).await {
            tracing::debug!(lease, error = %e, "an unused lease was not revoked; it expires by itself");
        }
    }
}

/// The holder in a lost txn's failure branch.
pub(crate) fn holder_in(reply: &wire::TxnResponse) -> Option<Holder> {
    reply
        .responses
        .iter()
        .filter_map(|r| r.response_range.as_ref())
        .flat_map(|r| r.kvs.first())
        .map(holder_from)
        .next()
}

/// A failure to reach etcd while campaigning: logged as a warning when it is news (the
/// first, or another than the last), at debug when it repeats.
fn failed(failing: &mut Option<String>, key: &str, error: &EtcdError, what: &str) {
    let why = error.to_string();
    if failing.as_deref() == Some(why.as_str()) {
        tracing::debug!(key = %key, error = %why, "{what}");
    } else {
        tracing::warn!(key = %key, error = %why, "{what}");
        *failing = Some(why);
    }
}

fn holder_from(kv: &wire::KeyValue) -> Holder {
    Holder {
        candidate: String::from_utf8_lossy(&kv.value.0).into_owned(),
        epoch: kv.create_revision,
    }
}

/// Who holds `key`, read from etcd.
async fn holder_of(client: &Client, key: &str) -> Result<Option<Holder>, EtcdError> {
    let range = RangeRequest {
        key: key.into(),
        ..Default::default()
    };
    let reply: wire::RangeResponse = client.call("/v3/kv/range", &range, Retry::Always).await?;
    Ok(reply.kvs.first().map(holder_from))
}

/// The holder of the leader key. Dropping it stops its keep-alives without revoking
/// the lease (as a process that dies would): the key goes when the lease expires.
/// [`Leader::resign`] gives it up at once.
#[derive(Debug)]
pub struct Leader {
    /// The cluster.
    client: Client,
    /// The election it won.
    config: ElectionConfig,
    /// The leader key's create_revision.
    epoch: i64,
    /// The lease the key is under.
    lease: i64,
    /// Its standing, as the keep-alive task tells it.
    state: watch::Receiver<Leadership>,
    /// Stops the keep-alive task.
    stop: CancellationToken,
    /// Tells the holder's stores it resigned.
    tell: watch::Sender<Leadership>,
}

impl Leader {
    fn start(
        client: Client,
        config: ElectionConfig,
        epoch: i64,
        lease: i64,
        granted_at: Instant,
    ) -> Leader {
        let (tell, state) = watch::channel(Leadership::Holding { epoch });
        let stop = CancellationToken::new();
        let keeper = KeepAlive {
            client: client.clone(),
            config: config.clone(),
            epoch,
            lease,
            // A lease granted after `granted_at` lives at least until then + TTL.
            confirmed_until: granted_at + config.ttl,
            tell: tell.clone(),
        };
        tokio::spawn(keeper.run(stop.clone()));
        Leader {
            client,
            config,
            epoch,
            lease,
            state,
            stop,
            tell,
        }
    }

    /// The epoch: the leader key's create_revision, the fencing token of this holder.
    pub fn epoch(&self) -> i64 {
        self.epoch
    }

    /// The lease the leader key is attached to.
    pub fn lease(&self) -> i64 {
        self.lease
    }

    /// The leader key.
    pub fn key(&self) -> String {
        self.config.leader_key()
    }

    /// The holder's standing, told as it changes (once deposed, for good).
    pub fn watch(&self) -> watch::Receiver<Leadership> {
        self.state.clone()
    }

    /// Whether this holder has been deposed.
    pub fn is_deposed(&self) -> bool {
        matches!(*self.state.borrow(), Leadership::Deposed { .. })
    }

    /// Waits until this holder is deposed, and says why.
    pub async fn deposed(&self) -> String {
        let mut state = self.state.clone();
        loop {
            if let Leadership::Deposed { why, .. } = &*state.borrow_and_update() {
                return why.clone();
            }
            if state.changed().await.is_err() {
                return "the keep-alive task ended".into();
            }
        }
    }

    /// The record store fenced on this holder's epoch; it also refuses to write, without
    /// asking etcd, once this holder is deposed.
    pub fn store(&self) -> FencedStore {
        FencedStore::new(self.client.clone(), &self.config.prefix, self.epoch)
            .with_leadership(self.state.clone())
    }

    /// Gives the key up at once (its lease revoked): a standby may win it now. This
    /// holder's stores refuse to write from now on.
    pub async fn resign(self) -> Result<(), EtcdError> {
        self.stop.cancel();
        let resigned = Leadership::Deposed {
            epoch: self.epoch,
            why: "resigned".into(),
        };
        // The holder itself keeps a receiver: this cannot fail.
        self.tell.send_replace(resigned);
        self.client.lease_revoke(self.lease).await.map(|revoked| {
            tracing::info!(key = %self.config.leader_key(), epoch = self.epoch, revoked, "resigned the leader key");
        })
    }
}

impl Drop for Leader {
    fn drop(&mut self) {
        self.stop.cancel();
    }
}

/// The holder's keep-alive task.
struct KeepAlive {
    /// The cluster.
    client: Client,
    /// The election.
    config: ElectionConfig,
    /// The holder's epoch.
    epoch: i64,
    /// The lease renewed.
    lease: i64,
    /// Until when the lease surely lives, by the keep-alives etcd confirmed.
    confirmed_until: Instant,
    /// Tells the holder its standing.
    tell: watch::Sender<Leadership>,
}

impl KeepAlive {
    async fn run(mut self, stop: CancellationToken) {
        let key = self.config.leader_key();
        let mut ticks = tokio::time::interval(self.config.keep_alive_every);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = stop.cancelled() => return,
                _ = ticks.tick() => {}
            }
            // Gives up when the lease may have expired, renewal in flight or not.
            let give_up = self
                .confirmed_until
                .checked_sub(self.config.step_down_margin)
                .unwrap_or(self.confirmed_until);
            let verdict = tokio::select! {
                _ = stop.cancelled() => return,
                _ = tokio::time::sleep_until(give_up) => Some(format!(
                    "no keep-alive of lease {} confirmed by etcd in time: it may have expired",
                    self.lease
                )),
                verdict = self.renew(&key) => verdict,
            };
            if let Some(why) = verdict {
                tracing::warn!(key = %key, epoch = self.epoch, lease = self.lease, why = %why, "deposed");
                let deposed = Leadership::Deposed {
                    epoch: self.epoch,
                    why,
                };
                if self.tell.send(deposed).is_err() {
                    tracing::debug!(key = %key, "deposed, and nobody watches the leadership any more");
                }
                // The lease may still be alive in etcd: give it up so a standby need not
                // wait for it (best effort; it expires by itself otherwise).
                if let Err(e) = self.client.lease_revoke(self.lease).await {
                    tracing::debug!(lease = self.lease, error = %e, "lease not revoked after deposition");
                }
                return;
            }
        }
    }

    /// One renewal and check of the key: `Some(why)` when deposed.
    async fn renew(&mut self, key: &str) -> Option<String> {
        let sent = Instant::now();
        match self.client.lease_keep_alive(self.lease).await {
            Ok(Some(ttl)) => self.confirmed_until = sent + ttl.min(self.config.ttl),
            Ok(None) => {
                return Some(format!(
                    "etcd says lease {} is gone (expired or revoked)",
                    self.lease
                ))
            }
            Err(e) => {
                tracing::warn!(key = %key, lease = self.lease, error = %e, "keep-alive failed; trying again");
                return None;
            }
        }
        match holder_of(&self.client, key).await {
            Ok(Some(holder)) if holder.epoch == self.epoch => None,
            Ok(Some(holder)) => Some(format!(
                "the leader key is {}'s at epoch {}",
                holder.candidate, holder.epoch
            )),
            Ok(None) => Some("the leader key was deleted".into()),
            Err(e) => {
                tracing::warn!(key = %key, error = %e, "cannot read the leader key; trying again");
                None
            }
        }
    }
}

/// How a refused write names who holds the key now.
pub(crate) fn describe(holder: Option<&Holder>) -> String {
    match holder {
        Some(h) => format!("held by {} at epoch {}", h.candidate, h.epoch),
        None => "held by nobody".into(),
    }
}

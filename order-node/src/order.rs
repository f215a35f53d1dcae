//! One order holon: gets its product made by negotiating with the live resources.
//!
//! For each step of the plan: a proposal round on `offer/<type>/*`; book the best
//! proposal (the shortest expected wait, then the shortest queue, then the name; a
//! resource that failed this step is tried last); `start` it when the resource is free
//! (retrying while it is busy); wait for `done` in the inbox. A resource that vanishes or
//! hands its booking back is rebooked elsewhere; a step that fails is retried on another
//! resource up to `max_attempts`, then the order fails with the reason.
//!
//! Every change of the order's progress is written to the journal before the order acts
//! on it, and a result is acknowledged only after its outcome is written: a restarted
//! order-node resumes each order where it stood (see [`Phase`]).

use std::collections::{BTreeSet, HashMap, HashSet};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use holon::journal::Journal;
use schemas::{reason, HolonId, MessageType, Plan, PlanStep, ResourceState, Service};
use tokio::sync::{broadcast, mpsc, watch, Notify};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};
use zenoh::query::ConsolidationMode;

use crate::config::OrderSettings;
use crate::inbox::{Delivery, Inboxes};
use crate::progress::{OrderProgress, Phase, StepOutcome};

/// Which resources are alive, who just left or came, and whose turn it is on each
/// free resource.
pub struct Presence {
    alive: Mutex<HashSet<HolonId>>,
    changes: broadcast::Sender<(HolonId, bool)>,
    /// Woken whenever a resource appears or becomes ready: orders that found no
    /// resource try again.
    appeared: watch::Sender<u64>,
    /// One waiting order is woken per booking that leaves an agenda (started or
    /// cancelled), so a freed place goes to one order, not to a stampede of them.
    room: Notify,
    /// The agenda length and whether it could take work (state not `init`), as each
    /// resource last published.
    published: Mutex<HashMap<HolonId, (usize, bool)>>,
    /// Per resource, from its state publications: the conversation first on its agenda
    /// while it is free (`None` while it is busy or has no booking). An order booked
    /// there waits on its own resource's channel only, so a state change wakes the
    /// orders it concerns, not all of them.
    turns: Mutex<HashMap<HolonId, watch::Sender<Option<String>>>>,
}

impl Presence {
    /// Watches `alive/resource/*` and `resource/*/state` for as long as the session lives.
    pub async fn watch(
        session: &zenoh::Session,
        keys: &schemas::CellKeys,
    ) -> Result<Arc<Presence>, zenoh::Error> {
        let (changes, _) = broadcast::channel(4096);
        let presence = Arc::new(Presence {
            alive: Mutex::new(HashSet::new()),
            changes,
            appeared: watch::channel(0).0,
            room: Notify::new(),
            published: Mutex::new(HashMap::new()),
            turns: Mutex::new(HashMap::new()),
        });
        let keys_for_callback = keys.clone();
        let weak = Arc::downgrade(&presence);
        session
            .liveliness()
            .declare_subscriber(keys.alive_kind(schemas::HolonKind::Resource))
            .history(true)
            .callback(move |sample| {
                let Some(presence) = weak.upgrade() else {
                    return;
                };
                let Some(holon) = keys_for_callback.holon_from_alive(sample.key_expr().as_str())
                else {
                    return;
                };
                let mut alive = presence.alive.lock().unwrap_or_else(|e| e.into_inner());
                match sample.kind() {
                    zenoh::sample::SampleKind::Put => {
                        if alive.insert(holon.clone()) {
                            info!(holon = %holon, "resource appeared");
                            let _ = presence.changes.send((holon, true));
                            presence.appeared.send_modify(|n| *n += 1);
                        }
                    }
                    zenoh::sample::SampleKind::Delete => {
                        alive.remove(&holon);
                        warn!(holon = %holon, "resource vanished");
                        let _ = presence.changes.send((holon, false));
                    }
                }
            })
            .background()
            .await?;
        let weak = Arc::downgrade(&presence);
        session
            .declare_subscriber(keys.resource_states())
            .callback(move |sample| {
                let Some(presence) = weak.upgrade() else {
                    return;
                };
                let Ok(snapshot) = serde_json::from_slice::<schemas::ResourceSnapshot>(
                    &sample.payload().to_bytes(),
                ) else {
                    return;
                };
                let news = {
                    let mut published =
                        presence.published.lock().unwrap_or_else(|e| e.into_inner());
                    let previous = published.get(&snapshot.holon).copied();
                    let (news, now) = read_state(previous, &snapshot);
                    published.insert(snapshot.holon.clone(), now);
                    news
                };
                presence
                    .turn_channel(&snapshot.holon)
                    .send_replace(news.turn);
                if news.became_ready {
                    // Back from a fault or first ready: as good as a new resource.
                    presence.appeared.send_modify(|n| *n += 1);
                }
                for _ in 0..news.places_freed {
                    presence.room.notify_one();
                }
            })
            .background()
            .await?;
        // Seed the set before any order looks at it: the subscriber's history arrives
        // asynchronously, and a resource missing from the set counts as vanished.
        let alive = holon::presence::tokens(
            session,
            &keys.alive_kind(schemas::HolonKind::Resource),
            Duration::from_secs(2),
        )
        .await?;
        presence
            .alive
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .extend(alive.iter().filter_map(|key| keys.holon_from_alive(key)));
        Ok(presence)
    }

    pub fn is_alive(&self, holon: &HolonId) -> bool {
        self.alive
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(holon)
    }

    /// Appearances (true) and departures (false) from now on.
    pub fn changes(&self) -> broadcast::Receiver<(HolonId, bool)> {
        self.changes.subscribe()
    }

    fn turn_channel(&self, resource: &HolonId) -> watch::Sender<Option<String>> {
        self.turns
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(resource.clone())
            .or_insert_with(|| watch::channel(None).0)
            .clone()
    }

    /// Completes when `resource` next publishes that it is free with `conversation_id`
    /// first on its agenda (publications from before this call do not count).
    pub async fn turn(&self, resource: &HolonId, conversation_id: &str) {
        let mut turns = self.turn_channel(resource).subscribe();
        turns.mark_unchanged();
        while turns.changed().await.is_ok() {
            if turns.borrow_and_update().as_deref() == Some(conversation_id) {
                return;
            }
        }
        std::future::pending::<()>().await
    }

    /// Appearances from now on: pass it to [`Presence::appeared_or_room`] after a look
    /// for resources, so one that appears during the look is not missed.
    pub fn appearances(&self) -> watch::Receiver<u64> {
        self.appeared.subscribe()
    }

    /// Completes when a resource appeared (or became ready) since `appearances` was
    /// taken, or when a booking left an agenda and this is the order woken for the place.
    pub async fn appeared_or_room(&self, appearances: &mut watch::Receiver<u64>) {
        tokio::select! {
            _ = appearances.changed() => {}
            _ = self.room.notified() => {}
        }
    }
}

/// What one state publication of a resource tells the orders waiting on it.
#[derive(Debug, PartialEq, Eq)]
struct StateNews {
    /// The conversation whose turn it is: the resource is free and it is first on the
    /// agenda.
    turn: Option<String>,
    /// The resource has just become able to take work (or is seen ready the first time).
    became_ready: bool,
    /// Places freed on its agenda since its previous publication.
    places_freed: usize,
}

/// Reads a snapshot against what the resource published before (its agenda length and
/// whether it was ready): the news, and what to remember for the next one.
fn read_state(
    previous: Option<(usize, bool)>,
    snapshot: &schemas::ResourceSnapshot,
) -> (StateNews, (usize, bool)) {
    let (length_before, ready_before) = previous.unwrap_or((0, false));
    let ready = snapshot.state != ResourceState::Init && snapshot.controller.is_ready();
    let news = StateNews {
        turn: (snapshot.state == ResourceState::Free)
            .then(|| snapshot.agenda.first().map(|b| b.conversation_id.clone()))
            .flatten(),
        became_ready: ready && !ready_before,
        places_freed: length_before.saturating_sub(snapshot.agenda.len()),
    };
    (news, (snapshot.agenda.len(), ready))
}

/// What every order of a node shares.
pub struct OrderContext {
    pub session: zenoh::Session,
    pub keys: schemas::CellKeys,
    pub settings: OrderSettings,
    pub presence: Arc<Presence>,
    /// Where results reach the running orders (one queryable for the node).
    pub inboxes: Arc<Inboxes>,
    /// Permits for proposal rounds in flight (see [`MAX_CONCURRENT_ROUNDS`]).
    pub rounds: tokio::sync::Semaphore,
    /// Orders waiting after a round nobody proposed in, or for a plan (see
    /// [`IDLE_POLL_SPACING`]).
    pub idle: Arc<std::sync::atomic::AtomicUsize>,
    pub journal: Option<Arc<Journal>>,
    /// Set while journal writes fail (logged once per fault, not per order).
    pub journal_failing: AtomicBool,
}

/// The journal kind of order records.
pub const ORDER_RECORD: &str = "order";

impl OrderContext {
    /// Writes the order's progress; the order acts on a change only once it is written.
    pub fn save(&self, progress: &OrderProgress) -> Result<(), OrderError> {
        let Some(journal) = &self.journal else {
            return Ok(());
        };
        // A commit may wait for an fsync: with thousands of orders writing at once that
        // would hold every worker thread, and nothing else (SIGTERM, queries) would run.
        // On the multi-thread runtime the worker hands its other tasks over while it waits.
        let write = || journal.put(ORDER_RECORD, progress.holon.name(), progress);
        let multi_thread = tokio::runtime::Handle::try_current()
            .is_ok_and(|h| h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread);
        let written = if multi_thread {
            tokio::task::block_in_place(write)
        } else {
            write()
        };
        match written {
            Ok(()) => {
                if self.journal_failing.swap(false, Ordering::SeqCst) {
                    info!("the journal can be written again: waiting orders resume");
                }
                Ok(())
            }
            Err(e) => {
                if !self.journal_failing.swap(true, Ordering::SeqCst) {
                    error!(error = %e, "the journal cannot be written: orders wait where they stand (results stay unacknowledged, so resources keep them) and resume once it can (tried every second); new work orders are refused");
                }
                Err(OrderError::Journal(e.to_string()))
            }
        }
    }

    /// Applies `change` to an order's progress once it is written: when the journal
    /// cannot write, the progress in memory stays the last one written (a restarted
    /// order task resumes from there, and an unacknowledged result comes again).
    pub fn commit(
        &self,
        progress: &Shared,
        change: impl FnOnce(&mut OrderProgress),
    ) -> Result<(), OrderError> {
        let mut p = lock(progress);
        let mut next = p.clone();
        change(&mut next);
        self.save(&next)?;
        *p = next;
        Ok(())
    }
}

/// Counts one order among the idle ones for as long as it lives.
struct IdleOrder {
    idle: Arc<std::sync::atomic::AtomicUsize>,
    /// How many others were idle when it joined them.
    others: usize,
}

impl IdleOrder {
    /// The least pause of this order's next ask: [`IDLE_POLL_SPACING`] per other idle
    /// order, so all of them together ask about once per spacing.
    fn spacing(&self) -> Duration {
        IDLE_POLL_SPACING * self.others.min(100_000) as u32
    }

    fn count(idle: &Arc<std::sync::atomic::AtomicUsize>) -> IdleOrder {
        IdleOrder {
            idle: idle.clone(),
            others: idle.fetch_add(1, Ordering::SeqCst),
        }
    }
}

impl Drop for IdleOrder {
    fn drop(&mut self) {
        self.idle.fetch_sub(1, Ordering::SeqCst);
    }
}

/// Why an order task stopped before its order ended.
#[derive(Debug, thiserror::Error)]
pub enum OrderError {
    /// The journal could not record a change: the task is restarted after a pause (not
    /// counted as a failure) from the last written progress.
    #[error("the journal cannot record the order's progress: {0}")]
    Journal(String),
    #[error("{0}")]
    Other(String),
}

impl From<String> for OrderError {
    fn from(why: String) -> Self {
        OrderError::Other(why)
    }
}

type Shared = Arc<Mutex<OrderProgress>>;

fn lock(progress: &Shared) -> std::sync::MutexGuard<'_, OrderProgress> {
    progress.lock().unwrap_or_else(|e| e.into_inner())
}

/// Runs one order until it is done, scrapped, failed or cancelled by an operator
/// (`operator_cancel`), or its node stops (`cancel`).
pub async fn run(
    ctx: Arc<OrderContext>,
    progress: Shared,
    cancel: CancellationToken,
    operator_cancel: CancellationToken,
) -> Result<(), OrderError> {
    let holon = lock(&progress).holon.clone();
    let session = &ctx.session;
    let mut inbox = ctx.inboxes.open(&holon);
    let mut token = OrderToken::new(&ctx, &holon);
    let publish = |progress: &Shared| {
        let snapshot = lock(progress).snapshot();
        let key = ctx.keys.state(&snapshot.holon);
        async move {
            let payload = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
            if let Err(e) = session.put(&key, payload).await {
                warn!(holon = %snapshot.holon, error = %e, "cannot publish the order's state");
            }
        }
    };
    publish(&progress).await;

    let work = async {
        if lock(&progress).plan.is_none() {
            let product = lock(&progress).product.clone();
            let plan = fetch_plan(&ctx, &product).await;
            ctx.commit(&progress, |p| match plan {
                Some(plan) => p.plan = Some(plan),
                None => p.fail(format!("no plan for product {product:?}")),
            })?;
            publish(&progress).await;
        }
        let mut changes = ctx.presence.changes();
        loop {
            let (step, conversation_id) = {
                let p = lock(&progress);
                match p.current_step() {
                    Some(step) => (step.clone(), p.conversation_id()),
                    None => break,
                }
            };
            let attempt = attempt_step(
                &ctx,
                &progress,
                &step,
                &conversation_id,
                &mut inbox.deliveries,
                &mut token,
                &mut changes,
                &publish,
            );
            tokio::pin!(attempt);
            // An operator's cancel (also one recorded before a restart) stops the
            // attempt unless its step runs: a running step is let finish and its result
            // recorded.
            let mut finishing = false;
            let (outcome, delivery) = loop {
                tokio::select! {
                    biased;
                    _ = operator_cancel.cancelled(), if !finishing => {
                        if matches!(lock(&progress).phase, Phase::Started(_)) {
                            info!(holon = %holon, %conversation_id, "cancel requested: the running step finishes first");
                            finishing = true;
                        } else {
                            break (StepOutcome::Cancelled, None);
                        }
                    }
                    ended = &mut attempt => break ended?,
                }
            };
            if outcome == StepOutcome::Cancelled {
                cancel_order(&ctx, &progress, &holon, &step, &conversation_id).await?;
                publish(&progress).await;
                break;
            }
            info!(holon = %holon, %conversation_id, outcome = %outcome, "step attempt ended");
            ctx.commit(&progress, |p| {
                p.record(outcome);
                if finishing {
                    p.cancel();
                }
            })?;
            // Recorded: now the result may be acknowledged.
            if let Some(delivery) = delivery {
                delivery.acknowledge().await;
            }
            publish(&progress).await;
        }
        Ok::<(), OrderError>(())
    };
    tokio::select! {
        result = work => result?,
        _ = cancel.cancelled() => {
            info!(holon = %holon, "order stopped with its node; it resumes from the journal");
            return Ok(());
        }
    }
    let p = lock(&progress).snapshot();
    info!(holon = %holon, status = %p.status, reason = p.reason.as_deref().unwrap_or(""), reworks = p.reworks, rebooks = p.rebooks, "order finished");
    // Results still arriving for this order (duplicates, late reports of abandoned
    // attempts) are acknowledged by the node from now on.
    token.undeclare().await;
    Ok(())
}

/// The order's liveliness token (`alive/order/<name>`), declared the first time the
/// order books and held until it ends: a resource keeps a booking only while its
/// requester's token lives. An order still looking for a resource holds none, so
/// thousands of waiting orders cost the cell no declaration.
struct OrderToken {
    session: zenoh::Session,
    key: String,
    holon: HolonId,
    token: Option<zenoh::liveliness::LivelinessToken>,
}

impl OrderToken {
    fn new(ctx: &OrderContext, holon: &HolonId) -> OrderToken {
        OrderToken {
            session: ctx.session.clone(),
            key: ctx.keys.alive(holon),
            holon: holon.clone(),
            token: None,
        }
    }

    /// Declares the token unless it is already declared.
    async fn declare(&mut self) -> Result<(), OrderError> {
        if self.token.is_none() {
            let declared = self
                .session
                .liveliness()
                .declare_token(&self.key)
                .await
                .map_err(|e| OrderError::Other(format!("cannot declare {}: {e}", self.key)))?;
            self.token = Some(declared);
        }
        Ok(())
    }

    /// Withdraws the token: the order wants no booking any more.
    async fn undeclare(&mut self) {
        if let Some(token) = self.token.take() {
            if let Err(e) = token.undeclare().await {
                warn!(holon = %self.holon, error = %e, "cannot withdraw the order's token; it goes with the session");
            }
        }
    }
}

/// Ends the order as cancelled: a booking it holds (or may hold) is cancelled first.
async fn cancel_order(
    ctx: &OrderContext,
    progress: &Shared,
    holon: &HolonId,
    step: &PlanStep,
    conversation_id: &str,
) -> Result<(), OrderError> {
    let phase = lock(progress).phase.clone();
    if let Phase::Booking(resource) | Phase::Booked(resource) = &phase {
        let cancel = request(
            ctx,
            holon,
            MessageType::BookingCancel,
            step,
            conversation_id,
        );
        match ask(ctx, &ctx.keys.service(resource.name()), &cancel).await {
            Some(answer) if answer.result == Some(true) => {
                info!(holon = %holon, %conversation_id, resource = %resource, "booking cancelled with the order")
            }
            _ => {
                // Not reachable now: cancel it when it is back (from its journal).
                tokio::spawn(cancel_when_back(
                    ctx.session.clone(),
                    ctx.presence.clone(),
                    resource.clone(),
                    ctx.keys.service(resource.name()),
                    cancel,
                ));
            }
        }
    }
    ctx.commit(progress, |p| p.cancel())?;
    info!(holon = %holon, "order cancelled by an operator");
    Ok(())
}

/// Asks the product holon for its plan until it answers or `no_resource_timeout`
/// passes; the pause between asks doubles up to `retry_max` (jittered), so orders
/// waiting for a product that is not there cost next to nothing.
async fn fetch_plan(ctx: &OrderContext, product: &str) -> Option<Plan> {
    let deadline = Instant::now() + ctx.settings.no_resource_timeout;
    let mut pause = ctx.settings.retry_interval.max(Duration::from_millis(200));
    loop {
        if let Ok(mut replies) = ctx
            .session
            .get(ctx.keys.plan(product))
            .timeout(ctx.settings.proposal_timeout)
            .with(holon::query::replies())
            .await
        {
            while let Some(reply) = replies.recv().await {
                if let Ok(sample) = reply.result() {
                    match serde_json::from_slice::<Plan>(&sample.payload().to_bytes()) {
                        Ok(plan) if plan.validate().is_ok() => return Some(plan),
                        _ => warn!(product, "invalid plan received"),
                    }
                }
            }
        }
        if Instant::now() >= deadline {
            return None;
        }
        // Counted among the idle orders: thousands waiting for a plan ask rarely.
        let idle = IdleOrder::count(&ctx.idle);
        let spaced = idle.spacing();
        tokio::time::sleep(jittered(pause.max(spaced)).min(deadline - Instant::now())).await;
        drop(idle);
        pause = (pause * 2).min(ctx.settings.retry_max.max(pause));
    }
}

fn request(
    ctx: &OrderContext,
    holon: &HolonId,
    kind: MessageType,
    step: &PlanStep,
    conversation_id: &str,
) -> Service {
    Service::request(kind, &step.service_type, conversation_id, holon.clone())
        .with_reply_to(ctx.keys.inbox(holon.name()))
        .with_info(step.info.clone())
}

/// Sends one request and returns the resource's answer (None: no answer or an error).
async fn ask(ctx: &OrderContext, key: &str, message: &Service) -> Option<Service> {
    let mut replies = ctx
        .session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(ctx.settings.request_timeout)
        .with(holon::query::replies())
        .await
        .ok()?;
    let reply = replies.recv().await?;
    match reply.result() {
        Ok(sample) => Service::from_json(&sample.payload().to_bytes()).ok(),
        Err(err) => {
            warn!(key, error = %err.payload().try_to_string().unwrap_or_default(), conversation_id = %message.conversation_id, "error reply");
            None
        }
    }
}

/// The proposals of a round, best first (see the module docs for the rule).
async fn proposals(
    ctx: &OrderContext,
    message: &Service,
    avoid: &BTreeSet<HolonId>,
) -> Vec<HolonId> {
    let Ok(replies) = ctx
        .session
        .get(ctx.keys.offers(&message.service_type))
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(ctx.settings.proposal_timeout)
        .await
    else {
        return Vec::new();
    };
    let mut offers = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        let Ok(sample) = reply.result() else { continue };
        let Ok(proposal) = Service::from_json(&sample.payload().to_bytes()) else {
            continue;
        };
        let (Some(true), Some(provider)) = (proposal.result, proposal.provider.clone()) else {
            continue;
        };
        let number = |k: &str| {
            proposal
                .info
                .get(k)
                .and_then(|v| v.as_u64())
                .unwrap_or(u64::MAX)
        };
        offers.push((
            avoid.contains(&provider),
            number("expected_wait_ms"),
            number("queue_position"),
            provider,
        ));
    }
    offers.sort();
    offers.into_iter().map(|(_, _, _, p)| p).collect()
}

enum Wait {
    /// The pause is over.
    Elapsed,
    /// Something ended the attempt; a result to acknowledge once recorded.
    Ended(StepOutcome, Option<Box<Delivery>>),
}

/// Pauses `pause`, watching the inbox (results of this conversation) and the provider's
/// presence. A provider that vanishes after `started` gets `vanished_grace` to come back
/// and report before the attempt counts as lost. Before `started`, the pause also ends
/// when the provider publishes that it is free with this conversation first.
#[allow(clippy::too_many_arguments)]
async fn watch(
    ctx: &OrderContext,
    provider: &HolonId,
    worked_with: &BTreeSet<HolonId>,
    conversation_id: &str,
    pause: Duration,
    started: bool,
    inbox: &mut mpsc::UnboundedReceiver<Delivery>,
    changes: &mut broadcast::Receiver<(HolonId, bool)>,
) -> Wait {
    let until = Instant::now() + pause;
    // Booked, not started: the pause ends early when the resource says it is our turn.
    let turn = async {
        if started {
            std::future::pending::<()>().await
        } else {
            ctx.presence.turn(provider, conversation_id).await
        }
    };
    tokio::pin!(turn);
    let lost = |why: &str| {
        Wait::Ended(
            StepOutcome::Lost {
                provider: provider.clone(),
                why: why.into(),
            },
            None,
        )
    };
    let grace = if started {
        ctx.settings.vanished_grace
    } else {
        Duration::ZERO
    };
    // When the provider is gone: the moment its grace ends.
    let mut gone_until = (!ctx.presence.is_alive(provider)).then(|| Instant::now() + grace);
    loop {
        let gone_deadline = gone_until.unwrap_or(until);
        tokio::select! {
            _ = &mut turn => return Wait::Elapsed,
            _ = tokio::time::sleep_until(until.min(gone_deadline)) => {
                if gone_until.is_some_and(|g| Instant::now() >= g) {
                    return lost("the resource vanished");
                }
                return Wait::Elapsed;
            }
            delivery = inbox.recv() => {
                let Some(delivery) = delivery else { return lost("inbox closed") };
                if delivery.message.conversation_id != conversation_id {
                    // A duplicate of a recorded result, or a late report of an abandoned
                    // attempt: acknowledged (no effect) if it comes from a resource this
                    // order booked, refused otherwise.
                    if delivery.message.provider.as_ref().is_some_and(|p| worked_with.contains(p)) {
                        info!(conversation_id = %delivery.message.conversation_id, current = %conversation_id, "result of an earlier conversation acknowledged and ignored");
                        delivery.acknowledge().await;
                    } else {
                        warn!(conversation_id = %delivery.message.conversation_id, current = %conversation_id, "result from a resource this order never booked refused");
                        delivery.refuse("not_booked", "this order never booked that resource".into()).await;
                    }
                    continue;
                }
                if delivery.message.provider.as_ref() != Some(provider) {
                    // Only the resource this attempt booked reports its result.
                    let from = delivery.message.provider.as_ref().map(|p| p.to_string()).unwrap_or_default();
                    warn!(%conversation_id, booked = %provider, from = %from, "result from a resource this attempt did not book refused");
                    delivery.refuse("not_booked", format!("{conversation_id} is booked on {provider}, not {from:?}")).await;
                    continue;
                }
                let message = &delivery.message;
                let from = provider.clone();
                let outcome = match message.message_type {
                    MessageType::Done => StepOutcome::Done { provider: from, results: message.info.get("results").and_then(|r| r.as_object()).cloned().unwrap_or_default() },
                    _ if message.reason.as_deref() == Some(reason::WITHDRAWN) => StepOutcome::Lost { provider: from, why: reason::WITHDRAWN.into() },
                    _ => StepOutcome::Failed { provider: from, reason: message.reason.clone().unwrap_or_else(|| "failed".into()) },
                };
                return Wait::Ended(outcome, Some(Box::new(delivery)));
            }
            change = changes.recv() => match change {
                Ok((holon, alive)) if &holon == provider => {
                    gone_until = if alive { None } else { Some(Instant::now() + grace) };
                }
                Ok(_) => {}
                Err(broadcast::error::RecvError::Lagged(_)) => {
                    if !ctx.presence.is_alive(provider) && gone_until.is_none() {
                        gone_until = Some(Instant::now() + grace);
                    }
                }
                Err(broadcast::error::RecvError::Closed) => return Wait::Elapsed,
            },
        }
    }
}

/// Works on one attempt of a step from wherever its phase stands; returns how it ended
/// and the result to acknowledge once the outcome is recorded.
#[allow(clippy::too_many_arguments)]
async fn attempt_step<F, Fut>(
    ctx: &OrderContext,
    progress: &Shared,
    step: &PlanStep,
    conversation_id: &str,
    inbox: &mut mpsc::UnboundedReceiver<Delivery>,
    token: &mut OrderToken,
    changes: &mut broadcast::Receiver<(HolonId, bool)>,
    publish: &F,
) -> Result<(StepOutcome, Option<Box<Delivery>>), OrderError>
where
    F: Fn(&Shared) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    let settings = &ctx.settings;
    let holon = lock(progress).holon.clone();
    let set_phase = |phase: Phase| ctx.commit(progress, |p| p.set_phase(phase));
    let give_up = Instant::now() + settings.no_resource_timeout;
    let unavailable_since = Instant::now();
    // The pause before the next retry: doubles while retries fail (see `retry_max`).
    let mut backoff = settings.retry_interval;
    let back_off = |backoff: &mut Duration| {
        let pause = jittered(*backoff);
        *backoff = (*backoff * 2).min(settings.retry_max);
        pause
    };
    loop {
        let phase = lock(progress).phase.clone();
        if phase != Phase::Proposing {
            // Resumed with a booking (or one that may exist): its requester is here.
            token.declare().await?;
        }
        match phase {
            Phase::Proposing => {
                let avoid = lock(progress).avoid.clone();
                let ask_proposals =
                    request(ctx, &holon, MessageType::ProposalReq, step, conversation_id);
                let mut booked = false;
                let mut appearances = ctx.presence.appearances();
                let candidates = {
                    let _turn = ctx.rounds.acquire().await.expect("never closed");
                    proposals(ctx, &ask_proposals, &avoid).await
                };
                let nobody_proposed = candidates.is_empty();
                if !nobody_proposed {
                    // Declared before the booking request: the resource must see the
                    // requester alive as soon as it holds the booking.
                    token.declare().await?;
                }
                for candidate in candidates {
                    set_phase(Phase::Booking(candidate.clone()))?;
                    let booking =
                        request(ctx, &holon, MessageType::BookingReq, step, conversation_id);
                    match ask(ctx, &ctx.keys.service(candidate.name()), &booking).await {
                        Some(answer) if answer.result == Some(true) => {
                            set_phase(Phase::Booked(candidate.clone()))?;
                            info!(holon = %holon, %conversation_id, resource = %candidate, service_type = %step.service_type, "booked");
                            booked = true;
                            break;
                        }
                        Some(answer) => {
                            info!(holon = %holon, %conversation_id, resource = %candidate, reason = answer.reason.as_deref().unwrap_or(""), "booking refused")
                        }
                        None => {}
                    }
                    set_phase(Phase::Proposing)?;
                }
                if booked {
                    backoff = settings.retry_interval;
                    publish(progress).await;
                    continue;
                }
                if Instant::now() >= give_up {
                    return Ok((StepOutcome::NoResource, None));
                }
                // Nothing bookable: try again after the pause, or as soon as a resource
                // appears or a place on an agenda frees up for this order.
                // Nobody could take it: a resource that appears, becomes ready or frees
                // a place wakes this order, so the fallback poll can be rare (thousands
                // of orders waiting for a missing resource then cost next to nothing).
                let idle = nobody_proposed.then(|| IdleOrder::count(&ctx.idle));
                let pause = match &idle {
                    Some(idle) => jittered(IDLE_POLL.max(settings.retry_max).max(idle.spacing())),
                    None => back_off(&mut backoff),
                }
                .min(give_up - Instant::now());
                tokio::select! {
                    _ = tokio::time::sleep(pause) => {}
                    _ = ctx.presence.appeared_or_room(&mut appearances) => {}
                }
                drop(idle);
            }
            Phase::Booking(candidate) => {
                // Resumed: the booking request may or may not have reached it. Booking is
                // idempotent per conversation, so ask again.
                let booking = request(ctx, &holon, MessageType::BookingReq, step, conversation_id);
                match ask(ctx, &ctx.keys.service(candidate.name()), &booking).await {
                    Some(answer) if answer.result == Some(true) => {
                        set_phase(Phase::Booked(candidate))?
                    }
                    _ => set_phase(Phase::Proposing)?,
                }
            }
            Phase::Booked(provider) => {
                let start = request(ctx, &holon, MessageType::Start, step, conversation_id);
                match ask(ctx, &ctx.keys.service(provider.name()), &start).await {
                    Some(answer) if answer.result == Some(true) => {
                        set_phase(Phase::Started(provider.clone()))?;
                        info!(holon = %holon, %conversation_id, resource = %provider, "started");
                        publish(progress).await;
                        continue;
                    }
                    Some(answer) => match answer.reason.as_deref() {
                        Some(reason::BUSY) => {}
                        Some(reason::UNAVAILABLE)
                            if unavailable_since.elapsed() < settings.no_resource_timeout => {}
                        Some(reason::NOT_BOOKED) => {
                            return Ok((
                                StepOutcome::Lost {
                                    provider,
                                    why: "the booking was lost".into(),
                                },
                                None,
                            ));
                        }
                        other => {
                            let why = other.unwrap_or("refused").to_string();
                            let cancel = request(
                                ctx,
                                &holon,
                                MessageType::BookingCancel,
                                step,
                                conversation_id,
                            );
                            let _ = ask(ctx, &ctx.keys.service(provider.name()), &cancel).await;
                            return Ok((
                                StepOutcome::Failed {
                                    provider,
                                    reason: format!("start refused: {why}"),
                                },
                                None,
                            ));
                        }
                    },
                    None => {}
                }
                let worked_with = lock(progress).worked_with.clone();
                if let Wait::Ended(outcome, delivery) = watch(
                    ctx,
                    &provider,
                    &worked_with,
                    conversation_id,
                    back_off(&mut backoff),
                    false,
                    inbox,
                    changes,
                )
                .await
                {
                    if matches!(outcome, StepOutcome::Lost { .. }) {
                        // The resource vanished with our booking: if it comes back with
                        // it (from its journal), take the booking back off its agenda.
                        let cancel = request(
                            ctx,
                            &holon,
                            MessageType::BookingCancel,
                            step,
                            conversation_id,
                        );
                        tokio::spawn(cancel_when_back(
                            ctx.session.clone(),
                            ctx.presence.clone(),
                            provider.clone(),
                            ctx.keys.service(provider.name()),
                            cancel,
                        ));
                    }
                    return Ok((outcome, delivery));
                }
            }
            Phase::Started(provider) => {
                let worked_with = lock(progress).worked_with.clone();
                return Ok(
                    match watch(
                        ctx,
                        &provider,
                        &worked_with,
                        conversation_id,
                        settings.step_timeout,
                        true,
                        inbox,
                        changes,
                    )
                    .await
                    {
                        Wait::Ended(outcome, delivery) => (outcome, delivery),
                        Wait::Elapsed => (
                            StepOutcome::Failed {
                                provider,
                                reason: format!("no result within {:?}", settings.step_timeout),
                            },
                            None,
                        ),
                    },
                );
            }
        }
    }
}

/// Sends `booking_cancel` until the resource answers: at once, then each time it is
/// seen back (a restart from its journal, a healed network cut), for as long as the
/// order-node runs. Without it a resource that returns would keep the abandoned booking
/// until its requester's grace ends (or, while the order runs, for good), and offer a
/// longer wait than it has.
async fn cancel_when_back(
    session: zenoh::Session,
    presence: Arc<Presence>,
    resource: HolonId,
    key: String,
    cancel: Service,
) {
    let mut changes = presence.changes();
    loop {
        if presence.is_alive(&resource) {
            match session
                .get(&key)
                .payload(cancel.to_json())
                .consolidation(ConsolidationMode::None)
                .timeout(Duration::from_secs(2))
                .with(holon::query::replies())
                .await
            {
                Ok(mut replies) => {
                    if let Ok(Some(reply)) =
                        tokio::time::timeout(Duration::from_secs(3), replies.recv()).await
                    {
                        if reply.result().is_ok() {
                            info!(conversation_id = %cancel.conversation_id, %resource, "abandoned booking cancelled");
                            return;
                        }
                    }
                }
                Err(e) => {
                    warn!(conversation_id = %cancel.conversation_id, %resource, error = %e, "cannot send the cancel of an abandoned booking")
                }
            }
        }
        // Wait for the resource to (re)appear, checking again now and then in case its
        // appearance was missed.
        let wait = async {
            loop {
                match changes.recv().await {
                    Ok((holon, true)) if holon == resource => return,
                    Ok(_) => {}
                    Err(broadcast::error::RecvError::Lagged(_)) => return,
                    Err(broadcast::error::RecvError::Closed) => std::future::pending().await,
                }
            }
        };
        let _ = tokio::time::timeout(Duration::from_secs(10), wait).await;
    }
}

/// How often an order that no resource could take asks again, at most, when nothing
/// woke it (an appearance, a resource ready again, a freed place).
const IDLE_POLL: Duration = Duration::from_secs(10);

/// The fallback pause of an idle order grows with the number of idle orders, so that
/// all of them together ask about once per this interval: 5,000 orders waiting for a
/// missing resource ask 10 times a second in all, not 500.
const IDLE_POLL_SPACING: Duration = Duration::from_millis(100);

/// Proposal rounds in flight at once on a node: when a resource appears and wakes
/// thousands of waiting orders, they ask in turn (oldest first), not all at once.
pub const MAX_CONCURRENT_ROUNDS: usize = 64;

/// `pause` less up to a quarter, at random: orders that wait together do not retry in
/// lockstep.
fn jittered(pause: Duration) -> Duration {
    use std::hash::BuildHasher;
    let random = std::collections::hash_map::RandomState::new().hash_one(std::time::Instant::now());
    pause.mul_f64(1.0 - (random % 1000) as f64 / 4000.0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::{BookingView, ResourceSnapshot};

    fn snapshot(state: &str, controller: &str, agenda: &[&str]) -> ResourceSnapshot {
        ResourceSnapshot {
            holon: HolonId::resource("robot1").unwrap(),
            state: serde_json::from_value(state.into()).expect("a resource state"),
            controller: serde_json::from_value(controller.into()).expect("a controller status"),
            agenda: agenda
                .iter()
                .map(|c| BookingView {
                    requester: HolonId::new(schemas::HolonKind::Order, "o-1").unwrap(),
                    conversation_id: c.to_string(),
                    service_type: "pick_n_place".into(),
                    requester_absent_since: None,
                })
                .collect(),
            current: None,
            undelivered: 0,
            services: vec!["pick_n_place".into()],
            journal_fault: None,
            at: 0,
        }
    }

    #[test]
    fn a_free_resource_gives_the_turn_to_the_first_booking() {
        let (news, now) = read_state(
            Some((2, true)),
            &snapshot("free", "ready", &["a/1/1", "b/1/1"]),
        );
        assert_eq!(news.turn.as_deref(), Some("a/1/1"));
        assert!(!news.became_ready);
        assert_eq!(news.places_freed, 0);
        assert_eq!(now, (2, true));
    }

    #[test]
    fn a_busy_or_empty_resource_gives_no_turn() {
        let (busy, _) = read_state(Some((1, true)), &snapshot("busy", "ready", &["a/1/1"]));
        assert_eq!(busy.turn, None);
        let (empty, _) = read_state(Some((0, true)), &snapshot("free", "ready", &[]));
        assert_eq!(empty.turn, None);
    }

    #[test]
    fn bookings_leaving_the_agenda_free_places() {
        let (news, now) = read_state(Some((3, true)), &snapshot("busy", "ready", &["c/1/1"]));
        assert_eq!(news.places_freed, 2);
        assert_eq!(now, (1, true));
        let (grew, _) = read_state(
            Some((1, true)),
            &snapshot("busy", "ready", &["c/1/1", "d/1/1"]),
        );
        assert_eq!(grew.places_freed, 0);
    }

    #[test]
    fn readiness_is_news_once() {
        let (first, now) = read_state(None, &snapshot("free", "ready", &[]));
        assert!(first.became_ready, "a resource seen ready the first time");
        let (again, _) = read_state(Some(now), &snapshot("free", "ready", &[]));
        assert!(!again.became_ready);
        let (fault, now) = read_state(Some(now), &snapshot("init", "fault", &[]));
        assert!(!fault.became_ready);
        assert_eq!(fault.turn, None);
        let (back, _) = read_state(Some(now), &snapshot("free", "ready", &[]));
        assert!(back.became_ready, "back from a fault");
    }

    #[test]
    fn jitter_shortens_by_at_most_a_quarter() {
        for _ in 0..1000 {
            let pause = jittered(Duration::from_millis(1000));
            assert!(
                pause <= Duration::from_millis(1000) && pause >= Duration::from_millis(750),
                "{pause:?}"
            );
        }
    }
}

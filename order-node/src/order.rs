//! One order holon: gets its product made by negotiating with the live resources.
//!
//! For each step of the plan: a proposal round on `offer/<type>/*`; book the best
//! proposal (the shortest expected wait, then the shortest queue, then the name; a
//! resource that failed this step is passed over while others propose); `start` it
//! when the resource is free (retrying while it is busy); wait for `done` in the
//! inbox. A resource that vanishes or hands its booking back is rebooked elsewhere; a
//! step that fails is retried on another resource up to `max_attempts`, then the order
//! fails with the reason.

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use schemas::{reason, HolonId, MessageType, Plan, PlanStep, Service};
use tokio::sync::{broadcast, mpsc};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};
use zenoh::query::ConsolidationMode;

use crate::config::OrderSettings;
use crate::progress::{OrderProgress, StepOutcome};

/// Which resources are alive, and who just left.
pub struct Presence {
    alive: Mutex<HashSet<HolonId>>,
    departures: broadcast::Sender<HolonId>,
}

impl Presence {
    /// Watches `alive/resource/*` for as long as the session lives.
    pub async fn watch(
        session: &zenoh::Session,
        keys: &schemas::CellKeys,
    ) -> Result<Arc<Presence>, zenoh::Error> {
        let (departures, _) = broadcast::channel(1024);
        let presence = Arc::new(Presence {
            alive: Mutex::new(HashSet::new()),
            departures,
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
                        }
                    }
                    zenoh::sample::SampleKind::Delete => {
                        alive.remove(&holon);
                        warn!(holon = %holon, "resource vanished");
                        let _ = presence.departures.send(holon);
                    }
                }
            })
            .background()
            .await?;
        Ok(presence)
    }

    pub fn is_alive(&self, holon: &HolonId) -> bool {
        self.alive
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains(holon)
    }

    pub fn departures(&self) -> broadcast::Receiver<HolonId> {
        self.departures.subscribe()
    }
}

/// What every order of a node shares.
pub struct OrderContext {
    pub session: zenoh::Session,
    pub keys: schemas::CellKeys,
    pub settings: OrderSettings,
    pub presence: Arc<Presence>,
}

type Shared = Arc<Mutex<OrderProgress>>;

fn lock(progress: &Shared) -> std::sync::MutexGuard<'_, OrderProgress> {
    progress.lock().unwrap_or_else(|e| e.into_inner())
}

/// Runs one order until it is done, scrapped or failed, or `cancel` is cancelled.
pub async fn run(
    ctx: Arc<OrderContext>,
    progress: Shared,
    cancel: CancellationToken,
) -> Result<(), String> {
    let holon = lock(&progress).holon.clone();
    let session = &ctx.session;
    let e = |e: zenoh::Error| e.to_string();
    // The inbox: every result is acknowledged on receipt and handed to the order.
    let (inbox_tx, mut inbox) = mpsc::unbounded_channel::<Service>();
    let me = holon.clone();
    let _inbox = session
        .declare_queryable(ctx.keys.inbox(holon.name()))
        .callback(move |query| {
            use zenoh::Wait;
            let payload = query
                .payload()
                .map(|p| p.to_bytes().into_owned())
                .unwrap_or_default();
            match Service::from_json(&payload) {
                Ok(message)
                    if message.requester == me
                        && matches!(message.message_type, MessageType::Done | MessageType::Failed) =>
                {
                    info!(holon = %me, conversation_id = %message.conversation_id, message_type = %message.message_type, provider = ?message.provider.as_ref().map(|p| p.to_string()), reason = message.reason.as_deref().unwrap_or(""), "received");
                    let mut ack = message.clone();
                    ack.result = Some(true);
                    let _ = query.reply(query.key_expr().clone(), ack.to_json()).wait();
                    let _ = inbox_tx.send(message);
                }
                Ok(other) => {
                    let _ = query
                        .reply_err(
                            schemas::ErrorReply::new(
                                "wrong_key",
                                format!("{} for {} is not for this inbox", other.message_type, other.requester),
                            )
                            .to_json(),
                        )
                        .wait();
                }
                Err(err) => {
                    let _ = query
                        .reply_err(schemas::ErrorReply::new("malformed", err.to_string()).to_json())
                        .wait();
                }
            }
        })
        .await
        .map_err(e)?;
    let publisher = session
        .declare_publisher(ctx.keys.state(&holon))
        .await
        .map_err(e)?;
    let token = session
        .liveliness()
        .declare_token(ctx.keys.alive(&holon))
        .await
        .map_err(e)?;
    let publish = |progress: &Shared| {
        let snapshot = lock(progress).snapshot();
        let publisher = &publisher;
        async move {
            let payload = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
            let _ = publisher.put(payload).await;
        }
    };
    publish(&progress).await;

    let work = async {
        if lock(&progress).plan.is_none() {
            let product = lock(&progress).product.clone();
            match fetch_plan(&ctx, &product).await {
                Some(plan) => lock(&progress).plan = Some(plan),
                None => lock(&progress).fail(format!("no plan for product {product:?}")),
            }
            publish(&progress).await;
        }
        let mut departures = ctx.presence.departures();
        loop {
            let (step, conversation_id) = {
                let p = lock(&progress);
                match p.current_step() {
                    Some(step) => (step.clone(), p.conversation_id()),
                    None => break,
                }
            };
            let outcome = attempt_step(
                &ctx,
                &progress,
                &step,
                &conversation_id,
                &mut inbox,
                &mut departures,
                &publish,
            )
            .await;
            info!(holon = %holon, %conversation_id, outcome = ?outcome, "step attempt ended");
            lock(&progress).record(outcome);
            publish(&progress).await;
        }
    };
    tokio::select! {
        _ = work => {}
        _ = cancel.cancelled() => {
            info!(holon = %holon, "order stopped with its node");
            return Ok(());
        }
    }
    let p = lock(&progress).snapshot();
    info!(holon = %holon, status = ?p.status, reason = p.reason.as_deref().unwrap_or(""), reworks = p.reworks, rebooks = p.rebooks, "order finished");
    let _ = token.undeclare().await;
    Ok(())
}

async fn fetch_plan(ctx: &OrderContext, product: &str) -> Option<Plan> {
    let deadline = Instant::now() + ctx.settings.no_resource_timeout;
    loop {
        if let Ok(replies) = ctx
            .session
            .get(ctx.keys.plan(product))
            .timeout(ctx.settings.proposal_timeout)
            .await
        {
            while let Ok(reply) = replies.recv_async().await {
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
        tokio::time::sleep(ctx.settings.retry_interval.max(Duration::from_millis(200))).await;
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
    let replies = ctx
        .session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(5))
        .await
        .ok()?;
    let reply = replies.recv_async().await.ok()?;
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
    avoid: &std::collections::BTreeSet<HolonId>,
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
    /// Something ended the attempt.
    Ended(StepOutcome),
}

/// Pauses `pause`, watching the inbox (results of this conversation) and the provider's
/// presence.
async fn watch(
    ctx: &OrderContext,
    provider: &HolonId,
    conversation_id: &str,
    pause: Duration,
    inbox: &mut mpsc::UnboundedReceiver<Service>,
    departures: &mut broadcast::Receiver<HolonId>,
) -> Wait {
    let until = Instant::now() + pause;
    loop {
        tokio::select! {
            _ = tokio::time::sleep_until(until) => return Wait::Elapsed,
            message = inbox.recv() => {
                let Some(message) = message else { return Wait::Ended(StepOutcome::Lost { provider: provider.clone(), why: "inbox closed".into() }) };
                if message.conversation_id != conversation_id {
                    continue; // a duplicate of an earlier conversation
                }
                let from = message.provider.clone().unwrap_or_else(|| provider.clone());
                return Wait::Ended(match message.message_type {
                    MessageType::Done => StepOutcome::Done { provider: from, results: message.info.get("results").and_then(|r| r.as_object()).cloned().unwrap_or_default() },
                    _ if message.reason.as_deref() == Some(reason::WITHDRAWN) => StepOutcome::Lost { provider: from, why: reason::WITHDRAWN.into() },
                    _ => StepOutcome::Failed { provider: from, reason: message.reason.unwrap_or_else(|| "failed".into()) },
                });
            }
            gone = departures.recv() => match gone {
                Ok(holon) if &holon == provider => return Wait::Ended(StepOutcome::Lost { provider: provider.clone(), why: "the resource vanished".into() }),
                Ok(_) => {}
                Err(broadcast::error::RecvError::Lagged(_)) => {
                    if !ctx.presence.is_alive(provider) {
                        return Wait::Ended(StepOutcome::Lost { provider: provider.clone(), why: "the resource vanished".into() });
                    }
                }
                Err(broadcast::error::RecvError::Closed) => return Wait::Elapsed,
            },
        }
    }
}

async fn attempt_step<F, Fut>(
    ctx: &OrderContext,
    progress: &Shared,
    step: &PlanStep,
    conversation_id: &str,
    inbox: &mut mpsc::UnboundedReceiver<Service>,
    departures: &mut broadcast::Receiver<HolonId>,
    publish: &F,
) -> StepOutcome
where
    F: Fn(&Shared) -> Fut,
    Fut: std::future::Future<Output = ()>,
{
    let (holon, avoid) = {
        let p = lock(progress);
        (p.holon.clone(), p.avoid.clone())
    };
    let settings = &ctx.settings;
    // 1. Proposals and booking.
    let give_up = Instant::now() + settings.no_resource_timeout;
    let provider = 'book: loop {
        let ask_proposals = request(ctx, &holon, MessageType::ProposalReq, step, conversation_id);
        for candidate in proposals(ctx, &ask_proposals, &avoid).await {
            let booking = request(ctx, &holon, MessageType::BookingReq, step, conversation_id);
            match ask(ctx, &ctx.keys.service(candidate.name()), &booking).await {
                Some(answer) if answer.result == Some(true) => break 'book candidate,
                Some(answer) => {
                    info!(holon = %holon, %conversation_id, resource = %candidate, reason = answer.reason.as_deref().unwrap_or(""), "booking refused")
                }
                None => {}
            }
        }
        if Instant::now() >= give_up {
            return StepOutcome::NoResource;
        }
        tokio::time::sleep(settings.retry_interval).await;
    };
    info!(holon = %holon, %conversation_id, resource = %provider, service_type = %step.service_type, "booked");
    lock(progress).resource = Some(provider.clone());
    publish(progress).await;

    // 2. Start when the resource is free.
    let service_key = ctx.keys.service(provider.name());
    let unavailable_since = Instant::now();
    loop {
        if !ctx.presence.is_alive(&provider) {
            return StepOutcome::Lost {
                provider,
                why: "the resource vanished".into(),
            };
        }
        let start = request(ctx, &holon, MessageType::Start, step, conversation_id);
        match ask(ctx, &service_key, &start).await {
            Some(answer) if answer.result == Some(true) => break,
            Some(answer) => match answer.reason.as_deref() {
                Some(reason::BUSY) => {}
                Some(reason::UNAVAILABLE)
                    if unavailable_since.elapsed() < settings.no_resource_timeout => {}
                Some(reason::NOT_BOOKED) => {
                    return StepOutcome::Lost {
                        provider,
                        why: "the booking was lost".into(),
                    }
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
                    let _ = ask(ctx, &service_key, &cancel).await;
                    return StepOutcome::Failed {
                        provider,
                        reason: format!("start refused: {why}"),
                    };
                }
            },
            None => {}
        }
        if let Wait::Ended(outcome) = watch(
            ctx,
            &provider,
            conversation_id,
            settings.retry_interval,
            inbox,
            departures,
        )
        .await
        {
            return outcome;
        }
    }
    info!(holon = %holon, %conversation_id, resource = %provider, "started");

    // 3. The result.
    match watch(
        ctx,
        &provider,
        conversation_id,
        settings.step_timeout,
        inbox,
        departures,
    )
    .await
    {
        Wait::Ended(outcome) => outcome,
        Wait::Elapsed => StepOutcome::Failed {
            provider,
            reason: format!("no result within {:?}", settings.step_timeout),
        },
    }
}

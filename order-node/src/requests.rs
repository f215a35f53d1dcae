//! The order's requests over zenoh: the plan from its product holon, proposal rounds,
//! one request to one resource, and the cancel of an abandoned booking. Each awaits at
//! most its configured timeout.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use schemas::{
    HolonId, MessageType, Outcome, OutcomeReply, OutcomeRequest, Plan, PlanStep, Reason, Service,
};
use tokio::sync::broadcast;
use tokio::time::Instant;
use tracing::{debug, info, warn};
use zenoh::query::ConsolidationMode;

use crate::attempt::Answer;
use crate::context::{jittered, IdleOrder, OrderContext};
use crate::presence::Presence;
use crate::ranking::{InFlight, Offer};

/// Asks the product holon for its plan until it answers or `no_resource_timeout`
/// passes; the pause between asks doubles up to `retry_max` (jittered), so orders
/// waiting for a product that is not there cost next to nothing.
pub async fn fetch_plan(ctx: &OrderContext, product: &str) -> Option<Plan> {
    let deadline = Instant::now() + ctx.settings.no_resource_timeout;
    let first = ctx.settings.retry_interval.max(Duration::from_millis(200));
    let mut backoff = holon::Backoff::new(first, ctx.settings.retry_max);
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
        let pause = backoff.next_pause().max(idle.spacing());
        tokio::time::sleep(jittered(pause).min(deadline.saturating_duration_since(Instant::now())))
            .await;
        drop(idle);
    }
}

/// The order's request of `kind` for `step`: its inbox as `reply_to`, the step's info;
/// a booking asks to start on its turn when the node's settings say so.
pub fn request(
    ctx: &OrderContext,
    holon: &HolonId,
    kind: MessageType,
    step: &PlanStep,
    conversation_id: &str,
) -> Service {
    let request = Service::request(kind, &step.service_type, conversation_id, holon.clone())
        .with_reply_to(ctx.keys.inbox(holon.name()))
        .with_info(step.info.clone());
    // What changes a booking carries this node's epoch (on etcd): the resource refuses
    // a deposed holder's once a newer holder asked about the booking.
    let request = match kind {
        MessageType::BookingReq | MessageType::Start | MessageType::BookingCancel => {
            request.with_epoch(ctx.epoch())
        }
        _ => request,
    };
    if kind == MessageType::BookingReq && ctx.settings.start_on_turn {
        request.with_start_on_turn()
    } else {
        request
    }
}

/// Sends one request and returns the resource's answer (None: no answer or an error).
pub async fn ask(ctx: &OrderContext, key: &str, message: &Service) -> Option<Service> {
    let mut replies = ctx
        .session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(ctx.settings.request_timeout)
        .with(holon::query::replies())
        .await
        .ok()?;
    // One answerer normally. Two while a resource is handed over to its successor (an
    // upgrade): the predecessor's stand-in says `unavailable` while the successor may
    // already answer for real, and the real answer wins (a booking it made is kept).
    let mut answer: Option<Service> = None;
    while let Some(reply) = replies.recv().await {
        let Some(service) = read_answer(key, message, &reply) else {
            continue;
        };
        let unavailable = service.reason.as_ref() == Some(&Reason::Unavailable);
        if !unavailable {
            return Some(service);
        }
        answer.get_or_insert(service);
    }
    answer
}

/// How much longer than a request an outcome question may wait: a fenced resource that
/// does not know the conversation asks its controller first.
pub const OUTCOME_EXTRA: Duration = Duration::from_secs(2);

/// Asks `provider` what became of `conversation_id` (`resource/<name>/outcome`): the
/// answer that says most (`done`, `failed` or `never_reached` at once; else `running`,
/// else `unknown`), or `None` when nobody answered (a resource of an older release, or
/// none serving the name).
pub async fn ask_outcome(
    ctx: &OrderContext,
    holon: &HolonId,
    provider: &HolonId,
    step: &PlanStep,
    conversation_id: &str,
) -> Option<OutcomeReply> {
    let key = ctx.keys.outcome(provider.name());
    let question = OutcomeRequest::new(conversation_id, &step.service_type, holon.clone());
    let mut replies = match ctx
        .session
        .get(&key)
        .payload(question.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(ctx.settings.request_timeout + OUTCOME_EXTRA)
        .with(holon::query::replies())
        .await
    {
        Ok(replies) => replies,
        Err(e) => {
            warn!(%holon, %conversation_id, resource = %provider, error = %e, "cannot ask the outcome");
            return None;
        }
    };
    let mut best: Option<OutcomeReply> = None;
    while let Some(reply) = replies.recv().await {
        let answer = match reply.result() {
            Ok(sample) => match OutcomeReply::from_json(&sample.payload().to_bytes()) {
                Ok(answer) => answer,
                Err(e) => {
                    warn!(%holon, %conversation_id, resource = %provider, error = %e, "outcome answer not understood");
                    continue;
                }
            },
            Err(err) => {
                warn!(%holon, %conversation_id, resource = %provider, error = %err.payload().try_to_string().unwrap_or_default(), "outcome question refused");
                continue;
            }
        };
        if &answer.provider != provider || answer.conversation_id != conversation_id {
            warn!(%holon, %conversation_id, resource = %provider, from = %answer.provider, "an outcome answer for another resource or conversation ignored");
            continue;
        }
        info!(%holon, %conversation_id, resource = %provider, outcome = %answer.outcome, source = ?answer.source, epoch = answer.epoch, reason = answer.reason.as_ref().map_or("", |r| r.as_str()), "outcome told");
        let rank = |a: &OutcomeReply| match a.outcome {
            Outcome::Unknown => 0,
            Outcome::Running => 1,
            Outcome::Done | Outcome::Failed | Outcome::NeverReached => 2,
        };
        if rank(&answer) == 2 {
            return Some(answer);
        }
        if best.as_ref().is_none_or(|b| rank(&answer) > rank(b)) {
            best = Some(answer);
        }
    }
    if best.is_none() {
        info!(%holon, %conversation_id, resource = %provider, "nobody said what became of the conversation");
    }
    best
}

/// A reply as a Service message; an error reply or one that cannot be read is logged
/// with what it says.
fn read_answer(key: &str, message: &Service, reply: &zenoh::query::Reply) -> Option<Service> {
    match reply.result() {
        Ok(sample) => match Service::from_json(&sample.payload().to_bytes()) {
            Ok(service) => Some(service),
            Err(e) => {
                warn!(key, error = %e, conversation_id = %message.conversation_id, "answer refused: not a Service message this node understands");
                None
            }
        },
        Err(err) => {
            warn!(key, error = %err.payload().try_to_string().unwrap_or_default(), conversation_id = %message.conversation_id, "error reply");
            None
        }
    }
}

/// The proposals of a round, best first: resources in `avoid` (they failed this step)
/// last; then the resource a staff holon advised, if it proposed; then the shortest
/// expected wait, then queue, as they are when the round ends
/// (see [`crate::ranking::BookingsInFlight`]); ties at random (orders that ask together
/// do not all pick the same name). The best counts as a booking in flight until its
/// answer comes.
pub async fn proposals(
    ctx: &OrderContext,
    message: &Service,
    avoid: &BTreeSet<HolonId>,
    advised: Option<&HolonId>,
) -> (Vec<HolonId>, Option<InFlight>) {
    let offers = offers(ctx, message, avoid).await;
    rank(ctx, message, offers, advised)
}

/// The proposals a round heard (every resource that proposed, `avoid` marked).
pub async fn offers(
    ctx: &OrderContext,
    message: &Service,
    avoid: &BTreeSet<HolonId>,
) -> Vec<Offer> {
    // A round stopped half-way (the order cancelled, the node stopping) drops its
    // reader: late proposals are dropped quietly.
    let Ok(mut replies) = ctx
        .session
        .get(ctx.keys.offers(&message.service_type))
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(ctx.settings.proposal_timeout)
        .with(holon::query::replies())
        .await
    else {
        return Vec::new();
    };
    let mut offers = Vec::new();
    while let Some(reply) = replies.recv().await {
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
        offers.push(Offer {
            avoided: avoid.contains(&provider),
            expected_wait_ms: number("expected_wait_ms"),
            queue_position: number("queue_position"),
            duration_ms: number("duration_ms"),
            provider,
        });
    }
    offers
}

/// A round's offers ranked (see [`proposals`]); the best counts as in flight.
pub fn rank(
    ctx: &OrderContext,
    message: &Service,
    offers: Vec<Offer>,
    advised: Option<&HolonId>,
) -> (Vec<HolonId>, Option<InFlight>) {
    let (ranked, in_flight) = ctx.bookings_in_flight.rank(
        offers,
        |resource| {
            ctx.presence
                .queue(resource, message.priority().unwrap_or(0))
        },
        advised,
    );
    debug!(conversation_id = %message.conversation_id, ranked = ?ranked.iter().map(|p| p.name()).collect::<Vec<_>>(), "proposals ranked");
    (ranked, in_flight)
}

/// Sends `booking_cancel` until the resource answers: at once, then each time it is
/// seen back (a restart from its journal, a healed network cut), for as long as the
/// order-node runs. Without it a resource that returns would keep the abandoned booking
/// until its requester's grace ends (or, while the order runs, for good), and offer a
/// longer wait than it has.
pub async fn cancel_when_back(
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
                    // Every reply is read: while the resource is handed over its
                    // stand-in refuses `unavailable` (not cancelled: asked again after
                    // its retry hint), and may answer next to the successor.
                    let mut retry_after = None;
                    while let Ok(Some(reply)) =
                        tokio::time::timeout(Duration::from_secs(3), replies.recv()).await
                    {
                        match read_answer(&key, &cancel, &reply) {
                            Some(answer)
                                if answer.reason.as_ref() == Some(&Reason::Unavailable) =>
                            {
                                retry_after = Some(
                                    answer.retry_after().unwrap_or(Duration::from_millis(100)),
                                );
                            }
                            Some(answer) if answer.result == Some(true) => {
                                info!(conversation_id = %cancel.conversation_id, %resource, "abandoned booking cancelled");
                                return;
                            }
                            // `not_booked`: it was not there, or its job began (a
                            // restarted resource begins one only on its order's start).
                            Some(answer) => {
                                info!(conversation_id = %cancel.conversation_id, %resource, reason = answer.reason.as_ref().map_or("", |r| r.as_str()), "abandoned booking: the resource did not hold it");
                                return;
                            }
                            None => {}
                        }
                    }
                    if let Some(pause) = retry_after {
                        debug!(conversation_id = %cancel.conversation_id, %resource, "the resource is being handed over: the cancel is sent again");
                        tokio::time::sleep(pause).await;
                        continue;
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

/// A resource's answer to a booking or a start, as the attempt reads it.
pub fn answer(reply: Option<Service>) -> Answer {
    match reply {
        Some(reply) if reply.started() => Answer::Started,
        Some(reply) if reply.result == Some(true) => Answer::Accepted,
        Some(reply) => Answer::Refused(reply.reason),
        None => Answer::Silent,
    }
}

/// Why an ask for advice brought none.
#[derive(Debug, thiserror::Error)]
enum NoAdvice {
    /// No answer within `orders.advice_timeout_ms`: counts toward the pause of asks
    /// ([`crate::advice_pause`]).
    #[error("{staff} gave no advice in time")]
    NotInTime {
        /// The staff holon asked.
        staff: HolonId,
    },
    /// The ask could not be sent (not counted toward the pause: the staff was not
    /// asked).
    #[error("cannot ask {staff}: {why}")]
    NotAsked {
        /// The staff holon asked.
        staff: HolonId,
        /// zenoh's error.
        why: String,
    },
    /// The staff refused the ask (it answered: asking goes on).
    #[error("{staff} refused: {why}")]
    Refused {
        /// The staff holon asked.
        staff: HolonId,
        /// Its refusal.
        why: String,
    },
    /// The staff's answer is not advice (it answered: asking goes on).
    #[error("malformed advice from {staff}: {why}")]
    Malformed {
        /// The staff holon asked.
        staff: HolonId,
        /// What does not parse.
        why: String,
    },
}

/// What came of asking the staff for advice.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Advised {
    /// No staff holon is alive (or the node never asks): contract net alone.
    NoStaff,
    /// This resource, if it proposed.
    Resource(HolonId),
    /// No usable advice: why (for the log).
    Unusable(String),
}

/// Asks the staff holon alive, if any, which resource to book for the next of `route`
/// (the steps still ahead of the order; `at`, where its part is, if it has one), waiting
/// at most `orders.advice_timeout_ms`.
/// Anything but an answer to this order's conversation naming a resource is unusable.
pub async fn advice(
    ctx: &OrderContext,
    holon: &HolonId,
    conversation_id: &str,
    route: Vec<schemas::RouteStep>,
    urgency: (i32, Option<u64>),
    avoid: &BTreeSet<HolonId>,
    at: Option<schemas::layout::LocationId>,
) -> Advised {
    let Some(staff) = ctx.presence.staff() else {
        return Advised::NoStaff;
    };
    if ctx.settings.advice_timeout.is_zero()
        || route.is_empty()
        || !ctx.advice_pause.may_ask(Instant::now())
    {
        return Advised::NoStaff;
    }
    let request = schemas::AdviceRequest {
        v: schemas::ADVICE_VERSION,
        order: holon.clone(),
        conversation_id: conversation_id.to_string(),
        priority: urgency.0,
        due: urgency.1,
        steps: route
            .into_iter()
            .take(schemas::advice::MAX_ADVICE_STEPS)
            .collect(),
        avoid: avoid
            .iter()
            .take(schemas::advice::MAX_AVOIDED)
            .cloned()
            .collect(),
        at,
    };
    let payload = serde_json::to_vec(&request).expect("a request serializes");
    let asked = async {
        let mut replies = ctx
            .session
            .get(ctx.keys.advice(staff.name()))
            .payload(payload)
            .consolidation(ConsolidationMode::None)
            .timeout(ctx.settings.advice_timeout)
            .with(holon::query::replies())
            .await
            .map_err(|e| NoAdvice::NotAsked {
                staff: staff.clone(),
                why: e.to_string(),
            })?;
        let not_in_time = || NoAdvice::NotInTime {
            staff: staff.clone(),
        };
        let reply = replies.recv().await.ok_or_else(not_in_time)?;
        let sample = reply.result().map_err(|e| {
            let why = e.payload().try_to_string().unwrap_or_default();
            // zenoh ends a query that outlived its timeout with this error reply (its
            // only word for it: zenoh's error replies carry no code).
            if why == "Timeout" {
                not_in_time()
            } else {
                NoAdvice::Refused {
                    staff: staff.clone(),
                    why: why.into_owned(),
                }
            }
        })?;
        serde_json::from_slice::<schemas::Advice>(&sample.payload().to_bytes()).map_err(|e| {
            NoAdvice::Malformed {
                staff: staff.clone(),
                why: e.to_string(),
            }
        })
    };
    let unanswered = |why: NoAdvice| {
        if ctx.advice_pause.unanswered(Instant::now()) {
            warn!(%staff, pause = ?crate::advice_pause::PAUSE, "the staff answered none of the last asks in time: orders go by contract net without asking it for a while");
        }
        Advised::Unusable(why.to_string())
    };
    let advice = match tokio::time::timeout(ctx.settings.advice_timeout, asked).await {
        Ok(Ok(advice)) => advice,
        Ok(Err(why @ NoAdvice::NotInTime { .. })) => return unanswered(why),
        Ok(Err(
            why @ (NoAdvice::NotAsked { .. }
            | NoAdvice::Refused { .. }
            | NoAdvice::Malformed { .. }),
        )) => {
            ctx.advice_pause.answered();
            return Advised::Unusable(why.to_string());
        }
        Err(_) => {
            return unanswered(NoAdvice::NotInTime {
                staff: staff.clone(),
            })
        }
    };
    ctx.advice_pause.answered();
    if advice.v != schemas::ADVICE_VERSION
        || &advice.order != holon
        || advice.conversation_id != conversation_id
    {
        return Advised::Unusable(format!(
            "advice from {staff} for another order or conversation ({} {})",
            advice.order, advice.conversation_id
        ));
    }
    match advice.resource {
        Some(resource) if resource.kind() == schemas::HolonKind::Resource => {
            debug!(%holon, %conversation_id, %staff, %resource, why = %advice.why, "advice");
            Advised::Resource(resource)
        }
        Some(other) => Advised::Unusable(format!("{staff} advised {other}, not a resource")),
        None => Advised::Unusable(format!("{staff} knows no resource: {}", advice.why)),
    }
}

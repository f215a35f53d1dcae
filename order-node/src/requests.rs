//! The order's requests over zenoh: the plan from its product holon, proposal rounds,
//! one request to one resource, and the cancel of an abandoned booking. Each awaits at
//! most its configured timeout.

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use schemas::{HolonId, MessageType, Plan, PlanStep, Service};
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
    let reply = replies.recv().await?;
    match reply.result() {
        Ok(sample) => Service::from_json(&sample.payload().to_bytes()).ok(),
        Err(err) => {
            warn!(key, error = %err.payload().try_to_string().unwrap_or_default(), conversation_id = %message.conversation_id, "error reply");
            None
        }
    }
}

/// The proposals of a round, best first: resources in `avoid` (they failed this step)
/// last; then the shortest expected wait, then queue, as they are when the round ends
/// (see [`crate::ranking::BookingsInFlight`]); ties at random (orders that ask together
/// do not all pick the same name). The best counts as a booking in flight until its
/// answer comes.
pub async fn proposals(
    ctx: &OrderContext,
    message: &Service,
    avoid: &BTreeSet<HolonId>,
) -> (Vec<HolonId>, Option<InFlight>) {
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
        return (Vec::new(), None);
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
    let (ranked, in_flight) = ctx.bookings_in_flight.rank(offers, |resource| {
        ctx.presence
            .queue(resource, message.priority().unwrap_or(0))
    });
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

/// A resource's answer to a booking or a start, as the attempt reads it.
pub fn answer(reply: Option<Service>) -> Answer {
    match reply {
        Some(reply) if reply.started() => Answer::Started,
        Some(reply) if reply.result == Some(true) => Answer::Accepted,
        Some(reply) => Answer::Refused(reply.reason),
        None => Answer::Silent,
    }
}

//! The staff holon's process: one task owns the cell model and handles, one at a time,
//! what the cell publishes and the orders' requests for advice.
//!
//! | event | what the task does |
//! |---|---|
//! | a resource's state snapshot | the model observes it (a job begun or ended is learned from) |
//! | a resource's token vanished | the resource and the intentions on it are forgotten |
//! | an order's state: it ended | its intentions are forgotten |
//! | an advice request | validated, answered from the model at once; the route becomes the order's intentions |
//! | the state interval passed, something changed | the state is republished |
//!
//! Every source feeds one bounded mailbox from zenoh's callbacks without waiting: a
//! request that finds it full is refused `unavailable` at once (the order goes by
//! contract net), a snapshot that finds it full is dropped with a warning (the next
//! one supersedes it).

use std::collections::BTreeSet;
use std::time::Duration;

use schemas::{
    unix_ms, AdviceRequest, ErrorReply, HolonId, HolonKind, OrderSnapshot, OrderStatus,
    ResourceSnapshot,
};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};
use zenoh::query::Query;
use zenoh::sample::SampleKind;

use crate::node::NodeError;
use crate::staff::config::StaffConfig;
use crate::staff::model::CellModel;
use crate::staff::planner;

/// How many events may wait for the staff's task.
pub const MAILBOX: usize = 1024;

/// What the staff's task reacts to.
enum StaffEvent {
    /// Boxed: a snapshot is large, the other events are small.
    Resource(Box<ResourceSnapshot>),
    ResourceGone(HolonId),
    ResourceBack(HolonId),
    OrderEnded(HolonId),
    Advice(Query),
}

/// The staff's own state, as it publishes it.
struct Published {
    /// Advice given since the process started.
    advised: u64,
    /// Requests refused as invalid.
    refused: u64,
    changed: bool,
}

/// Runs the staff holon until `shutdown` is cancelled.
pub async fn run(config: StaffConfig, shutdown: CancellationToken) -> Result<(), NodeError> {
    let holon = config.identity.holon.clone();
    let Some((session, claim)) = config.identity.join(&shutdown).await? else {
        return Ok(());
    };
    let zenoh_error = |e: zenoh::Error| NodeError::Zenoh(holon::zenoh_error::describe(&e));
    let (events, mut mailbox) = mpsc::channel::<StaffEvent>(MAILBOX);
    let keys = &config.identity.keys;

    let snapshots = events.clone();
    let _resource_states = session
        .declare_subscriber(keys.resource_states())
        .callback({
            let holon = holon.clone();
            move |sample| {
                match serde_json::from_slice::<ResourceSnapshot>(&sample.payload().to_bytes()) {
                    Ok(snapshot) => {
                        if snapshots.try_send(StaffEvent::Resource(Box::new(snapshot))).is_err() {
                            warn!(%holon, "the staff's mailbox is full: a resource's state was dropped (the next one supersedes it)");
                        }
                    }
                    Err(e) => debug!(%holon, error = %e, "an unreadable resource state ignored"),
                }
            }
        })
        .await
        .map_err(zenoh_error)?;
    let presence = events.clone();
    let _resources_alive = session
        .liveliness()
        .declare_subscriber(keys.alive_kind(HolonKind::Resource))
        .history(true)
        .callback({
            let keys = keys.clone();
            let holon = holon.clone();
            move |sample| {
                let Some(resource) = keys.holon_from_alive(sample.key_expr().as_str()) else {
                    return;
                };
                let event = match sample.kind() {
                    SampleKind::Put => StaffEvent::ResourceBack(resource),
                    SampleKind::Delete => StaffEvent::ResourceGone(resource),
                };
                if presence.try_send(event).is_err() {
                    warn!(%holon, "the staff's mailbox is full: a resource's presence change was dropped");
                }
            }
        })
        .await
        .map_err(zenoh_error)?;
    let ended = events.clone();
    let _order_states = session
        .declare_subscriber(keys.order_states())
        .callback(move |sample| {
            let Ok(order) = serde_json::from_slice::<OrderSnapshot>(&sample.payload().to_bytes())
            else {
                return;
            };
            if order.status != OrderStatus::Running {
                // Dropped when full: the intentions lapse by themselves.
                let _lapse_instead = ended.try_send(StaffEvent::OrderEnded(order.holon));
            }
        })
        .await
        .map_err(zenoh_error)?;
    let advice_key = keys.advice(holon.name());
    let asks = events.clone();
    let _advice = session
        .declare_queryable(&advice_key)
        .callback({
            let holon = holon.clone();
            move |query| match asks.try_send(StaffEvent::Advice(query)) {
                Ok(()) => {}
                Err(mpsc::error::TrySendError::Full(StaffEvent::Advice(query)))
                | Err(mpsc::error::TrySendError::Closed(StaffEvent::Advice(query))) => {
                    use zenoh::Wait;
                    let busy = ErrorReply::new(schemas::ErrorCode::Unavailable, "the staff is busy; go by contract net");
                    if let Err(e) = query.reply_err(busy.to_json()).wait() {
                        warn!(%holon, error = %e, "cannot refuse an advice request; the order's wait ends it");
                    }
                }
                Err(_) => {}
            }
        })
        .await
        .map_err(zenoh_error)?;
    drop(events);

    let state_key = keys.state(&holon);
    let (state, state_view) = watch::channel(Vec::new());
    let _state_queryable = session
        .declare_queryable(&state_key)
        .callback({
            let state_key = state_key.clone();
            let holon = holon.clone();
            move |query| {
                use zenoh::Wait;
                let snapshot = state_view.borrow().clone();
                if let Err(e) = query.reply(&state_key, snapshot).wait() {
                    warn!(%holon, error = %e, "cannot reply with the state");
                }
            }
        })
        .await
        .map_err(zenoh_error)?;

    let mut model = CellModel::default();
    // What the resources published before the staff came: asked once.
    seed(&session, &config, &mut model).await;
    let mut published = Published {
        advised: 0,
        refused: 0,
        changed: true,
    };
    state.send_replace(state_json(&holon, &model, &published));
    if let Err(e) = session.put(&state_key, state.borrow().clone()).await {
        warn!(%holon, error = %e, "cannot publish the state");
    }
    let holon::life::Announced {
        token,
        mut successors,
    } = config.identity.life().announce(&session).await?;
    info!(%holon, key = %advice_key, resources = model.resources().count(), "advising");
    let mut successor = None;

    let mut departed: BTreeSet<HolonId> = BTreeSet::new();
    let mut republish = tokio::time::interval(config.state_interval);
    republish.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = shutdown.cancelled() => break,
            offer = successors.next() => {
                info!(%holon, successor = %offer.request.successor, version = %offer.request.version, "a successor asks to take over");
                successor = Some(offer);
                break;
            }
            _ = republish.tick() => {
                if published.changed {
                    published.changed = false;
                    state.send_replace(state_json(&holon, &model, &published));
                    if let Err(e) = session.put(&state_key, state.borrow().clone()).await {
                        warn!(%holon, error = %e, "cannot publish the state");
                    }
                }
            }
            event = mailbox.recv() => {
                let Some(event) = event else { break };
                match event {
                    StaffEvent::Resource(snapshot) => {
                        if !departed.contains(&snapshot.holon) {
                            model.observe(*snapshot);
                            published.changed = true;
                        }
                    }
                    StaffEvent::ResourceGone(resource) => {
                        info!(%holon, %resource, "resource gone: no longer advised");
                        model.gone(&resource);
                        departed.insert(resource);
                        published.changed = true;
                    }
                    StaffEvent::ResourceBack(resource) => {
                        departed.remove(&resource);
                    }
                    StaffEvent::OrderEnded(order) => model.forget(&order),
                    StaffEvent::Advice(query) => {
                        answer(&holon, &config, &mut model, &mut published, query).await;
                    }
                }
            }
        }
    }
    let refusal = match &successor {
        Some(_) => "another successor is taking over already",
        None => "the holon is stopping",
    };
    successors.close(crate::VERSION, refusal).await;
    let ended = match successor {
        Some(offer) => {
            // What it learned goes with it: the successor learns again (nominal
            // durations until it has measured).
            crate::identity::hand_over(
                &config.identity,
                &session,
                offer,
                token,
                claim,
                &[(advice_key.clone(), false)],
                _advice,
                &shutdown,
            )
            .await
        }
        None => {
            if let Err(e) = token.undeclare().await {
                error!(%holon, error = %e, "cannot withdraw the liveliness token");
            }
            Ok(())
        }
    };
    holon::life::close(&holon.to_string(), session).await;
    info!(%holon, advised = published.advised, "holon stopped");
    ended
}

/// Asks every resource for its state once, at start.
async fn seed(session: &zenoh::Session, config: &StaffConfig, model: &mut CellModel) {
    let Ok(mut replies) = session
        .get(config.identity.keys.resource_states())
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .with(holon::query::replies())
        .await
    else {
        warn!(holon = %config.identity.holon, "cannot ask the resources for their state; learning from their next publications");
        return;
    };
    while let Some(reply) = replies.recv().await {
        let Ok(sample) = reply.result() else { continue };
        if let Ok(snapshot) =
            serde_json::from_slice::<ResourceSnapshot>(&sample.payload().to_bytes())
        {
            model.observe(snapshot);
        }
    }
}

/// Answers one advice request from the model, and keeps the order's route as its
/// intentions.
async fn answer(
    holon: &HolonId,
    config: &StaffConfig,
    model: &mut CellModel,
    published: &mut Published,
    query: Query,
) {
    let request = query
        .payload()
        .map(|p| p.to_bytes().to_vec())
        .unwrap_or_default();
    let request = serde_json::from_slice::<AdviceRequest>(&request)
        .map_err(|e| ErrorReply::new(schemas::ErrorCode::Malformed, e.to_string()))
        .and_then(|r| {
            r.validate()
                .map(|()| r)
                .map_err(|e| ErrorReply::new(schemas::ErrorCode::Invalid, e.to_string()))
        });
    let request = match request {
        Ok(request) => request,
        Err(refusal) => {
            published.refused += 1;
            published.changed = true;
            warn!(%holon, code = %refusal.code, why = %refusal.message, "advice request refused");
            if let Err(e) = query.reply_err(refusal.to_json()).await {
                warn!(%holon, error = %e, "cannot refuse an advice request; the order's wait ends it");
            }
            return;
        }
    };
    let now = unix_ms();
    let ttl = config.intention_ttl.as_millis() as u64;
    let (advice, intentions) = planner::advise(model, holon, &request, now, ttl);
    model.intend(&request.order, intentions, now);
    published.advised += 1;
    published.changed = true;
    debug!(%holon, order = %request.order, conversation_id = %request.conversation_id, resource = ?advice.resource.as_ref().map(|r| r.to_string()), why = %advice.why, message_type = "advice", "advised");
    let payload = serde_json::to_vec(&advice).expect("advice serializes");
    if let Err(e) = query.reply(query.key_expr().clone(), payload).await {
        warn!(%holon, order = %request.order, error = %e, "cannot send advice; the order goes by contract net");
    }
}

/// `staff/<name>/state`: what the staff learned and how much it advised.
fn state_json(holon: &HolonId, model: &CellModel, published: &Published) -> Vec<u8> {
    let snapshot = serde_json::json!({
        "holon": holon,
        "state": "serving",
        "version": crate::VERSION,
        "v": schemas::ADVICE_VERSION,
        "advised": published.advised,
        "refused": published.refused,
        "resources": model.resources().count(),
        "intentions": model.intentions().len(),
        "learned": model.learned(),
        "at": unix_ms(),
    });
    serde_json::to_vec(&snapshot).expect("a snapshot serializes")
}

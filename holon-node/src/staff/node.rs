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

use holon::life::{Behaviour, Leaving, LivelinessClaim, StandInSpec, Start, Work};
use schemas::{
    unix_ms, AdviceRequest, ErrorReply, HolonId, HolonKind, OrderSnapshot, OrderStatus,
    ResourceSnapshot,
};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};
use zenoh::query::Query;
use zenoh::sample::SampleKind;

use crate::staff::config::StaffConfig;
use crate::staff::model::CellModel;
use crate::staff::planner;
use crate::HolonError;

/// How many events may wait for the staff's task.
pub const MAILBOX: usize = 1024;

/// What the staff's task reacts to.
pub enum StaffEvent {
    /// Boxed: a snapshot is large, the other events are small.
    Resource(Box<ResourceSnapshot>),
    /// A resource's token went.
    ResourceGone(HolonId),
    /// A resource's token came (again).
    ResourceBack(HolonId),
    /// An order ended: its intentions are forgotten.
    OrderEnded(HolonId),
    /// A request for advice, to be answered.
    Advice(Query),
}

/// The staff's own state, as it publishes it.
struct Published {
    /// Advice given since the process started.
    advised: u64,
    /// Requests refused as invalid.
    refused: u64,
    /// Whether it changed since it was last published.
    changed: bool,
}

/// Runs the staff holon until `shutdown` is cancelled, or until it hands over to a
/// successor (what it learned goes with it: the successor learns again, from nominal
/// durations until it has measured).
pub async fn run(config: StaffConfig, shutdown: CancellationToken) -> Result<(), HolonError> {
    let process = config.identity.process();
    holon::life::run(process, &config, LivelinessClaim::default(), shutdown).await
}

/// What the staff's task reacts to next: one of its events, or the state interval.
pub enum Turn {
    /// An event from its mailbox.
    Event(StaffEvent),
    /// The state interval passed.
    Republish,
}

impl Behaviour for &StaffConfig {
    type Grant = ();
    type Work = Staff;
    type Error = HolonError;

    /// Subscribes to what the cell publishes, answers advice and the state, learns
    /// what the resources published before it came, and publishes its state.
    async fn start(&mut self, start: Start<()>) -> Result<Staff, HolonError> {
        let config = *self;
        let session = start.session;
        let holon = config.identity.holon.clone();
        let (events, mailbox) = mpsc::channel::<StaffEvent>(MAILBOX);
        let sources = Sources::declare(&session, config, events).await?;
        let state_key = config.identity.keys.state(&holon);
        let (state, state_view) = watch::channel(Vec::new());
        let state_queryable = session
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
            .map_err(|e| HolonError::Zenoh(holon::zenoh_error::describe(&e)))?;
        let layout = holon::layout::Follower::start(&session, &config.identity.keys);
        let mut model = CellModel::default();
        // What the resources published before the staff came: asked once.
        seed(&session, config, &mut model).await;
        let mut republish = tokio::time::interval(config.state_interval);
        republish.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut staff = Staff {
            config: config.clone(),
            session,
            mailbox,
            model,
            published: Published {
                advised: 0,
                refused: 0,
                changed: true,
            },
            departed: BTreeSet::new(),
            republish,
            state,
            state_key,
            sources,
            _state_queryable: state_queryable,
            layout,
        };
        staff.publish().await;
        info!(%holon, key = %staff.sources.advice_key, resources = staff.model.resources().count(), "advising");
        Ok(staff)
    }
}

/// Where the staff's events come from: zenoh's callbacks, each feeding its mailbox
/// without waiting. Dropping them undeclares them.
struct Sources {
    /// `staff/<name>/advice`.
    advice_key: String,
    /// The resources' states.
    _resource_states: zenoh::pubsub::Subscriber<()>,
    /// The resources' tokens.
    _resources_alive: zenoh::pubsub::Subscriber<()>,
    /// The orders' states (their ends).
    _order_states: zenoh::pubsub::Subscriber<()>,
    /// The advice requests.
    _advice: zenoh::query::Queryable<()>,
}

impl Sources {
    async fn declare(
        session: &zenoh::Session,
        config: &StaffConfig,
        events: mpsc::Sender<StaffEvent>,
    ) -> Result<Sources, HolonError> {
        let holon = config.identity.holon.clone();
        let zenoh_error = |e: zenoh::Error| HolonError::Zenoh(holon::zenoh_error::describe(&e));
        let keys = &config.identity.keys;
        let snapshots = events.clone();
        let resource_states = session
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
        let resources_alive = session
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
        let order_states = session
            .declare_subscriber(keys.order_states())
            .callback(move |sample| {
                let Ok(order) =
                    serde_json::from_slice::<OrderSnapshot>(&sample.payload().to_bytes())
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
        let advice = session
            .declare_queryable(&advice_key)
            .callback({
                let holon = holon.clone();
                move |query| match events.try_send(StaffEvent::Advice(query)) {
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
        Ok(Sources {
            advice_key,
            _resource_states: resource_states,
            _resources_alive: resources_alive,
            _order_states: order_states,
            _advice: advice,
        })
    }
}

/// The staff while it serves: the one owner of its cell model.
pub struct Staff {
    /// Its config.
    config: StaffConfig,
    /// Its session: the state is put there.
    session: zenoh::Session,
    /// What its sources fed it.
    mailbox: mpsc::Receiver<StaffEvent>,
    /// What it learned of the cell.
    model: CellModel,
    /// Its own figures.
    published: Published,
    /// Resources whose token went: their late snapshots are not observed.
    departed: BTreeSet<HolonId>,
    /// When the state is republished, if it changed.
    republish: tokio::time::Interval,
    /// The latest state, answered by its queryable.
    state: watch::Sender<Vec<u8>>,
    /// `staff/<name>/state`.
    state_key: String,
    /// Its subscribers and the advice queryable.
    sources: Sources,
    /// Answers `staff/<name>/state`.
    _state_queryable: zenoh::query::Queryable<()>,
    /// The cell's layout, followed from the start: the travel times of parts' moves.
    layout: holon::layout::Follower,
}

impl Staff {
    /// Publishes its state now.
    async fn publish(&mut self) {
        let holon = &self.config.identity.holon;
        self.state
            .send_replace(state_json(holon, &self.model, &self.published));
        if let Err(e) = self
            .session
            .put(&self.state_key, self.state.borrow().clone())
            .await
        {
            warn!(%holon, error = %e, "cannot publish the state");
        }
    }

    /// Answers one advice request from the model, and keeps the order's route as its
    /// intentions; an order's part's moves timed by the cell's layout as it stands.
    async fn answer(&mut self, query: Query) {
        let holon = &self.config.identity.holon;
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
                self.published.refused += 1;
                self.published.changed = true;
                warn!(%holon, code = %refusal.code, why = %refusal.message, "advice request refused");
                if let Err(e) = query.reply_err(refusal.to_json()).await {
                    warn!(%holon, error = %e, "cannot refuse an advice request; the order's wait ends it");
                }
                return;
            }
        };
        let layout = self.layout.latest();
        let now = unix_ms();
        let ttl = self.config.intention_ttl.as_millis() as u64;
        let (advice, intentions) =
            planner::advise(&self.model, layout.as_deref(), holon, &request, now, ttl);
        self.model.intend(&request.order, intentions, now);
        self.published.advised += 1;
        self.published.changed = true;
        debug!(%holon, order = %request.order, conversation_id = %request.conversation_id, resource = ?advice.resource.as_ref().map(|r| r.to_string()), why = %advice.why, message_type = "advice", "advised");
        let payload = serde_json::to_vec(&advice).expect("advice serializes");
        if let Err(e) = query.reply(query.key_expr().clone(), payload).await {
            warn!(%holon, order = %request.order, error = %e, "cannot send advice; the order goes by contract net");
        }
    }
}

impl Work for Staff {
    type Event = Turn;
    type Error = HolonError;

    async fn next(&mut self) -> holon::life::Next<Turn, HolonError> {
        tokio::select! {
            _ = self.republish.tick() => holon::life::Next::Event(Turn::Republish),
            event = self.mailbox.recv() => match event {
                Some(event) => holon::life::Next::Event(Turn::Event(event)),
                None => holon::life::Next::Ended(Ok(())),
            },
        }
    }

    async fn handle(&mut self, next: Turn) {
        let holon = self.config.identity.holon.clone();
        let event = match next {
            Turn::Republish => {
                if self.published.changed {
                    self.published.changed = false;
                    self.publish().await;
                }
                return;
            }
            Turn::Event(event) => event,
        };
        match event {
            StaffEvent::Resource(snapshot) => {
                if !self.departed.contains(&snapshot.holon) {
                    self.model.observe(*snapshot);
                    self.published.changed = true;
                }
            }
            StaffEvent::ResourceGone(resource) => {
                info!(%holon, %resource, "resource gone: no longer advised");
                self.model.gone(&resource);
                self.departed.insert(resource);
                self.published.changed = true;
            }
            StaffEvent::ResourceBack(resource) => {
                self.departed.remove(&resource);
            }
            StaffEvent::OrderEnded(order) => self.model.forget(&order),
            StaffEvent::Advice(query) => self.answer(query).await,
        }
    }

    /// On its advice key. What it learned goes with it: the successor learns again.
    fn stand_in(&self) -> StandInSpec {
        self.config
            .identity
            .stand_in(self.sources.advice_key.clone())
    }

    async fn stop(self, _how: &Leaving) -> Result<(), HolonError> {
        info!(holon = %self.config.identity.holon, advised = self.published.advised, "holon stopped");
        Ok(())
    }
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

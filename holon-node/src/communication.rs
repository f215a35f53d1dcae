//! The Communication component: the holon's zenoh side.
//!
//! It declares the holon's queryables (`resource/<name>/service`, one
//! `offer/<type>/<name>` per service type, `resource/<name>/state`, and
//! `resource/<name>/debug/crash` with `--allow-fault-injection`), decodes and validates
//! every request, runs it through the agenda manager's state machine in place and
//! replies with its answer. A
//! request that cannot be decoded, or is not allowed on the key it came to, gets an
//! error reply (`{"code", "message"}`) and never reaches the agenda.
//!
//! It also publishes a state snapshot on `resource/<name>/state` after every change and
//! delivers each `done` / `failed` to its `reply_to`, again and again with a growing
//! interval, until the requester acknowledges it.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

use holon::ChildError;
use schemas::{ErrorReply, MessageType, SchemaError, Service};
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};
use zenoh::query::{ConsolidationMode, Query};

use crate::agenda::{AgendaAction, AgendaEvent};
use crate::node::{agenda_transition, start_execution, CommunicationMessage, Node};

/// Which of the holon's queryables a query came to.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Endpoint {
    Service,
    Offer(String),
    State,
    Crash,
}

impl Endpoint {
    /// The queryable's own concrete key: replies go out on it, so a client with zenoh's
    /// default consolidation keeps one reply per resource, and access control can
    /// check that a reply comes from the resource whose key it carries.
    fn key(&self, config: &crate::config::ResourceConfig) -> String {
        let name = config.holon.name();
        match self {
            Endpoint::Service => config.keys.service(name),
            Endpoint::Offer(service_type) => config.keys.offer(service_type, name),
            Endpoint::State => config.keys.state(&config.holon),
            Endpoint::Crash => config.keys.debug_crash(name),
        }
    }
}

struct Incoming {
    endpoint: Endpoint,
    query: Query,
}

/// A result waiting for its acknowledgement.
struct Delivery {
    message: Service,
    next_attempt: Instant,
    interval: Duration,
    attempts: u32,
    in_flight: bool,
}

pub async fn run(node: Arc<Node>, token: CancellationToken) -> Result<(), ChildError> {
    let config = &node.config;
    let holon = config.holon.to_string();
    let session = &node.session;
    let (incoming_tx, mut incoming) = mpsc::unbounded_channel::<Incoming>();

    let mut endpoints = vec![(config.keys.service(config.holon.name()), Endpoint::Service)];
    endpoints.push((config.keys.state(&config.holon), Endpoint::State));
    if config.allow_fault_injection {
        endpoints.push((
            config.keys.debug_crash(config.holon.name()),
            Endpoint::Crash,
        ));
    }
    // Dropping a queryable undeclares it: they live exactly as long as this component.
    let mut queryables = Vec::new();
    for (key, endpoint) in endpoints {
        queryables.push(declare(session, &key, endpoint, &incoming_tx).await?);
    }
    // The offers exist only while the resource can take work: not before its controller
    // is ready, not while it is in fault or estop, not once the holon withdraws.
    let mut offers = Vec::new();
    sync_offers(&node, &mut offers, &incoming_tx).await?;
    let publisher = session
        .declare_publisher(config.keys.state(&config.holon))
        .await?;

    // Results not yet acknowledged, from before a restart of this component.
    let mut deliveries: BTreeMap<String, Delivery> = BTreeMap::new();
    for message in node.undelivered() {
        schedule(&mut deliveries, message, config.delivery.retry_initial);
    }
    let mut attempts: JoinSet<(String, Result<bool, String>)> = JoinSet::new();
    let mut mailbox = node.communication_mail.take().await;
    publish(&node, &publisher).await;
    info!(%holon, component = "communication", "serving");
    node.serving.notify_one();

    loop {
        let next_attempt = deliveries
            .values()
            .filter(|d| !d.in_flight)
            .map(|d| d.next_attempt)
            .min();
        tokio::select! {
            _ = token.cancelled() => break,
            _ = node.faults.communication.notified() => panic!("fault injection: communication crashed"),
            Some(incoming) = incoming.recv() => {
                let mut followups = Vec::new();
                handle_query(&node, incoming, &mut followups).await;
                // After the reply: what the agenda's transition asks for besides.
                for action in followups {
                    match action {
                        AgendaAction::Reply(_) => {}
                        AgendaAction::Execute(job) => start_execution(&node, job).await?,
                        AgendaAction::Deliver(message) => {
                            schedule(&mut deliveries, message, config.delivery.retry_initial);
                            send_due(&holon, session, config.delivery.attempt_timeout, &mut deliveries, &mut attempts);
                        }
                        AgendaAction::StateChanged => {
                            sync_offers(&node, &mut offers, &incoming_tx).await?;
                            publish(&node, &publisher).await;
                        }
                    }
                }
            }
            message = mailbox.recv() => match message.ok_or("communication mailbox closed")? {
                CommunicationMessage::Deliver(message) => {
                    // The first attempt goes out at once (not at the timer's next tick).
                    schedule(&mut deliveries, message, config.delivery.retry_initial);
                    send_due(&holon, session, config.delivery.attempt_timeout, &mut deliveries, &mut attempts);
                }
                CommunicationMessage::StateChanged => {
                    sync_offers(&node, &mut offers, &incoming_tx).await?;
                    publish(&node, &publisher).await;
                }
                CommunicationMessage::StopOffering => sync_offers(&node, &mut offers, &incoming_tx).await?,
            },
            _ = async { tokio::time::sleep_until(next_attempt.unwrap_or_else(Instant::now)).await }, if next_attempt.is_some() => {
                send_due(&holon, session, config.delivery.attempt_timeout, &mut deliveries, &mut attempts);
            }
            Some(joined) = attempts.join_next(), if !attempts.is_empty() => {
                let Ok((conversation_id, acked)) = joined else { continue };
                let Some(delivery) = deliveries.get_mut(&conversation_id) else { continue };
                delivery.in_flight = false;
                match acked {
                    Ok(true) => {
                        info!(%holon, %conversation_id, message_type = %delivery.message.message_type, attempts = delivery.attempts, "result acknowledged");
                        deliveries.remove(&conversation_id);
                        node.agenda_mail
                            .sender
                            .send(AgendaEvent::ResultAcknowledged { conversation_id })
                            .await
                            .map_err(|_| "agenda mailbox closed")?;
                    }
                    Ok(false) | Err(_) => {
                        let refused = acked.is_err();
                        let why = match acked { Err(e) => e, _ => "no acknowledgement".into() };
                        delivery.next_attempt = Instant::now() + delivery.interval;
                        if refused && repeat_worth_logging(delivery.attempts) {
                            warn!(%holon, %conversation_id, attempt = delivery.attempts, reason = %why, retry_in = ?delivery.interval, "result refused; it is sent again until acknowledged");
                        } else {
                            debug!(%holon, %conversation_id, reason = %why, retry_in = ?delivery.interval, "result not acknowledged yet");
                        }
                        delivery.interval = (delivery.interval * 2).min(config.delivery.retry_max);
                    }
                }
            }
        }
    }
    attempts.shutdown().await;
    drop(offers);
    drop(queryables);
    Ok(())
}

/// Declares the offer queryables when the resource can take work, undeclares them when
/// it cannot (controller not ready, fault, estop, withdrawing).
async fn sync_offers(
    node: &Node,
    offers: &mut Vec<zenoh::query::Queryable<()>>,
    incoming: &mpsc::UnboundedSender<Incoming>,
) -> Result<(), ChildError> {
    let config = &node.config;
    let able = node.can_take_work();
    if able && offers.is_empty() {
        for service_type in config.catalog.service_types() {
            let key = config.keys.offer(service_type, config.holon.name());
            let endpoint = Endpoint::Offer(service_type.to_string());
            offers.push(declare(&node.session, &key, endpoint, incoming).await?);
        }
        info!(holon = %config.holon, "offering");
    } else if !able && !offers.is_empty() {
        offers.clear();
        info!(holon = %config.holon, "no longer offering");
    }
    Ok(())
}

async fn declare(
    session: &zenoh::Session,
    key: &str,
    endpoint: Endpoint,
    incoming: &mpsc::UnboundedSender<Incoming>,
) -> Result<zenoh::query::Queryable<()>, ChildError> {
    let tx = incoming.clone();
    let queryable = session
        .declare_queryable(key)
        .callback(move |query| {
            let _ = tx.send(Incoming {
                endpoint: endpoint.clone(),
                query,
            });
        })
        .await?;
    debug!(%key, "queryable declared");
    Ok(queryable)
}

/// Starts an attempt for every result whose time has come.
fn send_due(
    holon: &str,
    session: &zenoh::Session,
    timeout: Duration,
    deliveries: &mut BTreeMap<String, Delivery>,
    attempts: &mut JoinSet<(String, Result<bool, String>)>,
) {
    let now = Instant::now();
    for (conversation_id, delivery) in deliveries.iter_mut() {
        if delivery.in_flight || delivery.next_attempt > now {
            continue;
        }
        delivery.in_flight = true;
        delivery.attempts += 1;
        if repeat_worth_logging(delivery.attempts) {
            info!(%holon, conversation_id = %conversation_id, message_type = %delivery.message.message_type, reply_to = delivery.message.reply_to.as_deref().unwrap_or(""), attempt = delivery.attempts, "sending result");
        } else {
            debug!(%holon, conversation_id = %conversation_id, attempt = delivery.attempts, "sending result again");
        }
        let session = session.clone();
        let message = delivery.message.clone();
        let conversation_id = conversation_id.clone();
        attempts.spawn(async move {
            let acked = deliver(&session, &message, timeout).await;
            (conversation_id, acked)
        });
    }
}

/// Whether the `attempt`th try of the same delivery is logged above debug: the first,
/// then every tenth (a requester that stays away does not fill the log).
fn repeat_worth_logging(attempt: u32) -> bool {
    attempt == 1 || attempt.is_multiple_of(10)
}

fn schedule(
    deliveries: &mut BTreeMap<String, Delivery>,
    message: Service,
    first_interval: Duration,
) {
    deliveries
        .entry(message.conversation_id.clone())
        .or_insert(Delivery {
            message,
            next_attempt: Instant::now(),
            interval: first_interval,
            attempts: 0,
            in_flight: false,
        });
}

/// One delivery attempt: true when the requester acknowledged.
async fn deliver(
    session: &zenoh::Session,
    message: &Service,
    timeout: Duration,
) -> Result<bool, String> {
    let key = message.reply_to.as_deref().ok_or("no reply_to")?;
    let mut replies = session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .with(holon::query::replies())
        .await
        .map_err(|e| e.to_string())?;
    while let Some(reply) = replies.recv().await {
        match reply.result() {
            Ok(sample) if sample.key_expr().as_str() != key => {
                warn!(conversation_id = %message.conversation_id, reply_to = key, from = %sample.key_expr(), "an acknowledgement from another key than reply_to is ignored");
            }
            Ok(sample) => match Service::from_json(&sample.payload().to_bytes()) {
                Ok(ack)
                    if ack.conversation_id == message.conversation_id
                        && ack.message_type == message.message_type
                        && ack.result == Some(true) =>
                {
                    return Ok(true)
                }
                Ok(other) => {
                    debug!(conversation_id = %message.conversation_id, ?other, "reply is not an acknowledgement")
                }
                Err(e) => {
                    debug!(conversation_id = %message.conversation_id, error = %e, "undecodable reply to a result")
                }
            },
            Err(err) => {
                let text = err
                    .payload()
                    .try_to_string()
                    .map(|s| s.into_owned())
                    .unwrap_or_default();
                // The requester refused it (malformed, not booked, ...): the caller logs why.
                return Err(format!("refused by the requester: {text}"));
            }
        }
    }
    Ok(false)
}

async fn publish(node: &Node, publisher: &zenoh::pubsub::Publisher<'_>) {
    let snapshot = node.snapshot();
    let payload = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
    if let Err(e) = publisher.put(payload).await {
        warn!(holon = %node.config.holon, error = %e, "cannot publish the state");
    }
}

async fn reply_error(node: &Node, query: &Query, code: &str, message: String) {
    warn!(holon = %node.config.holon, key = %query.key_expr(), code, error = %message, "request rejected");
    if let Err(e) = query
        .reply_err(ErrorReply::new(code, message).to_json())
        .await
    {
        warn!(holon = %node.config.holon, error = %e, "cannot send the error reply");
    }
}

async fn reply(node: &Node, endpoint: &Endpoint, query: &Query, message: &Service) {
    // One line at `info` per commitment (a booking made or cancelled, a job started);
    // proposals, refusals and status reads are many and go at `debug`. Logging every
    // request at `info` cost about a tenth of a booking's CPU (profiled).
    let commitment = message.result == Some(true)
        && matches!(
            message.message_type,
            MessageType::BookingReq | MessageType::BookingCancel | MessageType::Start
        );
    macro_rules! sent {
        ($level:ident) => {
            $level!(
                holon = %node.config.holon,
                conversation_id = %message.conversation_id,
                message_type = %message.message_type,
                requester = %message.requester,
                result = message.result.map_or("", |r| if r { "true" } else { "false" }),
                reason = message.reason.as_deref().unwrap_or(""),
                "sent"
            )
        };
    }
    if commitment {
        sent!(info);
    } else {
        sent!(debug);
    }
    if let Err(e) = query
        .reply(endpoint.key(&node.config), message.to_json())
        .await
    {
        warn!(holon = %node.config.holon, conversation_id = %message.conversation_id, error = %e, "cannot send the reply");
    }
}

/// Answers one query; what the agenda's transition asks for besides the reply goes to
/// `followups`.
async fn handle_query(node: &Node, incoming: Incoming, followups: &mut Vec<AgendaAction>) {
    let Incoming { endpoint, query } = incoming;
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    match &endpoint {
        Endpoint::State => {
            let snapshot = serde_json::to_vec(&node.snapshot()).expect("a snapshot serializes");
            if let Err(e) = query.reply(endpoint.key(&node.config), snapshot).await {
                warn!(holon = %node.config.holon, error = %e, "cannot reply with the state");
            }
            return;
        }
        Endpoint::Crash => {
            let component = String::from_utf8_lossy(&payload).trim().to_string();
            match node.faults.get(&component) {
                Some(fault) => {
                    warn!(holon = %node.config.holon, %component, "fault injection requested");
                    let _ = query.reply(endpoint.key(&node.config), format!("crashing {component}")).await;
                    fault.notify_one();
                }
                None => {
                    reply_error(node, &query, "invalid", format!("unknown component {component:?} (interfacing, execution, agenda, communication)")).await
                }
            }
            return;
        }
        Endpoint::Service | Endpoint::Offer(_) => {}
    }
    let request = match Service::from_json(&payload) {
        Ok(request) => request,
        Err(e) => {
            let code = if matches!(e, SchemaError::Json(_) | SchemaError::TooLarge { .. }) {
                "malformed"
            } else {
                "invalid"
            };
            return reply_error(node, &query, code, e.to_string()).await;
        }
    };
    debug!(
        holon = %node.config.holon,
        conversation_id = %request.conversation_id,
        message_type = %request.message_type,
        requester = %request.requester,
        service_type = %request.service_type,
        "received"
    );
    let allowed = match &endpoint {
        Endpoint::Offer(service_type) => {
            request.message_type == MessageType::ProposalReq
                && &request.service_type == service_type
        }
        _ => matches!(
            request.message_type,
            MessageType::ProposalReq
                | MessageType::BookingReq
                | MessageType::BookingCancel
                | MessageType::Start
                | MessageType::Status
        ),
    };
    if !allowed {
        let message = match &endpoint {
            Endpoint::Offer(t) => format!("{} offers {t}: only proposal_req for {t} is answered here", query.key_expr()),
            _ => format!("{} is not a request a resource answers (proposal_req, booking_req, booking_cancel, start, status)", request.message_type),
        };
        return reply_error(node, &query, "wrong_key", message).await;
    }
    if let Some(provider) = &request.provider {
        if provider != &node.config.holon {
            return reply_error(
                node,
                &query,
                "invalid",
                format!("addressed to {provider}, this is {}", node.config.holon),
            )
            .await;
        }
    }
    if request.message_type == MessageType::Status {
        // A read of the state, not an agenda transition.
        let mut answer = request.accepted(&node.config.holon);
        if let Ok(serde_json::Value::Object(info)) = serde_json::to_value(node.snapshot()) {
            answer.info = info;
        }
        return reply(node, &endpoint, &query, &answer).await;
    }
    // The agenda manager's state machine, called in place (see `node::agenda`).
    let Some(actions) = agenda_transition(node, AgendaEvent::Request(request)) else {
        return reply_error(
            node,
            &query,
            "unavailable",
            "the journal could not record the request; nothing changed".into(),
        )
        .await;
    };
    for action in actions {
        match action {
            AgendaAction::Reply(answer) => reply(node, &endpoint, &query, &answer).await,
            other => followups.push(other),
        }
    }
}

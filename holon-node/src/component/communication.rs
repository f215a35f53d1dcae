//! The communication component: the holon's zenoh side.
//!
//! It declares the holon's queryables (`resource/<name>/service`, one
//! `offer/<type>/<name>` per service type while the resource takes work,
//! `resource/<name>/state`, `resource/<name>/packml` (PackML commands),
//! `resource/<name>/carriers` (a conveyor's: an operator's word on its carriers),
//! `resource/<name>/outcome` (what became of a conversation, answered by
//! [`super::outcome`] in a task of its own), and `resource/<name>/debug/crash` with
//! `--allow-fault-injection`), decodes and checks every request, and hands each agenda
//! request, with its query, to the agenda manager, which answers it. A request that
//! cannot be decoded, or is not allowed on the key it came to, gets an error reply
//! (`{"code", "message"}`) from here and never reaches the agenda; state reads and
//! `status` are answered here from the published views.
//!
//! It also publishes the state snapshot on `resource/<name>/state` whenever a view
//! changes. Results are not its business: the agenda manager, which owns them, delivers
//! them ([`crate::component::agenda_manager::courier`]).
//!
//! A request to `service` or to an offer of an unfenced resource is decoded and checked
//! in the queryable's callback and goes from there straight into the agenda manager's
//! mailbox (a malformed or misaddressed one is refused there, at once): one queue
//! between zenoh and the agenda. The rest (state reads, `status`, PackML, fault
//! injection, and a fenced resource's requests, whose claim is confirmed first) wait in
//! this component's queue and are answered or passed on by its task.
//!
//! Back-pressure: both queues hold [`QUERY_QUEUE`]; when the one a query is for is full
//! (the resource is far behind), the query is refused at once with `unavailable`, and
//! the requester asks again after its pause. While the agenda manager's mailbox is full
//! this component's task waits, and queries queue up here. The agenda manager never
//! waits on this component (it sends it nothing), so that wait ends.

pub mod outcome;

use std::sync::Arc;

use holon::ChildError;
use schemas::{ErrorCode, ErrorReply, HolonId, MessageType, Service};
use tokio::sync::{mpsc, Notify};
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::component::agenda_manager::AgendaMessage;
use crate::component::question::Question;
use crate::config::ResourceConfig;
use crate::fault_injection::Faults;
use crate::machine::agenda::AgendaEvent;
use crate::views::Views;

/// How many queries wait for this component before new ones are refused `unavailable`.
pub const QUERY_QUEUE: usize = 1024;

/// What the communication component is linked to.
pub struct Links {
    /// Its keys, its service types, whether fault injection is declared.
    pub config: ResourceConfig,
    pub session: zenoh::Session,
    /// The agenda manager's mailbox.
    pub agenda: mpsc::Sender<AgendaMessage>,
    /// What it publishes and answers state reads from.
    pub views: Arc<Views>,
    pub faults: Arc<Faults>,
    /// Notified each time it has declared its queryables.
    pub serving: Arc<Notify>,
    /// A fenced resource's fence: the claim is confirmed with the controller before a
    /// booking or a start is taken.
    pub fence: Option<robot_bridge::client::FenceHandle>,
}

/// How long a fenced resource waits for the controller to confirm its claim before it
/// takes a booking or a start; unconfirmed, the request is left unanswered.
pub const CONFIRM_WAIT: std::time::Duration = std::time::Duration::from_secs(1);

/// Which of the holon's queryables a query came to.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Endpoint {
    Service,
    Offer(String),
    State,
    Packml,
    /// A conveyor's: an operator's word on its carriers.
    Carriers,
    Outcome,
    /// The resource's part of the cell's layout (only with `[layout]`).
    Layout,
    Crash,
}

impl Endpoint {
    /// The queryable's own concrete key (see [`Question`]).
    fn key(&self, config: &ResourceConfig) -> String {
        let name = config.holon.name();
        match self {
            Endpoint::Service => config.keys.service(name),
            Endpoint::Offer(service_type) => config.keys.offer(service_type, name),
            Endpoint::State => config.keys.state(&config.holon),
            Endpoint::Packml => config.keys.packml(name),
            Endpoint::Carriers => config.keys.carriers(name),
            Endpoint::Outcome => config.keys.outcome(name),
            Endpoint::Layout => config.keys.layout(name),
            Endpoint::Crash => config.keys.debug_crash(name),
        }
    }
}

/// A query as it arrives: the queryable it came to, and the question to answer.
struct Arrival {
    endpoint: Endpoint,
    question: Question,
}

/// The holon's queryables; dropping one undeclares it.
struct Queryables {
    /// Service, state, PackML, outcome, (with `[layout]`) layout and (with fault
    /// injection) crash: for the component's life.
    fixed: Vec<zenoh::query::Queryable<()>>,
    /// One per service type, only while the resource takes work.
    offers: Vec<zenoh::query::Queryable<()>>,
    /// Where every queryable's callback queues its queries.
    arrivals: mpsc::Sender<Arrival>,
}

impl Queryables {
    async fn declare(
        links: &Links,
        arrivals: mpsc::Sender<Arrival>,
    ) -> Result<Queryables, ChildError> {
        let config = &links.config;
        let mut endpoints = vec![
            Endpoint::Service,
            Endpoint::State,
            Endpoint::Packml,
            Endpoint::Outcome,
        ];
        if config.layout.is_some() {
            endpoints.push(Endpoint::Layout);
        }
        let conveyor = config.layout.as_ref().and_then(|p| p.transporter.as_ref());
        if matches!(
            conveyor,
            Some(schemas::layout::TransporterSpec::Conveyor(_))
        ) {
            endpoints.push(Endpoint::Carriers);
        }
        if config.allow_fault_injection {
            endpoints.push(Endpoint::Crash);
        }
        let mut fixed = Vec::new();
        for endpoint in endpoints {
            fixed.push(declare(links, endpoint, &arrivals).await?);
        }
        Ok(Queryables {
            fixed,
            offers: Vec::new(),
            arrivals,
        })
    }

    /// Undeclares every queryable (the component is stopping).
    async fn undeclare(self, holon: &HolonId) {
        for queryable in self.offers.into_iter().chain(self.fixed) {
            if let Err(e) = queryable.undeclare().await {
                warn!(%holon, error = %e, "cannot undeclare a queryable; it goes with the session");
            }
        }
    }

    /// Declares the offer queryables when the resource takes work, undeclares them when
    /// it does not (controller not ready, fault, estop, journal fault, withdrawing).
    async fn sync_offers(&mut self, links: &Links) -> Result<(), ChildError> {
        let config = &links.config;
        let accepting = links.views.accepting();
        if accepting && self.offers.is_empty() {
            for service_type in config.catalog.service_types() {
                let endpoint = Endpoint::Offer(service_type.to_string());
                self.offers
                    .push(declare(links, endpoint, &self.arrivals).await?);
            }
            info!(holon = %config.holon, "offering");
        } else if !accepting && !self.offers.is_empty() {
            self.offers.clear();
            info!(holon = %config.holon, "no longer offering");
        }
        Ok(())
    }
}

/// Declares one queryable whose callback takes the agenda's requests straight to the
/// agenda manager (an unfenced resource's `service` and offers) and queues the other
/// queries for this component.
async fn declare(
    links: &Links,
    endpoint: Endpoint,
    arrivals: &mpsc::Sender<Arrival>,
) -> Result<zenoh::query::Queryable<()>, ChildError> {
    let key = endpoint.key(&links.config);
    let holon = links.config.holon.clone();
    let arrivals = arrivals.clone();
    let answer_key = key.clone();
    let direct =
        matches!(endpoint, Endpoint::Service | Endpoint::Offer(_)) && links.fence.is_none();
    let agenda = direct.then(|| links.agenda.clone());
    let queryable = links
        .session
        .declare_queryable(&key)
        .callback(move |query| {
            let question = Question::new(query, answer_key.clone());
            let question = match &agenda {
                Some(agenda) => match to_agenda_now(&holon, &endpoint, question, agenda) {
                    Some(question) => question,
                    None => return,
                },
                None => question,
            };
            let arrival = Arrival {
                endpoint: endpoint.clone(),
                question,
            };
            match arrivals.try_send(arrival) {
                Ok(()) => {}
                Err(mpsc::error::TrySendError::Full(arrival)) => arrival.question.reject_now(
                    &holon,
                    schemas::ErrorCode::Unavailable,
                    format!(
                        "{QUERY_QUEUE} requests are waiting for this resource; ask again shortly"
                    ),
                ),
                // The component is stopping; its successor declares the queryables anew
                // and the requester asks again.
                Err(mpsc::error::TrySendError::Closed(_)) => {
                    debug!(%holon, "a query arrived while the communication component stopped")
                }
            }
        })
        .await?;
    debug!(%key, "queryable declared");
    Ok(queryable)
}

/// In a queryable's callback (it must not wait): decodes and checks an agenda request;
/// refuses it at once when it is malformed or misaddressed, puts it into the agenda
/// manager's mailbox (refused `unavailable` when that is full), or gives the question
/// back for this component's task (a `status` read).
fn to_agenda_now(
    holon: &HolonId,
    endpoint: &Endpoint,
    question: Question,
    agenda: &mpsc::Sender<AgendaMessage>,
) -> Option<Question> {
    let request = match decode(holon, endpoint, &question) {
        Ok(request) if request.message_type == MessageType::Status => return Some(question),
        Ok(request) => request,
        Err((code, message)) => {
            question.reject_now(holon, code, message);
            return None;
        }
    };
    let message = AgendaMessage {
        event: AgendaEvent::Request(request),
        question: Some(question),
    };
    match agenda.try_send(message) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(message)) => {
            if let Some(question) = message.question {
                question.reject_now(
                    holon,
                    ErrorCode::Unavailable,
                    format!(
                        "{QUERY_QUEUE} requests are waiting for this resource; ask again shortly"
                    ),
                );
            }
        }
        // The holon is stopping: the requester asks again (another resource, or this
        // one's successor).
        Err(mpsc::error::TrySendError::Closed(_)) => {
            debug!(%holon, "a request arrived while the agenda manager stopped")
        }
    }
    None
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let config = &links.config;
    let holon = &config.holon;
    // A fenced resource declares nothing until it holds its controller's claim: a
    // standby neither offers nor answers (docs/reliability.md, "Standby resources").
    let mut fence = links.views.fence.subscribe();
    tokio::select! {
        _ = token.cancelled() => return Ok(()),
        held = fence.wait_for(|fence| fence.serves()) => {
            held.map_err(|_| "the fence view closed")?;
        }
    }
    // The views are watched before anything is read from them: a change from now on
    // wakes the loop below, however early it comes (the controller may become ready
    // while the queryables are being declared).
    let mut agenda_view = links.views.agenda.subscribe();
    let mut execution_view = links.views.execution.subscribe();
    let mut absences = links.views.absences.subscribe();
    let mut retries = links.views.delivery_retries.subscribe();
    let (arrivals_tx, mut arrivals) = mpsc::channel(QUERY_QUEUE);
    let mut queryables = Queryables::declare(&links, arrivals_tx).await?;
    links.views.answering.send_replace(true);
    queryables.sync_offers(&links).await?;
    let publisher = links
        .session
        .declare_publisher(config.keys.state(holon))
        .await?;
    // The last snapshot published (its time cleared): an unchanged one is not sent again.
    let mut last_published = None;
    publish(&links, &publisher, &mut last_published).await;
    info!(%holon, component = "communication", "serving");
    links.serving.notify_one();

    // Whether the last view changes are published.
    let mut settled = true;
    loop {
        tokio::select! {
            _ = token.cancelled() => break,
            _ = links.faults.communication.notified() => panic!("fault injection: communication crashed"),
            Some(arrival) = arrivals.recv() => {
                if let Some(message) = answer(&links, arrival).await {
                    links.agenda.send(message).await.map_err(|_| "agenda mailbox closed")?;
                }
            }
            changed = agenda_view.changed() => {
                changed.map_err(|_| "the agenda view closed")?;
                settled = false;
            }
            changed = execution_view.changed() => {
                changed.map_err(|_| "the execution view closed")?;
                settled = false;
            }
            changed = absences.changed() => {
                changed.map_err(|_| "the absences view closed")?;
                settled = false;
            }
            changed = fence.changed() => {
                changed.map_err(|_| "the fence view closed")?;
                settled = false;
            }
            changed = retries.changed() => {
                changed.map_err(|_| "the delivery retries view closed")?;
                settled = false;
            }
        }
        if !settled {
            // The changes of one moment (a job begins: the agenda says busy and the
            // execution its first step; it ends: the execution is idle and the agenda
            // holds its result) are published once: the other components are let run
            // first, then every view is taken as it is now.
            tokio::task::yield_now().await;
            agenda_view.borrow_and_update();
            execution_view.borrow_and_update();
            absences.borrow_and_update();
            fence.borrow_and_update();
            retries.borrow_and_update();
            queryables.sync_offers(&links).await?;
            publish(&links, &publisher, &mut last_published).await;
            settled = true;
        }
    }
    queryables.undeclare(holon).await;
    Ok(())
}

/// Publishes the state snapshot, unless it says what the last one said (only its time
/// would differ): `last` is the last one published, with its time cleared. Nor is it
/// published while a job passes between the agenda and the execution
/// ([`Views::job_in_passage`]): the next view change, which ends that moment, publishes
/// both halves of it at once.
async fn publish(
    links: &Links,
    publisher: &zenoh::pubsub::Publisher<'_>,
    last: &mut Option<schemas::ResourceSnapshot>,
) {
    if links.views.job_in_passage() {
        return;
    }
    let snapshot = links.views.snapshot();
    let mut unstamped = snapshot.clone();
    unstamped.at = 0;
    if last.as_ref() == Some(&unstamped) {
        return;
    }
    let payload = serde_json::to_vec(&snapshot).expect("a snapshot serializes");
    if let Err(e) = publisher.put(payload).await {
        warn!(holon = %links.config.holon, error = %e, "cannot publish the state; readers see it at the next change or by asking");
        return;
    }
    *last = Some(unstamped);
}

/// Answers one query here, or returns it as a message for the agenda manager.
async fn answer(links: &Arc<Links>, arrival: Arrival) -> Option<AgendaMessage> {
    let Arrival { endpoint, question } = arrival;
    let holon = &links.config.holon;
    let work = matches!(
        endpoint,
        Endpoint::Service
            | Endpoint::Offer(_)
            | Endpoint::Packml
            | Endpoint::Carriers
            | Endpoint::Outcome
    );
    if work && !links.views.fence.borrow().serves() {
        // A fenced resource stepping down: the holder of the controller answers; this
        // one says nothing (the query ends without its reply).
        debug!(%holon, key = %question.asked_key(), "not holding the controller: a request left to the holder");
        return None;
    }
    match &endpoint {
        Endpoint::State => {
            let snapshot =
                serde_json::to_vec(&links.views.snapshot()).expect("a snapshot serializes");
            question.answer_bytes(holon, "state", snapshot).await;
            return None;
        }
        Endpoint::Layout => {
            let part = links.config.layout.as_ref().map(|part| part.to_json());
            question
                .answer_bytes(holon, "layout", part.unwrap_or_default())
                .await;
            return None;
        }
        Endpoint::Crash => {
            let component = String::from_utf8_lossy(&question.payload())
                .trim()
                .to_string();
            match links.faults.get(&component) {
                Some(fault) => {
                    warn!(%holon, %component, "fault injection requested");
                    question.answer_bytes(holon, "crash", format!("crashing {component}").into_bytes()).await;
                    fault.notify_one();
                }
                None => {
                    question.reject(holon, schemas::ErrorCode::Invalid, format!("unknown component {component:?} (interfacing, execution, agenda, communication)")).await
                }
            }
            return None;
        }
        Endpoint::Packml => {
            return match schemas::PackmlRequest::from_json(&question.payload()) {
                Ok(request) => {
                    info!(%holon, command = ?request.command, mode = ?request.mode, by = request.by.as_deref().unwrap_or(""), "PackML request");
                    Some(AgendaMessage {
                        event: AgendaEvent::Packml(request),
                        question: Some(question),
                    })
                }
                Err(e) => {
                    question
                        .reject(holon, schemas::ErrorCode::Malformed, e.to_string())
                        .await;
                    None
                }
            };
        }
        Endpoint::Carriers => {
            let by = question
                .requested_by()
                .unwrap_or_else(|| "(not said)".to_string());
            return match serde_json::from_slice::<schemas::CarrierWord>(&question.payload()) {
                Ok(word) => {
                    debug!(%holon, carrier = %word.carrier, in_service = word.in_service, %by, "an operator's word on a carrier");
                    Some(AgendaMessage {
                        event: AgendaEvent::CarrierWord { word, by },
                        question: Some(question),
                    })
                }
                Err(e) => {
                    let why = format!(
                        "not a word on a carrier (`{{\"carrier\": \"p3\", \"in_service\": false}}`): {e}"
                    );
                    question
                        .reject(holon, schemas::ErrorCode::Malformed, why)
                        .await;
                    None
                }
            };
        }
        Endpoint::Outcome => {
            // It may ask the controller: answered by a task of its own.
            tokio::spawn(outcome::answer(Arc::clone(links), question));
            return None;
        }
        Endpoint::Service | Endpoint::Offer(_) => {}
    }
    let request = match decode(holon, &endpoint, &question) {
        Ok(request) => request,
        Err((code, message)) => {
            question.reject(holon, code, message).await;
            return None;
        }
    };
    if request.message_type == MessageType::Status {
        // A read of the state, not an agenda transition.
        let mut status = request.accepted(holon);
        if let Ok(serde_json::Value::Object(info)) = serde_json::to_value(links.views.snapshot()) {
            status.info = info;
        }
        question.answer(holon, &status).await;
        return None;
    }
    if matches!(
        request.message_type,
        MessageType::BookingReq | MessageType::Start
    ) {
        if let Err(why) = confirm_claim(links).await {
            // A holder frozen and thawed may still have requests queued from before it
            // learnt it was deposed: the holder of the controller answers them.
            info!(%holon, conversation_id = %request.conversation_id, message_type = %request.message_type, %why, "the claim is not confirmed: the request is left to the holder");
            return None;
        }
    }
    Some(AgendaMessage {
        event: AgendaEvent::Request(request),
        question: Some(question),
    })
}

/// For a fenced resource: whether the controller still grants this process the epoch it
/// serves with (a claim again, answered with the same epoch while it holds it; not asked
/// again within half a lease of the last grant, [`robot_bridge::client::FenceHandle::confirmed`]).
async fn confirm_claim(links: &Links) -> Result<(), String> {
    let Some(fence) = &links.fence else {
        return Ok(());
    };
    let crate::views::FenceView::Holding(held) = *links.views.fence.borrow() else {
        return Err("it does not hold the controller".into());
    };
    if fence.confirmed() {
        // Granted less than half a lease ago: nobody else can hold it yet.
        return Ok(());
    }
    let name = links.config.holon.name();
    match tokio::time::timeout(CONFIRM_WAIT, fence.claim(name)).await {
        Ok(Ok(epoch)) if epoch.0 == held => Ok(()),
        Ok(Ok(epoch)) => Err(format!("the controller granted epoch {epoch}, not {held}")),
        Ok(Err(e)) => Err(e.to_string()),
        Err(_) => Err(format!("no answer within {CONFIRM_WAIT:?}")),
    }
}

/// Decodes a request and checks that it may come to `endpoint`: the request, or the
/// error reply's code and message.
fn decode(
    holon: &HolonId,
    endpoint: &Endpoint,
    question: &Question,
) -> Result<Service, (ErrorCode, String)> {
    let request = Service::from_json(&question.payload()).map_err(|e| {
        let refusal = ErrorReply::for_schema_error(&e);
        (refusal.code, refusal.message)
    })?;
    debug!(
        %holon,
        conversation_id = %request.conversation_id,
        message_type = %request.message_type,
        requester = %request.requester,
        service_type = %request.service_type,
        "received"
    );
    let allowed = match endpoint {
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
        let message = match endpoint {
            Endpoint::Offer(t) => format!("{} offers {t}: only proposal_req for {t} is answered here", question.asked_key()),
            _ => format!("{} is not a request a resource answers (proposal_req, booking_req, booking_cancel, start, status)", request.message_type),
        };
        return Err((ErrorCode::WrongKey, message));
    }
    if let Some(provider) = &request.provider {
        if provider != holon {
            return Err((
                ErrorCode::Invalid,
                format!("addressed to {provider}, this is {holon}"),
            ));
        }
    }
    Ok(request)
}

/// The outcome of a conversation is answered from these links.
impl outcome::Sources for Links {
    fn config(&self) -> &ResourceConfig {
        &self.config
    }

    fn views(&self) -> &Views {
        &self.views
    }

    fn fence(&self) -> Option<&robot_bridge::client::FenceHandle> {
        self.fence.as_ref()
    }
}

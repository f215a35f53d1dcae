//! The Agenda Manager: the seed's Figure 4 as a pure state machine.
//!
//! Its state is the execution status (`init`, `free`, `busy`), the bookings in the order
//! they were made, the results not yet acknowledged, and whether the holon is
//! withdrawing. The status is `init` until the execution component reports `ready` (the
//! controller is connected and ready), `busy` while a job runs, `free` otherwise; it
//! goes back to `init` when the execution component reports the controller unavailable.
//! A booking (and its job) is identified by its requester and `conversation_id`.
//!
//! Every event, with the checks of a request in the order they are made (the first
//! that applies answers; "the conversation" is the request's requester and
//! `conversation_id`):
//!
//! | event | condition, in order | outcome | next |
//! |---|---|---|---|
//! | `proposal_req` | type not offered | `proposal` false `unknown_service` | same |
//! | | controller not ready, or withdrawing | `proposal` false `unavailable` | same |
//! | | agenda full | `proposal` false `agenda_full` | same |
//! | | `info.priority` is not an integer from -1000 to 1000 | refused `invalid_info` | same |
//! | | otherwise | `proposal` true with the queue and the expected wait where a booking of its priority would go | same |
//! | `booking_req` | type not offered | refused `unknown_service` | same |
//! | | the requester is a resource | refused `not_a_requester` (nothing would release it) | same |
//! | | the conversation is booked | true again with its queue position (no second booking) | same |
//! | | start on turn asked, and the conversation's job runs or finished with its result undelivered | true, `started` again (no second execution) | same |
//! | | the conversation's job is running | refused `busy` | same |
//! | | controller not ready, or withdrawing | refused `unavailable` (no commitment without hardware) | same |
//! | | agenda full | refused `agenda_full` | same |
//! | | `info.priority` or `info.due` is not one | refused `invalid_info` | same |
//! | | start on turn asked, and the info lacks what the steps need or there is no `reply_to` | refused `invalid_info` | same |
//! | | start on turn asked, `free`, nothing booked ahead | true, `started`; the booking becomes the job, execution starts | `busy` |
//! | | otherwise | true with the queue position; booking inserted by priority (below) | same + booking |
//! | `booking_cancel` | the conversation is booked | true; booking removed | same − booking |
//! | | otherwise | refused `not_booked` | same |
//! | `start` | type not offered | refused `unknown_service` | same |
//! | | the conversation's job runs, or finished with its result undelivered | true again (no second execution) | same |
//! | | the conversation is not booked ("not booked" beats "busy") | refused `not_booked` | same |
//! | | withdrawing | refused `unavailable` | same |
//! | | the booking is for another service type | refused `not_booked` | same |
//! | | `busy` | refused `busy` (the booking stays) | same |
//! | | controller not ready | refused `unavailable` (the booking stays) | same |
//! | | the info (the start's, else the booking's) lacks what the steps need | refused `invalid_info` | same |
//! | | neither the start nor the booking has `reply_to` | refused `invalid_info` | same |
//! | | otherwise | true; the booking becomes the job, execution starts | `busy` |
//! | `status`, `proposal`, `done`, `failed` | (`status` is answered by the communication component) | refused `unknown_service` | same |
//! | execution ready | | | `free` (or `busy`) |
//! | execution unavailable | | | `init` (a running job ends first) |
//! | execution finished the running job | | its `done` / `failed` is delivered until acknowledged | `free` or `init` |
//! | execution finished another job (stale) | | nothing | same |
//! | result acknowledged | the result is undelivered | removed | same |
//! | | otherwise | nothing | same |
//! | withdraw (SIGTERM) | not yet withdrawing | every booking with a `reply_to` gets `failed` `withdrawn`; bookings cleared | withdrawing |
//! | | already withdrawing | nothing | same |
//! | hand over (a successor asks, `cell upgrade`) | not withdrawing | bookings kept for the successor; the running job finishes | handing over |
//! | | withdrawing | nothing | same |
//! | hand-over abandoned (the running job outlasted the successor's wait) | handing over | | serving again |
//! | requester gone (absent longer than the grace) | | its bookings removed; its running job and undelivered results stay | same − bookings |
//! | restored from the journal | handed over by a predecessor just now | bookings as they were | `init` |
//! | | otherwise (a restart) | bookings kept, none starts on its turn: each waits for its requester's `start` ([`Inheritance::Restarted`]) | `init` |
//! | after any event | `free`, not withdrawing or handing over, and the first booking asked to start on its turn | the booking becomes the job, execution starts | `busy` |
//!
//! "Withdrawing" in the rows above reads "withdrawing or handing over": both take no
//! new work and start nothing. A refusal `unavailable` while handing over says so in
//! `info.detail` and carries `info.retry_after_ms` ([`HANDOVER_RETRY`]): the successor
//! answers within moments.
//!
//! Every change of state is followed by a `StateChanged` action (a new snapshot).
//!
//! Bookings wait by priority ([`schemas::info_key::PRIORITY`], higher first), equal
//! priorities in the order they came. A new booking goes ahead of the waiting bookings
//! of lower priority at the back, but stops behind one that later bookings have passed
//! `max_overtakes` times. So a booking starts after at most the jobs ahead of it when it
//! was booked, plus `max_overtakes`: low priority is served later, never starved.

use std::sync::Arc;

use schemas::{
    reason, unix_ms, BookingView, ControllerStatus, CurrentJobView, HolonId, HolonKind,
    MessageType, ResourceSnapshot, ResourceState, Service,
};
use serde_json::{json, Map, Value};

use crate::catalog::ServiceCatalog;

/// How many later bookings of higher priority may go ahead of a waiting one, unless
/// the config says (`agenda.max_overtakes`).
pub const DEFAULT_MAX_OVERTAKES: u32 = 4;

/// How the journal's bookings came to this process, which decides whether those asked
/// to start on their turn still do.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Inheritance {
    /// A predecessor handed them over a moment ago: their requesters knew of the
    /// hand-over and kept them, so each starts on its turn as it was booked to.
    HandedOver,
    /// The holon was away (it stopped, crashed, or its successor never served): a
    /// requester may have given up on its booking and booked again, here or elsewhere,
    /// with its cancel not yet arrived. Started on its turn, such a booking would run
    /// the step twice; so every booking waits for its requester's `start` (an order
    /// that still holds it sends one when its turn comes, an order that gave up sends
    /// the cancel).
    Restarted,
}

/// A commitment on the agenda.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Booking {
    pub requester: HolonId,
    pub conversation_id: String,
    pub service_type: String,
    pub reply_to: Option<String>,
    /// The booking's `info`, used when `start` carries none.
    pub info: Map<String, Value>,
    /// The requester asked for the job to start by itself on its turn
    /// ([`schemas::info_key::START_ON_TURN`]); its `reply_to` and `info` were checked
    /// when it was booked.
    #[serde(default)]
    pub start_on_turn: bool,
    /// Its priority ([`schemas::info_key::PRIORITY`]): it went ahead of waiting
    /// bookings of lower priority when it was made.
    #[serde(default)]
    pub priority: i32,
    /// When its order is due, in Unix milliseconds, if it said (shown, not used here).
    #[serde(default)]
    pub due: Option<u64>,
    /// How many later bookings went ahead of it; at `max_overtakes` none may.
    #[serde(default)]
    pub overtaken: u32,
}

/// A booking being executed.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Job {
    pub requester: HolonId,
    pub conversation_id: String,
    pub service_type: String,
    /// Where `done` / `failed` goes.
    pub reply_to: String,
    pub info: Map<String, Value>,
}

/// How an execution ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Every step completed; `results` maps each action to the controller's result.
    Done { results: Map<String, Value> },
    /// A step failed; `reason` is one of [`schemas::reason`], `detail` is for people.
    Failed { reason: String, detail: String },
}

/// As an operator reads it in a log: `done pick=picking_done place=placing_done`, or
/// `failed controller_error: pick failed: gripper empty`.
impl std::fmt::Display for Outcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Outcome::Done { results } => {
                f.write_str("done")?;
                for (action, result) in results {
                    match result.as_str() {
                        Some(text) => write!(f, " {action}={text}")?,
                        None => write!(f, " {action}={result}")?,
                    }
                }
                Ok(())
            }
            Outcome::Failed { reason, detail } => write!(f, "failed {reason}: {detail}"),
        }
    }
}

/// What the agenda manager reacts to.
#[derive(Debug, Clone, PartialEq)]
pub enum AgendaEvent {
    /// A Service request from another holon, via the communication component.
    Request(Service),
    /// Execution is ready: the controller is connected and ready, nothing runs.
    ExecutionReady,
    /// Execution cannot run services: the controller is away, in fault or estop.
    ExecutionUnavailable,
    /// Execution finished the job of `conversation_id`.
    ExecutionFinished {
        conversation_id: String,
        outcome: Outcome,
    },
    /// The requester acknowledged the result of `conversation_id`.
    ResultAcknowledged { conversation_id: String },
    /// The holon is shutting down: take no new work, hand every booking back (a
    /// `failed` with reason `withdrawn` to its `reply_to`), let the running job finish.
    Withdraw,
    /// A successor process is taking the holon over (a planned upgrade): take no new
    /// work and start nothing, keep every booking (the successor restores them from the
    /// journal), let the running job finish.
    HandOver,
    /// The hand-over did not happen (the running job outlasted the successor's wait):
    /// serve again.
    HandOverAbandoned,
    /// `requester` has been absent from the cell (no liveliness token) longer than the
    /// booking grace: its bookings end. The running job and undelivered results stay.
    RequesterGone { requester: HolonId },
}

/// What the task around the agenda manager must do.
#[derive(Debug, Clone, PartialEq)]
pub enum AgendaAction {
    /// Answer the request being handled.
    Reply(Service),
    /// Have the execution component execute this job.
    Execute(Job),
    /// Deliver this `done` / `failed` to its `reply_to` until acknowledged.
    Deliver(Service),
    /// The state changed: publish a snapshot.
    StateChanged,
}

/// What the journal keeps of the agenda manager: everything that must survive a crash.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct AgendaRecord {
    pub bookings: Vec<Booking>,
    /// The job that was executing: after a crash it is reported `interrupted`.
    pub current: Option<Job>,
    pub undelivered: Vec<Service>,
}

/// The execution status in Figure 4 (plus `init`).
#[derive(Debug, Clone, PartialEq)]
pub enum Status {
    Init,
    Free,
    Busy(Job),
}

/// Where one conversation (a requester and a `conversation_id`) stands on the agenda.
#[derive(Debug, Clone, Copy)]
struct Conversation {
    /// Its booking's index, if it is booked.
    booked: Option<usize>,
    /// Its job is running.
    running: bool,
    /// Its job finished and the result is not acknowledged yet.
    finished: bool,
}

/// The Agenda Manager's state.
#[derive(Debug, Clone)]
pub struct AgendaManager {
    holon: HolonId,
    catalog: Arc<ServiceCatalog>,
    capacity: usize,
    /// How many later bookings of higher priority may go ahead of a waiting one.
    max_overtakes: u32,
    execution_ready: bool,
    current: Option<Job>,
    bookings: Vec<Booking>,
    /// `done` / `failed` not yet acknowledged, oldest first.
    undelivered: Vec<Service>,
    /// Shutting down: no new bookings or starts.
    withdrawing: bool,
    /// Being handed over to a successor process: no new bookings or starts, bookings kept.
    handing_over: bool,
}

impl AgendaManager {
    pub fn new(holon: HolonId, catalog: Arc<ServiceCatalog>, capacity: usize) -> Self {
        AgendaManager {
            holon,
            catalog,
            capacity,
            max_overtakes: DEFAULT_MAX_OVERTAKES,
            execution_ready: false,
            current: None,
            bookings: Vec::new(),
            undelivered: Vec::new(),
            withdrawing: false,
            handing_over: false,
        }
    }

    /// The same agenda, letting at most `max_overtakes` later bookings of higher
    /// priority go ahead of a waiting one (0: first come, first served).
    pub fn with_max_overtakes(mut self, max_overtakes: u32) -> Self {
        self.max_overtakes = max_overtakes;
        self
    }

    /// What the journal keeps.
    pub fn record(&self) -> AgendaRecord {
        AgendaRecord {
            bookings: self.bookings.clone(),
            current: self.current.clone(),
            undelivered: self.undelivered.clone(),
        }
    }

    /// The agenda manager after a restart of the process: the bookings and undelivered
    /// results come back; a job that was executing is reported `failed` with reason
    /// `interrupted` (never re-executed), as one more undelivered result. Unless a
    /// predecessor has just handed them over, no booking starts by itself on its turn
    /// (see [`Inheritance::Restarted`]).
    pub fn restore(
        holon: HolonId,
        catalog: Arc<ServiceCatalog>,
        capacity: usize,
        record: AgendaRecord,
        inheritance: Inheritance,
    ) -> AgendaManager {
        let mut manager = AgendaManager::new(holon, catalog, capacity);
        manager.bookings = record.bookings;
        if inheritance == Inheritance::Restarted {
            for booking in &mut manager.bookings {
                booking.start_on_turn = false;
            }
        }
        manager.undelivered = record.undelivered;
        if let Some(job) = record.current {
            let message = manager.result_message(
                job,
                Outcome::Failed {
                    reason: reason::INTERRUPTED.into(),
                    detail: "the resource holon stopped while the step ran; it was not completed"
                        .into(),
                },
            );
            manager.undelivered.push(message);
        }
        manager
    }

    /// Whether the holon is shutting down (no new bookings or starts).
    pub fn is_withdrawing(&self) -> bool {
        self.withdrawing
    }

    /// Whether the holon is being handed over to a successor.
    pub fn is_handing_over(&self) -> bool {
        self.handing_over
    }

    /// Withdrawing or handing over: it takes no new work and starts nothing.
    fn leaving(&self) -> bool {
        self.withdrawing || self.handing_over
    }

    /// True once withdrawing and nothing is left to finish or deliver.
    pub fn is_drained(&self) -> bool {
        self.withdrawing && self.current.is_none() && self.undelivered.is_empty()
    }

    pub fn status(&self) -> Status {
        match (&self.current, self.execution_ready) {
            (Some(job), _) => Status::Busy(job.clone()),
            (None, true) => Status::Free,
            (None, false) => Status::Init,
        }
    }

    /// The status as the snapshot shows it.
    pub fn state(&self) -> ResourceState {
        match (&self.current, self.execution_ready) {
            (Some(_), _) => ResourceState::Busy,
            (None, true) => ResourceState::Free,
            (None, false) => ResourceState::Init,
        }
    }

    pub fn bookings(&self) -> &[Booking] {
        &self.bookings
    }

    pub fn undelivered(&self) -> &[Service] {
        &self.undelivered
    }

    pub fn current(&self) -> Option<&Job> {
        self.current.as_ref()
    }

    /// The seed's FSM: one event in, the actions out. No I/O.
    pub fn handle(&mut self, event: AgendaEvent) -> Vec<AgendaAction> {
        let mut actions = self.transition(event);
        actions.extend(self.turn());
        actions
    }

    /// The machine without its last row: no booking starts on its turn. For an event
    /// that must be kept while the journal cannot record a job's start (the booking then
    /// waits; its requester's `start` is refused until the journal can be written).
    pub fn handle_holding_turns(&mut self, event: AgendaEvent) -> Vec<AgendaAction> {
        self.transition(event)
    }

    /// The last row of the table, as actions.
    fn turn(&mut self) -> Vec<AgendaAction> {
        let mut actions = Vec::new();
        if let Some(job) = self.start_on_turn() {
            actions.push(AgendaAction::Execute(job));
            actions.push(AgendaAction::StateChanged);
        }
        actions
    }

    /// The row of the table for `event`.
    fn transition(&mut self, event: AgendaEvent) -> Vec<AgendaAction> {
        match event {
            AgendaEvent::Request(request) => self.request(request),
            AgendaEvent::ExecutionReady => self.set_ready(true),
            AgendaEvent::ExecutionUnavailable => self.set_ready(false),
            AgendaEvent::ExecutionFinished {
                conversation_id,
                outcome,
            } => self.finished(&conversation_id, outcome),
            AgendaEvent::Withdraw => self.withdraw(),
            AgendaEvent::HandOver => self.hand_over(true),
            AgendaEvent::HandOverAbandoned => self.hand_over(false),
            AgendaEvent::RequesterGone { requester } => self.release(&requester),
            AgendaEvent::ResultAcknowledged { conversation_id } => {
                let before = self.undelivered.len();
                self.undelivered
                    .retain(|r| r.conversation_id != conversation_id);
                if self.undelivered.len() == before {
                    vec![]
                } else {
                    vec![AgendaAction::StateChanged]
                }
            }
        }
    }

    fn hand_over(&mut self, handing_over: bool) -> Vec<AgendaAction> {
        if self.withdrawing || self.handing_over == handing_over {
            return vec![];
        }
        self.handing_over = handing_over;
        vec![AgendaAction::StateChanged]
    }

    fn withdraw(&mut self) -> Vec<AgendaAction> {
        if self.withdrawing {
            return vec![];
        }
        self.withdrawing = true;
        self.handing_over = false;
        let mut actions = Vec::new();
        for booking in std::mem::take(&mut self.bookings) {
            let Some(reply_to) = booking.reply_to else {
                // Nowhere to tell: the requester finds out when its start is refused.
                continue;
            };
            let message = self.result_message(
                Job {
                    requester: booking.requester,
                    conversation_id: booking.conversation_id,
                    service_type: booking.service_type,
                    reply_to,
                    info: Map::new(),
                },
                Outcome::Failed {
                    reason: reason::WITHDRAWN.into(),
                    detail: "the resource is shutting down; book elsewhere".into(),
                },
            );
            self.undelivered.push(message.clone());
            actions.push(AgendaAction::Deliver(message));
        }
        actions.push(AgendaAction::StateChanged);
        actions
    }

    fn release(&mut self, requester: &HolonId) -> Vec<AgendaAction> {
        let before = self.bookings.len();
        self.bookings.retain(|b| &b.requester != requester);
        if self.bookings.len() == before {
            vec![]
        } else {
            vec![AgendaAction::StateChanged]
        }
    }

    fn set_ready(&mut self, ready: bool) -> Vec<AgendaAction> {
        if self.execution_ready == ready {
            return vec![];
        }
        self.execution_ready = ready;
        vec![AgendaAction::StateChanged]
    }

    /// Where the request's conversation stands on this agenda.
    fn conversation(&self, request: &Service) -> Conversation {
        let same = |requester: &HolonId, conversation_id: &str| {
            requester == &request.requester && conversation_id == request.conversation_id
        };
        Conversation {
            booked: self
                .bookings
                .iter()
                .position(|b| same(&b.requester, &b.conversation_id)),
            running: self
                .current
                .as_ref()
                .is_some_and(|job| same(&job.requester, &job.conversation_id)),
            finished: self
                .undelivered
                .iter()
                .any(|r| same(&r.requester, &r.conversation_id)),
        }
    }

    /// A request from another holon: the rows of the table above, in their order.
    fn request(&mut self, request: Service) -> Vec<AgendaAction> {
        match request.message_type {
            MessageType::ProposalReq => self.proposal(&request),
            MessageType::BookingReq => self.book(request),
            MessageType::BookingCancel => self.cancel(&request),
            MessageType::Start => self.start(request),
            // Not agenda requests: the communication component answers `status` itself
            // (a read of the state) and rejects the others.
            MessageType::Proposal
            | MessageType::Done
            | MessageType::Failed
            | MessageType::Status => self.refuse(&request, reason::UNKNOWN_SERVICE, None),
        }
    }

    fn refuse(&self, request: &Service, why: &str, detail: Option<String>) -> Vec<AgendaAction> {
        let mut reply = request.refused(&self.holon, why);
        if let Some(detail) = detail {
            reply.info.insert("detail".into(), Value::String(detail));
        }
        if why == reason::UNAVAILABLE && self.handing_over {
            handing_over_hint(&mut reply.info);
        }
        vec![AgendaAction::Reply(reply)]
    }

    fn proposal(&self, request: &Service) -> Vec<AgendaAction> {
        let refusal = if !self.catalog.offers(&request.service_type) {
            Some(reason::UNKNOWN_SERVICE)
        } else if !self.execution_ready || self.leaving() {
            Some(reason::UNAVAILABLE)
        } else if self.bookings.len() >= self.capacity {
            Some(reason::AGENDA_FULL)
        } else {
            None
        };
        let mut reply = request.accepted(&self.holon);
        reply.message_type = MessageType::Proposal;
        if let Some(why) = refusal {
            reply.result = Some(false);
            reply.reason = Some(why.to_string());
        }
        let priority = match request.priority() {
            Ok(priority) => priority,
            Err(detail) => return self.refuse(request, reason::INVALID_INFO, Some(detail)),
        };
        reply.info = self.proposal_info(&request.service_type, priority);
        if refusal == Some(reason::UNAVAILABLE) && self.handing_over {
            handing_over_hint(&mut reply.info);
        }
        vec![AgendaAction::Reply(reply)]
    }

    fn book(&mut self, request: Service) -> Vec<AgendaAction> {
        let conversation = self.conversation(&request);
        let taking_work = self.execution_ready && !self.leaving();
        let full = self.bookings.len() >= self.capacity;
        match (conversation, taking_work, full) {
            _ if !self.catalog.offers(&request.service_type) => {
                self.refuse(&request, reason::UNKNOWN_SERVICE, None)
            }
            _ if request.requester.kind() == HolonKind::Resource => {
                self.refuse(&request, reason::NOT_A_REQUESTER, None)
            }
            (
                Conversation {
                    booked: Some(position),
                    ..
                },
                _,
                _,
            ) => {
                vec![AgendaAction::Reply(self.booked_reply(&request, position))]
            }
            // Asked again (a lost reply, a restarted order) after the job began on
            // its turn: it has begun.
            (Conversation { running: true, .. } | Conversation { finished: true, .. }, ..)
                if request.start_on_turn() =>
            {
                vec![AgendaAction::Reply(self.started_reply(&request))]
            }
            (Conversation { running: true, .. }, _, _) => self.refuse(&request, reason::BUSY, None),
            (_, false, _) => self.refuse(&request, reason::UNAVAILABLE, None),
            (_, true, true) => self.refuse(&request, reason::AGENDA_FULL, None),
            (_, true, false) => self.append(request),
        }
    }

    /// Appends the booking of `request`; one that asks to start on its turn is checked
    /// as a start would be, and begins at once when it is the next job of a free
    /// resource.
    fn append(&mut self, request: Service) -> Vec<AgendaAction> {
        let (priority, due) = match (request.priority(), request.due()) {
            (Ok(priority), Ok(due)) => (priority, due),
            (Err(detail), _) | (_, Err(detail)) => {
                return self.refuse(&request, reason::INVALID_INFO, Some(detail))
            }
        };
        let start_on_turn = request.start_on_turn();
        if start_on_turn {
            if let Err(detail) = self.catalog.check(&request.service_type, &request.info) {
                return self.refuse(&request, reason::INVALID_INFO, Some(detail));
            }
            if request.reply_to.is_none() {
                let detail = "a booking that starts on its turn needs reply_to".to_string();
                return self.refuse(&request, reason::INVALID_INFO, Some(detail));
            }
        }
        let at = self.insertion_point(priority);
        for passed in &mut self.bookings[at..] {
            passed.overtaken += 1;
        }
        self.bookings.insert(
            at,
            Booking {
                requester: request.requester.clone(),
                conversation_id: request.conversation_id.clone(),
                service_type: request.service_type.clone(),
                reply_to: request.reply_to.clone(),
                info: request.info.clone(),
                start_on_turn,
                priority,
                due,
                overtaken: 0,
            },
        );
        match self.start_on_turn() {
            Some(job) => vec![
                AgendaAction::Reply(self.started_reply(&request)),
                AgendaAction::Execute(job),
                AgendaAction::StateChanged,
            ],
            None => {
                let reply = self.booked_reply(&request, at);
                vec![AgendaAction::Reply(reply), AgendaAction::StateChanged]
            }
        }
    }

    /// The last row of the table: a free resource whose first booking asked to start
    /// on its turn makes it the running job.
    fn start_on_turn(&mut self) -> Option<Job> {
        let first = self.bookings.first()?;
        if self.state() != ResourceState::Free || self.leaving() || !first.start_on_turn {
            return None;
        }
        // Checked when it was booked; a booking without one waits for a `start`.
        let reply_to = first.reply_to.clone()?;
        let info = first.info.clone();
        Some(self.run_booking(0, reply_to, info))
    }

    /// Makes the booking at `index` the running job, its results to `reply_to`.
    fn run_booking(&mut self, index: usize, reply_to: String, info: Map<String, Value>) -> Job {
        let booking = self.bookings.remove(index);
        let job = Job {
            requester: booking.requester,
            conversation_id: booking.conversation_id,
            service_type: booking.service_type,
            reply_to,
            info,
        };
        self.current = Some(job.clone());
        job
    }

    fn cancel(&mut self, request: &Service) -> Vec<AgendaAction> {
        match self.conversation(request).booked {
            Some(index) => {
                self.bookings.remove(index);
                vec![
                    AgendaAction::Reply(request.accepted(&self.holon)),
                    AgendaAction::StateChanged,
                ]
            }
            None => self.refuse(request, reason::NOT_BOOKED, None),
        }
    }

    fn start(&mut self, request: Service) -> Vec<AgendaAction> {
        let conversation = self.conversation(&request);
        let booking = conversation
            .booked
            .map(|index| (index, self.bookings[index].service_type.clone()));
        match (conversation, booking, self.state(), self.leaving()) {
            _ if !self.catalog.offers(&request.service_type) => {
                self.refuse(&request, reason::UNKNOWN_SERVICE, None)
            }
            // A repeated start of the running job, or of one that finished and whose
            // result is on its way: it has begun.
            (Conversation { running: true, .. } | Conversation { finished: true, .. }, ..) => {
                vec![AgendaAction::Reply(request.accepted(&self.holon))]
            }
            (_, None, _, _) => self.refuse(&request, reason::NOT_BOOKED, None),
            (_, Some(_), _, true) => self.refuse(&request, reason::UNAVAILABLE, None),
            (_, Some((_, booked_type)), _, _) if booked_type != request.service_type => {
                let detail = format!("the booking is for {booked_type}");
                self.refuse(&request, reason::NOT_BOOKED, Some(detail))
            }
            (_, Some(_), ResourceState::Busy, _) => self.refuse(&request, reason::BUSY, None),
            (_, Some(_), ResourceState::Init, _) => {
                self.refuse(&request, reason::UNAVAILABLE, None)
            }
            (_, Some((index, _)), ResourceState::Free, false) => self.begin(index, request),
        }
    }

    /// Makes the booking at `index` the running job, if what the steps need is there.
    fn begin(&mut self, index: usize, request: Service) -> Vec<AgendaAction> {
        let booking = &self.bookings[index];
        let info = if request.info.is_empty() {
            booking.info.clone()
        } else {
            request.info.clone()
        };
        if let Err(detail) = self.catalog.check(&request.service_type, &info) {
            return self.refuse(&request, reason::INVALID_INFO, Some(detail));
        }
        let Some(reply_to) = request
            .reply_to
            .clone()
            .or_else(|| booking.reply_to.clone())
        else {
            let detail = "neither the start nor the booking has reply_to".to_string();
            return self.refuse(&request, reason::INVALID_INFO, Some(detail));
        };
        let job = self.run_booking(index, reply_to, info);
        vec![
            AgendaAction::Reply(request.accepted(&self.holon)),
            AgendaAction::Execute(job),
            AgendaAction::StateChanged,
        ]
    }

    fn finished(&mut self, conversation_id: &str, outcome: Outcome) -> Vec<AgendaAction> {
        let Some(job) = self
            .current
            .take_if(|job| job.conversation_id == conversation_id)
        else {
            // Not the running job (a stale report): nothing changes.
            return vec![];
        };
        let message = self.result_message(job, outcome);
        self.undelivered.push(message.clone());
        vec![AgendaAction::Deliver(message), AgendaAction::StateChanged]
    }

    /// The `done` / `failed` message that reports `outcome` of `job` to its requester.
    fn result_message(&self, job: Job, outcome: Outcome) -> Service {
        let (message_type, result, why, info) = match outcome {
            Outcome::Done { results } => {
                (MessageType::Done, true, None, json!({ "results": results }))
            }
            Outcome::Failed { reason, detail } => (
                MessageType::Failed,
                false,
                Some(reason),
                json!({ "detail": detail }),
            ),
        };
        Service {
            v: schemas::SERVICE_VERSION,
            message_type,
            service_type: job.service_type,
            conversation_id: job.conversation_id,
            requester: job.requester,
            provider: Some(self.holon.clone()),
            reply_to: Some(job.reply_to),
            result: Some(result),
            reason: why,
            info: match info {
                Value::Object(map) => map,
                _ => Map::new(),
            },
        }
    }

    /// The answer to a booking whose job has begun (queue position 0).
    fn started_reply(&self, request: &Service) -> Service {
        let mut reply = self.queued_reply(request, 0);
        reply
            .info
            .insert(schemas::info_key::STARTED.into(), Value::Bool(true));
        reply
    }

    /// The answer to a booking at `position` on the agenda.
    fn booked_reply(&self, request: &Service, position: usize) -> Service {
        self.queued_reply(request, position + 1 + self.current.is_some() as usize)
    }

    /// An accepted booking: the proposal's figures and the booking's queue position.
    fn queued_reply(&self, request: &Service, queue_position: usize) -> Service {
        let mut reply = request.accepted(&self.holon);
        reply.info = self.proposal_info(&request.service_type, request.priority().unwrap_or(0));
        reply
            .info
            .insert("queue_position".into(), json!(queue_position));
        reply
    }

    /// Where a new booking of `priority` goes: ahead of the waiting bookings of lower
    /// priority at the back of the agenda, stopping at one of equal or higher
    /// priority, or one already passed `max_overtakes` times. So equal priorities are
    /// first come, first served, and a waiting booking starts after at most the jobs
    /// ahead of it when it was made plus `max_overtakes` (no starvation).
    fn insertion_point(&self, priority: i32) -> usize {
        let mut at = self.bookings.len();
        while at > 0 {
            let ahead = &self.bookings[at - 1];
            if ahead.priority >= priority || ahead.overtaken >= self.max_overtakes {
                break;
            }
            at -= 1;
        }
        at
    }

    /// What a proposal says: the queue ahead and the expected wait before this service
    /// could start for a booking of `priority`, from the nominal durations of the jobs
    /// ahead of where it would go.
    fn proposal_info(&self, service_type: &str, priority: i32) -> Map<String, Value> {
        let nominal = |t: &str| {
            self.catalog
                .get(t)
                .map(|d| d.nominal_duration.as_millis() as u64)
                .unwrap_or(0)
        };
        let at = self.insertion_point(priority);
        let ahead: u64 = self.bookings[..at]
            .iter()
            .map(|b| nominal(&b.service_type))
            .chain(self.current.iter().map(|j| nominal(&j.service_type)))
            .sum();
        let mut info = Map::new();
        info.insert("state".into(), json!(self.state()));
        info.insert(
            "queue_position".into(),
            json!(at + self.current.is_some() as usize),
        );
        info.insert("agenda_length".into(), json!(self.bookings.len()));
        info.insert("expected_wait_ms".into(), json!(ahead));
        info.insert("duration_ms".into(), json!(nominal(service_type)));
        info
    }

    /// The agenda's part of the snapshot published on `resource/<name>/state`: the
    /// controller, the step in progress and the requesters' absences are the other
    /// components' to fill in (see [`crate::views::Views::snapshot`]).
    pub fn snapshot(&self) -> ResourceSnapshot {
        ResourceSnapshot {
            holon: self.holon.clone(),
            state: self.state(),
            controller: ControllerStatus::Disconnected,
            agenda: self
                .bookings
                .iter()
                .map(|b| BookingView {
                    requester: b.requester.clone(),
                    conversation_id: b.conversation_id.clone(),
                    service_type: b.service_type.clone(),
                    requester_absent_since: None,
                    priority: b.priority,
                    due: b.due,
                    overtaken: b.overtaken,
                    program: crate::catalog::program(&b.info).ok().flatten(),
                })
                .collect(),
            current: self.current.as_ref().map(|j| CurrentJobView {
                requester: j.requester.clone(),
                conversation_id: j.conversation_id.clone(),
                service_type: j.service_type.clone(),
                step: None,
                program: crate::catalog::program(&j.info).ok().flatten(),
                started_at: None,
            }),
            undelivered: self.undelivered.len(),
            services: self.catalog.service_types().map(String::from).collect(),
            nominal_ms: self
                .catalog
                .service_types()
                .filter_map(|t| {
                    let nominal = self.catalog.get(t)?.nominal_duration.as_millis() as u64;
                    Some((t.to_string(), nominal))
                })
                .collect(),
            journal_fault: None,
            delivery_retries: 0,
            handing_over: self.handing_over,
            host: None,
            version: None,
            v: 0,
            at: unix_ms(),
        }
    }
}

/// When a requester refused `unavailable` during a hand-over is told to ask again.
pub const HANDOVER_RETRY: std::time::Duration = std::time::Duration::from_millis(100);

/// Says, on a refusal `unavailable`, that the resource is being handed over.
pub fn handing_over_hint(info: &mut Map<String, Value>) {
    info.insert(
        "detail".into(),
        Value::String(
            "the resource is being handed over to its successor (an upgrade); bookings are kept; ask again shortly"
                .into(),
        ),
    );
    info.insert(
        schemas::info_key::RETRY_AFTER_MS.into(),
        Value::from(HANDOVER_RETRY.as_millis() as u64),
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::catalog::pick_n_place;

    const INBOX: &str = "holarchy/t/order/o-1/inbox";

    fn manager() -> AgendaManager {
        let mut m = AgendaManager::new(
            HolonId::resource("robot1").unwrap(),
            Arc::new(pick_n_place()),
            3,
        );
        m.handle(AgendaEvent::ExecutionReady);
        m
    }

    fn poses() -> Map<String, Value> {
        json!({"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}})
            .as_object()
            .unwrap()
            .clone()
    }

    fn msg(kind: MessageType, order: &str, conversation: &str) -> Service {
        Service::request(
            kind,
            "pick_n_place",
            conversation,
            HolonId::order(order).unwrap(),
        )
        .with_reply_to(INBOX)
    }

    fn book(order: &str, conversation: &str) -> Service {
        msg(MessageType::BookingReq, order, conversation)
    }

    fn start(order: &str, conversation: &str) -> Service {
        msg(MessageType::Start, order, conversation).with_info(poses())
    }

    fn reply(actions: &[AgendaAction]) -> &Service {
        match actions.first() {
            Some(AgendaAction::Reply(r)) => r,
            other => panic!("expected a reply first, got {other:?}"),
        }
    }

    fn assert_refused(actions: &[AgendaAction], why: &str) {
        let r = reply(actions);
        assert_eq!(r.result, Some(false), "{r:?}");
        assert_eq!(r.reason.as_deref(), Some(why));
        assert_eq!(actions.len(), 1, "a refusal changes nothing: {actions:?}");
    }

    fn assert_accepted(actions: &[AgendaAction]) {
        let r = reply(actions);
        assert_eq!(r.result, Some(true), "{r:?}");
        assert_eq!(r.provider, Some(HolonId::resource("robot1").unwrap()));
    }

    fn done(conversation: &str) -> AgendaEvent {
        AgendaEvent::ExecutionFinished {
            conversation_id: conversation.into(),
            outcome: Outcome::Done {
                results: Map::new(),
            },
        }
    }

    #[test]
    fn starts_in_init_until_execution_is_ready() {
        let mut m = AgendaManager::new(
            HolonId::resource("robot1").unwrap(),
            Arc::new(pick_n_place()),
            3,
        );
        assert_eq!(m.status(), Status::Init);
        assert_refused(
            &m.handle(AgendaEvent::Request(book("o-1", "c1"))),
            "unavailable",
        );
        assert_eq!(
            m.handle(AgendaEvent::ExecutionReady),
            vec![AgendaAction::StateChanged]
        );
        assert_eq!(m.status(), Status::Free);
        assert_eq!(m.handle(AgendaEvent::ExecutionReady), vec![]);
    }

    #[test]
    fn free_empty_to_free_booked_on_booking_request() {
        let mut m = manager();
        let actions = m.handle(AgendaEvent::Request(book("o-1", "c1")));
        assert_accepted(&actions);
        assert_eq!(reply(&actions).info["queue_position"], 1);
        assert_eq!(actions[1], AgendaAction::StateChanged);
        assert_eq!(m.bookings().len(), 1);
        let actions = m.handle(AgendaEvent::Request(book("o-2", "c2")));
        assert_eq!(reply(&actions).info["queue_position"], 2);
        assert_eq!(m.status(), Status::Free);
    }

    #[test]
    fn a_repeated_booking_request_books_once() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        let again = m.handle(AgendaEvent::Request(book("o-1", "c1")));
        assert_accepted(&again);
        assert_eq!(again.len(), 1);
        assert_eq!(m.bookings().len(), 1);
    }

    #[test]
    fn free_booked_to_busy_on_start_from_a_booked_requester() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        let actions = m.handle(AgendaEvent::Request(start("o-2", "c2")));
        assert_accepted(&actions);
        match &actions[1] {
            AgendaAction::Execute(job) => {
                assert_eq!(job.conversation_id, "c2");
                assert_eq!(job.reply_to, INBOX);
                assert_eq!(job.info, poses());
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(actions[2], AgendaAction::StateChanged);
        assert!(matches!(m.status(), Status::Busy(ref j) if j.conversation_id == "c2"));
        assert_eq!(m.bookings().len(), 1, "the started booking left the list");
    }

    fn book_on_turn(order: &str, conversation: &str) -> Service {
        book(order, conversation)
            .with_info(poses())
            .with_start_on_turn()
    }

    fn executed(actions: &[AgendaAction]) -> Vec<String> {
        actions
            .iter()
            .filter_map(|a| match a {
                AgendaAction::Execute(job) => Some(job.conversation_id.clone()),
                _ => None,
            })
            .collect()
    }

    #[test]
    fn a_booking_on_turn_starts_at_once_on_a_free_resource() {
        let mut m = manager();
        let actions = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")));
        assert_accepted(&actions);
        assert!(reply(&actions).started(), "{actions:?}");
        assert_eq!(executed(&actions), ["c1"]);
        assert_eq!(actions.last(), Some(&AgendaAction::StateChanged));
        assert!(
            matches!(m.status(), Status::Busy(ref j) if j.conversation_id == "c1" && j.reply_to == INBOX)
        );
        assert!(m.bookings().is_empty());
        // Asked again (a lost reply): begun, not begun twice.
        let again = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")));
        assert!(reply(&again).started());
        assert_eq!(again.len(), 1, "{again:?}");
        // A start (the order's fallback) finds it running.
        assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1"))));
        // Finished, its result not yet acknowledged: still begun, never run again.
        m.handle(done("c1"));
        let after = m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")));
        assert!(reply(&after).started());
        assert!(executed(&after).is_empty());
        assert!(m.bookings().is_empty());
    }

    #[test]
    fn a_booking_on_turn_waits_for_the_running_job_and_starts_when_it_ends() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")));
        let second = m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")));
        assert_accepted(&second);
        assert!(!reply(&second).started());
        assert_eq!(reply(&second).info["queue_position"], 2);
        let third = m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")));
        assert_eq!(reply(&third).info["queue_position"], 3);
        // The first ends: its result goes out and the next starts, in one transition.
        let actions = m.handle(done("c1"));
        assert!(matches!(actions[0], AgendaAction::Deliver(ref r) if r.conversation_id == "c1"));
        assert_eq!(executed(&actions), ["c2"]);
        assert_eq!(m.bookings().len(), 1);
        // Not while the controller is away; again when it is back.
        m.handle(AgendaEvent::ExecutionUnavailable);
        assert!(executed(&m.handle(done("c2"))).is_empty());
        assert_eq!(m.status(), Status::Init);
        assert_eq!(executed(&m.handle(AgendaEvent::ExecutionReady)), ["c3"]);
    }

    #[test]
    fn a_booking_on_turn_does_not_pass_one_that_waits_for_its_start() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        let actions = m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")));
        assert!(!reply(&actions).started());
        assert!(executed(&actions).is_empty());
        // The booking ahead is cancelled: the one on turn is first, and starts.
        let actions = m.handle(AgendaEvent::Request(msg(
            MessageType::BookingCancel,
            "o-1",
            "c1",
        )));
        assert_accepted(&actions);
        assert_eq!(executed(&actions), ["c2"]);
    }

    #[test]
    fn a_booking_on_turn_without_what_its_start_needs_is_refused() {
        let mut m = manager();
        let no_poses = book("o-1", "c1").with_start_on_turn();
        assert_refused(
            &m.handle(AgendaEvent::Request(no_poses)),
            reason::INVALID_INFO,
        );
        let mut no_reply_to = book_on_turn("o-1", "c1");
        no_reply_to.reply_to = None;
        assert_refused(
            &m.handle(AgendaEvent::Request(no_reply_to)),
            reason::INVALID_INFO,
        );
        assert!(m.bookings().is_empty());
        assert_eq!(m.status(), Status::Free);
    }

    #[test]
    fn a_withdrawing_resource_starts_nothing_on_its_turn() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")));
        m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")));
        m.handle(AgendaEvent::Withdraw);
        assert!(executed(&m.handle(done("c1"))).is_empty());
        assert_eq!(m.status(), Status::Free);
    }

    #[test]
    fn a_resource_may_not_book() {
        let mut m = manager();
        let by_a_resource = Service::request(
            MessageType::BookingReq,
            "pick_n_place",
            "c1",
            HolonId::resource("robot2").unwrap(),
        )
        .with_reply_to(INBOX);
        let actions = m.handle(AgendaEvent::Request(by_a_resource));
        assert_refused(&actions, reason::NOT_A_REQUESTER);
        assert!(m.bookings().is_empty());
    }

    #[test]
    fn start_by_the_last_booked_client_leaves_busy_with_no_bookings() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert!(matches!(m.status(), Status::Busy(_)));
        assert!(m.bookings().is_empty());
    }

    #[test]
    fn start_uses_the_booking_info_when_it_has_none() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1").with_info(poses())));
        let actions = m.handle(AgendaEvent::Request(msg(MessageType::Start, "o-1", "c1")));
        assert!(matches!(&actions[1], AgendaAction::Execute(job) if job.info == poses()));
    }

    #[test]
    fn start_while_busy_is_refused_and_keeps_the_booking() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_refused(&m.handle(AgendaEvent::Request(start("o-2", "c2"))), "busy");
        assert_eq!(m.bookings().len(), 1);
    }

    #[test]
    fn start_without_a_booking_is_refused() {
        let mut m = manager();
        assert_refused(
            &m.handle(AgendaEvent::Request(start("o-1", "c1"))),
            "not_booked",
        );
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        // Another requester, or another conversation of the same requester.
        assert_refused(
            &m.handle(AgendaEvent::Request(start("o-2", "c1"))),
            "not_booked",
        );
        assert_refused(
            &m.handle(AgendaEvent::Request(start("o-1", "c9"))),
            "not_booked",
        );
        // Not booked beats busy: a stranger is told it holds no booking.
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_refused(
            &m.handle(AgendaEvent::Request(start("o-3", "c3"))),
            "not_booked",
        );
    }

    #[test]
    fn start_while_unavailable_is_refused_and_keeps_the_booking() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::ExecutionUnavailable);
        assert_eq!(m.status(), Status::Init);
        assert_refused(
            &m.handle(AgendaEvent::Request(start("o-1", "c1"))),
            "unavailable",
        );
        assert_eq!(m.bookings().len(), 1);
        m.handle(AgendaEvent::ExecutionReady);
        assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1"))));
    }

    #[test]
    fn start_without_what_the_steps_need_is_refused() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        let actions = m.handle(AgendaEvent::Request(msg(MessageType::Start, "o-1", "c1")));
        assert_refused(&actions, "invalid_info");
        assert!(reply(&actions).info["detail"]
            .as_str()
            .unwrap()
            .contains("info.pick"));
        let mut booking_without_reply_to = book("o-2", "c2");
        booking_without_reply_to.reply_to = None;
        m.handle(AgendaEvent::Request(booking_without_reply_to));
        let mut no_reply_to = start("o-2", "c2");
        no_reply_to.reply_to = None;
        assert_refused(&m.handle(AgendaEvent::Request(no_reply_to)), "invalid_info");
        assert_eq!(m.bookings().len(), 2);
        assert_eq!(m.status(), Status::Free);
    }

    #[test]
    fn a_repeated_start_of_the_running_job_is_accepted_without_a_second_execution() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        let again = m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_accepted(&again);
        assert_eq!(again.len(), 1);
    }

    #[test]
    fn unknown_service_types_are_refused() {
        let mut m = manager();
        let mut weld = book("o-1", "c1");
        weld.service_type = "weld".into();
        assert_refused(
            &m.handle(AgendaEvent::Request(weld.clone())),
            "unknown_service",
        );
        weld.message_type = MessageType::Start;
        assert_refused(
            &m.handle(AgendaEvent::Request(weld.clone())),
            "unknown_service",
        );
        weld.message_type = MessageType::ProposalReq;
        let proposal = m.handle(AgendaEvent::Request(weld));
        assert_eq!(reply(&proposal).message_type, MessageType::Proposal);
        assert_eq!(reply(&proposal).reason.as_deref(), Some("unknown_service"));
        assert!(m.bookings().is_empty());
    }

    #[test]
    fn start_for_a_booking_of_another_service_type_is_refused() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        let mut inspect = start("o-1", "c1");
        inspect.service_type = "inspect".into();
        assert_refused(&m.handle(AgendaEvent::Request(inspect)), "not_booked");
    }

    #[test]
    fn booking_cancel_removes_the_booking() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        let actions = m.handle(AgendaEvent::Request(msg(
            MessageType::BookingCancel,
            "o-1",
            "c1",
        )));
        assert_accepted(&actions);
        assert_eq!(actions[1], AgendaAction::StateChanged);
        assert_eq!(m.bookings().len(), 1);
        assert_eq!(m.bookings()[0].conversation_id, "c2");
        // Cancel by the last booked client leaves an empty agenda.
        m.handle(AgendaEvent::Request(msg(
            MessageType::BookingCancel,
            "o-2",
            "c2",
        )));
        assert!(m.bookings().is_empty());
        assert_eq!(m.status(), Status::Free);
    }

    #[test]
    fn booking_cancel_without_a_booking_is_refused() {
        let mut m = manager();
        assert_refused(
            &m.handle(AgendaEvent::Request(msg(
                MessageType::BookingCancel,
                "o-1",
                "c1",
            ))),
            "not_booked",
        );
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        assert_refused(
            &m.handle(AgendaEvent::Request(msg(
                MessageType::BookingCancel,
                "o-2",
                "c1",
            ))),
            "not_booked",
        );
        assert_eq!(m.bookings().len(), 1);
    }

    #[test]
    fn bookings_and_cancels_while_busy_keep_it_busy() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_accepted(&m.handle(AgendaEvent::Request(book("o-2", "c2"))));
        assert!(matches!(m.status(), Status::Busy(_)));
        assert_accepted(&m.handle(AgendaEvent::Request(msg(
            MessageType::BookingCancel,
            "o-2",
            "c2",
        ))));
        assert!(matches!(m.status(), Status::Busy(_)));
        // The running job cannot be booked again.
        assert_refused(&m.handle(AgendaEvent::Request(book("o-1", "c1"))), "busy");
    }

    #[test]
    fn done_from_execution_frees_the_resource_and_delivers_the_result() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        let actions = m.handle(done("c1"));
        let AgendaAction::Deliver(result) = &actions[0] else {
            panic!("{actions:?}")
        };
        assert_eq!(result.message_type, MessageType::Done);
        assert_eq!(result.result, Some(true));
        assert_eq!(result.conversation_id, "c1");
        assert_eq!(result.reply_to.as_deref(), Some(INBOX));
        assert_eq!(result.provider, Some(HolonId::resource("robot1").unwrap()));
        assert_eq!(actions[1], AgendaAction::StateChanged);
        assert_eq!(m.status(), Status::Free);
        assert_eq!(m.bookings().len(), 1, "busy_booked goes to free_booked");
        assert_eq!(m.undelivered().len(), 1);
    }

    #[test]
    fn failed_from_execution_carries_the_reason() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        let actions = m.handle(AgendaEvent::ExecutionFinished {
            conversation_id: "c1".into(),
            outcome: Outcome::Failed {
                reason: reason::CONTROLLER_DISCONNECTED.into(),
                detail: "the connection broke".into(),
            },
        });
        let AgendaAction::Deliver(result) = &actions[0] else {
            panic!("{actions:?}")
        };
        assert_eq!(result.message_type, MessageType::Failed);
        assert_eq!(result.result, Some(false));
        assert_eq!(result.reason.as_deref(), Some("controller_disconnected"));
        assert_eq!(result.info["detail"], "the connection broke");
    }

    #[test]
    fn a_stale_finish_changes_nothing() {
        let mut m = manager();
        assert_eq!(m.handle(done("c1")), vec![]);
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_eq!(m.handle(done("c9")), vec![]);
        assert!(matches!(m.status(), Status::Busy(_)));
    }

    #[test]
    fn unavailable_while_busy_returns_to_init_after_the_job_ends() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        m.handle(AgendaEvent::ExecutionUnavailable);
        assert!(matches!(m.status(), Status::Busy(_)));
        m.handle(done("c1"));
        assert_eq!(m.status(), Status::Init);
    }

    #[test]
    fn acknowledgement_removes_the_undelivered_result() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        m.handle(done("c1"));
        let ack = |c: &str| AgendaEvent::ResultAcknowledged {
            conversation_id: c.into(),
        };
        assert_eq!(m.handle(ack("c9")), vec![]);
        assert_eq!(m.handle(ack("c1")), vec![AgendaAction::StateChanged]);
        assert!(m.undelivered().is_empty());
        assert_eq!(m.handle(ack("c1")), vec![]);
    }

    #[test]
    fn withdraw_hands_every_booking_back_and_lets_the_running_job_finish() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        let mut silent = book("o-3", "c3");
        silent.reply_to = None;
        m.handle(AgendaEvent::Request(silent));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        let actions = m.handle(AgendaEvent::Withdraw);
        let handed_back: Vec<&Service> = actions
            .iter()
            .filter_map(|a| match a {
                AgendaAction::Deliver(s) => Some(s),
                _ => None,
            })
            .collect();
        assert_eq!(
            handed_back.len(),
            1,
            "only bookings with a reply_to can be told"
        );
        assert_eq!(handed_back[0].conversation_id, "c2");
        assert_eq!(handed_back[0].message_type, MessageType::Failed);
        assert_eq!(handed_back[0].reason.as_deref(), Some("withdrawn"));
        assert!(m.bookings().is_empty());
        assert!(
            !m.is_drained(),
            "the running job and the hand-back are pending"
        );
        assert_eq!(m.handle(AgendaEvent::Withdraw), vec![]);
        // No new work.
        assert_refused(
            &m.handle(AgendaEvent::Request(book("o-4", "c4"))),
            "unavailable",
        );
        let mut proposal = book("o-4", "p");
        proposal.message_type = MessageType::ProposalReq;
        assert_eq!(
            reply(&m.handle(AgendaEvent::Request(proposal)))
                .reason
                .as_deref(),
            Some("unavailable")
        );
        // The running job finishes and is delivered.
        m.handle(done("c1"));
        for c in ["c1", "c2"] {
            m.handle(AgendaEvent::ResultAcknowledged {
                conversation_id: c.into(),
            });
        }
        assert!(m.is_drained());
    }

    #[test]
    fn a_start_of_a_finished_job_whose_result_is_undelivered_is_accepted_again() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        m.handle(done("c1"));
        let again = m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_accepted(&again);
        assert_eq!(again.len(), 1, "no second execution");
        m.handle(AgendaEvent::ResultAcknowledged {
            conversation_id: "c1".into(),
        });
        assert_refused(
            &m.handle(AgendaEvent::Request(start("o-1", "c1"))),
            "not_booked",
        );
    }

    /// The agenda of a busy resource with two bookings on turn behind the running job,
    /// journalled and restored as `inheritance` says, its controller ready again: the
    /// restored agenda and the jobs that started.
    fn restored_with_bookings_on_turn(inheritance: Inheritance) -> (AgendaManager, Vec<String>) {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book_on_turn("o-1", "c1")));
        m.handle(AgendaEvent::Request(book_on_turn("o-2", "c2")));
        m.handle(AgendaEvent::Request(book_on_turn("o-3", "c3")));
        let json = serde_json::to_string(&m.record()).unwrap();
        let mut restored = AgendaManager::restore(
            HolonId::resource("robot1").unwrap(),
            Arc::new(pick_n_place()),
            3,
            serde_json::from_str(&json).unwrap(),
            inheritance,
        );
        let started = executed(&restored.handle(AgendaEvent::ExecutionReady));
        (restored, started)
    }

    #[test]
    fn bookings_handed_over_start_on_their_turn_in_the_successor() {
        let (_, started) = restored_with_bookings_on_turn(Inheritance::HandedOver);
        assert_eq!(started, ["c2"]);
    }

    #[test]
    fn after_a_restart_a_booking_on_turn_waits_for_its_requesters_start() {
        let (mut m, started) = restored_with_bookings_on_turn(Inheritance::Restarted);
        assert!(started.is_empty(), "{started:?}");
        assert_eq!(m.state(), ResourceState::Free);
        // Its order gave up on it while the resource was away: the cancel is taken.
        let cancel = msg(MessageType::BookingCancel, "o-2", "c2");
        let actions = m.handle(AgendaEvent::Request(cancel));
        assert_accepted(&actions);
        assert!(executed(&actions).is_empty(), "{actions:?}");
        // The other order still holds its booking and asks to start.
        let actions = m.handle(AgendaEvent::Request(start("o-3", "c3")));
        assert_accepted(&actions);
        assert_eq!(executed(&actions), ["c3"]);
    }

    #[test]
    fn restore_reports_the_interrupted_job_and_redelivers_results() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        m.handle(AgendaEvent::Request(book("o-3", "c3")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        m.handle(done("c1"));
        m.handle(AgendaEvent::Request(start("o-2", "c2")));
        let record = m.record();
        let json = serde_json::to_string(&record).unwrap();
        let record: AgendaRecord = serde_json::from_str(&json).unwrap();
        let restored = AgendaManager::restore(
            HolonId::resource("robot1").unwrap(),
            Arc::new(pick_n_place()),
            3,
            record,
            Inheritance::Restarted,
        );
        assert_eq!(restored.bookings().len(), 1);
        assert_eq!(restored.bookings()[0].conversation_id, "c3");
        assert_eq!(
            restored.status(),
            Status::Init,
            "no job runs after a restart"
        );
        let delivered: Vec<(&str, MessageType, Option<&str>)> = restored
            .undelivered()
            .iter()
            .map(|s| {
                (
                    s.conversation_id.as_str(),
                    s.message_type,
                    s.reason.as_deref(),
                )
            })
            .collect();
        assert_eq!(
            delivered,
            vec![
                ("c1", MessageType::Done, None),
                ("c2", MessageType::Failed, Some("interrupted"))
            ]
        );
    }

    #[test]
    fn the_agenda_has_a_capacity() {
        let mut m = manager();
        for i in 0..3 {
            assert_accepted(&m.handle(AgendaEvent::Request(book("o-1", &format!("c{i}")))));
        }
        assert_refused(
            &m.handle(AgendaEvent::Request(book("o-1", "c3"))),
            "agenda_full",
        );
        let mut proposal = book("o-2", "p");
        proposal.message_type = MessageType::ProposalReq;
        let actions = m.handle(AgendaEvent::Request(proposal));
        assert_eq!(reply(&actions).reason.as_deref(), Some("agenda_full"));
    }

    #[test]
    fn proposals_report_the_expected_wait() {
        let mut m = manager();
        let mut proposal = book("o-9", "p1");
        proposal.message_type = MessageType::ProposalReq;
        let actions = m.handle(AgendaEvent::Request(proposal.clone()));
        let r = reply(&actions);
        assert_eq!(r.message_type, MessageType::Proposal);
        assert_eq!(r.result, Some(true));
        assert_eq!(r.info["expected_wait_ms"], 0);
        assert_eq!(r.info["state"], "free");
        assert_eq!(actions.len(), 1, "a proposal books nothing");
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-2", "c2")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        let actions = m.handle(AgendaEvent::Request(proposal.clone()));
        assert_eq!(reply(&actions).info["expected_wait_ms"], 2000);
        assert_eq!(reply(&actions).info["queue_position"], 2);
        m.handle(AgendaEvent::ExecutionUnavailable);
        let actions = m.handle(AgendaEvent::Request(proposal));
        assert_eq!(reply(&actions).reason.as_deref(), Some("unavailable"));
    }

    /// A ready agenda of room for 16 bookings, running `c0` so the others wait.
    fn busy_manager(max_overtakes: u32) -> AgendaManager {
        let mut m = AgendaManager::new(
            HolonId::resource("robot1").unwrap(),
            Arc::new(pick_n_place()),
            16,
        )
        .with_max_overtakes(max_overtakes);
        m.handle(AgendaEvent::ExecutionReady);
        m.handle(AgendaEvent::Request(book("o-0", "c0")));
        assert_accepted(&m.handle(AgendaEvent::Request(start("o-0", "c0"))));
        m
    }

    fn urgent(order: &str, conversation: &str, priority: i32) -> Service {
        book(order, conversation).with_urgency(priority, None)
    }

    fn waiting(m: &AgendaManager) -> Vec<(&str, i32, u32)> {
        m.bookings()
            .iter()
            .map(|b| (b.conversation_id.as_str(), b.priority, b.overtaken))
            .collect()
    }

    #[test]
    fn bookings_wait_by_priority_then_in_the_order_they_came() {
        let mut m = busy_manager(4);
        m.handle(AgendaEvent::Request(urgent("o-1", "c1", 0)));
        m.handle(AgendaEvent::Request(urgent("o-2", "c2", 0)));
        let rush = m.handle(AgendaEvent::Request(urgent("o-3", "c3", 100)));
        assert_accepted(&rush);
        assert_eq!(
            reply(&rush).info["queue_position"],
            2,
            "behind the running job only"
        );
        m.handle(AgendaEvent::Request(urgent("o-4", "c4", 100)));
        m.handle(AgendaEvent::Request(urgent("o-5", "c5", 50)));
        m.handle(AgendaEvent::Request(urgent("o-6", "c6", -5)));
        assert_eq!(
            waiting(&m),
            vec![
                ("c3", 100, 0),
                ("c4", 100, 0),
                ("c5", 50, 0),
                ("c1", 0, 3),
                ("c2", 0, 3),
                ("c6", -5, 0)
            ]
        );
        // A proposal says where a booking of its priority would stand: a rush order
        // waits for the running job and the two rush bookings only.
        let mut ask = urgent("o-9", "p1", 100);
        ask.message_type = MessageType::ProposalReq;
        let r = m.handle(AgendaEvent::Request(ask.clone()));
        assert_eq!(reply(&r).info["queue_position"], 3);
        assert_eq!(reply(&r).info["expected_wait_ms"], 3000);
        ask.info.remove(schemas::info_key::PRIORITY);
        let r = m.handle(AgendaEvent::Request(ask));
        assert_eq!(
            reply(&r).info["queue_position"],
            6,
            "priority 0 waits behind c2"
        );
        // The snapshot shows each booking's priority and how often it was passed.
        let view = m.snapshot();
        assert_eq!(view.agenda[3].priority, 0);
        assert_eq!(view.agenda[3].overtaken, 3);
        assert_eq!(view.agenda[0].priority, 100);
    }

    #[test]
    fn a_waiting_booking_is_passed_at_most_max_overtakes_times() {
        let mut m = busy_manager(2);
        m.handle(AgendaEvent::Request(urgent("o-1", "c1", 0)));
        for (order, conversation) in [("o-2", "c2"), ("o-3", "c3"), ("o-4", "c4")] {
            m.handle(AgendaEvent::Request(urgent(order, conversation, 10)));
        }
        // c2 and c3 passed c1; c4 may not (c1 was passed twice), nor can anything later.
        assert_eq!(
            waiting(&m),
            vec![("c2", 10, 0), ("c3", 10, 0), ("c1", 0, 2), ("c4", 10, 0)]
        );
        m.handle(AgendaEvent::Request(urgent("o-5", "c5", 1000)));
        assert_eq!(
            waiting(&m)[2..],
            [("c1", 0, 2), ("c5", 1000, 0), ("c4", 10, 1)],
            "the bound holds for every priority"
        );
        // With no overtakes allowed, bookings wait in the order they came.
        let mut fifo = busy_manager(0);
        fifo.handle(AgendaEvent::Request(urgent("o-1", "c1", -1000)));
        fifo.handle(AgendaEvent::Request(urgent("o-2", "c2", 1000)));
        assert_eq!(waiting(&fifo), vec![("c1", -1000, 0), ("c2", 1000, 0)]);
    }

    #[test]
    fn a_priority_or_due_time_that_is_not_one_is_refused_and_changes_nothing() {
        let mut m = busy_manager(4);
        for (key, bad) in [
            (schemas::info_key::PRIORITY, json!("high")),
            (schemas::info_key::PRIORITY, json!(1001)),
            (schemas::info_key::PRIORITY, json!(1.5)),
            (schemas::info_key::DUE, json!(-1)),
            (schemas::info_key::DUE, json!("tomorrow")),
        ] {
            let mut request = book("o-1", "c1");
            request.info.insert(key.into(), bad.clone());
            let actions = m.handle(AgendaEvent::Request(request.clone()));
            assert_refused(&actions, "invalid_info");
            let detail = reply(&actions).info["detail"].as_str().unwrap().to_string();
            assert!(detail.contains(key), "{bad}: {detail}");
            if key == schemas::info_key::PRIORITY {
                request.message_type = MessageType::ProposalReq;
                assert_refused(&m.handle(AgendaEvent::Request(request)), "invalid_info");
            }
        }
        assert!(m.bookings().is_empty());
        let ok = m.handle(AgendaEvent::Request(
            book("o-1", "c1").with_urgency(-1000, Some(1_700_000_000_000)),
        ));
        assert_accepted(&ok);
        assert_eq!(m.bookings()[0].due, Some(1_700_000_000_000));
    }

    #[test]
    fn a_booking_journalled_before_priorities_reads_as_priority_zero() {
        let old = json!({"requester": "order/o-1", "conversation_id": "c1",
            "service_type": "pick_n_place", "reply_to": INBOX, "info": {}});
        let booking: Booking = serde_json::from_value(old).unwrap();
        assert_eq!(
            (booking.priority, booking.due, booking.overtaken),
            (0, None, 0)
        );
    }

    #[test]
    fn a_requester_gone_for_good_loses_its_bookings_not_its_running_job() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(book("o-1", "c2")));
        m.handle(AgendaEvent::Request(book("o-2", "c3")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        let actions = m.handle(AgendaEvent::RequesterGone {
            requester: HolonId::order("o-1").unwrap(),
        });
        assert_eq!(actions, vec![AgendaAction::StateChanged]);
        let left: Vec<_> = m
            .bookings()
            .iter()
            .map(|b| b.conversation_id.as_str())
            .collect();
        assert_eq!(left, vec!["c3"], "o-2's booking stays");
        assert_eq!(m.current().map(|j| j.conversation_id.as_str()), Some("c1"));
        let again = m.handle(AgendaEvent::RequesterGone {
            requester: HolonId::order("o-1").unwrap(),
        });
        assert!(again.is_empty(), "nothing left to release: {again:?}");
    }

    fn proposal_req(order: &str, service_type: &str) -> Service {
        Service::request(
            MessageType::ProposalReq,
            service_type,
            "c0",
            HolonId::order(order).unwrap(),
        )
    }

    #[test]
    fn proposal_refusals_come_in_the_tables_order() {
        let mut m = AgendaManager::new(
            HolonId::resource("robot1").unwrap(),
            Arc::new(pick_n_place()),
            1,
        );
        // Not offered beats unavailable.
        let r = m.handle(AgendaEvent::Request(proposal_req("o-1", "weld")));
        assert_eq!(reply(&r).reason.as_deref(), Some("unknown_service"));
        let r = m.handle(AgendaEvent::Request(proposal_req("o-1", "pick_n_place")));
        assert_eq!(reply(&r).reason.as_deref(), Some("unavailable"));
        m.handle(AgendaEvent::ExecutionReady);
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        let r = m.handle(AgendaEvent::Request(proposal_req("o-2", "pick_n_place")));
        assert_eq!(reply(&r).reason.as_deref(), Some("agenda_full"));
        assert_eq!(reply(&r).message_type, MessageType::Proposal);
        // A proposal changes nothing.
        assert_eq!(r.len(), 1);
    }

    #[test]
    fn a_booking_request_for_the_running_conversation_is_refused_busy() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        m.handle(AgendaEvent::Request(start("o-1", "c1")));
        assert_refused(&m.handle(AgendaEvent::Request(book("o-1", "c1"))), "busy");
    }

    #[test]
    fn a_repeated_withdraw_and_an_unknown_acknowledgement_change_nothing() {
        let mut m = manager();
        m.handle(AgendaEvent::Request(book("o-1", "c1")));
        assert!(!m.handle(AgendaEvent::Withdraw).is_empty());
        assert_eq!(m.handle(AgendaEvent::Withdraw), vec![]);
        assert_eq!(
            m.handle(AgendaEvent::ResultAcknowledged {
                conversation_id: "nobody".into()
            }),
            vec![]
        );
        assert_eq!(
            m.handle(AgendaEvent::RequesterGone {
                requester: HolonId::order("o-9").unwrap()
            }),
            vec![]
        );
    }

    #[test]
    fn requests_that_are_not_for_the_agenda_are_refused() {
        let mut m = manager();
        for kind in [
            MessageType::Status,
            MessageType::Done,
            MessageType::Proposal,
        ] {
            assert_refused(
                &m.handle(AgendaEvent::Request(msg(kind, "o-1", "c1"))),
                "unknown_service",
            );
        }
    }
}

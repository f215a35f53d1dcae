//! The agenda machine ([`AgendaMachine`]): the seed's Figure 4 (the Agenda Manager's
//! decisions) as a pure state machine, owned by the agenda manager component
//! ([`crate::component::agenda_manager`]).
//!
//! Its state is the execution status (`init`, `free`, `busy`), the bookings in the order
//! they were made, the results not yet acknowledged, and whether the holon is
//! withdrawing. The status is `init` until the execution component reports `ready` (the
//! controller is connected and ready), `busy` while a job runs, `free` otherwise; it
//! goes back to `init` when the execution component reports the controller unavailable.
//! A booking (and its job) is identified by its requester and `conversation_id`.
//!
//! A controller that runs several jobs at once (`[controller] jobs_at_once`, a conveyor
//! moving several pallets) runs that many: `busy` then means every one of them runs,
//! and `free` that another may begin beside those running; "the running job" in the
//! rows below reads "a running job", each ending on its own, and the last row begins
//! as many bookings as there is room for. With one (the default) it is the seed's
//! agenda.
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
//! | PackML command (`resource/<name>/packml`) | the unit refuses it ([`crate::machine::packml`]) | the refusal, naming the state | same |
//! | | Hold | accepted; bookings kept, the running job finishes | Holding, then Held |
//! | | Stop | accepted; every booking with a `reply_to` gets `failed` `withdrawn`; the running job finishes | Stopping, then Stopped |
//! | | Abort | accepted; bookings handed back as for Stop; the execution aborts the running job | Aborting, then Aborted |
//! | | another command, a mode change | accepted | as the unit says |
//! | execution unavailable with `fault` / `estop` | not Aborting, Aborted, Clearing | bookings handed back as for Stop | `init`, Aborted |
//! | tick (each second while Held with bookings) | Held for `held_bookings_ms` | bookings handed back as for Stop | same − bookings |
//! | after any event | `free`, not withdrawing or handing over, in PackML Execute and Production, and the first booking asked to start on its turn | the booking becomes the job, execution starts | `busy` |
//!
//! "Withdrawing" in the rows above reads "withdrawing or handing over, or out of PackML
//! Execute and Production": none takes new work or starts anything (a refusal out of
//! Execute names the PackML state in `info.detail` and `info.packml_state`). A refusal `unavailable` while handing over says so in
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
    ControllerStatus, HolonId, PackmlReply, PackmlRequest, PackmlState, Reason, ResourceState,
    Service, UnitMode,
};
use serde_json::{Map, Value};

use crate::catalog::{Parameters, ServiceCatalog};
use crate::machine::packml::PackmlUnit;

mod carriers;
mod jobs;
mod leaving;
mod packml;
mod places;
mod queue;
mod record;
mod requests;
mod snapshot;
mod travel;

pub use carriers::Carriers;
pub use packml::{packml_hint, PackmlSettings};
pub use places::{PlaceHold, Places};
pub use record::{AgendaRecord, AgendaRecordRef};

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
    /// Its `info` as the steps use it, read when booked (or the journal opened; not
    /// journalled); `None` when it does not fit the steps (a `start` is to bring one).
    #[serde(skip)]
    pub parameters: Option<Arc<Parameters>>,
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
    /// The highest epoch of its order-node it was asked at ([`schemas::info_key::EPOCH`],
    /// an order-node on etcd): a request of a lower one is refused `stale_epoch`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub requester_epoch: Option<u64>,
}

/// A booking being executed.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Job {
    pub requester: HolonId,
    pub conversation_id: String,
    pub service_type: String,
    /// Where `done` / `failed` goes (empty for an operator's job).
    pub reply_to: String,
    pub info: Map<String, Value>,
    /// Its `info` as the steps use it, read when it was booked or started (the execution
    /// reads it from `info` only for a job that lacks it). Not journalled.
    #[serde(skip)]
    pub parameters: Option<Arc<Parameters>>,
    /// An operator's single job in Maintenance mode: who asked. Its result goes to no
    /// inbox; it is kept in the PackML figures (`packml.operator_job`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub operator: Option<String>,
}

/// How an execution ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Every step completed; `results` maps each action to the controller's result.
    Done { results: Map<String, Value> },
    /// A step failed; `reason` says why in the cell's words, `detail` is for people.
    Failed { reason: Reason, detail: String },
    /// The controller has a newer holder (a fenced resource deposed mid-job): this
    /// holder says nothing of the job; the new holder's word and the controller's
    /// record of its steps count.
    Deposed { detail: String },
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
            Outcome::Deposed { detail } => write!(f, "deposed: {detail}"),
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
    /// Execution cannot run services: the controller is away (`disconnected`), in
    /// `fault` or `estop`; with what the controller said of it, if anything.
    ExecutionUnavailable(ControllerStatus, Option<String>),
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
    /// A fenced resource was deposed (a newer holder has its controller): take no new
    /// work, start nothing, drop every booking without a word. The new holder's agenda
    /// is the truth: an order that booked with it again must not hear that its booking
    /// went; one that did not is refused `not_booked` when it asks to start.
    Deposed,
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
    /// An operator's PackML command or unit mode change (`resource/<name>/packml`).
    Packml(PackmlRequest),
    /// An operator's word on a conveyor's carrier (`resource/<name>/carriers`): taken
    /// out of service or put back ([`carriers`]); `by` is who says it.
    CarrierWord {
        word: schemas::CarrierWord,
        by: String,
    },
    /// A second has passed: bookings held too long are handed back.
    Tick,
    /// The cell's layout as it stands (a transporter's: it times its moves by it and
    /// refuses those it cannot make, [`travel`]).
    Layout(Arc<schemas::layout::CellLayout>),
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
    /// Answer the PackML request being handled.
    PackmlReply(PackmlReply),
    /// Answer the word on a carrier being handled, or refuse it with why.
    CarrierAnswer(Result<schemas::CarrierReply, (schemas::ErrorCode, String)>),
    /// Have the execution component abort the running step (PackML Abort): the
    /// controller is told to stop now.
    Abort,
    /// The state changed: publish a snapshot.
    StateChanged,
}

/// The execution status in Figure 4 (plus `init`).
#[derive(Debug, Clone, PartialEq)]
pub enum Status {
    Init,
    Free,
    Busy(Job),
}

/// The Agenda Manager's state.
#[derive(Debug, Clone)]
pub struct AgendaMachine {
    holon: HolonId,
    catalog: Arc<ServiceCatalog>,
    capacity: usize,
    /// How many later bookings of higher priority may go ahead of a waiting one.
    max_overtakes: u32,
    execution_ready: bool,
    /// The jobs executing, in the order they began (at most `jobs_at_once`).
    running: Vec<Job>,
    /// How many jobs its controller runs at once (`[controller] jobs_at_once`): 1, or
    /// a transporter's moves at once.
    jobs_at_once: usize,
    bookings: Vec<Booking>,
    /// `done` / `failed` not yet acknowledged, oldest first.
    undelivered: Vec<Service>,
    /// Shutting down: no new bookings or starts.
    withdrawing: bool,
    /// Being handed over to a successor process: no new bookings or starts, bookings kept.
    handing_over: bool,
    /// The PackML unit: orders' work is taken only in Execute and Production.
    packml: PackmlUnit,
    /// Whether `packml` came from the journal (else the settings' initial state applies).
    packml_restored: bool,
    /// How long bookings wait on a Held resource ([`PackmlSettings::held_bookings_ms`]).
    held_bookings_ms: u64,
    /// The controller as the execution last reported it.
    controller: ControllerStatus,
    /// The cell's layout, as last heard (transporters only; None until then).
    layout: Option<Arc<schemas::layout::CellLayout>>,
    /// Its own locations and the places held at them ([`places`]).
    places: Places,
    /// A conveyor's carriers and those out of service ([`carriers`]).
    carriers: Carriers,
}

impl AgendaMachine {
    /// An empty agenda, its PackML unit in Execute and Production since `now` (Unix ms).
    pub fn new(holon: HolonId, catalog: Arc<ServiceCatalog>, capacity: usize, now: u64) -> Self {
        AgendaMachine {
            holon,
            catalog,
            capacity,
            max_overtakes: DEFAULT_MAX_OVERTAKES,
            execution_ready: false,
            running: Vec::new(),
            jobs_at_once: 1,
            bookings: Vec::new(),
            undelivered: Vec::new(),
            withdrawing: false,
            handing_over: false,
            packml: PackmlUnit::new(PackmlState::Execute, UnitMode::Production, now),
            packml_restored: false,
            held_bookings_ms: PackmlSettings::default().held_bookings_ms,
            controller: ControllerStatus::Disconnected,
            layout: None,
            places: Places::default(),
            carriers: Carriers::default(),
        }
    }

    /// The same agenda, holding places at the locations of `part` (the resource's own
    /// part of the layout); those the journal had held stay held.
    pub fn with_locations(mut self, part: Option<&schemas::layout::LayoutPart>) -> Self {
        let held = std::mem::take(&mut self.places.held);
        self.places = Places::of(part);
        self.places.restore(held);
        let pallets = match part.and_then(|p| p.transporter.as_ref()) {
            Some(schemas::layout::TransporterSpec::Conveyor(c)) => c.pallets,
            _ => 0,
        };
        let out = std::mem::take(&mut self.carriers.out);
        self.carriers = Carriers::new(pallets, out);
        self
    }

    /// The places held at its locations.
    pub fn places(&self) -> &Places {
        &self.places
    }

    /// Its carriers, if it is a conveyor, and those out of service.
    pub fn carriers(&self) -> &Carriers {
        &self.carriers
    }

    /// The same agenda with the holon's PackML settings: a unit restored from the
    /// journal keeps its state and mode; a new one starts as the settings say (since
    /// the agenda was made).
    pub fn with_packml(mut self, settings: PackmlSettings) -> Self {
        self.held_bookings_ms = settings.held_bookings_ms;
        if !self.packml_restored {
            let since = self.packml.since();
            self.packml = PackmlUnit::new(settings.initial_state, settings.initial_mode, since);
        }
        self
    }

    /// The PackML unit.
    pub fn packml(&self) -> &PackmlUnit {
        &self.packml
    }

    /// Whether it takes orders' work now: the controller ready, not leaving, and in
    /// PackML Execute and Production.
    pub fn takes_work(&self) -> bool {
        self.execution_ready && !self.leaving() && self.packml.takes_orders()
    }

    /// The same agenda, running up to `jobs_at_once` jobs at once (at least one).
    pub fn with_jobs_at_once(mut self, jobs_at_once: usize) -> Self {
        self.jobs_at_once = jobs_at_once.max(1);
        self
    }

    /// The same agenda, letting at most `max_overtakes` later bookings of higher
    /// priority go ahead of a waiting one (0: first come, first served).
    pub fn with_max_overtakes(mut self, max_overtakes: u32) -> Self {
        self.max_overtakes = max_overtakes;
        self
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
        now: u64,
    ) -> AgendaMachine {
        let mut manager = AgendaMachine::new(holon, catalog, capacity, now);
        manager.bookings = record.bookings;
        for booking in &mut manager.bookings {
            booking.parameters = manager
                .catalog
                .parameters(&booking.service_type, &booking.info)
                .ok()
                .map(Arc::new);
        }
        if inheritance == Inheritance::Restarted {
            for booking in &mut manager.bookings {
                booking.start_on_turn = false;
            }
        }
        manager.undelivered = record.undelivered;
        manager.places.restore(record.places);
        manager.carriers.out = record.carriers_out;
        if let Some(unit) = record.packml {
            manager.packml = unit.restored();
            manager.packml_restored = true;
        }
        for job in record.current.into_iter().chain(record.more_running) {
            if job.operator.is_some() {
                manager.packml.operator_job_ended(
                    &job.conversation_id,
                    "failed interrupted: the resource holon stopped while the job ran".into(),
                    false,
                );
                continue;
            }
            let message = manager.result_message(
                job,
                Outcome::Failed {
                    reason: Reason::Interrupted,
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
        self.withdrawing && self.running.is_empty() && self.undelivered.is_empty()
    }

    /// Whether another job may begin beside those running (with one job at once:
    /// whether none runs).
    fn has_room(&self) -> bool {
        self.running.len() < self.jobs_at_once
    }

    /// The status, with the first job begun when it is `busy`.
    pub fn status(&self) -> Status {
        match (self.state(), self.running.first()) {
            (ResourceState::Busy, Some(job)) => Status::Busy(job.clone()),
            (ResourceState::Free, _) => Status::Free,
            (ResourceState::Init | ResourceState::Busy, _) => Status::Init,
        }
    }

    /// The status as the snapshot shows it: `busy` while no other job can begin
    /// (every job it runs at once runs), `free` while one can, `init` while the
    /// controller is not ready and nothing runs.
    pub fn state(&self) -> ResourceState {
        match (self.running.is_empty(), self.execution_ready) {
            (false, _) if !self.has_room() => ResourceState::Busy,
            (_, true) => ResourceState::Free,
            (false, false) => ResourceState::Busy,
            (true, false) => ResourceState::Init,
        }
    }

    pub fn bookings(&self) -> &[Booking] {
        &self.bookings
    }

    pub fn undelivered(&self) -> &[Service] {
        &self.undelivered
    }

    /// The job executing (the first begun, when several run).
    pub fn current(&self) -> Option<&Job> {
        self.running.first()
    }

    /// The jobs executing, in the order they began.
    pub fn running(&self) -> &[Job] {
        &self.running
    }

    /// The seed's FSM: one event in, at `now` (Unix ms), the actions out. No I/O, no
    /// clock: the time is the event's.
    pub fn handle(&mut self, event: AgendaEvent, now: u64) -> Vec<AgendaAction> {
        let mut actions = self.transition(event, now);
        actions.extend(self.settle(now));
        actions.extend(self.turn());
        actions
    }

    /// The machine without its last row: no booking starts on its turn. For an event
    /// that must be kept while the journal cannot record a job's start (the booking then
    /// waits; its requester's `start` is refused until the journal can be written).
    pub fn handle_holding_turns(&mut self, event: AgendaEvent, now: u64) -> Vec<AgendaAction> {
        let mut actions = self.transition(event, now);
        actions.extend(self.settle(now));
        actions
    }

    /// The PackML row "after every event": an acting state whose work is done moves on.
    fn settle(&mut self, now: u64) -> Vec<AgendaAction> {
        if self
            .packml
            .settle(!self.running.is_empty(), self.controller, now)
        {
            vec![AgendaAction::StateChanged]
        } else {
            vec![]
        }
    }

    /// The last row of the table, as actions: as many bookings begin as there is room
    /// for.
    fn turn(&mut self) -> Vec<AgendaAction> {
        let mut actions = Vec::new();
        while let Some(job) = self.start_on_turn() {
            actions.push(AgendaAction::Execute(job));
            actions.push(AgendaAction::StateChanged);
        }
        actions
    }

    /// The row of the table for `event`.
    fn transition(&mut self, event: AgendaEvent, now: u64) -> Vec<AgendaAction> {
        match event {
            AgendaEvent::Request(request) => self.request(request, now),
            AgendaEvent::ExecutionReady => self.controller_now(ControllerStatus::Ready, None, now),
            AgendaEvent::ExecutionUnavailable(status, said) => {
                self.controller_now(status, said.as_deref(), now)
            }
            AgendaEvent::Packml(request) => self.packml_request(request, now),
            AgendaEvent::CarrierWord { word, by } => self.carrier_word(&word, &by),
            AgendaEvent::Tick => self.tick(now),
            AgendaEvent::Layout(layout) => {
                self.layout = Some(layout);
                vec![]
            }
            AgendaEvent::ExecutionFinished {
                conversation_id,
                outcome,
            } => self.finished(&conversation_id, outcome),
            AgendaEvent::Withdraw => self.withdraw(),
            AgendaEvent::Deposed => self.deposed(),
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
}

/// When a requester refused `unavailable` during a hand-over is told to ask again.
pub use holon::life::HANDOVER_RETRY;

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
mod tests;

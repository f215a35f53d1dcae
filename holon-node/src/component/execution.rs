//! The execution component: the one owner of the execution state machine
//! ([`crate::machine::execution`]) and, through the interfacing module, of the controller
//! connection.
//!
//! Its task runs the controller client ([`interfacing::serve`]) with itself as the
//! client's owner ([`Driver`]): jobs and aborts from the agenda manager's side come
//! from its mailbox when the client asks for its next request, and what the controller
//! does is handed to it as the client's events. Each event goes through the machine;
//! its actions are carried out at once: commands go back to the client (a
//! [`ControllerRequest::Step`] with its step id, for a fenced resource), `ready`,
//! `unavailable` and finished jobs to the agenda manager; after every event it
//! republishes its view (the controller and the step in progress) when that changed.
//!
//! A move's `departed` (the controller said the move has left its origin) goes to the
//! job's requester once, from a task of its own bounded by the delivery's attempt
//! timeout: the controller's events never wait on the requester; one that is not
//! acknowledged is only logged (the requester releases the origin at `done` instead).
//!
//! A command and its reply cross no queue between tasks. It waits for room in the
//! agenda manager's mailbox (the agenda manager never waits on it): no cycle of waits.

use std::collections::VecDeque;
use std::sync::Arc;

use holon::ChildError;
use robot_bridge::client::{ControllerEvent, ControllerRequest, Owner, StepId};
use schemas::{HolonId, MessageType, Service};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::component::agenda_manager::{courier, AgendaMessage};
use crate::component::interfacing;
use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};
use crate::machine::agenda::AgendaEvent;
use crate::machine::delivery::AttemptOutcome;
use crate::machine::execution::lanes::Executions;
use crate::machine::execution::{ExecutionAction, ExecutionEvent, ExecutionRequest};
use crate::views::{ExecutionView, RunningView, Views};

/// What the execution component is linked to.
pub struct Links {
    pub holon: HolonId,
    /// The state machines it owns: one per job its controller runs at once.
    pub execution: Handover<Executions>,
    /// Jobs (and aborts) from the agenda manager.
    pub jobs: Mailbox<ExecutionRequest>,
    /// The controller connection it runs.
    pub interfacing: interfacing::Links,
    /// The agenda manager's mailbox.
    pub agenda: mpsc::Sender<AgendaMessage>,
    /// Where it publishes its view.
    pub views: Arc<Views>,
    /// Its faults (and the interfacing module's) to inject on request.
    pub faults: Arc<Faults>,
    /// Where a move's `departed` is sent from.
    pub session: zenoh::Session,
    /// How long a `departed` waits for its acknowledgement (the results' attempt
    /// timeout, `[delivery] attempt_timeout_ms`).
    pub departed_timeout: std::time::Duration,
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let mut execution = links.execution.take().await;
    let mut jobs = links.jobs.take().await;
    let mut driver = Driver {
        links: &links,
        execution: &mut execution,
        jobs: &mut jobs,
        commands: VecDeque::new(),
        to_agenda: VecDeque::new(),
        failure: None,
    };
    driver.publish();
    tokio::select! {
        _ = interfacing::serve(&links.interfacing, &mut driver, token.clone()) => {}
        _ = links.faults.execution.notified() => panic!("fault injection: execution crashed"),
        _ = links.faults.interfacing.notified() => panic!("fault injection: interfacing crashed"),
    }
    match driver.failure {
        Some(failure) => Err(failure),
        None if token.is_cancelled() => Ok(()),
        None => Err("the controller client stopped".into()),
    }
}

/// The execution as the controller client's owner: the machine, its mailbox, and what
/// its actions left to do.
struct Driver<'a> {
    links: &'a Links,
    execution: &'a mut Executions,
    jobs: &'a mut mpsc::Receiver<ExecutionRequest>,
    /// Requests for the controller client, oldest first (at most a step's command per
    /// lane and an abort).
    commands: VecDeque<ControllerRequest>,
    /// Events for the agenda manager, oldest first.
    to_agenda: VecDeque<AgendaEvent>,
    /// Why the component fails, once it must (the client then stops).
    failure: Option<ChildError>,
}

impl Owner for Driver<'_> {
    /// A command the machine gave, else the next job (cancel-safe: a job taken from the
    /// mailbox is handled before the next await).
    async fn request(&mut self) -> Option<ControllerRequest> {
        loop {
            if self.failure.is_some() {
                return None;
            }
            if let Some(request) = self.commands.pop_front() {
                return Some(request);
            }
            if !self.tell_agenda().await {
                return None;
            }
            let event = match self.jobs.recv().await {
                Some(ExecutionRequest::Start(job)) => ExecutionEvent::Start(job),
                Some(ExecutionRequest::Abort) => ExecutionEvent::Abort,
                None => {
                    self.failure = Some("execution mailbox closed".into());
                    return None;
                }
            };
            self.handle(event);
        }
    }

    async fn report(&mut self, event: ControllerEvent) -> bool {
        self.handle(ExecutionEvent::Controller(event));
        self.tell_agenda().await
    }
}

impl Driver<'_> {
    /// One event through the machine; its actions are queued for the client and the
    /// agenda manager.
    fn handle(&mut self, event: ExecutionEvent) {
        let holon = &self.links.holon;
        debug!(%holon, component = "execution", event = ?event, "event");
        let before = self.execution.describe();
        let actions = self.execution.handle(event);
        let after = self.execution.describe();
        if before != after {
            info!(%holon, component = "execution", from = %before, to = %after, "transition");
        }
        self.publish();
        for (lane, action) in actions {
            self.carry_out(lane, action);
        }
    }

    /// Queues one action of lane `lane`.
    fn carry_out(&mut self, lane: usize, action: ExecutionAction) {
        let holon = &self.links.holon;
        match action {
            ExecutionAction::Command(command) => {
                info!(%holon, component = "execution", command_id = command.id, action = %command.action, "command to controller");
                let request = match self.step_id(lane) {
                    Ok(Some(step)) => ControllerRequest::Step { command, step },
                    Ok(None) => ControllerRequest::Command(command),
                    Err(failure) => {
                        self.failure = Some(failure);
                        return;
                    }
                };
                self.commands.push_back(request);
            }
            ExecutionAction::AskStepStatus => match self.step_id(lane) {
                Ok(Some(step)) => {
                    info!(%holon, component = "execution", step = step.as_str(), "the step's answer was lost: its outcome is asked of the controller");
                    self.commands.push_back(ControllerRequest::StepStatus(step));
                }
                Ok(None) => {}
                Err(failure) => self.failure = Some(failure),
            },
            ExecutionAction::AbortController => {
                info!(%holon, component = "execution", "abort: the controller is told to stop");
                self.commands.push_back(ControllerRequest::Abort);
            }
            ExecutionAction::Ready => self.to_agenda.push_back(AgendaEvent::ExecutionReady),
            ExecutionAction::Unavailable(status, said) => self
                .to_agenda
                .push_back(AgendaEvent::ExecutionUnavailable(status, said)),
            ExecutionAction::Finished {
                conversation_id,
                outcome,
            } => {
                info!(%holon, component = "execution", %conversation_id, outcome = %outcome, "job finished");
                self.to_agenda.push_back(AgendaEvent::ExecutionFinished {
                    conversation_id,
                    outcome,
                });
            }
            ExecutionAction::Departed {
                conversation_id,
                requester,
                service_type,
                reply_to,
            } => self.tell_departed(Service {
                v: schemas::SERVICE_VERSION,
                message_type: MessageType::Departed,
                service_type,
                conversation_id,
                requester,
                provider: Some(holon.clone()),
                reply_to: Some(reply_to),
                result: None,
                reason: None,
                info: Default::default(),
            }),
            // The view is republished after every event (see `handle`).
            ExecutionAction::StateChanged => {}
        }
    }

    /// Sends `departed` to its requester once, from a task of its own (see the module's
    /// doc): the outcome is logged, nothing waits for it.
    fn tell_departed(&self, message: Service) {
        let holon = self.links.holon.clone();
        let session = self.links.session.clone();
        let timeout = self.links.departed_timeout;
        info!(%holon, component = "execution", conversation_id = %message.conversation_id, message_type = %message.message_type, "the move has left its origin: its requester is told");
        tokio::spawn(async move {
            match courier::attempt(&session, &message, timeout).await {
                AttemptOutcome::Acknowledged => {
                    debug!(%holon, conversation_id = %message.conversation_id, "departed acknowledged")
                }
                other => {
                    warn!(%holon, conversation_id = %message.conversation_id, outcome = ?other, "departed not acknowledged: the requester releases the move's origin at its done instead")
                }
            }
        });
    }

    /// The step id of lane `lane`'s step in progress, for a fenced resource:
    /// `<conversation>#<index>`.
    fn step_id(&self, lane: usize) -> Result<Option<StepId>, ChildError> {
        if !self.links.interfacing.fenced() {
            return Ok(None);
        }
        let Some((conversation, index)) = self.execution.lane(lane).current_step_index() else {
            return Ok(None);
        };
        StepId::of(conversation, index)
            .map(Some)
            .map_err(|e| ChildError::from(format!("no step id for {conversation:?}: {e}")))
    }

    /// Hands the agenda manager what the machine told it, in order, waiting for room;
    /// false when its mailbox is closed (the component fails). Cancel-safe: an event
    /// leaves the queue only once sent.
    async fn tell_agenda(&mut self) -> bool {
        while !self.to_agenda.is_empty() {
            let Ok(permit) = self.links.agenda.reserve().await else {
                self.failure = Some("agenda mailbox closed".into());
                return false;
            };
            let event = self.to_agenda.pop_front().expect("not empty");
            permit.send(event.into());
        }
        true
    }

    /// Republishes the execution's view if it changed. A job seen running for the first
    /// time is stamped with the time now: its measured duration is what a staff holon
    /// learns from.
    fn publish(&self) {
        self.links.views.execution.send_if_modified(|published| {
            let running = self
                .execution
                .running()
                .map(|job| RunningView {
                    since: published
                        .running
                        .iter()
                        .find(|seen| seen.conversation_id == job.conversation_id)
                        .map_or_else(schemas::unix_ms, |seen| seen.since),
                    conversation_id: job.conversation_id.to_string(),
                    step: job.step,
                })
                .collect();
            let view = ExecutionView {
                controller: self.execution.controller(),
                running,
            };
            let changed = *published != view;
            *published = view;
            changed
        });
    }
}

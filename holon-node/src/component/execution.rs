//! The execution component: the one owner of the execution state machine
//! ([`crate::execution`]).
//!
//! Its events come from two mailboxes: jobs from the agenda manager, and what the
//! interfacing component reports of the controller. It carries out the machine's
//! actions: commands go to the interfacing component, `ready`, `unavailable` and
//! finished jobs to the agenda manager; after every event it republishes its view (the
//! controller and the step in progress) when that changed.
//!
//! It waits for room in the agenda manager's mailbox (which never waits on it), never
//! in the interfacing component's: that mailbox holds at most the running step's
//! command and an abort (the machine sends a step's command after the last one's
//! reply), so a command goes with `try_send` and the two never wait on each other.

use std::sync::Arc;

use holon::ChildError;
use robot_bridge::client::{ControllerEvent, ControllerRequest, FenceHandle, StepId};
use schemas::HolonId;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info};

use crate::agenda::AgendaEvent;
use crate::component::agenda_manager::AgendaMessage;
use crate::execution::{Execution, ExecutionAction, ExecutionEvent, ExecutionRequest};
use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};
use crate::views::{ExecutionView, Views};

/// What the execution component is linked to.
pub struct Links {
    pub holon: HolonId,
    /// The state machine it owns.
    pub execution: Handover<Execution>,
    /// Jobs (and aborts) from the agenda manager.
    pub jobs: Mailbox<ExecutionRequest>,
    /// What the interfacing component reports.
    pub controller: Mailbox<ControllerEvent>,
    /// The interfacing component's command mailbox.
    pub commands: mpsc::Sender<ControllerRequest>,
    /// The agenda manager's mailbox.
    pub agenda: mpsc::Sender<AgendaMessage>,
    /// Where it publishes its view.
    pub views: Arc<Views>,
    /// A fenced resource's fence: each step's command goes through it, with its step id.
    pub fence: Option<FenceHandle>,
    /// Its fault to inject on request.
    pub faults: Arc<Faults>,
}

pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let holon = &links.holon;
    let mut execution = links.execution.take().await;
    let mut jobs = links.jobs.take().await;
    let mut controller = links.controller.take().await;
    publish(&links, &execution);
    loop {
        let event = tokio::select! {
            _ = token.cancelled() => return Ok(()),
            _ = links.faults.execution.notified() => panic!("fault injection: execution crashed"),
            request = jobs.recv() => match request.ok_or("execution mailbox closed")? {
                ExecutionRequest::Start(job) => ExecutionEvent::Start(job),
                ExecutionRequest::Abort => ExecutionEvent::Abort,
            },
            event = controller.recv() => ExecutionEvent::Controller(event.ok_or("controller mailbox closed")?),
        };
        debug!(%holon, component = "execution", event = ?event, "event");
        let before = execution.state().to_string();
        let actions = execution.handle(event);
        let after = execution.state().to_string();
        if before != after {
            info!(%holon, component = "execution", from = %before, to = %after, "transition");
        }
        publish(&links, &execution);
        let step = execution
            .current_step_index()
            .map(|(conversation, index)| (conversation.to_string(), index));
        for action in actions {
            carry_out(&links, action, step.as_ref()).await?;
        }
    }
}

/// Republishes the execution's view if it changed. A job seen running for the first
/// time is stamped with the time now: its measured duration is what a staff holon
/// learns from.
fn publish(links: &Links, execution: &Execution) {
    let running = execution.current_conversation();
    links.views.execution.send_if_modified(|published| {
        let running_since = running.map(|conversation| match &published.running_since {
            Some((same, since)) if same == conversation => (same.clone(), *since),
            _ => (conversation.to_string(), schemas::unix_ms()),
        });
        let view = ExecutionView {
            controller: execution.controller(),
            step: execution.current_step(),
            running_since,
        };
        let changed = *published != view;
        *published = view;
        changed
    });
}

/// Carries out one action; `step` is the running job's conversation and the index of
/// its step in progress (a command's step id, for a fenced resource).
async fn carry_out(
    links: &Links,
    action: ExecutionAction,
    step: Option<&(String, usize)>,
) -> Result<(), ChildError> {
    let holon = &links.holon;
    let to_agenda = |event: AgendaEvent| async {
        links
            .agenda
            .send(event.into())
            .await
            .map_err(|_| ChildError::from("agenda mailbox closed"))
    };
    match action {
        ExecutionAction::Command(command) => {
            info!(%holon, component = "execution", command_id = command.id, action = %command.action, "command to controller");
            match (&links.fence, step) {
                (Some(fence), Some((conversation, index))) => {
                    let step = StepId::of(conversation, *index).map_err(|e| {
                        ChildError::from(format!("no step id for {conversation:?}: {e}"))
                    })?;
                    fence
                        .command(command, step)
                        .await
                        .map_err(|e| ChildError::from(format!("the fence: {e}")))?;
                }
                _ => to_controller(links, command.into())?,
            }
        }
        ExecutionAction::AbortController => {
            info!(%holon, component = "execution", "abort: the controller is told to stop");
            to_controller(links, ControllerRequest::Abort)?;
        }
        ExecutionAction::Ready => to_agenda(AgendaEvent::ExecutionReady).await?,
        ExecutionAction::Unavailable(status) => {
            to_agenda(AgendaEvent::ExecutionUnavailable(status)).await?
        }
        ExecutionAction::Finished {
            conversation_id,
            outcome,
        } => {
            info!(%holon, component = "execution", %conversation_id, outcome = %outcome, "job finished");
            to_agenda(AgendaEvent::ExecutionFinished {
                conversation_id,
                outcome,
            })
            .await?
        }
        // The view is republished after every event (see `run`).
        ExecutionAction::StateChanged => {}
    }
    Ok(())
}

/// Hands a request to the interfacing component without waiting for room (see the
/// module's doc): a full mailbox would be a bug, and the component fails.
fn to_controller(links: &Links, request: ControllerRequest) -> Result<(), ChildError> {
    links.commands.try_send(request).map_err(|e| match e {
        mpsc::error::TrySendError::Full(_) => ChildError::from(
            "the command mailbox is full (it holds at most a step's command and an abort: a bug)",
        ),
        mpsc::error::TrySendError::Closed(_) => ChildError::from("command mailbox closed"),
    })
}

//! The fence of a standby holon, the client's side (`docs/controller-protocol.md`,
//! "Fencing (standby)"): a [`FenceHandle`] the holon keeps, asking the connection task
//! (the one owner of the connection's state) over a mailbox; each answer comes back on
//! a oneshot, every wait bounded.
//!
//! While it holds the claim, the connection task sends the dialect's heartbeat every
//! lease/4 and writes the epoch in every command (a [`super::ControllerRequest::Step`]
//! adds the step id). When the controller says the epoch is stale, or the connection that held
//! the claim ends, a [`FenceEvent`] tells the holon to step down; it may claim again.

use std::time::Duration;

use tokio::sync::{mpsc, oneshot, watch};
use tokio::time::Instant;

use super::ClientConfig;
use crate::fence_wire::{valid_token, MAX_NAME_BYTES, MAX_STEP_BYTES};

/// An epoch the controller granted (+1 per grant).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct Epoch(pub u64);

impl std::fmt::Display for Epoch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// A step id: the holon's `conversation_id`, `#`, the command's index in the step, e.g.
/// `orders1-3/2/1#2`. 1 to 128 printable ASCII bytes, no space, none of `<>&'"`.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct StepId(String);

impl StepId {
    /// A step id from its text.
    pub fn new(text: impl Into<String>) -> Result<StepId, FenceError> {
        let text = text.into();
        if valid_token(&text, MAX_STEP_BYTES) {
            Ok(StepId(text))
        } else {
            Err(FenceError::Invalid(format!(
                "{:?} is not a step id (1 to {MAX_STEP_BYTES} printable bytes, no space, none of <>&'\")",
                text.chars().take(80).collect::<String>()
            )))
        }
    }

    /// The step id of command `index` of the step of `conversation_id`.
    pub fn of(conversation_id: &str, index: usize) -> Result<StepId, FenceError> {
        StepId::new(format!("{conversation_id}#{index}"))
    }

    pub fn as_str(&self) -> &str {
        &self.0
    }
}

/// Why a claim was not granted.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ClaimError {
    /// Another live session holds the claim, with this epoch; try again later.
    #[error("the controller is held by another session (epoch {0})")]
    Held(Epoch),
    /// The dialect or the controller cannot fence: standby is refused.
    #[error("the controller cannot fence: {0}")]
    NotSupported(String),
    #[error("not connected to the controller")]
    NotConnected,
    #[error("the controller refused the claim: {0}")]
    Refused(String),
    /// Another claim is still waiting for its answer.
    #[error("a claim is already under way")]
    Busy,
    #[error("no answer to the claim within {0:?}")]
    Timeout(Duration),
    /// The connection task is gone.
    #[error("the controller client has stopped")]
    Gone,
}

/// Why a fence request other than a claim failed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FenceError {
    #[error("the controller cannot fence: {0}")]
    NotSupported(String),
    #[error("not connected to the controller")]
    NotConnected,
    #[error("invalid: {0}")]
    Invalid(String),
    #[error("the controller refused: {0}")]
    Refused(String),
    #[error("no answer within {0:?}")]
    Timeout(Duration),
    #[error("the controller client has stopped")]
    Gone,
}

/// A step id's state on the controller.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StepStatus {
    /// It ran, with this result.
    Done { result: String },
    /// It ended failed, with this message.
    Failed { message: String },
    /// It runs now.
    Running,
    /// The controller does not know it (never begun, or forgotten).
    Unknown,
}

/// What the connection task tells the holon about the fence.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FenceEvent {
    /// The controller refused our epoch (`stale_epoch`): a newer holder exists. Step down.
    Deposed {
        /// Ours.
        epoch: Epoch,
        /// The controller's, when it said.
        current: Option<Epoch>,
    },
    /// The connection that held the claim ended: the claim is gone with it.
    Lost {
        /// The epoch it held.
        epoch: Epoch,
    },
}

/// A request to the connection task.
#[derive(Debug)]
pub enum FenceRequest {
    /// Claim the controller as `name`.
    Claim {
        name: String,
        reply: oneshot::Sender<Result<Epoch, ClaimError>>,
    },
    /// Ask a step id's state.
    StepStatus {
        step: StepId,
        reply: oneshot::Sender<Result<StepStatus, FenceError>>,
    },
    /// For tests: stop (true) or resume (false) heartbeats, as a frozen process would.
    PauseHeartbeats(bool),
}

/// Answers a claim on `reply`; an asker that is gone (it gave up waiting) is logged.
pub(super) fn answer_claim(
    reply: oneshot::Sender<Result<Epoch, ClaimError>>,
    answer: Result<Epoch, ClaimError>,
) {
    if let Err(answer) = reply.send(answer) {
        tracing::debug!(?answer, "a claim answered after its asker stopped waiting");
    }
}

/// The connection task's end of the fence: requests in, events out.
pub struct FencePort {
    /// Requests from the [`FenceHandle`].
    pub requests: mpsc::Receiver<FenceRequest>,
    /// Where [`FenceEvent`]s go.
    pub events: mpsc::Sender<FenceEvent>,
    /// Until when the claim is known held without asking ([`FenceHandle::confirmed`]):
    /// written by the connection task alone.
    pub confirmed: watch::Sender<Option<Instant>>,
}

/// The holon's end of the fence.
#[derive(Debug, Clone)]
pub struct FenceHandle {
    /// To the connection task.
    requests: mpsc::Sender<FenceRequest>,
    /// The longest wait for an answer.
    wait: Duration,
    /// The dialect's name, if it cannot fence.
    unsupported: Option<String>,
    /// Until when the claim is known held without asking the controller: half a lease
    /// after the last claim the controller granted was sent (see [`Self::confirmed`]).
    confirmed: watch::Receiver<Option<Instant>>,
}

/// A fence handle, the port for [`super::run_fenced`], and the fence's events.
pub fn channel(config: &ClientConfig) -> (FenceHandle, FencePort, mpsc::Receiver<FenceEvent>) {
    let (requests, request_rx) = mpsc::channel(16);
    let (event_tx, events) = mpsc::channel(16);
    let (confirmed, confirmed_rx) = watch::channel(None);
    let handle = FenceHandle {
        requests,
        confirmed: confirmed_rx,
        wait: config.command_timeout + config.connect_timeout,
        unsupported: (!config.dialect.fencing_supported()).then(|| {
            format!(
                "the dialect {} has no fence (claim, epochs, step ids)",
                config.dialect.name
            )
        }),
    };
    let port = FencePort {
        requests: request_rx,
        events: event_tx,
        confirmed,
    };
    (handle, port, events)
}

impl FenceHandle {
    /// Whether the controller's dialect can fence; without it a standby is refused.
    pub fn fencing_supported(&self) -> bool {
        self.unsupported.is_none()
    }

    /// Whether this process is known to hold the claim now without asking the
    /// controller: a claim of its own was granted, sent less than half a lease ago, on a
    /// connection still open. The controller grants another session only after a lease
    /// of silence from the holder, counted from when it heard the holder, which is after
    /// we sent; half a lease leaves room for the two clocks. Not a fence (the epoch on
    /// every command is): it spares a claim round trip per booking while requests come
    /// often, as a lease-based read does.
    pub fn confirmed(&self) -> bool {
        self.confirmed
            .borrow()
            .is_some_and(|until| Instant::now() < until)
    }

    /// Claims the controller as `name`: the epoch granted, or why not.
    pub async fn claim(&self, name: &str) -> Result<Epoch, ClaimError> {
        if let Some(why) = &self.unsupported {
            return Err(ClaimError::NotSupported(why.clone()));
        }
        if !valid_token(name, MAX_NAME_BYTES) {
            return Err(ClaimError::Refused(format!("{name:?} is not a holon name")));
        }
        let (reply, answer) = oneshot::channel();
        let request = FenceRequest::Claim {
            name: name.to_string(),
            reply,
        };
        let sent = tokio::time::timeout(self.wait, self.requests.send(request)).await;
        if !matches!(sent, Ok(Ok(()))) {
            return Err(ClaimError::Gone);
        }
        match tokio::time::timeout(self.wait, answer).await {
            Ok(Ok(result)) => result,
            Ok(Err(_)) => Err(ClaimError::Gone),
            Err(_) => Err(ClaimError::Timeout(self.wait)),
        }
    }

    /// The controller's state of step `step`.
    pub async fn step_status(&self, step: &StepId) -> Result<StepStatus, FenceError> {
        if let Some(why) = &self.unsupported {
            return Err(FenceError::NotSupported(why.clone()));
        }
        let (reply, answer) = oneshot::channel();
        let request = FenceRequest::StepStatus {
            step: step.clone(),
            reply,
        };
        let sent = tokio::time::timeout(self.wait, self.requests.send(request)).await;
        if !matches!(sent, Ok(Ok(()))) {
            return Err(FenceError::Gone);
        }
        match tokio::time::timeout(self.wait, answer).await {
            Ok(Ok(result)) => result,
            Ok(Err(_)) => Err(FenceError::Gone),
            Err(_) => Err(FenceError::Timeout(self.wait)),
        }
    }

    /// For tests: stops (true) or resumes (false) the heartbeats, as if the holon froze.
    pub async fn pause_heartbeats(&self, paused: bool) -> Result<(), FenceError> {
        let request = FenceRequest::PauseHeartbeats(paused);
        match tokio::time::timeout(self.wait, self.requests.send(request)).await {
            Ok(Ok(())) => Ok(()),
            _ => Err(FenceError::Gone),
        }
    }
}

/// The fence's state across connections, kept by the connection task alone.
#[derive(Debug, Default)]
pub(super) struct Claimed {
    /// The last epoch granted to us; written in every command.
    pub(super) epoch: Option<Epoch>,
    /// Whether the current connection holds the claim.
    pub(super) held: bool,
    /// The lease the controller said.
    pub(super) lease: Duration,
    /// (Tests) heartbeats stopped.
    pub(super) paused: bool,
}

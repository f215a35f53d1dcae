//! The fence on one connection: the claim and its answer, heartbeats every lease/4 while
//! it is held, the epoch and step id written in commands, step status queries, and the
//! controller's `stale_epoch` (the holder must step down).

use std::collections::VecDeque;

use tokio::sync::oneshot;
use tokio::time::Instant;
use tracing::{debug, info, warn};

use super::super::fence::{
    answer_claim, ClaimError, Epoch, FenceError, FenceEvent, FenceRequest, StepId, StepStatus,
};
use super::{Connection, ConnectionEnd, Step};
use crate::dialect::{Parsed, Values};
use crate::fence_wire::{
    REASON_HELD, REASON_NOT_FENCED, REASON_STALE_EPOCH, STEP_DONE, STEP_FAILED, STEP_RUNNING,
    STEP_UNKNOWN,
};

/// The shortest pause before a running step's state is asked again.
const MIN_ASK_AGAIN: std::time::Duration = std::time::Duration::from_millis(50);

/// What the fence awaits on this connection.
#[derive(Default)]
pub(super) struct FenceWaits {
    /// A claim sent, awaiting its answer.
    claim: Option<ClaimWait>,
    /// Step status queries sent, oldest first.
    status: VecDeque<StatusWait>,
    /// When the next heartbeat goes, while the claim is held.
    pub(super) heartbeat_at: Option<Instant>,
    /// The owner's queries of steps that were still running: asked again when due.
    again: Vec<(Instant, StepId)>,
}

/// A claim awaiting its answer.
struct ClaimWait {
    /// Who asked.
    reply: oneshot::Sender<Result<Epoch, ClaimError>>,
    /// When the answer is due.
    deadline: Instant,
    /// When it was sent: a grant holds for half a lease from then.
    sent: Instant,
}

/// A step status query awaiting its answer.
struct StatusWait {
    step: StepId,
    reply: StatusReply,
    deadline: Instant,
}

/// Who asked a step's state.
pub(super) enum StatusReply {
    /// The fence's handle: answered on its oneshot.
    Handle(oneshot::Sender<Result<StepStatus, FenceError>>),
    /// The client's owner ([`super::super::ControllerRequest::StepStatus`]): answered
    /// as an event once the step has ended (asked again while it runs).
    Owner,
}

impl FenceWaits {
    /// The earliest of the fence's due times.
    pub(super) fn next_wake(&self) -> Option<Instant> {
        self.claim
            .as_ref()
            .map(|wait| wait.deadline)
            .into_iter()
            .chain(self.status.iter().map(|w| w.deadline))
            .chain(self.heartbeat_at)
            .chain(self.again.iter().map(|(at, _)| *at))
            .min()
    }
}

impl<O: super::Owner> Connection<'_, '_, O> {
    /// The epoch to write in commands, while we have one.
    pub(super) fn epoch_values(&self, values: &mut Values, step: Option<&StepId>) {
        if self.dialect.fence.is_none() {
            return;
        }
        if let Some(epoch) = self.claimed.as_ref().and_then(|c| c.epoch) {
            values.set("epoch", epoch.0.to_string());
        }
        if let Some(step) = step {
            values.set("step", step.as_str().to_string());
        }
    }

    async fn fence_event(&mut self, event: FenceEvent) {
        if let Some(port) = self.fence.as_mut() {
            // Bounded: a holon that does not read its fence events misses them.
            if port.events.try_send(event.clone()).is_err() {
                warn!(
                    ?event,
                    "the fence event could not be told: nobody reads them"
                );
            }
        }
    }

    /// A request from the fence handle.
    pub(super) async fn fence_request(&mut self, request: FenceRequest) -> Step {
        let now = Instant::now();
        let timeout = self.config.command_timeout;
        match request {
            FenceRequest::PauseHeartbeats(paused) => {
                if let Some(c) = self.claimed.as_mut() {
                    c.paused = paused;
                }
                Ok(())
            }
            FenceRequest::Claim { name, reply } => {
                let Some(fence) = self.dialect.fence else {
                    answer_claim(
                        reply,
                        Err(ClaimError::NotSupported(format!(
                            "the dialect {} has no fence",
                            self.dialect.name
                        ))),
                    );
                    return Ok(());
                };
                if self.fence_waits.claim.is_some() {
                    answer_claim(reply, Err(ClaimError::Busy));
                    return Ok(());
                }
                let mut values = Values::default();
                values.set("name", name);
                let bytes = self
                    .dialect
                    .write_command(fence.claim, &values)
                    .map_err(ConnectionEnd::Lost)?;
                self.outbox.push(bytes);
                self.last_traffic = now;
                self.fence_waits.claim = Some(ClaimWait {
                    reply,
                    deadline: now + timeout,
                    sent: now,
                });
                Ok(())
            }
            FenceRequest::StepStatus { step, reply } => {
                self.ask_status(step, StatusReply::Handle(reply)).await
            }
        }
    }

    /// Asks the controller step `step`'s state, for whoever asked.
    pub(super) async fn ask_status(&mut self, step: StepId, reply: StatusReply) -> Step {
        let fence = match (self.dialect.fence, &self.fence) {
            (Some(fence), Some(_)) => fence,
            _ => {
                let why = FenceError::NotSupported(self.dialect.name.clone());
                return self.answer_status(step, reply, Err(why)).await;
            }
        };
        let now = Instant::now();
        let mut values = Values::default();
        values.set("step", step.as_str().to_string());
        let bytes = self
            .dialect
            .write_command(fence.step_status, &values)
            .map_err(ConnectionEnd::Lost)?;
        self.outbox.push(bytes);
        self.last_traffic = now;
        self.fence_waits.status.push_back(StatusWait {
            step,
            reply,
            deadline: now + self.config.command_timeout,
        });
        Ok(())
    }

    /// Answers a step state query: the handle on its oneshot; the owner with an event,
    /// once the step has ended (a step still running is asked again when due).
    async fn answer_status(
        &mut self,
        step: StepId,
        reply: StatusReply,
        status: Result<StepStatus, FenceError>,
    ) -> Step {
        match reply {
            StatusReply::Handle(reply) => {
                if reply.send(status).is_err() {
                    debug!(
                        step = step.as_str(),
                        "a step state asked by a fence handle that is gone"
                    );
                }
                Ok(())
            }
            StatusReply::Owner if status == Ok(StepStatus::Running) => {
                let again = Instant::now() + self.config.reconnect_interval.max(MIN_ASK_AGAIN);
                self.fence_waits.again.push((again, step));
                Ok(())
            }
            StatusReply::Owner => {
                self.report(super::super::ControllerEvent::StepStatus { step, status })
                    .await
            }
        }
    }

    /// A message that may be the fence's; `None`: it is not.
    pub(super) async fn fence_incoming(&mut self, parsed: &Parsed) -> Option<Step> {
        // Only a fenced client ([`super::super::run_fenced`]) sends the fence's messages.
        self.fence.as_ref()?;
        let fence = self.dialect.fence?;
        let read = |r: usize| self.dialect.read_reply(r, parsed);
        let number = |v: &Values, name: &str| v.get(name).and_then(|e| e.parse::<u64>().ok());
        if let Ok(Some(v)) = read(fence.granted) {
            let (Some(epoch), Some(lease)) = (number(&v, "epoch"), number(&v, "lease_ms")) else {
                return Some(
                    self.protocol_error("a claim granted without a number epoch and lease".into())
                        .await,
                );
            };
            let lease = std::time::Duration::from_millis(lease.max(4));
            let mut news = true;
            if let Some(c) = self.claimed.as_mut() {
                news = !c.held || c.epoch != Some(Epoch(epoch));
                c.epoch = Some(Epoch(epoch));
                c.held = true;
                c.lease = lease;
            }
            self.fence_waits.heartbeat_at = Some(Instant::now() + lease / 4);
            if news {
                info!(epoch, lease = ?lease, "claim granted");
            } else {
                debug!(epoch, "claim confirmed");
            }
            if let Some(wait) = self.fence_waits.claim.take() {
                self.set_confirmed(Some(wait.sent + lease / 2));
                answer_claim(wait.reply, Ok(Epoch(epoch)));
            }
            return Some(Ok(()));
        }
        if let Ok(Some(v)) = read(fence.refused) {
            let epoch = number(&v, "epoch").map(Epoch);
            let reason = v.get("reason").unwrap_or("").to_string();
            if let Some(ClaimWait { reply, .. }) = self.fence_waits.claim.take() {
                self.set_confirmed(None);
                let error = match (reason.as_str(), epoch) {
                    (REASON_HELD, Some(epoch)) => ClaimError::Held(epoch),
                    (REASON_NOT_FENCED, _) => {
                        ClaimError::NotSupported("the controller is not fenced".into())
                    }
                    _ => ClaimError::Refused(reason),
                };
                answer_claim(reply, Err(error));
            } else if reason == REASON_STALE_EPOCH {
                self.deposed(epoch).await;
            } else if let Some(wait) = self.fence_waits.status.pop_front() {
                let refused = Err(FenceError::Refused(reason));
                return Some(self.answer_status(wait.step, wait.reply, refused).await);
            }
            return Some(Ok(()));
        }
        if let Ok(Some(v)) = read(fence.step_state) {
            let step = v.get("step").unwrap_or("");
            let at = self
                .fence_waits
                .status
                .iter()
                .position(|w| w.step.as_str() == step);
            let Some(wait) = at.and_then(|i| self.fence_waits.status.remove(i)) else {
                warn!(%step, "a step state nobody asked for; ignored");
                return Some(Ok(()));
            };
            let status = match v.get("step_state").unwrap_or("") {
                STEP_DONE => StepStatus::Done {
                    result: v.get("result").unwrap_or("").to_string(),
                },
                STEP_FAILED => StepStatus::Failed {
                    message: v.get("message").unwrap_or("").to_string(),
                },
                STEP_RUNNING => StepStatus::Running,
                STEP_UNKNOWN => StepStatus::Unknown,
                other => {
                    let refused = Err(FenceError::Refused(format!("unknown step state {other:?}")));
                    return Some(self.answer_status(wait.step, wait.reply, refused).await);
                }
            };
            return Some(self.answer_status(wait.step, wait.reply, Ok(status)).await);
        }
        None
    }

    /// Until when the claim is known held without asking ([`super::super::FenceHandle::confirmed`]);
    /// `None` once it may not be.
    fn set_confirmed(&mut self, until: Option<Instant>) {
        if let Some(port) = self.fence.as_mut() {
            port.confirmed.send_replace(until);
        }
    }

    /// The controller said our epoch is stale: we hold nothing; the holon must step down.
    pub(super) async fn deposed(&mut self, current: Option<Epoch>) {
        let Some(c) = self.claimed.as_mut() else {
            return;
        };
        let epoch = c.epoch.unwrap_or(Epoch(0));
        let was = std::mem::replace(&mut c.held, false);
        self.fence_waits.heartbeat_at = None;
        self.set_confirmed(None);
        warn!(%epoch, ?current, held = was, "the controller refused our epoch (stale_epoch): step down");
        self.fence_event(FenceEvent::Deposed { epoch, current })
            .await;
    }

    /// Due heartbeats and expired fence waits.
    pub(super) async fn fence_timers(&mut self, now: Instant) -> Step {
        if self
            .fence_waits
            .claim
            .as_ref()
            .is_some_and(|wait| wait.deadline <= now)
        {
            if let Some(ClaimWait { reply, .. }) = self.fence_waits.claim.take() {
                answer_claim(reply, Err(ClaimError::Timeout(self.config.command_timeout)));
            }
        }
        while self
            .fence_waits
            .status
            .front()
            .is_some_and(|w| w.deadline <= now)
        {
            if let Some(wait) = self.fence_waits.status.pop_front() {
                let timeout = Err(FenceError::Timeout(self.config.command_timeout));
                self.answer_status(wait.step, wait.reply, timeout).await?;
            }
        }
        let (due, later) = std::mem::take(&mut self.fence_waits.again)
            .into_iter()
            .partition(|(at, _)| *at <= now);
        self.fence_waits.again = later;
        for (_, step) in due {
            self.ask_status(step, StatusReply::Owner).await?;
        }
        let Some(at) = self.fence_waits.heartbeat_at else {
            return Ok(());
        };
        if at > now {
            return Ok(());
        }
        let (Some(fence), Some(c)) = (self.dialect.fence, self.claimed.as_ref()) else {
            return Ok(());
        };
        self.fence_waits.heartbeat_at = Some(now + c.lease / 4);
        if !c.held || c.paused {
            return Ok(());
        }
        let mut values = Values::default();
        values.set("epoch", c.epoch.unwrap_or(Epoch(0)).0.to_string());
        let bytes = self
            .dialect
            .write_command(fence.heartbeat, &values)
            .map_err(ConnectionEnd::Lost)?;
        self.outbox.push(bytes);
        self.last_traffic = now;
        Ok(())
    }

    /// The connection ends: what the fence awaited fails, a claim held is lost.
    pub(super) async fn fence_ends(&mut self) {
        if let Some(ClaimWait { reply, .. }) = self.fence_waits.claim.take() {
            answer_claim(reply, Err(ClaimError::NotConnected));
        }
        // Every query waiting or to be asked again fails: the owner asks again once a
        // connection is back.
        let again = std::mem::take(&mut self.fence_waits.again)
            .into_iter()
            .map(|(_, step)| (step, StatusReply::Owner));
        let waits: Vec<_> = self
            .fence_waits
            .status
            .drain(..)
            .map(|w| (w.step, w.reply))
            .chain(again)
            .collect();
        for (step, reply) in waits {
            if self
                .answer_status(step, reply, Err(FenceError::NotConnected))
                .await
                .is_err()
            {
                return;
            }
        }
        self.set_confirmed(None);
        let Some(c) = self.claimed.as_mut() else {
            return;
        };
        if std::mem::replace(&mut c.held, false) {
            let epoch = c.epoch.unwrap_or(Epoch(0));
            warn!(%epoch, "the connection holding the claim ended: the claim is lost");
            self.fence_event(FenceEvent::Lost { epoch }).await;
        }
    }
}

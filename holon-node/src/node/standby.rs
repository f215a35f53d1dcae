//! A fenced resource's life (docs/reliability.md, "Standby resources"): the controller's
//! claim, not liveliness, decides whether this process serves.
//!
//! Each round starts the five components with the controller client in fenced mode
//! ([`robot_bridge::client::run_fenced`]) and claims the controller as the holon's name,
//! every [`CLAIM_RETRY`] while another session holds it ([`crate::machine::fence::Claim`]). Until
//! it holds the claim the resource is a standby: the communication component declares
//! nothing and the name's liveliness token is not declared, so it may wait beside a live
//! primary of the same name (the twin check of an unfenced resource is not made: the
//! fence decides). On a grant it asks the controller the outcome of the steps its
//! journal left in flight, then serves: the token is declared, offers made. Each
//! process reports its role and epoch on `resource/<name>/fence/<zid>`
//! ([`super::fence_report`]). Deposed (a command refused `stale_epoch`) or
//! its connection lost, it steps down: the token goes, offers stop, bookings are handed
//! back `withdrawn` (as a shutdown does), the components stop, and a new round claims
//! again.

use std::sync::Arc;
use std::time::Duration;

use holon::life::{Held, Leadership, Next, Work};
use robot_bridge::client::{fence, Epoch, FenceEvent, FenceHandle, FencePort, StepId};
use schemas::Reason;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};

use super::fence_report::Reporter;
use super::{Node, NodeError, Resource, Wiring};
use crate::config::ResourceConfig;
use crate::machine::agenda::AgendaEvent;
use crate::machine::fence::{Claim, ClaimAction, ClaimEvent, CLAIM_RETRY};
use crate::views::FenceView;

/// The controller fence as a resource's leadership: the controller's claim decides
/// whether this process serves, and a deposed holder claims again.
pub(super) struct ControllerFence<'a> {
    /// The resource's config.
    config: &'a ResourceConfig,
    /// What this process says of itself (declared once the session is open).
    reporter: Option<Reporter>,
    /// The fence of the round under way.
    round: Option<Round>,
}

/// One round's fence: the controller client's handle and what it says.
struct Round {
    /// Claims the controller, asks the outcome of steps.
    handle: FenceHandle,
    /// What the controller client says of the fence (granted, deposed, lost).
    events: mpsc::Receiver<FenceEvent>,
    /// The claim's pure machine.
    claim: Claim,
    /// The epoch held, once granted.
    epoch: Option<u64>,
}

impl<'a> ControllerFence<'a> {
    /// A fence for `config`'s controller, not claimed yet.
    pub(super) fn new(config: &'a ResourceConfig) -> ControllerFence<'a> {
        ControllerFence {
            config,
            reporter: None,
            round: None,
        }
    }

    /// Reports this process a standby; `holder_epoch` when the controller said it.
    async fn report_standby(&self, holder_epoch: Option<u64>) {
        if let Some(reporter) = &self.reporter {
            reporter.standby(holder_epoch).await;
        }
    }
}

impl<'a> Leadership<Node<'a>> for ControllerFence<'a> {
    /// A new round: the controller client in fenced mode, for the components to start
    /// with (the claim goes through their controller connection).
    async fn win(
        &mut self,
        _life: &holon::life::Life,
        session: &zenoh::Session,
        _shutdown: &CancellationToken,
    ) -> Result<Option<Option<(FenceHandle, FencePort)>>, NodeError> {
        if self.reporter.is_none() {
            self.reporter = Some(Reporter::declare(self.config, session).await);
        }
        let (handle, port, events) = fence::channel(&self.config.controller);
        if !handle.fencing_supported() {
            return Err(NodeError::Fence(format!(
                "the dialect {} has no fence (claim, epochs, step ids)",
                self.config.controller.dialect.name
            )));
        }
        self.round = Some(Round {
            handle: handle.clone(),
            events,
            claim: Claim::default(),
            epoch: None,
        });
        Ok(Some(Some((handle, port))))
    }

    /// Claims the controller, every [`CLAIM_RETRY`] while another session holds it (a
    /// standby meanwhile); once granted, learns what the journal left in flight.
    async fn hold(
        &mut self,
        work: &mut Resource,
        shutdown: &CancellationToken,
    ) -> Result<Held<NodeError>, NodeError> {
        let holon = &self.config.holon;
        let epoch = match self.claim(work, shutdown).await? {
            Ok(epoch) => epoch,
            Err(held) => return Ok(held),
        };
        let round = self.round.as_mut().expect("a round is under way");
        round.epoch = Some(epoch.0);
        // Granted: learn what the journal left in flight, then serve.
        in_flight_outcomes(self.config, &work.wiring, &round.handle).await;
        work.wiring
            .communication
            .views
            .fence
            .send_replace(FenceView::Holding(epoch.0));
        debug!(%holon, epoch = epoch.0, "granted");
        Ok(Held::Held)
    }

    /// A standby takes no successor (`--standby` is not with `--take-over`).
    fn takes_successors(&self) -> bool {
        false
    }

    async fn serving(&mut self, life: &holon::life::Life) {
        let epoch = self
            .round
            .as_ref()
            .and_then(|r| r.epoch)
            .unwrap_or_default();
        if let Some(reporter) = &self.reporter {
            reporter.holder(epoch).await;
        }
        info!(holon = %self.config.holon, epoch, key = %life.presence_key, "holding the controller: holon ready, serving");
    }

    /// Deposed (a command refused `stale_epoch`) or its connection lost.
    async fn lost(&mut self) -> String {
        let Some(round) = self.round.as_mut() else {
            return std::future::pending().await;
        };
        loop {
            let Some(event) = round.events.recv().await else {
                return std::future::pending().await;
            };
            let stepped_down = round
                .claim
                .handle(ClaimEvent::Fence(event))
                .into_iter()
                .find_map(|action| match action {
                    ClaimAction::StepDown { why, .. } => Some(why),
                    _ => None,
                });
            if let Some(why) = stepped_down {
                warn!(holon = %self.config.holon, epoch = round.epoch.unwrap_or_default(), %why, "deposed: stepping down (token withdrawn, no offers, bookings dropped: the new holder's agenda is the truth); claiming again");
                return why;
            }
        }
    }

    /// A standby again: it says so, and a new round claims.
    async fn deposed(&mut self, _why: &str) -> Result<(), NodeError> {
        self.report_standby(None).await;
        Ok(())
    }
}

impl ControllerFence<'_> {
    /// The claim, until granted (its epoch) or ended otherwise (how).
    async fn claim(
        &mut self,
        work: &mut Resource,
        shutdown: &CancellationToken,
    ) -> Result<Result<Epoch, Held<NodeError>>, NodeError> {
        let holon = &self.config.holon;
        let round = self.round.as_mut().expect("a round is under way");
        loop {
            let event = tokio::select! {
                _ = shutdown.cancelled() => {
                    info!(%holon, "stopping while not holding the controller");
                    return Ok(Err(Held::Stopped));
                }
                next = work.next() => match next {
                    Next::Ended(result) => return Ok(Err(Held::Ended(result))),
                    Next::Event(never) => match never {},
                },
                Some(event) = round.events.recv() => ClaimEvent::Fence(event),
                answer = round.handle.claim(holon.name()) => ClaimEvent::Answer(answer),
            };
            let mut granted = None;
            let mut retry = false;
            for action in round.claim.handle(event) {
                match action {
                    ClaimAction::Serve(epoch) => granted = Some(epoch),
                    ClaimAction::Standby(holder) => {
                        if let Some(reporter) = &self.reporter {
                            reporter.standby(Some(holder.0)).await;
                        }
                        info!(%holon, holder_epoch = holder.0, "standby: another session holds the controller; claiming every 200 ms, serving nothing until granted")
                    }
                    ClaimAction::Retry(reason) => {
                        if let Some(reason) = reason {
                            info!(%holon, %reason, "standby: cannot claim the controller yet; retrying");
                        }
                        retry = true;
                    }
                    ClaimAction::Refuse(why) => {
                        error!(%holon, %why, "standby refused: the controller cannot fence");
                        return Err(NodeError::Fence(why));
                    }
                    ClaimAction::StepDown { .. } => {}
                }
            }
            if let Some(epoch) = granted {
                return Ok(Ok(epoch));
            }
            if retry {
                tokio::select! {
                    _ = tokio::time::sleep(CLAIM_RETRY) => {}
                    _ = shutdown.cancelled() => {}
                }
            }
        }
    }
}

/// The longest a deposed holder waits for its running job to end and its
/// results acknowledged (or its shutdown grace, if shorter); what is not acknowledged
/// stays in its journal and goes out when it serves again.
pub(super) const STEP_DOWN_GRACE: Duration = Duration::from_secs(2);

/// Drops every booking without a word ([`AgendaEvent::Deposed`]: an order may have
/// booked the same conversation with the new holder, which a `withdrawn` would cancel)
/// and waits, at most `grace`, until the agenda is drained: nothing runs and every
/// result is acknowledged. Unlike a shutdown it waits for the agenda itself to say so.
pub(super) async fn step_down(wiring: &Wiring, grace: Duration) {
    let links = &wiring.agenda_manager;
    let holon = &links.holon;
    let mut agenda = links.views.agenda.subscribe();
    let bookings = links.views.agenda.borrow().snapshot.agenda.len();
    info!(%holon, bookings, "stepping down: no new work, bookings dropped");
    let deposed = links.mailbox.sender.send(AgendaEvent::Deposed.into());
    if tokio::time::timeout(grace, deposed).await.is_err() {
        error!(%holon, "the agenda manager did not take the deposition: its bookings stay");
        return;
    }
    let drained = tokio::time::timeout(grace, agenda.wait_for(|view| view.drained))
        .await
        .map(|waited| waited.map(|_| ()));
    match drained {
        Ok(Ok(())) => {
            info!(%holon, "stepped down: every booking dropped, every result acknowledged")
        }
        Ok(Err(_)) => error!(%holon, "the agenda view closed while stepping down"),
        Err(_) => {
            let view = links.views.agenda.borrow();
            warn!(%holon, running = view.snapshot.current.is_some(), undelivered = view.snapshot.undelivered, ?grace, "step-down grace elapsed; stopping anyway (what is left stays in the journal)");
        }
    }
}

/// How long the grant waits, at most, for the outcomes of the steps left in flight.
const IN_FLIGHT_WAIT: Duration = Duration::from_secs(5);

/// Asks the controller the outcome of every step of each job this holon's journal left
/// running (now `failed interrupted`, never re-executed) and logs it: a step the
/// controller ran is not run again by anyone. A standby on another host has no journal
/// of its primary's, so it has nothing in flight of its own.
async fn in_flight_outcomes(config: &ResourceConfig, wiring: &Wiring, fence: &FenceHandle) {
    let holon = &config.holon;
    let interrupted: Vec<(String, String)> = wiring
        .communication
        .views
        .agenda
        .borrow()
        .deliverable
        .iter()
        .filter(|result| result.reason == Some(Reason::Interrupted))
        .map(|result| (result.conversation_id.clone(), result.service_type.clone()))
        .collect();
    let catalog = Arc::clone(&config.catalog);
    let asked = tokio::time::timeout(IN_FLIGHT_WAIT, async {
        for (conversation, service_type) in interrupted {
            let steps = catalog.get(&service_type).map_or(0, |d| d.steps.len());
            for index in 0..steps {
                let Ok(step) = StepId::of(&conversation, index) else {
                    continue;
                };
                match fence.step_status(&step).await {
                    Ok(status) => {
                        info!(%holon, step = step.as_str(), ?status, "a step left in flight, as the controller knows it")
                    }
                    Err(e) => {
                        debug!(%holon, step = step.as_str(), error = %e, "cannot ask a step's state")
                    }
                }
            }
        }
    })
    .await;
    if asked.is_err() {
        warn!(%holon, within = ?IN_FLIGHT_WAIT, "the steps left in flight were not all asked");
    }
}

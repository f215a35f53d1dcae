//! A fenced resource's life (docs/reliability.md, "Standby resources"): the controller's
//! claim, not liveliness, decides whether this process serves.
//!
//! Each round starts the five components with the controller client in fenced mode
//! ([`robot_bridge::client::run_fenced`]) and claims the controller as the holon's name,
//! every [`CLAIM_RETRY`] while another session holds it ([`crate::fence::Claim`]). Until
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

use robot_bridge::client::{fence, FenceHandle, StepId};
use schemas::Reason;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};

use super::fence_report::Reporter;
use super::{supervisor_ended, wait_stopped, NodeError, Wiring, STARTUP_TIMEOUT};
use crate::agenda::{AgendaEvent, Inheritance};
use crate::config::ResourceConfig;
use crate::fence::{Claim, ClaimAction, ClaimEvent, CLAIM_RETRY};
use crate::views::FenceView;

/// The supervisor's task.
type Supervision = JoinHandle<Result<(), holon::supervisor::SupervisorError>>;

/// How a round of claiming and serving ended.
enum Round {
    /// Stopped (SIGTERM) or the supervisor gave up: the process ends with this.
    End(Result<(), NodeError>),
    /// Deposed: claim again.
    SteppedDown,
}

/// Runs a fenced resource until `shutdown` is cancelled or its supervisor gives up.
pub(super) async fn serve(
    config: &ResourceConfig,
    session: &zenoh::Session,
    alive_key: &str,
    shutdown: CancellationToken,
) -> Result<(), NodeError> {
    let reporter = Reporter::declare(config, session).await;
    loop {
        match round(config, session, alive_key, &shutdown, &reporter).await? {
            Round::End(outcome) => return outcome,
            Round::SteppedDown => continue,
        }
    }
}

/// One round: components up, claim, serve while holding, step down.
async fn round(
    config: &ResourceConfig,
    session: &zenoh::Session,
    alive_key: &str,
    shutdown: &CancellationToken,
    reporter: &Reporter,
) -> Result<Round, NodeError> {
    let holon = &config.holon;
    let (handle, port, mut events) = fence::channel(&config.controller);
    if !handle.fencing_supported() {
        return Err(NodeError::Fence(format!(
            "the dialect {} has no fence (claim, epochs, step ids)",
            config.controller.dialect.name
        )));
    }
    let wiring = Wiring::new(
        config,
        session,
        Inheritance::Restarted,
        Some((handle.clone(), port)),
    )?;
    let components = CancellationToken::new();
    let mut supervision = tokio::spawn(wiring.supervisor(config).run(components.clone()));
    let mut claim = Claim::default();

    // Claiming: a standby until the controller grants the claim.
    let epoch = loop {
        let event = tokio::select! {
            _ = shutdown.cancelled() => {
                info!(%holon, "stopping while not holding the controller");
                return Ok(Round::End(stop(holon, components, supervision).await));
            }
            result = &mut supervision => return Ok(Round::End(supervisor_ended(result))),
            Some(event) = events.recv() => ClaimEvent::Fence(event),
            answer = handle.claim(holon.name()) => ClaimEvent::Answer(answer),
        };
        let mut granted = None;
        let mut retry = false;
        for action in claim.handle(event) {
            match action {
                ClaimAction::Serve(epoch) => granted = Some(epoch),
                ClaimAction::Standby(holder) => {
                    reporter.standby(Some(holder.0)).await;
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
                    // A stop's outcome is secondary to the refusal.
                    let _ = stop(holon, components, supervision).await;
                    return Err(NodeError::Fence(why));
                }
                ClaimAction::StepDown { .. } => {}
            }
        }
        if let Some(epoch) = granted {
            break epoch;
        }
        if retry {
            tokio::select! {
                _ = tokio::time::sleep(CLAIM_RETRY) => {}
                _ = shutdown.cancelled() => {}
            }
        }
    };

    // Granted: learn what the journal left in flight, then serve.
    in_flight_outcomes(config, &wiring, &handle).await;
    let serving = wiring.communication.serving.notified();
    wiring
        .communication
        .views
        .fence
        .send_replace(FenceView::Holding(epoch.0));
    let started = tokio::select! {
        _ = serving => Ok(()),
        _ = tokio::time::sleep(STARTUP_TIMEOUT) => Err(NodeError::Startup(STARTUP_TIMEOUT)),
        result = &mut supervision => Err(supervisor_ended(result).err().unwrap_or(NodeError::Startup(STARTUP_TIMEOUT))),
    };
    if let Err(e) = started {
        components.cancel();
        wait_stopped(holon, supervision).await;
        return Err(e);
    }
    let token = session
        .liveliness()
        .declare_token(alive_key)
        .await
        .map_err(|e| NodeError::Zenoh(holon::zenoh_error::describe(&e)))?;
    reporter.holder(epoch.0).await;
    info!(%holon, epoch = epoch.0, key = %alive_key, "holding the controller: holon ready, serving");

    // Serving, until stopped or deposed.
    let why = loop {
        tokio::select! {
            _ = shutdown.cancelled() => {
                wiring.withdraw(config.shutdown_grace).await;
                undeclare(holon, token).await;
                return Ok(Round::End(stop(holon, components, supervision).await));
            }
            result = &mut supervision => {
                undeclare(holon, token).await;
                return Ok(Round::End(supervisor_ended(result)));
            }
            Some(event) = events.recv() => {
                let stepped_down = claim.handle(ClaimEvent::Fence(event)).into_iter().find_map(|action| match action {
                    ClaimAction::StepDown { why, .. } => Some(why),
                    _ => None,
                });
                if let Some(why) = stepped_down {
                    break why;
                }
            }
        }
    };

    // Deposed: no one may book it from now on; its bookings are dropped.
    warn!(%holon, epoch = epoch.0, %why, "deposed: stepping down (token withdrawn, no offers, bookings dropped: the new holder's agenda is the truth); claiming again");
    wiring
        .communication
        .views
        .fence
        .send_replace(FenceView::Standby);
    undeclare(holon, token).await;
    reporter.standby(None).await;
    step_down(&wiring, config.shutdown_grace.min(STEP_DOWN_GRACE)).await;
    let stopped = stop(holon, components, supervision).await;
    drop(wiring);
    stopped?;
    info!(%holon, "stepped down: a standby again");
    Ok(Round::SteppedDown)
}

/// The longest a deposed holder waits for its running job to end and its
/// results acknowledged (or its shutdown grace, if shorter); what is not acknowledged
/// stays in its journal and goes out when it serves again.
const STEP_DOWN_GRACE: Duration = Duration::from_secs(2);

/// Drops every booking without a word ([`AgendaEvent::Deposed`]: an order may have
/// booked the same conversation with the new holder, which a `withdrawn` would cancel)
/// and waits, at most `grace`, until the agenda is drained: nothing runs and every
/// result is acknowledged. Unlike a shutdown it waits for the agenda itself to say so.
async fn step_down(wiring: &Wiring, grace: Duration) {
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

/// Stops the components (each within its shutdown timeout).
async fn stop(
    holon: &schemas::HolonId,
    components: CancellationToken,
    supervision: Supervision,
) -> Result<(), NodeError> {
    components.cancel();
    wait_stopped(holon, supervision).await;
    Ok(())
}

/// Withdraws the name's liveliness token.
async fn undeclare(holon: &schemas::HolonId, token: zenoh::liveliness::LivelinessToken) {
    if let Err(e) = token.undeclare().await {
        error!(%holon, error = %e, "cannot withdraw the liveliness token");
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

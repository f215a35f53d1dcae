//! The resource holon process: five components under one supervisor.
//!
//! Start order: interfacing, execution, agenda manager, requesters (the booking
//! lifetime), communication; the stop order is the reverse, so the holon stops taking
//! requests first and closes the controller connection last (see [`crate::component`]).
//! The components talk through mailboxes, and each owns its state; both live here,
//! beside the supervisor ([`crate::handover`]), so restarting a component loses neither
//! its state nor a message in flight.

use std::sync::Arc;
use std::time::Duration;

use holon::{ChildSpec, Supervisor};
use robot_bridge::client::ControllerEvent;
use schemas::{RobotCommand, Service};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use crate::absences::{Absences, Moment};
use crate::agenda::{AgendaEvent, Job};
use crate::component::agenda_manager::{self, AgendaMessage, JournalledAgenda};
use crate::component::delivery::Deliveries;
use crate::component::{communication, execution, interfacing, requesters};
use crate::config::ResourceConfig;
use crate::execution::Execution;
use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};
use crate::views::Views;

/// How long a holon waits for zenoh to open and for its components to come up.
pub const STARTUP_TIMEOUT: Duration = Duration::from_secs(10);

/// Why a holon process stops with an error.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    #[error(transparent)]
    Session(#[from] holon::session::SessionError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("the components did not come up within {0:?}")]
    Startup(Duration),
    #[error(transparent)]
    Supervisor(#[from] holon::supervisor::SupervisorError),
    #[error(transparent)]
    Journal(#[from] holon::journal::JournalError),
    #[error(transparent)]
    Claim(#[from] holon::presence::ClaimError),
}

/// The components' links, built once per process: they outlive the components'
/// restarts, and each component sees only its own.
struct Wiring {
    interfacing: Arc<interfacing::Links>,
    execution: Arc<execution::Links>,
    agenda_manager: Arc<agenda_manager::Links>,
    requesters: Arc<requesters::Links>,
    communication: Arc<communication::Links>,
}

impl Wiring {
    /// The mailboxes, the owned states (the agenda restored from the journal if the
    /// holon has one) and the views, linked.
    fn new(config: &ResourceConfig, session: &zenoh::Session) -> Result<Wiring, NodeError> {
        let holon = config.holon.clone();
        let agenda = JournalledAgenda::open(config)?;
        // Results not acknowledged before a restart (and an interrupted job's `failed`)
        // go out when the communication component starts (from the agenda's view).
        let deliveries = Deliveries::new(holon.clone(), session.clone(), config.delivery);
        let views = Arc::new(Views::new(agenda.view(), Absences::new(Moment::now())));
        let faults = Arc::new(Faults::default());
        let agenda_mail: Mailbox<AgendaMessage> = Mailbox::new();
        let jobs: Mailbox<Job> = Mailbox::new();
        let controller: Mailbox<ControllerEvent> = Mailbox::new();
        let commands: Mailbox<RobotCommand> = Mailbox::new();
        let results: Mailbox<Service> = Mailbox::new();
        Ok(Wiring {
            interfacing: Arc::new(interfacing::Links {
                controller: config.controller.clone(),
                commands: commands.share(),
                events: controller.sender.clone(),
                faults: faults.clone(),
            }),
            execution: Arc::new(execution::Links {
                holon: holon.clone(),
                execution: Handover::new(Execution::new(config.catalog.clone())),
                jobs: jobs.share(),
                controller,
                commands: commands.sender.clone(),
                agenda: agenda_mail.sender.clone(),
                views: views.clone(),
                faults: faults.clone(),
            }),
            agenda_manager: Arc::new(agenda_manager::Links {
                holon: holon.clone(),
                agenda: Handover::new(agenda),
                mailbox: agenda_mail.share(),
                jobs: jobs.sender.clone(),
                results: results.sender.clone(),
                views: views.clone(),
                faults: faults.clone(),
            }),
            requesters: Arc::new(requesters::Links {
                holon,
                session: session.clone(),
                keys: config.keys.clone(),
                grace: config.requester_grace,
                agenda: agenda_mail.sender.clone(),
                views: views.clone(),
            }),
            communication: Arc::new(communication::Links {
                config: config.clone(),
                session: session.clone(),
                deliveries: Handover::new(deliveries),
                results,
                agenda: agenda_mail.sender,
                views,
                faults,
                serving: Arc::new(Notify::new()),
            }),
        })
    }

    /// The supervisor of the five components, in start order.
    fn supervisor(&self, config: &ResourceConfig) -> Supervisor {
        fn spec<L: Send + Sync + 'static, F>(
            name: &str,
            links: &Arc<L>,
            run: fn(Arc<L>, CancellationToken) -> F,
        ) -> ChildSpec
        where
            F: std::future::Future<Output = Result<(), holon::ChildError>> + Send + 'static,
        {
            let links = links.clone();
            ChildSpec::new(name, move |token| run(links.clone(), token))
        }
        Supervisor::new(config.holon.to_string(), config.strategy, config.intensity)
            .child(spec("interfacing", &self.interfacing, interfacing::run))
            .child(spec("execution", &self.execution, execution::run))
            .child(spec("agenda", &self.agenda_manager, agenda_manager::run))
            .child(spec("requesters", &self.requesters, requesters::run))
            .child(spec(
                "communication",
                &self.communication,
                communication::run,
            ))
    }

    /// Stops taking work, hands every booking back, and waits (at most `grace`) until
    /// the running job has finished and every result is acknowledged.
    async fn withdraw(&self, grace: Duration) {
        let links = &self.agenda_manager;
        let holon = &links.holon;
        let bookings = links.views.agenda.borrow().snapshot.agenda.len();
        info!(%holon, bookings, "withdrawing: no new work, handing bookings back");
        if links
            .mailbox
            .sender
            .send(AgendaEvent::Withdraw.into())
            .await
            .is_err()
        {
            error!(%holon, "the agenda manager is gone: bookings are not handed back");
            return;
        }
        let mut agenda = links.views.agenda.subscribe();
        let drained = tokio::time::timeout(grace, agenda.wait_for(|view| view.drained))
            .await
            .map(|waited| waited.map(|_| ()));
        match drained {
            Ok(Ok(())) => {
                info!(%holon, "withdrawn: the running job finished and every result was acknowledged")
            }
            Ok(Err(_)) => error!(%holon, "the agenda view closed while withdrawing"),
            Err(_) => {
                let view = links.views.agenda.borrow();
                warn!(%holon, running = view.snapshot.current.is_some(), undelivered = view.snapshot.undelivered, ?grace, "shutdown grace elapsed; stopping anyway");
            }
        }
    }
}

/// Runs a resource holon until `shutdown` is cancelled (then it withdraws its token,
/// stops its components in reverse order, closes the session and returns `Ok`) or its
/// supervisor gives up (then it returns the error, for a non-zero exit).
pub async fn run(config: ResourceConfig, shutdown: CancellationToken) -> Result<(), NodeError> {
    let holon = config.holon.clone();
    let alive_key = config.keys.alive(&holon);
    let session = config
        .zenoh
        .open(
            &holon::tls::identity("resource", holon.name()),
            STARTUP_TIMEOUT,
        )
        .await?;
    info!(%holon, zid = %session.zid(), "zenoh session open");
    let outcome = serve(&config, &session, &alive_key, shutdown).await;
    if let Err(e) = session.close().await {
        error!(%holon, error = %e, "cannot close the zenoh session");
    }
    info!(%holon, "holon stopped");
    outcome
}

/// The holon's life on an open session: claim its name, start its components, declare
/// its token, serve until shutdown or until the supervisor gives up, then stop.
async fn serve(
    config: &ResourceConfig,
    session: &zenoh::Session,
    alive_key: &str,
    shutdown: CancellationToken,
) -> Result<(), NodeError> {
    let holon = &config.holon;
    // A twin (the same name alive elsewhere in the cell) is refused before this process
    // answers anything.
    let _claim =
        holon::presence::claim(session, alive_key, &holon.to_string(), STARTUP_TIMEOUT).await?;
    let wiring = Wiring::new(config, session)?;
    let serving = wiring.communication.serving.notified();
    let components = CancellationToken::new();
    let mut supervision = tokio::spawn(wiring.supervisor(config).run(components.clone()));
    let started = tokio::select! {
        _ = serving => Ok(()),
        _ = tokio::time::sleep(STARTUP_TIMEOUT) => Err(NodeError::Startup(STARTUP_TIMEOUT)),
        result = &mut supervision => Err(supervisor_ended(result)
            .err()
            .unwrap_or(NodeError::Startup(STARTUP_TIMEOUT))),
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
    info!(%holon, key = %alive_key, "holon ready");

    let outcome = tokio::select! {
        _ = shutdown.cancelled() => {
            wiring.withdraw(config.shutdown_grace).await;
            Ok(())
        }
        result = &mut supervision => supervisor_ended(result),
    };
    // Withdraw presence first: no one should book a holon that is going away.
    if let Err(e) = token.undeclare().await {
        error!(%holon, error = %e, "cannot withdraw the liveliness token");
    }
    if outcome.is_ok() {
        components.cancel();
        wait_stopped(holon, supervision).await;
    }
    outcome
}

/// What the supervisor's end means for the holon.
fn supervisor_ended(
    result: Result<Result<(), holon::supervisor::SupervisorError>, tokio::task::JoinError>,
) -> Result<(), NodeError> {
    match result {
        Ok(Ok(())) => Ok(()),
        Ok(Err(e)) => Err(NodeError::Supervisor(e)),
        Err(e) => Err(NodeError::Zenoh(format!("supervisor task: {e}"))),
    }
}

/// Waits for the supervisor to stop the components (each within its shutdown timeout).
async fn wait_stopped(
    holon: &schemas::HolonId,
    supervision: tokio::task::JoinHandle<Result<(), holon::supervisor::SupervisorError>>,
) {
    if let Err(e) = supervisor_ended(supervision.await) {
        warn!(%holon, error = %e, "the components did not stop cleanly");
    }
}

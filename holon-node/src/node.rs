//! The resource holon process: four component tasks under one supervisor.
//!
//! Start order: execution (with the interfacing module's controller connection),
//! agenda manager, requesters (the booking lifetime), communication; the stop order is
//! the reverse, so the holon stops taking requests first and closes the controller
//! connection last (see [`crate::component`]).
//! The components talk through mailboxes, and each owns its state; both live here,
//! beside the supervisor ([`crate::handover`]), so restarting a component loses neither
//! its state nor a message in flight.

use std::sync::Arc;
use std::time::Duration;

use holon::life::{Behaviour, Leaving, LivelinessClaim, Next, StandInSpec, Start, Work};
use holon::{ChildSpec, Supervisor};
use robot_bridge::client::{FenceHandle, FencePort};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tracing::{error, info, warn};

use crate::component::agenda_manager::{self, AgendaMessage, JournalledAgenda};
use crate::component::{communication, execution, interfacing, layout, requesters};
use crate::config::ResourceConfig;
use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};
use crate::machine::absences::{Absences, Moment};
use crate::machine::agenda::{AgendaEvent, Inheritance};
use crate::machine::execution::lanes::Executions;
use crate::views::{FenceView, Views};

mod fence_report;
mod stand_in;
mod standby;

use stand_in::stand_in_answer;

pub use crate::identity::STARTUP_TIMEOUT;

/// Why a holon process stops with an error.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// A step of the holon's life cycle: its session, its name, a take-over, a
    /// hand-over.
    #[error(transparent)]
    Life(#[from] holon::life::LifeError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("the components did not come up within {0:?}")]
    Startup(Duration),
    #[error(transparent)]
    Supervisor(#[from] holon::supervisor::SupervisorError),
    #[error(transparent)]
    Journal(#[from] holon::journal::JournalError),
    /// A fenced resource cannot claim its controller (docs/reliability.md).
    #[error("standby refused: {0}")]
    Fence(String),
}

/// The components' links, built once per process: they outlive the components'
/// restarts, and each component sees only its own.
struct Wiring {
    /// The execution component's (with the interfacing module's).
    execution: Arc<execution::Links>,
    /// The agenda manager's: the agenda and its mailbox.
    agenda_manager: Arc<agenda_manager::Links>,
    /// The requesters component's: the bookings' lifetime.
    requesters: Arc<requesters::Links>,
    /// The communication component's: the queryables, the views, the config.
    communication: Arc<communication::Links>,
    /// A transporter's: the cell's layout, for its agenda.
    layout: Option<Arc<layout::Links>>,
}

/// How long a resource handing over waits for its results to be acknowledged before it
/// lets go (the successor delivers what is left).
const RESULTS_BEFORE_RELEASE: Duration = Duration::from_secs(2);

impl Wiring {
    /// The mailboxes, the owned states (the agenda restored from the journal if the
    /// holon has one) and the views, linked.
    fn new(
        config: &ResourceConfig,
        session: &zenoh::Session,
        inheritance: Inheritance,
        fence: Option<(FenceHandle, FencePort)>,
    ) -> Result<Wiring, NodeError> {
        let holon = config.holon.clone();
        let agenda = JournalledAgenda::open(config, inheritance)?;
        let mut views = Views::new(agenda.view(), Absences::new(Moment::now()));
        views.time_scale = config.time_scale;
        let views = Arc::new(views);
        if fence.is_some() {
            views.fence.send_replace(FenceView::Standby);
        }
        let (fence, port) = fence.map(|(f, p)| (f, Handover::new(p))).unzip();
        let faults = Arc::new(Faults::default());
        // Requests come straight from the queryables' callbacks: as many may wait as
        // waited for the communication component before (see `communication`).
        let agenda_mail: Mailbox<AgendaMessage> =
            Mailbox::with_capacity(communication::QUERY_QUEUE);
        let jobs: Mailbox<crate::machine::execution::ExecutionRequest> = Mailbox::new();
        Ok(Wiring {
            execution: Arc::new(execution::Links {
                holon: holon.clone(),
                execution: Handover::new(Executions::new(
                    config.catalog.clone(),
                    port.is_some(),
                    config.jobs_at_once,
                )),
                jobs: jobs.share(),
                interfacing: interfacing::Links {
                    controller: config.controller.clone(),
                    reconnect_max: config.reconnect_max,
                    fence: port,
                    fence_view: views.fence.subscribe(),
                },
                agenda: agenda_mail.sender.clone(),
                views: views.clone(),
                faults: faults.clone(),
                session: session.clone(),
                departed_timeout: config.delivery.attempt_timeout,
            }),
            agenda_manager: Arc::new(agenda_manager::Links {
                holon: holon.clone(),
                agenda: Handover::new(agenda),
                mailbox: agenda_mail.share(),
                jobs: jobs.sender.clone(),
                session: session.clone(),
                delivery: config.delivery,
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
            layout: config
                .layout
                .clone()
                .filter(|part| part.transporter.is_some())
                .map(|own| {
                    Arc::new(layout::Links {
                        holon: config.holon.clone(),
                        session: session.clone(),
                        keys: config.keys.clone(),
                        own,
                        agenda: agenda_mail.sender.clone(),
                    })
                }),
            communication: Arc::new(communication::Links {
                config: config.clone(),
                session: session.clone(),
                agenda: agenda_mail.sender,
                views,
                faults,
                serving: Arc::new(Notify::new()),
                fence,
            }),
        })
    }

    /// The supervisor of the four component tasks, in start order.
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
        let supervisor =
            Supervisor::new(config.holon.to_string(), config.strategy, config.intensity)
                .child(spec("execution", &self.execution, execution::run))
                .child(spec("agenda", &self.agenda_manager, agenda_manager::run))
                .child(spec("requesters", &self.requesters, requesters::run));
        let supervisor = match &self.layout {
            Some(links) => supervisor.child(spec("layout", links, layout::run)),
            None => supervisor,
        };
        supervisor.child(spec(
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
        // With a journal, results whose requesters have gone (an order-node stopped
        // on purpose, before the resources) need not be waited for: they are delivered
        // when the holon is back.
        let durable = self.communication.config.data_dir.is_some();
        let mut agenda = links.views.agenda.subscribe();
        let mut absences = links.views.absences.subscribe();
        let drained = tokio::time::timeout(grace, async {
            loop {
                {
                    let view = agenda.borrow_and_update();
                    if view.drained {
                        return Ok::<usize, tokio::sync::watch::error::RecvError>(0);
                    }
                    let absences = absences.borrow_and_update();
                    if durable && only_absent_requesters_wait(&view, &absences) {
                        return Ok(view.deliverable.len());
                    }
                }
                tokio::select! {
                    changed = agenda.changed() => changed?,
                    changed = absences.changed() => changed?,
                }
            }
        })
        .await;
        match drained {
            Ok(Ok(0)) => {
                info!(%holon, "withdrawn: the running job finished and every result was acknowledged")
            }
            Ok(Ok(kept)) => {
                info!(%holon, results = kept, "withdrawn: the running job finished; its requesters are gone, so the results not yet acknowledged stay in the journal and are delivered when this resource is back")
            }
            Ok(Err(_)) => error!(%holon, "the agenda view closed while withdrawing"),
            Err(_) => {
                let view = links.views.agenda.borrow();
                warn!(%holon, running = view.snapshot.current.is_some(), undelivered = view.snapshot.undelivered, ?grace, "shutdown grace elapsed; stopping anyway");
            }
        }
    }

    /// Prepares a hand-over to a successor: takes no new work and starts nothing, keeps
    /// the bookings, and waits until the running job has finished (its result is in the
    /// journal). Within `wait`: else the hand-over is abandoned (the resource serves on)
    /// and the error says why. Then it waits (at most [`RESULTS_BEFORE_RELEASE`]) for
    /// its results to be acknowledged.
    async fn hand_over(&self, wait: Duration) -> Result<(), String> {
        let links = &self.agenda_manager;
        let holon = &links.holon;
        let mut agenda = links.views.agenda.subscribe();
        if links
            .mailbox
            .sender
            .send(AgendaEvent::HandOver.into())
            .await
            .is_err()
        {
            return Err("the agenda manager is gone".into());
        }
        let running = links.views.agenda.borrow().snapshot.current.is_some();
        info!(%holon, running, bookings = links.views.agenda.borrow().snapshot.agenda.len(), "handing over: no new work, bookings kept, the running step finishes");
        let quiet = tokio::time::timeout(
            wait,
            agenda.wait_for(|view| view.snapshot.handing_over && view.snapshot.current.is_none()),
        )
        .await
        .map(|waited| waited.map(|_| ()));
        match quiet {
            Ok(Ok(())) => Ok(()),
            Ok(Err(_)) => Err("the agenda manager stopped while handing over".to_string()),
            Err(_) => {
                self.abandon_hand_over().await;
                Err(format!(
                    "its running step did not finish within {wait:?}; it serves on (try again with a longer --take-over-wait-ms)"
                ))
            }
        }?;
        // Its result (and any other not yet acknowledged) is delivered now, not after
        // the gap: should the successor never serve, its order would otherwise wait
        // out its grace for it and do the step again elsewhere. Bounded: a result whose
        // order-node is away goes with the journal, and the successor delivers it.
        let delivered = tokio::time::timeout(
            RESULTS_BEFORE_RELEASE,
            agenda.wait_for(|view| view.snapshot.undelivered == 0),
        )
        .await;
        if delivered.is_err() {
            let undelivered = links.views.agenda.borrow().snapshot.undelivered;
            warn!(%holon, undelivered, within = ?RESULTS_BEFORE_RELEASE, "results not acknowledged before the hand-over; the successor delivers them from the journal");
        }
        // The running step's result must be in the journal: a successor reads only that.
        if let Some(fault) = self.journal_fault() {
            self.abandon_hand_over().await;
            return Err(format!("its journal cannot be written ({fault}): what it holds in memory only would be lost; it serves on"));
        }
        Ok(())
    }

    /// Serves on after a hand-over was prepared and not done.
    async fn abandon_hand_over(&self) {
        let links = &self.agenda_manager;
        if links
            .mailbox
            .sender
            .send(AgendaEvent::HandOverAbandoned.into())
            .await
            .is_err()
        {
            error!(holon = %links.holon, "the agenda manager is gone: the hand-over cannot be undone");
        }
    }

    /// Why the journal cannot be written, while it cannot.
    fn journal_fault(&self) -> Option<String> {
        self.agenda_manager
            .views
            .agenda
            .borrow()
            .snapshot
            .journal_fault
            .clone()
    }
}

/// Withdrawing: nothing runs, and every result still to be acknowledged is journalled
/// (none held by a journal fault) and waits for a requester that is gone.
fn only_absent_requesters_wait(
    view: &crate::views::AgendaView,
    absences: &crate::machine::absences::Absences,
) -> bool {
    view.snapshot.current.is_none()
        && view.snapshot.journal_fault.is_none()
        && view.deliverable.len() == view.snapshot.undelivered
        && view
            .deliverable
            .iter()
            .all(|result| absences.absent_since(&result.requester).is_some())
}

/// Runs a resource holon until `shutdown` is cancelled (then it withdraws its token,
/// stops its components in reverse order, closes the session and returns `Ok`), until
/// it hands over to a successor, or until its supervisor gives up (then it returns the
/// error, for a non-zero exit). A fenced resource's leadership is its controller's
/// claim ([`standby::ControllerFence`]), any other's the name's liveliness claim.
pub async fn run(config: ResourceConfig, shutdown: CancellationToken) -> Result<(), NodeError> {
    let holon = config.holon.clone();
    for warning in config.controller.dialect.warnings() {
        warn!(%holon, dialect = %config.controller.dialect.name, "{warning}");
    }
    let process = holon::life::Process {
        life: life(&config),
        zenoh: &config.zenoh,
        tls_identity: holon::role::identity(holon::role::Role::Resource, holon.name()),
    };
    let node = Node { config: &config };
    let outcome = if config.fenced {
        let fence = standby::ControllerFence::new(&config);
        holon::life::run(process, node, fence, shutdown).await
    } else {
        holon::life::run(process, node, LivelinessClaim::default(), shutdown).await
    };
    info!(%holon, "holon stopped");
    outcome
}

/// Who the resource is, for the life cycle every holon shares.
fn life(config: &ResourceConfig) -> holon::life::Life {
    holon::life::Life {
        presence_key: config.keys.alive(&config.holon),
        holder: config.holon.to_string(),
        version: crate::VERSION,
        take_over: config.take_over,
        data_dir: config.data_dir.clone(),
        startup_timeout: STARTUP_TIMEOUT,
    }
}

/// A resource's own part of its life: it starts its components.
struct Node<'a> {
    /// Its config.
    config: &'a ResourceConfig,
}

/// The supervisor's task.
type Supervision = tokio::task::JoinHandle<Result<(), holon::supervisor::SupervisorError>>;

impl Behaviour for Node<'_> {
    /// A fenced resource's controller handle, from its leadership.
    type Grant = Option<(FenceHandle, FencePort)>;
    type Work = Resource;
    type Error = NodeError;

    /// Wires the components (the agenda restored from the journal: a hand-over's when
    /// a predecessor released it just now) and starts their supervisor.
    async fn start(&mut self, start: Start<Self::Grant>) -> Result<Resource, NodeError> {
        let inheritance = match start.handed_over {
            true => Inheritance::HandedOver,
            false => Inheritance::Restarted,
        };
        let wiring = Wiring::new(self.config, &start.session, inheritance, start.grant)?;
        let components = CancellationToken::new();
        let supervision = tokio::spawn(wiring.supervisor(self.config).run(components.clone()));
        Ok(Resource {
            wiring,
            components,
            supervision: Some(supervision),
        })
    }
}

/// A resource's components at work, under their supervisor.
struct Resource {
    /// Their links and owned states (the journal closes when they are dropped).
    wiring: Wiring,
    /// Stops the components.
    components: CancellationToken,
    /// The supervisor's task, until it ended.
    supervision: Option<Supervision>,
}

impl Resource {
    /// The supervisor's end (pending once it was seen).
    async fn supervisor_end(&mut self) -> Result<(), NodeError> {
        match &mut self.supervision {
            Some(supervision) => {
                let result = supervision.await;
                self.supervision = None;
                supervisor_ended(result)
            }
            None => std::future::pending().await,
        }
    }

    /// Its config.
    fn config(&self) -> &ResourceConfig {
        &self.wiring.communication.config
    }
}

impl Work for Resource {
    /// A resource's events are its components': the driver only sees them end.
    type Event = std::convert::Infallible;
    type Error = NodeError;

    /// The components serve (the communication component said so).
    async fn ready(&mut self) -> Result<(), NodeError> {
        let serving = self.wiring.communication.serving.clone();
        tokio::select! {
            _ = serving.notified() => Ok(()),
            _ = tokio::time::sleep(STARTUP_TIMEOUT) => Err(NodeError::Startup(STARTUP_TIMEOUT)),
            ended = self.supervisor_end() => Err(ended.err().unwrap_or(NodeError::Startup(STARTUP_TIMEOUT))),
        }
    }

    async fn next(&mut self) -> Next<Self::Event, NodeError> {
        Next::Ended(self.supervisor_end().await)
    }

    async fn handle(&mut self, event: Self::Event) {
        match event {}
    }

    /// A successor with another data directory would not take over the agenda; a
    /// journal that cannot be written would lose what is held in memory only.
    fn refusal(&self, request: &holon::takeover::Request) -> Option<String> {
        let data_dir = &self.config().data_dir;
        if !holon::life::same_data_dir(data_dir.as_deref(), request.data_dir.as_deref()) {
            return Some(format!(
                "its data dir {:?} is not this holon's {:?}: it would not take over the agenda",
                request.data_dir, data_dir
            ));
        }
        self.wiring.journal_fault().map(|fault| format!("its journal cannot be written ({fault}): what it holds in memory only would be lost; it serves on"))
    }

    async fn prepare(&mut self, wait: Duration) -> Result<(), String> {
        self.wiring.hand_over(wait).await
    }

    async fn leave(&mut self, how: &Leaving) {
        let config = self.config();
        let holon = &config.holon;
        match how {
            Leaving::Stopping => self.wiring.withdraw(config.shutdown_grace).await,
            // Requesters learn the hand-over is planned from this last state, published
            // before the token goes, so it is seen first.
            Leaving::HandingOver => {
                let last_state = serde_json::to_vec(&self.wiring.communication.views.snapshot())
                    .expect("a snapshot serializes");
                if let Err(e) = self
                    .wiring
                    .communication
                    .session
                    .put(config.keys.state(holon), last_state)
                    .await
                {
                    warn!(%holon, error = %e, "cannot publish the hand-over state; requesters see a vanished resource");
                }
            }
            // No one may book it from now on.
            Leaving::Deposed(_) => {
                self.wiring
                    .communication
                    .views
                    .fence
                    .send_replace(FenceView::Standby);
            }
            Leaving::WorkEnded => {}
        }
    }

    /// On its Service key: `unavailable` with a retry hint, in a Service reply.
    fn stand_in(&self) -> StandInSpec {
        let holon = &self.config().holon;
        StandInSpec {
            keys: vec![(self.config().keys.service(holon.name()), false)],
            answer: stand_in_answer(holon.clone()),
        }
    }

    /// Stops the components in reverse order; deposed, it first drops its bookings
    /// ([`standby::step_down`]). The journal closes with the links.
    async fn stop(mut self, how: &Leaving) -> Result<(), NodeError> {
        let holon = self.config().holon.clone();
        if let Leaving::Deposed(_) = how {
            let grace = self.config().shutdown_grace.min(standby::STEP_DOWN_GRACE);
            standby::step_down(&self.wiring, grace).await;
        }
        self.components.cancel();
        if let Some(supervision) = self.supervision.take() {
            wait_stopped(&holon, supervision).await;
        }
        drop(self.wiring);
        if let Leaving::Deposed(_) = how {
            info!(%holon, "stepped down: a standby again");
        }
        Ok(())
    }
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

//! The resource holon process: four components under one supervisor.
//!
//! Start order: interfacing, execution, agenda manager, requesters (the booking
//! lifetime, see [`crate::requesters`]), communication (stop order is the
//! reverse, so the holon stops taking requests first and closes the controller
//! connection last). The components talk through mailboxes that outlive them, and the
//! FSM states (agenda, execution) live beside the supervisor, so restarting a component
//! loses neither the agenda nor a message in flight.

use std::collections::HashSet;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;

use holon::{ChildError, ChildSpec, Supervisor};
use robot_bridge::client::{self, ControllerEvent};
use schemas::{HolonId, ResourceSnapshot, RobotCommand, Service};
use tokio::sync::{mpsc, Notify};
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};

use crate::agenda::{AgendaAction, AgendaEvent, AgendaManager, AgendaRecord};
use crate::config::ResourceConfig;
use crate::execution::{Execution, ExecutionAction, ExecutionEvent};
use crate::requesters::{Absences, Moment};
use holon::journal::Journal;

/// How long a holon waits for zenoh to open and for its components to come up.
pub const STARTUP_TIMEOUT: Duration = Duration::from_secs(10);

const MAILBOX: usize = 256;

/// How often a journal that cannot be written is tried again.
const JOURNAL_RETRY: Duration = Duration::from_secs(1);

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

/// A message to the communication component.
#[derive(Debug)]
pub enum CommunicationMessage {
    /// Deliver this result to its `reply_to` until acknowledged.
    Deliver(Service),
    /// Publish a state snapshot.
    StateChanged,
    /// The holon is shutting down: undeclare the offer queryables.
    StopOffering,
}

/// A mailbox: the sender is cloned freely; the receiver is held by the running
/// component and taken over by its successor after a restart.
pub struct Mailbox<T> {
    pub sender: mpsc::Sender<T>,
    receiver: Arc<tokio::sync::Mutex<mpsc::Receiver<T>>>,
}

impl<T> Mailbox<T> {
    fn new() -> Self {
        let (sender, receiver) = mpsc::channel(MAILBOX);
        Mailbox {
            sender,
            receiver: Arc::new(tokio::sync::Mutex::new(receiver)),
        }
    }

    pub async fn take(&self) -> tokio::sync::OwnedMutexGuard<mpsc::Receiver<T>> {
        self.receiver.clone().lock_owned().await
    }
}

/// Fault injection: makes a component panic, as `exit(Pid, kill)` would in Erlang.
/// Reachable only through `debug/crash`, declared with `--allow-fault-injection`.
#[derive(Default)]
pub struct Faults {
    pub interfacing: Notify,
    pub execution: Notify,
    pub agenda: Notify,
    pub communication: Notify,
}

impl Faults {
    pub fn get(&self, component: &str) -> Option<&Notify> {
        match component {
            "interfacing" => Some(&self.interfacing),
            "execution" => Some(&self.execution),
            "agenda" => Some(&self.agenda),
            "communication" => Some(&self.communication),
            _ => None,
        }
    }
}

/// Everything the components share; it outlives their restarts.
pub struct Node {
    pub config: ResourceConfig,
    pub session: zenoh::Session,
    agenda: Mutex<AgendaManager>,
    execution: Mutex<Execution>,
    pub agenda_mail: Mailbox<AgendaEvent>,
    pub execution_mail: Mailbox<ExecutionEvent>,
    pub controller_mail: Mailbox<ControllerEvent>,
    pub command_mail: Mailbox<RobotCommand>,
    pub communication_mail: Mailbox<CommunicationMessage>,
    pub faults: Faults,
    /// Notified each time the communication component has declared its queryables.
    pub serving: Notify,
    /// Set when the holon starts shutting down: offers stay undeclared.
    pub withdrawing: AtomicBool,
    /// The durable state, if the holon has a data directory.
    journal: Option<Journal>,
    /// Which requesters are absent from the cell, kept by the requesters component
    /// (read here for the snapshot).
    absences: Mutex<Absences>,
    /// Set while the journal cannot be written (a full disk, ...): why. The resource
    /// then stops offering, refuses requests that would change its agenda, and holds
    /// results back until a write succeeds (the agenda component retries it).
    journal_fault: Mutex<Option<String>>,
    /// Results that happened while the journal could not record them, oldest first:
    /// delivered once they are written.
    held: Mutex<Vec<Service>>,
}

/// The journal record that holds the agenda.
const AGENDA_RECORD: (&str, &str) = ("agenda", "agenda");

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    // A component that panicked while holding the lock left a complete state behind:
    // the FSMs change their state only in `handle`, which does no I/O and cannot await.
    mutex.lock().unwrap_or_else(|e| e.into_inner())
}

impl Node {
    /// The node, its agenda restored from the journal if it has one. Results not
    /// acknowledged before a restart (and an interrupted job's `failed`) are delivered by
    /// the communication component, which delivers every undelivered result when it starts.
    pub fn new(config: ResourceConfig, session: zenoh::Session) -> Result<Node, NodeError> {
        let journal = match &config.data_dir {
            Some(dir) => {
                let file = format!("resource-{}.sqlite", config.holon.name());
                Some(Journal::open(dir, &file, config.durability)?)
            }
            None => None,
        };
        let record: AgendaRecord = match &journal {
            Some(journal) => journal
                .get(AGENDA_RECORD.0, AGENDA_RECORD.1)?
                .unwrap_or_default(),
            None => AgendaRecord::default(),
        };
        match &journal {
            Some(journal) => {
                info!(holon = %config.holon, journal = %journal.path().display(), bookings = record.bookings.len(), interrupted = record.current.is_some(), undelivered = record.undelivered.len(), "journal opened")
            }
            None => {
                warn!(holon = %config.holon, "no data directory: the agenda is not durable (use --data-dir)")
            }
        }
        let agenda = AgendaManager::restore(
            config.holon.clone(),
            config.catalog.clone(),
            config.agenda_capacity,
            record,
        );
        if let Some(journal) = &journal {
            // The interrupted job became an undelivered result: record that at once.
            journal.put(AGENDA_RECORD.0, AGENDA_RECORD.1, &agenda.record())?;
        }
        let execution = Execution::new(config.catalog.clone());
        let node = Node {
            config,
            session,
            agenda: Mutex::new(agenda),
            execution: Mutex::new(execution),
            agenda_mail: Mailbox::new(),
            execution_mail: Mailbox::new(),
            controller_mail: Mailbox::new(),
            command_mail: Mailbox::new(),
            communication_mail: Mailbox::new(),
            faults: Faults::default(),
            serving: Notify::new(),
            withdrawing: AtomicBool::new(false),
            journal,
            absences: Mutex::new(Absences::new(Moment::now())),
            journal_fault: Mutex::new(None),
            held: Mutex::new(Vec::new()),
        };
        Ok(node)
    }

    /// The snapshot published on `resource/<name>/state`.
    pub fn snapshot(&self) -> ResourceSnapshot {
        let (controller, step) = {
            let execution = lock(&self.execution);
            (execution.controller().as_str(), execution.current_step())
        };
        let mut snapshot = lock(&self.agenda).snapshot(controller, step);
        snapshot.journal_fault = lock(&self.journal_fault).clone();
        let absences = lock(&self.absences);
        for booking in &mut snapshot.agenda {
            booking.requester_absent_since = absences
                .absent_since(&booking.requester)
                .map(|since| since.unix_ms);
        }
        snapshot
    }

    /// The requesters of the bookings on the agenda.
    pub fn booked_requesters(&self) -> HashSet<HolonId> {
        lock(&self.agenda)
            .bookings()
            .iter()
            .map(|b| b.requester.clone())
            .collect()
    }

    /// Replaces what is known of the requesters' presence (a requesters component
    /// starting).
    pub fn set_absences(&self, absences: Absences) {
        *lock(&self.absences) = absences;
    }

    /// Changes what is known of the requesters' presence.
    pub fn update_absences<R>(&self, change: impl FnOnce(&mut Absences) -> R) -> R {
        change(&mut lock(&self.absences))
    }

    /// Stops offering, hands every booking back, and waits (at most the configured
    /// grace) until the running job has finished and every result is acknowledged.
    async fn withdraw(&self) {
        let holon = &self.config.holon;
        self.withdrawing.store(true, Ordering::SeqCst);
        let _ = self
            .communication_mail
            .sender
            .send(CommunicationMessage::StopOffering)
            .await;
        let held = std::mem::take(&mut *lock(&self.held));
        if !held.is_empty() {
            // Stopping with results the journal could not record: deliver them anyway,
            // so the orders record the outcomes. After a restart this resource reports
            // those steps `interrupted` (its journal still shows them running), which
            // the orders acknowledge and ignore as late reports of finished conversations.
            warn!(holon = %holon, results = held.len(), "shutting down while the journal cannot be written: delivering the held results unrecorded");
            for result in held {
                if let Err(e) = self
                    .communication_mail
                    .sender
                    .send(CommunicationMessage::Deliver(result))
                    .await
                {
                    error!(holon = %holon, error = %e, "cannot deliver a held result");
                }
            }
        }
        let bookings = lock(&self.agenda).bookings().len();
        info!(holon = %holon, bookings, "withdrawing: no new work, handing bookings back");
        let _ = self.agenda_mail.sender.send(AgendaEvent::Withdraw).await;
        let deadline = tokio::time::Instant::now() + self.config.shutdown_grace;
        loop {
            if lock(&self.agenda).is_drained() {
                info!(holon = %holon, "withdrawn: the running job finished and every result was acknowledged");
                return;
            }
            if tokio::time::Instant::now() >= deadline {
                let agenda = lock(&self.agenda);
                warn!(holon = %holon, running = agenda.current().is_some(), undelivered = agenda.undelivered().len(), grace = ?self.config.shutdown_grace, "shutdown grace elapsed; stopping anyway");
                return;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Whether the resource can take new work: its controller is ready and it is not
    /// withdrawing.
    pub fn can_take_work(&self) -> bool {
        // One lock at a time (the agenda's is taken before the fault's elsewhere).
        let journal_ok = self.journal_fault().is_none();
        let ready = lock(&self.agenda).status_name() != "init";
        !self.withdrawing.load(Ordering::SeqCst) && journal_ok && ready
    }

    /// Why the journal cannot be written, while it cannot.
    pub fn journal_fault(&self) -> Option<String> {
        lock(&self.journal_fault).clone()
    }

    /// Records that the journal write failed: the first failure is logged and the state
    /// republished (offers stop); repeats are not logged again.
    fn journal_failed(&self, error: &holon::journal::JournalError) {
        let mut fault = lock(&self.journal_fault);
        if fault.is_none() {
            error!(holon = %self.config.holon, component = "agenda", error = %error, "the journal cannot be written: no new work is taken and results are held until a write succeeds (retried every second)");
            if let Err(e) = self
                .communication_mail
                .sender
                .try_send(CommunicationMessage::StateChanged)
            {
                warn!(holon = %self.config.holon, error = %e, "cannot announce the journal fault; the next state change will");
            }
        }
        *fault = Some(error.to_string());
    }

    /// A journal write succeeded: if it was failing, the fault ends and the held results
    /// are released (to deliver, after a state change).
    fn journal_written(&self) -> Vec<AgendaAction> {
        if lock(&self.journal_fault).take().is_none() {
            return vec![];
        }
        let held = std::mem::take(&mut *lock(&self.held));
        info!(holon = %self.config.holon, component = "agenda", results = held.len(), "the journal can be written again: held results are delivered, new work is taken");
        held.into_iter()
            .map(AgendaAction::Deliver)
            .chain([AgendaAction::StateChanged])
            .collect()
    }

    /// Results not yet acknowledged (for a restarted communication component).
    pub fn undelivered(&self) -> Vec<Service> {
        lock(&self.agenda).undelivered().to_vec()
    }

    pub(crate) async fn state_changed(&self) {
        let _ = self
            .communication_mail
            .sender
            .send(CommunicationMessage::StateChanged)
            .await;
    }
}

/// The interfacing component: robot-bridge's controller client.
async fn interfacing(node: Arc<Node>, token: CancellationToken) -> Result<(), ChildError> {
    let mut commands = node.command_mail.take().await;
    tokio::select! {
        _ = client::run(node.config.controller.clone(), &mut commands, node.controller_mail.sender.clone(), token.clone()) => {
            if token.is_cancelled() { Ok(()) } else { Err("the controller client stopped".into()) }
        }
        _ = node.faults.interfacing.notified() => panic!("fault injection: interfacing crashed"),
    }
}

/// The execution component: runs the execution FSM.
async fn execution(node: Arc<Node>, token: CancellationToken) -> Result<(), ChildError> {
    let holon = node.config.holon.to_string();
    let mut starts = node.execution_mail.take().await;
    let mut controller = node.controller_mail.take().await;
    loop {
        let event = tokio::select! {
            _ = token.cancelled() => return Ok(()),
            _ = node.faults.execution.notified() => panic!("fault injection: execution crashed"),
            event = starts.recv() => event.ok_or("execution mailbox closed")?,
            event = controller.recv() => ExecutionEvent::Controller(event.ok_or("controller mailbox closed")?),
        };
        let (before, actions, after) = {
            let mut execution = lock(&node.execution);
            let before = format!("{:?}", state_name(execution.state()));
            let actions = execution.handle(event.clone());
            (before, actions, state_name(execution.state()))
        };
        debug!(%holon, component = "execution", event = ?event, "event");
        if before != format!("{after:?}") {
            info!(%holon, component = "execution", from = %before.trim_matches('"'), to = %after, "transition");
        }
        for action in actions {
            match action {
                ExecutionAction::Command(command) => {
                    info!(%holon, component = "execution", command_id = command.id, action = %command.action, "command to controller");
                    node.command_mail
                        .sender
                        .send(command)
                        .await
                        .map_err(|_| "command mailbox closed")?;
                }
                ExecutionAction::Ready => send_agenda(&node, AgendaEvent::ExecutionReady).await?,
                ExecutionAction::Unavailable => {
                    send_agenda(&node, AgendaEvent::ExecutionUnavailable).await?
                }
                ExecutionAction::Finished {
                    conversation_id,
                    outcome,
                } => {
                    info!(%holon, component = "execution", %conversation_id, outcome = %outcome, "job finished");
                    send_agenda(
                        &node,
                        AgendaEvent::ExecutionFinished {
                            conversation_id,
                            outcome,
                        },
                    )
                    .await?
                }
                ExecutionAction::StateChanged => node.state_changed().await,
            }
        }
    }
}

fn state_name(state: &crate::execution::ExecutionState) -> String {
    match state {
        crate::execution::ExecutionState::Init => "init".into(),
        crate::execution::ExecutionState::Ready => "ready".into(),
        crate::execution::ExecutionState::Running { step, .. } => format!("step {}", step + 1),
    }
}

pub(crate) async fn send_agenda(node: &Node, event: AgendaEvent) -> Result<(), ChildError> {
    node.agenda_mail
        .sender
        .send(event)
        .await
        .map_err(|_| "agenda mailbox closed".into())
}

/// The agenda manager component: runs the agenda FSM on the events of the execution
/// and communication components (job finished, result acknowledged, withdraw, ...).
/// Requests from other holons do not pass through its mailbox: the communication
/// component runs them through [`agenda_transition`] in place, which saves two task
/// hops per request (profiled: about a fifth of a booking above the zenoh floor).
async fn agenda(node: Arc<Node>, token: CancellationToken) -> Result<(), ChildError> {
    let mut mailbox = node.agenda_mail.take().await;
    let mut journal_retry = tokio::time::interval(JOURNAL_RETRY);
    journal_retry.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let actions = tokio::select! {
            _ = token.cancelled() => return Ok(()),
            _ = node.faults.agenda.notified() => panic!("fault injection: agenda manager crashed"),
            _ = journal_retry.tick() => retry_journal(&node),
            event = mailbox.recv() => {
                let event = event.ok_or("agenda mailbox closed")?;
                let Some(actions) = agenda_transition(&node, event) else {
                    continue;
                };
                actions
            }
        };
        for action in actions {
            match action {
                // Events have nobody to answer.
                AgendaAction::Reply(_) => {}
                AgendaAction::Execute(job) => start_execution(&node, job).await?,
                AgendaAction::Deliver(result) => node
                    .communication_mail
                    .sender
                    .send(CommunicationMessage::Deliver(result))
                    .await
                    .map_err(|_| "communication mailbox closed")?,
                AgendaAction::StateChanged => node.state_changed().await,
            }
        }
    }
}

/// One event through the agenda FSM, under its lock, and the journal write of what
/// changed: the actions for the caller to perform, or `None` when the write failed
/// (then the agenda is as it was and nothing is answered or done).
pub(crate) fn agenda_transition(node: &Node, event: AgendaEvent) -> Option<Vec<AgendaAction>> {
    let holon = &node.config.holon;
    let mut agenda = lock(&node.agenda);
    let before = agenda.status_name();
    let previous = node.journal.as_ref().map(|_| agenda.clone());
    // An acknowledgement is recorded with the next write, not on its own: if the
    // process dies first, the result is delivered once more and the order, which
    // ignores duplicates, acknowledges it again. That saves an fsync per job.
    let lazily = matches!(event, AgendaEvent::ResultAcknowledged { .. });
    // A request can be refused when it cannot be recorded; the other events are facts
    // (a job finished, a requester left) that the agenda must keep even then.
    let refusable = matches!(event, AgendaEvent::Request(_));
    let mut actions = agenda.handle(event);
    let changed = previous
        .as_ref()
        .is_some_and(|p| !lazily && p.record() != agenda.record());
    if let (Some(journal), Some(previous), true) = (&node.journal, previous, changed) {
        // Nothing is acknowledged before it is committed.
        match journal.put(AGENDA_RECORD.0, AGENDA_RECORD.1, &agenda.record()) {
            Ok(()) => actions.extend(node.journal_written()),
            Err(e) if refusable => {
                node.journal_failed(&e);
                warn!(%holon, component = "agenda", error = %e, "journal write failed; the request is refused");
                *agenda = previous;
                return None;
            }
            Err(e) => {
                // Kept in memory; results wait for the write (see `retry_journal`).
                node.journal_failed(&e);
                let mut held = lock(&node.held);
                actions.retain(|action| match action {
                    AgendaAction::Deliver(result) => {
                        held.push(result.clone());
                        false
                    }
                    _ => true,
                });
            }
        }
    }
    let after = agenda.status_name();
    if before != after {
        info!(%holon, component = "agenda", from = before, to = after, "transition");
    }
    Some(actions)
}

/// While the journal cannot be written: tries to write the agenda as it is now; on
/// success the fault ends and the held results are released.
fn retry_journal(node: &Node) -> Vec<AgendaAction> {
    let (Some(journal), true) = (&node.journal, node.journal_fault().is_some()) else {
        return vec![];
    };
    let agenda = lock(&node.agenda);
    match journal.put(AGENDA_RECORD.0, AGENDA_RECORD.1, &agenda.record()) {
        Ok(()) => node.journal_written(),
        Err(e) => {
            debug!(holon = %node.config.holon, error = %e, "the journal still cannot be written");
            node.journal_failed(&e);
            vec![]
        }
    }
}

/// Hands a job the agenda accepted to the execution component.
pub(crate) async fn start_execution(
    node: &Node,
    job: crate::agenda::Job,
) -> Result<(), ChildError> {
    info!(holon = %node.config.holon, component = "agenda", conversation_id = %job.conversation_id, requester = %job.requester, "starting execution");
    node.execution_mail
        .sender
        .send(ExecutionEvent::Start(job))
        .await
        .map_err(|_| "execution mailbox closed".into())
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
            &holon::tls::identity("resource", config.holon.name()),
            STARTUP_TIMEOUT,
        )
        .await?;
    info!(holon = %holon, zid = %session.zid(), "zenoh session open");
    // A twin (the same name alive elsewhere in the cell) is refused before this process
    // answers anything.
    let _claim =
        match holon::presence::claim(&session, &alive_key, &holon.to_string(), STARTUP_TIMEOUT)
            .await
        {
            Ok(claim) => claim,
            Err(e) => {
                let _ = session.close().await;
                return Err(e.into());
            }
        };
    let node = match Node::new(config, session.clone()) {
        Ok(node) => Arc::new(node),
        Err(e) => {
            let _ = session.close().await;
            return Err(e);
        }
    };

    let supervisor = Supervisor::new(
        holon.to_string(),
        node.config.strategy,
        node.config.intensity,
    )
    .child(ChildSpec::new("interfacing", {
        let node = node.clone();
        move |token| interfacing(node.clone(), token)
    }))
    .child(ChildSpec::new("execution", {
        let node = node.clone();
        move |token| execution(node.clone(), token)
    }))
    .child(ChildSpec::new("agenda", {
        let node = node.clone();
        move |token| agenda(node.clone(), token)
    }))
    .child(ChildSpec::new("requesters", {
        let node = node.clone();
        move |token| crate::requesters::run(node.clone(), token)
    }))
    .child(ChildSpec::new("communication", {
        let node = node.clone();
        move |token| crate::communication::run(node.clone(), token)
    }));

    let serving = node.serving.notified();
    let components = CancellationToken::new();
    let mut supervision = tokio::spawn(supervisor.run(components.clone()));
    let started = tokio::select! {
        _ = serving => Ok(()),
        _ = tokio::time::sleep(STARTUP_TIMEOUT) => Err(NodeError::Startup(STARTUP_TIMEOUT)),
        result = &mut supervision => match result {
            Ok(Ok(())) => Err(NodeError::Startup(STARTUP_TIMEOUT)),
            Ok(Err(e)) => Err(e.into()),
            Err(e) => Err(NodeError::Zenoh(holon::zenoh_error::describe(&e))),
        },
    };
    if let Err(e) = started {
        components.cancel();
        let _ = supervision.await;
        let _ = session.close().await;
        return Err(e);
    }
    let token = session
        .liveliness()
        .declare_token(&alive_key)
        .await
        .map_err(|e| NodeError::Zenoh(holon::zenoh_error::describe(&e)))?;
    info!(holon = %holon, key = %alive_key, "holon ready");

    let outcome = tokio::select! {
        _ = shutdown.cancelled() => {
            node.withdraw().await;
            Ok(())
        }
        result = &mut supervision => match result {
            Ok(Ok(())) => Ok(()),
            Ok(Err(e)) => Err(NodeError::Supervisor(e)),
            Err(e) => Err(NodeError::Zenoh(format!("supervisor task: {e}"))),
        },
    };
    // Withdraw presence first: no one should book a holon that is going away.
    if let Err(e) = token.undeclare().await {
        error!(holon = %holon, error = %e, "cannot withdraw the liveliness token");
    }
    if outcome.is_ok() {
        components.cancel();
        let _ = supervision.await;
    }
    if let Err(e) = session.close().await {
        error!(holon = %holon, error = %e, "cannot close the zenoh session");
    }
    info!(holon = %holon, "holon stopped");
    outcome
}

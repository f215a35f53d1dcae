//! The agenda and what keeps it durable: the state machine's transitions, what the
//! journal is to record of them, and what follows from how the write went. No I/O but
//! [`JournalledAgenda::write`], which the agenda manager's task calls between
//! [`apply`](JournalledAgenda::apply) and [`settle`](JournalledAgenda::settle).

use holon::journal::{Journal, JournalError};
use schemas::{HolonId, PackmlState, Service};
use tracing::{debug, error, info, warn};

use crate::config::ResourceConfig;
use crate::machine::agenda::{AgendaAction, AgendaEvent, AgendaMachine, AgendaRecord, Inheritance};
use crate::views::AgendaView;

/// The journal record that holds the agenda.
const AGENDA_RECORD: (&str, &str) = ("agenda", "agenda");

/// The journal could not record a request: it is refused and nothing changed.
#[derive(Debug)]
pub(super) struct NotRecorded;

/// An event through the agenda whose journal write is its task's to do
/// ([`JournalledAgenda::apply`]).
#[must_use = "the task writes what it asks, then settles it"]
pub(super) struct Pending {
    /// The transition's actions, before the write.
    actions: Vec<AgendaAction>,
    /// The agenda before the event, when the journal is to record the agenda as it is
    /// now (the undo of a request the write refuses).
    pub(super) undo: Option<AgendaMachine>,
    /// A request, refused when it cannot be recorded.
    refusable: bool,
    /// A fact (not a request), kept even when it cannot be recorded.
    fact: Option<AgendaEvent>,
    /// The holon withdraws (or is deposed).
    withdraw: bool,
    /// The held results released by a withdrawal.
    released: Vec<AgendaAction>,
    /// The resource's state and PackML state before the event (for the log).
    before: (schemas::ResourceState, PackmlState),
    /// When the event happened (Unix ms).
    now: u64,
}

impl Pending {
    /// Whether the task is to write the agenda before the event is settled.
    pub(super) fn must_write(&self) -> bool {
        self.undo.is_some()
    }
}

/// Events taken together whose one journal write is their task's to do
/// ([`JournalledAgenda::apply_batch`]).
#[must_use = "the task writes what it asks, then settles it"]
pub(super) struct Batch {
    /// Each event's actions, in order.
    actions: Vec<Vec<AgendaAction>>,
    /// The agenda before the batch, when the journal is to record it as it is now.
    pub(super) undo: Option<AgendaMachine>,
    /// The resource's state and PackML state before the batch (for the log).
    before: (schemas::ResourceState, PackmlState),
}

/// The agenda and what keeps it durable; owned by the running agenda manager.
pub struct JournalledAgenda {
    /// The state machine.
    pub(super) agenda: AgendaMachine,
    /// The durable state, if the holon has a data directory.
    pub(super) journal: Option<Journal>,
    /// Set while the journal cannot be written (a full disk, ...): why. The resource
    /// then stops offering, refuses requests that would change its agenda, and holds
    /// results back until a write succeeds (retried every [`super::JOURNAL_RETRY`]).
    fault: Option<String>,
    /// Results that happened while the journal could not record them, oldest first:
    /// delivered once they are written.
    held: Vec<Service>,
}

impl JournalledAgenda {
    /// The agenda, restored from the journal if the holon has a data directory. Results
    /// not acknowledged before a restart (and an interrupted job's `failed`) are
    /// delivered by the agenda manager, which takes them from the agenda when it starts.
    pub fn open(
        config: &ResourceConfig,
        inheritance: Inheritance,
    ) -> Result<JournalledAgenda, JournalError> {
        let holon = &config.holon;
        let journal = match &config.data_dir {
            Some(dir) => {
                let file = format!("resource-{}.sqlite", holon.name());
                // A successor opens the journal its predecessor is closing.
                let patience = match config.take_over {
                    Some(_) => holon::takeover::JOURNAL_PATIENCE,
                    None => std::time::Duration::ZERO,
                };
                Some(Journal::open_when_free(
                    dir,
                    &file,
                    config.durability,
                    patience,
                )?)
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
                info!(%holon, journal = %journal.path().display(), bookings = record.bookings.len(), interrupted = record.current.is_some(), undelivered = record.undelivered.len(), ?inheritance, "journal opened")
            }
            None => {
                warn!(%holon, "no data directory: the agenda is not durable (use --data-dir)")
            }
        }
        let agenda = AgendaMachine::restore(
            holon.clone(),
            config.catalog.clone(),
            config.agenda_capacity,
            record,
            inheritance,
            schemas::unix_ms(),
        )
        .with_max_overtakes(config.agenda_max_overtakes)
        .with_jobs_at_once(config.jobs_at_once)
        .with_packml(config.packml)
        .with_locations(config.layout.as_ref());
        if let Some(journal) = &journal {
            // The interrupted job became an undelivered result: record that at once.
            journal.put(AGENDA_RECORD.0, AGENDA_RECORD.1, &agenda.record_ref())?;
        }
        Ok(JournalledAgenda {
            agenda,
            journal,
            fault: None,
            held: Vec::new(),
        })
    }

    /// What the other components see of the agenda.
    pub fn view(&self) -> AgendaView {
        let mut snapshot = self.agenda.snapshot();
        snapshot.journal_fault = self.fault.clone();
        AgendaView {
            snapshot,
            deliverable: self.deliverable(),
            accepting: self.agenda.takes_work() && self.fault.is_none(),
            drained: self.agenda.is_drained(),
        }
    }

    /// The results not yet acknowledged that may go out: all but those the journal could
    /// not record yet.
    pub(super) fn deliverable(&self) -> Vec<Service> {
        self.agenda
            .undelivered()
            .iter()
            .filter(|r| !self.held.contains(r))
            .cloned()
            .collect()
    }

    /// One event through the state machine at `now` (Unix ms), and what the journal is
    /// to record of it: no I/O. Its task writes the agenda if [`Pending::must_write`]
    /// says so, then [`settles`](Self::settle) the event with how the write went.
    pub(super) fn apply(&mut self, holon: &HolonId, event: AgendaEvent, now: u64) -> Pending {
        let before = (self.agenda.state(), self.agenda.packml().state());
        // The agenda before the event: what a request the journal cannot record leaves
        // (the undo), and what tells whether there is anything to write (compared in
        // place, never copied again).
        let previous = self.journal.as_ref().map(|_| self.agenda.clone());
        // An acknowledgement is recorded with the next write, not on its own: if the
        // process dies first, the result is delivered once more and the order, which
        // ignores duplicates, acknowledges it again. That saves an fsync per job.
        let lazily = matches!(event, AgendaEvent::ResultAcknowledged { .. });
        // A request can be refused when it cannot be recorded; the other events are facts
        // (a job finished, a requester left) that the agenda must keep even then.
        let refusable = matches!(event, AgendaEvent::Request(_) | AgendaEvent::Packml(_));
        // Stopping: the held results go out now, and so do the bookings handed back,
        // whether or not the journal can record the withdrawal (see `release_held`).
        let withdraw = matches!(event, AgendaEvent::Withdraw | AgendaEvent::Deposed);
        let released = if withdraw {
            self.release_held(holon)
        } else {
            vec![]
        };
        // Kept for a fact the journal cannot record (see `settle`).
        let fact = (!refusable).then(|| event.clone());
        let actions = self.agenda.handle(event, now);
        let undo = previous.filter(|p| !lazily && !p.same_record(&self.agenda));
        Pending {
            actions,
            undo,
            refusable,
            fact,
            withdraw,
            released,
            before,
            now,
        }
    }

    /// Ends an event's transition once its task wrote what it asked (`written`; `None`
    /// when nothing was to be written): the actions to carry out, or [`NotRecorded`]
    /// when a request could not be recorded (then the agenda is as it was). No I/O.
    pub(super) fn settle(
        &mut self,
        holon: &HolonId,
        pending: Pending,
        written: Option<Result<(), JournalError>>,
    ) -> Result<Vec<AgendaAction>, NotRecorded> {
        let Pending {
            mut actions,
            undo,
            refusable,
            fact,
            withdraw,
            released,
            before,
            now,
        } = pending;
        match (undo, written) {
            (_, None) | (None, _) => {}
            (Some(_), Some(Ok(()))) => actions.extend(self.written(holon)),
            (Some(previous), Some(Err(e))) if refusable => {
                self.failed(holon, &e);
                warn!(%holon, component = "agenda", error = %e, "journal write failed; the request is refused");
                self.agenda = previous;
                return Err(NotRecorded);
            }
            (Some(previous), Some(Err(e))) => {
                // Kept in memory; results wait for the write (see `retry`). A job must
                // not begin unrecorded (a crash would run it again): the fact is kept
                // without a booking starting on its turn.
                if let Some(fact) = fact.filter(|_| {
                    actions
                        .iter()
                        .any(|a| matches!(a, AgendaAction::Execute(_)))
                }) {
                    self.agenda = previous;
                    actions = self.agenda.handle_holding_turns(fact, now);
                }
                if self.failed(holon, &e) {
                    actions.push(AgendaAction::StateChanged);
                }
                if withdraw {
                    warn!(%holon, component = "agenda", error = %e, "stopping while the journal cannot be written: the bookings are handed back unrecorded (after a restart the agenda may still list them until their orders end)");
                    return Ok(actions.into_iter().chain(released).collect());
                }
                let held = &mut self.held;
                actions.retain(|action| match action {
                    AgendaAction::Deliver(result) => {
                        held.push(result.clone());
                        false
                    }
                    _ => true,
                });
            }
        }
        actions.extend(released);
        self.log_transition(holon, before);
        Ok(actions)
    }

    /// The events that arrived together, through the state machine one after another
    /// at `now`: their actions, in order, and whether the journal is to record the
    /// agenda once for all of them. No I/O. `None` when they are to be taken one at a
    /// time instead ([`apply`](Self::apply)): while the journal is failing, or when the
    /// holon withdraws.
    pub(super) fn apply_batch(&mut self, events: &[AgendaEvent], now: u64) -> Option<Batch> {
        let one_by_one = events.len() == 1
            || self.journal.is_none()
            || self.fault.is_some()
            || events
                .iter()
                .any(|e| matches!(e, AgendaEvent::Withdraw | AgendaEvent::Deposed));
        if one_by_one {
            return None;
        }
        let before = (self.agenda.state(), self.agenda.packml().state());
        let previous = self.agenda.clone();
        let mut changed = false;
        let mut actions = Vec::with_capacity(events.len());
        for event in events.iter().cloned() {
            // Acknowledgements alone are not written (see `apply`).
            let lazily = matches!(event, AgendaEvent::ResultAcknowledged { .. });
            let record = (!lazily && !changed).then(|| self.agenda.record());
            actions.push(self.agenda.handle(event, now));
            changed |= record.is_some_and(|r| !self.agenda.keeps(&r));
        }
        Some(Batch {
            actions,
            undo: changed.then_some(previous),
            before,
        })
    }

    /// Ends a batch once its task wrote what it asked (`written`; `None` when nothing
    /// was to be written): the actions of each event, or `None` when the write failed
    /// (then the agenda is as it was before the batch, and the events are to be taken
    /// one at a time). No I/O.
    pub(super) fn settle_batch(
        &mut self,
        holon: &HolonId,
        batch: Batch,
        written: Option<Result<(), JournalError>>,
    ) -> Option<Vec<Vec<AgendaAction>>> {
        if let (Some(previous), Some(Err(e))) = (batch.undo, written) {
            debug!(%holon, error = %e, "the journal could not record a batch: its events are taken one at a time");
            self.agenda = previous;
            return None;
        }
        self.log_transition(holon, batch.before);
        Some(batch.actions)
    }

    /// Logs a change of the resource's state or PackML state (not every event: most
    /// leave both as they were).
    fn log_transition(&self, holon: &HolonId, before: (schemas::ResourceState, PackmlState)) {
        let after = self.agenda.state();
        if before.0 != after {
            info!(%holon, component = "agenda", from = %before.0, to = %after, "transition");
        }
        let unit = self.agenda.packml();
        if before.1 != unit.state() {
            info!(%holon, component = "packml", from = %before.1, to = %unit.state(), state = unit.state().number(), mode = %unit.mode(), "PackML state");
        }
    }

    /// Whether a tick could change the agenda now.
    pub(super) fn wants_tick(&self) -> bool {
        self.agenda.wants_tick()
    }

    /// Writes the agenda as it is now to the journal (its task's I/O).
    pub(super) fn write(&self) -> Result<(), JournalError> {
        match &self.journal {
            Some(journal) => {
                journal.put(AGENDA_RECORD.0, AGENDA_RECORD.1, &self.agenda.record_ref())
            }
            None => Ok(()),
        }
    }

    /// Whether the journal is failing: its task then tries to write the agenda as it
    /// is now every [`super::JOURNAL_RETRY`], and [`retried`](Self::retried) says how it went.
    pub(super) fn failing(&self) -> bool {
        self.fault.is_some()
    }

    /// How the retried write went: on success the fault ends and the held results are
    /// released. No I/O.
    pub(super) fn retried(
        &mut self,
        holon: &HolonId,
        written: Result<(), JournalError>,
    ) -> Vec<AgendaAction> {
        match written {
            Ok(()) => self.written(holon),
            Err(e) => {
                debug!(%holon, error = %e, "the journal still cannot be written");
                self.failed(holon, &e);
                vec![]
            }
        }
    }

    /// Records that a journal write failed; true when that is news (the first failure,
    /// logged; the view then shows the fault and offers stop).
    fn failed(&mut self, holon: &HolonId, error: &JournalError) -> bool {
        let news = self.fault.is_none();
        if news {
            error!(%holon, component = "agenda", error = %error, "the journal cannot be written: no new work is taken and results are held until a write succeeds (retried every second)");
        }
        self.fault = Some(error.to_string());
        news
    }

    /// A journal write succeeded: if it was failing, the fault ends and the held results
    /// are released (to deliver, after a state change).
    fn written(&mut self, holon: &HolonId) -> Vec<AgendaAction> {
        if self.fault.take().is_none() {
            return vec![];
        }
        let held = std::mem::take(&mut self.held);
        info!(%holon, component = "agenda", results = held.len(), "the journal can be written again: held results are delivered, new work is taken");
        held.into_iter()
            .map(AgendaAction::Deliver)
            .chain([AgendaAction::StateChanged])
            .collect()
    }

    /// Stopping with results the journal could not record: they are delivered anyway, so
    /// the orders record the outcomes (and so are the bookings handed back, see `apply`). After a restart this resource reports those
    /// steps `interrupted` (its journal still shows them running), which the orders
    /// acknowledge and ignore as late reports of finished conversations.
    fn release_held(&mut self, holon: &HolonId) -> Vec<AgendaAction> {
        let held = std::mem::take(&mut self.held);
        if !held.is_empty() {
            warn!(%holon, results = held.len(), "shutting down while the journal cannot be written: delivering the held results unrecorded");
        }
        held.into_iter().map(AgendaAction::Deliver).collect()
    }
}

//! What each component publishes of the state it owns, for the others to read.
//!
//! A component's state has one owner (see [`crate::handover`]); what others need of it
//! is published on a `watch` channel after every change: the agenda manager its agenda,
//! the execution component the controller and the step in progress, the requesters
//! component who is absent. The communication component composes the snapshot that
//! `resource/<name>/state` publishes from the three, and declares its offers only while
//! the agenda says it takes work. A reader never waits for an owner, and an owner never
//! waits for a reader.

use schemas::{ControllerStatus, ResourceSnapshot, Service};
use tokio::sync::watch;

use crate::machine::absences::Absences;

/// What the agenda manager publishes after every change of the agenda.
#[derive(Debug, Clone)]
pub struct AgendaView {
    /// The agenda's part of the snapshot: its state, bookings, running job,
    /// undelivered results and journal fault ([`Views::snapshot`] adds the rest).
    pub snapshot: ResourceSnapshot,
    /// The results not yet acknowledged that may go out (all but those the journal
    /// could not record yet): a starting communication component delivers them.
    pub deliverable: Vec<Service>,
    /// Whether the resource takes new work: its controller is ready, it is not
    /// withdrawing or being handed over, and its journal can be written.
    pub accepting: bool,
    /// Withdrawing, and nothing is left to finish or deliver: the holon may stop.
    pub drained: bool,
}

/// What the execution component publishes after every change.
#[derive(Debug, Clone, PartialEq)]
pub struct ExecutionView {
    /// The controller as the interfacing component last reported it.
    pub controller: ControllerStatus,
    /// The jobs running, in the order of their lanes (one, unless the controller runs
    /// several jobs at once).
    pub running: Vec<RunningView>,
}

/// A job the execution runs.
#[derive(Debug, Clone, PartialEq)]
pub struct RunningView {
    /// Its conversation.
    pub conversation_id: String,
    /// The action of its step in progress, e.g. `pick`.
    pub step: Option<String>,
    /// When it began (Unix ms): its measured duration is what a staff holon learns from.
    pub since: u64,
}

/// Where a resource stands with its controller's fence (docs/reliability.md, "Standby
/// resources"), written by the node's fence loop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FenceView {
    /// Not fenced: it serves as soon as it is up.
    Unfenced,
    /// Fenced, not holding the claim: it neither offers nor answers.
    Standby,
    /// Holding the claim with this epoch: it serves.
    Holding(u64),
}

impl FenceView {
    /// Whether the resource may serve.
    pub fn serves(self) -> bool {
        !matches!(self, FenceView::Standby)
    }
}

/// The published views, one per owner.
pub struct Views {
    /// Written by the agenda manager.
    pub agenda: watch::Sender<AgendaView>,
    /// Written by the execution component.
    pub execution: watch::Sender<ExecutionView>,
    /// Written by the requesters component.
    pub absences: watch::Sender<Absences>,
    /// Written by the communication component: how many times a result went out again
    /// because its first attempt was not acknowledged, since the process started.
    pub delivery_retries: watch::Sender<u64>,
    /// Written by the node's fence loop: whether this process holds the controller.
    pub fence: watch::Sender<FenceView>,
    /// Written by the communication component: true once its queryables are declared.
    /// Results go out only from then on, so an order that hears of one can ask the
    /// resource about it (`resource/<name>/outcome`).
    pub answering: watch::Sender<bool>,
    /// The machine this process runs on, named in every snapshot.
    host: String,
    /// The plant's time scale, named in every snapshot when it is not real time.
    pub time_scale: schemas::TimeScale,
}

impl Views {
    pub fn new(agenda: AgendaView, absences: Absences) -> Views {
        Views {
            agenda: watch::Sender::new(agenda),
            execution: watch::Sender::new(ExecutionView {
                controller: ControllerStatus::Disconnected,
                running: Vec::new(),
            }),
            absences: watch::Sender::new(absences),
            delivery_retries: watch::Sender::new(0),
            fence: watch::Sender::new(FenceView::Unfenced),
            answering: watch::Sender::new(false),
            host: holon::presence::host_name(),
            time_scale: schemas::TimeScale::REAL,
        }
    }

    /// The snapshot published on `resource/<name>/state`, as of now.
    pub fn snapshot(&self) -> ResourceSnapshot {
        let mut snapshot = self.agenda.borrow().snapshot.clone();
        let execution = self.execution.borrow();
        snapshot.controller = execution.controller;
        for job in snapshot
            .current
            .iter_mut()
            .chain(&mut snapshot.more_running)
        {
            let running = execution
                .running
                .iter()
                .find(|running| running.conversation_id == job.conversation_id);
            job.step = running.and_then(|running| running.step.clone());
            job.started_at = running.map(|running| running.since);
        }
        let absences = self.absences.borrow();
        for booking in &mut snapshot.agenda {
            booking.requester_absent_since = absences
                .absent_since(&booking.requester)
                .map(|since| since.unix_ms);
        }
        snapshot.delivery_retries = *self.delivery_retries.borrow();
        snapshot.host = Some(self.host.clone());
        snapshot.epoch = match *self.fence.borrow() {
            FenceView::Holding(epoch) => Some(epoch),
            FenceView::Unfenced | FenceView::Standby => None,
        };
        snapshot.version = Some(crate::VERSION.to_string());
        snapshot.time_scale = (!self.time_scale.is_real()).then(|| self.time_scale.factor());
        snapshot.v = schemas::SERVICE_VERSION;
        snapshot.at = schemas::unix_ms();
        snapshot
    }

    /// Sets the agenda view for readers without waking its watchers: a state read sees it
    /// at once, and the snapshot's publisher learns of it at [`Views::announce_agenda`],
    /// which the agenda manager calls once its answers are out, so that the publication
    /// does not take a CPU from them.
    pub fn set_agenda_quietly(&self, view: AgendaView) {
        self.agenda.send_if_modified(|current| {
            *current = view;
            false
        });
    }

    /// Wakes the agenda view's watchers (the snapshot's publisher, a stopping holon
    /// waiting for its agenda to empty) for a view set by [`Views::set_agenda_quietly`].
    pub fn announce_agenda(&self) {
        self.agenda.send_modify(|_| {});
    }

    /// Whether a job is on its way between the agenda and the execution: the agenda runs
    /// it and the execution has not begun it yet, or the execution has ended it and the
    /// agenda has not learnt that yet. A moment that lasts until the next view change
    /// and that nobody else needs to see: the snapshot is published once the two agree
    /// again (a job's beginning and its step together, its end and its result together).
    pub fn job_in_passage(&self) -> bool {
        let agenda = self.agenda.borrow();
        let execution = self.execution.borrow();
        let snapshot = &agenda.snapshot;
        snapshot
            .current
            .iter()
            .chain(&snapshot.more_running)
            .any(|job| {
                !execution
                    .running
                    .iter()
                    .any(|running| running.conversation_id == job.conversation_id)
            })
    }

    /// Whether the resource takes new work (see [`AgendaView::accepting`]).
    pub fn accepting(&self) -> bool {
        self.agenda.borrow().accepting && self.fence.borrow().serves()
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use schemas::{CurrentJobView, HolonId};

    use super::*;
    use crate::machine::absences::Moment;
    use crate::machine::agenda::AgendaMachine;

    /// The views with the agenda running `current`, and the execution running `running`.
    fn views(current: Option<&str>, running: Option<&str>) -> Views {
        let holon = HolonId::resource("robot1").unwrap();
        let catalog = Arc::new(crate::catalog::pick_n_place());
        let mut snapshot = AgendaMachine::new(holon, catalog, 3, schemas::unix_ms()).snapshot();
        snapshot.current = current.map(|conversation| CurrentJobView {
            requester: HolonId::order("o-1").unwrap(),
            conversation_id: conversation.into(),
            service_type: "pick_n_place".into(),
            step: None,
            program: None,
            started_at: None,
        });
        let agenda = AgendaView {
            snapshot,
            deliverable: vec![],
            accepting: true,
            drained: false,
        };
        let views = Views::new(agenda, Absences::new(Moment::now()));
        views.execution.send_modify(|view| {
            view.running = running
                .map(|conversation| RunningView {
                    conversation_id: conversation.to_string(),
                    step: None,
                    since: 1,
                })
                .into_iter()
                .collect();
        });
        views
    }

    #[test]
    fn a_job_is_in_passage_only_while_the_agenda_and_the_execution_disagree_on_it() {
        // Nothing runs; the same job runs on both sides.
        assert!(!views(None, None).job_in_passage());
        assert!(!views(Some("c1"), Some("c1")).job_in_passage());
        // Handed to the execution, not begun there yet.
        assert!(views(Some("c2"), None).job_in_passage());
        assert!(views(Some("c2"), Some("c1")).job_in_passage());
        // Ended in the execution, not yet learnt by the agenda: its view shows the job
        // and the execution none (or, with the agenda already past it, nothing runs).
        assert!(!views(None, Some("c1")).job_in_passage());
    }
}

//! The agenda's PackML rows (see the table in [`crate::machine::agenda`]): the controller's
//! state as it drives the unit, an operator's command, mode change or single job, and
//! the tick that hands back the bookings of a resource held too long.

use schemas::{ControllerStatus, PackmlReply, PackmlRequest, PackmlState};
use serde_json::{Map, Value};

use super::{AgendaAction, AgendaMachine, Job};
use crate::machine::packml::{Consequence, PackmlUnit};
use schemas::UnitMode;

/// How the PackML unit starts when the journal has none, and how long a held resource
/// keeps its bookings (the holon's `[packml]` config).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackmlSettings {
    /// The state of a resource that has never run: Execute, Idle or Stopped.
    pub initial_state: PackmlState,
    pub initial_mode: UnitMode,
    /// How long bookings wait on a Held resource before they are handed back (orders
    /// then rebook elsewhere at once).
    pub held_bookings_ms: u64,
}

impl Default for PackmlSettings {
    fn default() -> Self {
        PackmlSettings {
            initial_state: PackmlState::Execute,
            initial_mode: UnitMode::Production,
            held_bookings_ms: 30_000,
        }
    }
}

impl AgendaMachine {
    /// The controller's state as the execution reports it: ready or not, and what
    /// that does to the PackML unit (a fault aborts, hands every booking back).
    pub(super) fn controller_now(
        &mut self,
        status: ControllerStatus,
        said: Option<&str>,
        now: u64,
    ) -> Vec<AgendaAction> {
        let ready = status.is_ready();
        if self.execution_ready == ready && self.controller == status {
            return vec![];
        }
        self.execution_ready = ready;
        self.controller = status;
        let reported = match said {
            Some(said) => format!("{status}: {said}"),
            None => status.to_string(),
        };
        let mut actions = match self.packml.controller(status, said, now) {
            Consequence::None => vec![],
            Consequence::HandBack | Consequence::Abort => self.hand_back(&format!(
                "the resource was aborted: its controller reported {reported}; book elsewhere"
            )),
        };
        actions.push(AgendaAction::StateChanged);
        actions
    }

    /// An operator's PackML command or mode change: the reply, and what the new state
    /// does to the bookings and the running step.
    pub(super) fn packml_request(&mut self, request: PackmlRequest, now: u64) -> Vec<AgendaAction> {
        let by = request.by.as_deref().unwrap_or("an operator");
        if let Some(job) = request.job {
            return self.operator_job(job, by, now);
        }
        let outcome = match (request.command, request.mode) {
            (Some(command), _) => self.packml.command(command, by, now),
            (None, Some(mode)) => self.packml.set_mode(mode).map(|()| Consequence::None),
            (None, None) => Ok(Consequence::None),
        };
        let mut actions = Vec::new();
        let refused = match outcome {
            Ok(consequence) => {
                match consequence {
                    Consequence::None => {}
                    Consequence::HandBack => actions.extend(
                        self.hand_back(&format!("the resource was stopped ({by}); book elsewhere")),
                    ),
                    Consequence::Abort => {
                        actions.extend(self.hand_back(&format!(
                            "the resource was aborted ({by}); book elsewhere"
                        )));
                        if !self.running.is_empty() {
                            actions.push(AgendaAction::Abort);
                        }
                    }
                }
                actions.extend(self.settle(now));
                actions.push(AgendaAction::StateChanged);
                None
            }
            Err(refusal) => Some(refusal),
        };
        let state = self.packml.state();
        actions.insert(
            0,
            AgendaAction::PackmlReply(PackmlReply {
                job: None,
                state,
                state_number: state.number(),
                mode: self.packml.mode(),
                detail: refused.as_ref().map(|r| r.to_string()),
                refused,
            }),
        );
        actions
    }

    /// An operator's single job (Maintenance mode): begun at once, or refused.
    fn operator_job(
        &mut self,
        request: schemas::packml::JobRequest,
        by: &str,
        now: u64,
    ) -> Vec<AgendaAction> {
        let why = match (
            self.execution_ready,
            !self.running.is_empty(),
            self.leaving(),
        ) {
            (_, true, _) => Some(", a job runs"),
            (false, _, _) => Some(", its controller is not ready"),
            (_, _, true) => Some(", it is stopping"),
            _ => None,
        };
        let parameters = self
            .catalog
            .parameters(&request.service_type, &request.info);
        let refusal = if !self.packml.allows_operator_job() || why.is_some() {
            Some(schemas::Refusal::JobNotAllowed {
                state: self.packml.state(),
                mode: self.packml.mode(),
                why: why.unwrap_or("").to_string(),
            })
        } else if let Err(detail) = &parameters {
            Some(schemas::Refusal::InvalidJob {
                detail: detail.clone(),
            })
        } else if !self.catalog.offers(&request.service_type) {
            Some(schemas::Refusal::InvalidJob {
                detail: format!("{} is not offered here", request.service_type),
            })
        } else {
            None
        };
        let state = self.packml.state();
        let mut reply = PackmlReply {
            job: None,
            state,
            state_number: state.number(),
            mode: self.packml.mode(),
            detail: refusal.as_ref().map(|r| r.to_string()),
            refused: refusal,
        };
        if reply.refused.is_some() {
            return vec![AgendaAction::PackmlReply(reply)];
        }
        let conversation_id = self
            .packml
            .operator_job_began(&request.service_type, by, now);
        let job = Job {
            requester: self.holon.clone(),
            conversation_id: conversation_id.clone(),
            service_type: request.service_type,
            reply_to: String::new(),
            info: request.info,
            parameters: parameters.ok().map(std::sync::Arc::new),
            operator: Some(by.to_string()),
        };
        self.running.push(job.clone());
        reply.job = Some(conversation_id);
        vec![
            AgendaAction::PackmlReply(reply),
            AgendaAction::Execute(job),
            AgendaAction::StateChanged,
        ]
    }

    /// A second passed: a resource Held longer than `held_bookings_ms` hands its
    /// bookings back.
    pub(super) fn tick(&mut self, now: u64) -> Vec<AgendaAction> {
        let held_for = now.saturating_sub(self.packml.since());
        if self.packml.state() != PackmlState::Held
            || held_for < self.held_bookings_ms
            || self.bookings.is_empty()
        {
            return vec![];
        }
        let mut actions = self.hand_back(&format!(
            "the resource has been held for more than {} s; book elsewhere",
            self.held_bookings_ms / 1000
        ));
        actions.push(AgendaAction::StateChanged);
        actions
    }

    /// Whether a [`AgendaEvent::Tick`] could change anything now (the agenda manager
    /// sends one each second only then).
    pub fn wants_tick(&self) -> bool {
        self.packml.state() == PackmlState::Held && !self.bookings.is_empty()
    }
}

/// Says, on a refusal `unavailable`, why a resource out of Execute or Production takes
/// no work: its PackML state and mode.
pub fn packml_hint(unit: &PackmlUnit, info: &mut Map<String, Value>) {
    info.insert(
        "detail".into(),
        Value::String(format!(
            "the resource is {} ({}) in {} mode: it takes orders' work only in Execute and Production",
            unit.state(),
            unit.state().number(),
            unit.mode()
        )),
    );
    info.insert("packml_state".into(), Value::from(unit.state().number()));
}

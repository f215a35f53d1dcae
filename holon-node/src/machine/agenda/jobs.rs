//! The jobs the agenda runs: the last row of its table (a booking that starts on its
//! turn when there is room), a booking made the running job, a job's end, and the
//! `done` / `failed` that reports it to its requester.

use std::sync::Arc;

use schemas::{MessageType, Reason, ResourceState, Service};
use serde_json::{json, Map, Value};

use super::{AgendaAction, AgendaMachine, Job, Outcome};
use crate::catalog::Parameters;

impl AgendaMachine {
    /// The last row of the table: a free resource whose first booking asked to start
    /// on its turn makes it the running job.
    pub(super) fn start_on_turn(&mut self) -> Option<Job> {
        let first = self.bookings.first()?;
        if self.state() != ResourceState::Free
            || self.leaving()
            || !self.packml.takes_orders()
            || !first.start_on_turn
        {
            return None;
        }
        // Checked when it was booked; a booking without one waits for a `start`.
        let reply_to = first.reply_to.clone()?;
        Some(self.run_booking(0, reply_to, None))
    }

    /// Makes the booking at `index` the running job, its results to `reply_to`, with
    /// the `info` its start brought (read) or, without one, the booking's.
    pub(super) fn run_booking(
        &mut self,
        index: usize,
        reply_to: String,
        started_with: Option<(Map<String, Value>, Parameters)>,
    ) -> Job {
        let booking = self.bookings.remove(index);
        let (info, parameters) = match started_with {
            Some((info, parameters)) => (info, Some(Arc::new(parameters))),
            None => (booking.info, booking.parameters),
        };
        let job = Job {
            requester: booking.requester,
            conversation_id: booking.conversation_id,
            service_type: booking.service_type,
            reply_to,
            info,
            parameters,
            operator: None,
        };
        self.running.push(job.clone());
        job
    }

    pub(super) fn finished(
        &mut self,
        conversation_id: &str,
        outcome: Outcome,
    ) -> Vec<AgendaAction> {
        let Some(index) = self
            .running
            .iter()
            .position(|job| job.conversation_id == conversation_id)
        else {
            // Not a running job (a stale report): nothing changes.
            return vec![];
        };
        let job = self.running.remove(index);
        if let Outcome::Deposed { detail } = &outcome {
            tracing::info!(holon = %self.holon, conversation_id, %detail, "the job is left to the new holder: no result from here");
            return vec![AgendaAction::StateChanged];
        }
        let done = matches!(outcome, Outcome::Done { .. });
        if job.operator.is_some() {
            // An operator's job: kept in the figures, delivered to nobody.
            self.packml
                .operator_job_ended(&job.conversation_id, outcome.to_string(), done);
            return vec![AgendaAction::StateChanged];
        }
        self.packml.step_ended(done);
        let message = self.result_message(job, outcome);
        self.undelivered.push(message.clone());
        vec![AgendaAction::Deliver(message), AgendaAction::StateChanged]
    }

    /// The `done` / `failed` message that reports `outcome` of `job` to its requester.
    pub(super) fn result_message(&self, job: Job, outcome: Outcome) -> Service {
        let (message_type, result, why, info) = match outcome {
            Outcome::Done { results } => {
                (MessageType::Done, true, None, json!({ "results": results }))
            }
            Outcome::Failed { reason, detail } => (
                MessageType::Failed,
                false,
                Some(reason),
                json!({ "detail": detail }),
            ),
            // Never delivered (see `finished`); said as what it is, were it to be.
            Outcome::Deposed { detail } => (
                MessageType::Failed,
                false,
                Some(Reason::Interrupted),
                json!({ "detail": detail }),
            ),
        };
        Service {
            v: schemas::SERVICE_VERSION,
            message_type,
            service_type: job.service_type,
            conversation_id: job.conversation_id,
            requester: job.requester,
            provider: Some(self.holon.clone()),
            reply_to: Some(job.reply_to),
            result: Some(result),
            reason: why,
            info: match info {
                Value::Object(map) => map,
                _ => Map::new(),
            },
        }
    }
}

//! The waiting queue: where a booking of a priority goes (ahead of lower priorities, at
//! most `max_overtakes` times past one), the queue and the expected wait a proposal
//! shows, and the queue position in a booking's answer.

use schemas::Service;
use serde_json::{json, Map, Value};

use super::AgendaMachine;

impl AgendaMachine {
    /// The answer to a booking whose job has begun (queue position 0).
    pub(super) fn started_reply(&self, request: &Service) -> Service {
        let mut reply = self.queued_reply(request, 0);
        reply
            .info
            .insert(schemas::info_key::STARTED.into(), Value::Bool(true));
        reply
    }

    /// The answer to a booking at `position` on the agenda.
    pub(super) fn booked_reply(&self, request: &Service, position: usize) -> Service {
        self.queued_reply(request, position + 1 + !self.has_room() as usize)
    }

    /// An accepted booking: the proposal's figures and the booking's queue position.
    fn queued_reply(&self, request: &Service, queue_position: usize) -> Service {
        let mut reply = request.accepted(&self.holon);
        reply.info = self.proposal_info(request, request.priority().unwrap_or(0));
        reply
            .info
            .insert("queue_position".into(), json!(queue_position));
        reply
    }

    /// Where a new booking of `priority` goes: ahead of the waiting bookings of lower
    /// priority at the back of the agenda, stopping at one of equal or higher
    /// priority, or one already passed `max_overtakes` times. So equal priorities are
    /// first come, first served, and a waiting booking starts after at most the jobs
    /// ahead of it when it was made plus `max_overtakes` (no starvation).
    pub(super) fn insertion_point(&self, priority: i32) -> usize {
        let mut at = self.bookings.len();
        while at > 0 {
            let ahead = &self.bookings[at - 1];
            if ahead.priority >= priority || ahead.overtaken >= self.max_overtakes {
                break;
            }
            at -= 1;
        }
        at
    }

    /// What a proposal says: the queue ahead and the expected wait before `request`'s
    /// service could start for a booking of `priority`, from the durations of the jobs
    /// ahead of where it would go, and its own duration: each a service's nominal
    /// duration, or a transporter's move its travel time ([`super::travel`]).
    pub(super) fn proposal_info(&self, request: &Service, priority: i32) -> Map<String, Value> {
        let at = self.insertion_point(priority);
        let ahead = self.wait_behind(at);
        let mut info = Map::new();
        info.insert("state".into(), json!(self.state()));
        info.insert(
            "queue_position".into(),
            json!(at + !self.has_room() as usize),
        );
        info.insert("agenda_length".into(), json!(self.bookings.len()));
        info.insert("expected_wait_ms".into(), json!(ahead));
        info.insert(
            "duration_ms".into(),
            json!(self.duration_ms(&request.service_type, &request.info)),
        );
        info
    }

    /// How long a job behind the first `at` bookings waits before it begins: the jobs
    /// running and those bookings, each begun on the first of the `jobs_at_once` lanes
    /// to be free (with one lane, their durations added up). A running job is counted
    /// whole: the agenda does not know how far it is.
    fn wait_behind(&self, at: usize) -> u64 {
        let mut lanes: Vec<u64> = vec![0; self.jobs_at_once.max(1)];
        let durations = self
            .running
            .iter()
            .map(|j| self.duration_ms(&j.service_type, &j.info))
            .chain(
                self.bookings[..at]
                    .iter()
                    .map(|b| self.duration_ms(&b.service_type, &b.info)),
            );
        for duration in durations {
            let first_free = lanes.iter_mut().min().expect("at least one lane");
            *first_free += duration;
        }
        lanes.into_iter().min().unwrap_or(0)
    }
}

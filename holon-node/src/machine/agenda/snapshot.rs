//! The agenda's part of the state snapshot a resource publishes.

use schemas::{BookingView, ControllerStatus, CurrentJobView, ResourceSnapshot};

use super::AgendaMachine;

impl AgendaMachine {
    /// The agenda's part of the snapshot published on `resource/<name>/state`: the
    /// controller, the step in progress and the requesters' absences are the other
    /// components' to fill in (see [`crate::views::Views::snapshot`]).
    pub fn snapshot(&self) -> ResourceSnapshot {
        ResourceSnapshot {
            state: self.state(),
            controller: ControllerStatus::Disconnected,
            agenda: self
                .bookings
                .iter()
                .map(|b| BookingView {
                    requester: b.requester.clone(),
                    conversation_id: b.conversation_id.clone(),
                    service_type: b.service_type.clone(),
                    requester_absent_since: None,
                    priority: b.priority,
                    due: b.due,
                    overtaken: b.overtaken,
                    program: program_of(b.parameters.as_deref(), &b.info),
                })
                .collect(),
            current: self.running.first().map(job_view),
            more_running: self.running.iter().skip(1).map(job_view).collect(),
            undelivered: self.undelivered.len(),
            services: self.catalog.service_types().map(String::from).collect(),
            nominal_ms: self
                .catalog
                .service_types()
                .filter_map(|t| {
                    let nominal = self.catalog.get(t)?.nominal_duration.as_millis() as u64;
                    Some((t.to_string(), nominal))
                })
                .collect(),
            handing_over: self.handing_over,
            packml: Some(self.packml.status()),
            places: self
                .places
                .held()
                .iter()
                .map(|(location, holds)| {
                    let parts = holds.iter().map(|h| h.part.clone()).collect();
                    (location.to_string(), parts)
                })
                .collect(),
            carriers_out: self.carriers.out().iter().cloned().collect(),
            // Host, epoch, version, time scale, `v` and `at` are stamped when the view
            // is read (`Views::snapshot`).
            ..ResourceSnapshot::blank(self.holon.clone())
        }
    }
}

/// A running job as the snapshot shows it (its step and start are the execution's to
/// fill in).
fn job_view(job: &super::Job) -> CurrentJobView {
    CurrentJobView {
        requester: job.requester.clone(),
        conversation_id: job.conversation_id.clone(),
        service_type: job.service_type.clone(),
        step: None,
        program: program_of(job.parameters.as_deref(), &job.info),
        started_at: None,
    }
}

/// A booking's or job's program: as read when it was booked, else (its `info` does not
/// fit the steps, or it came from the journal as the job that ran) from its `info`.
fn program_of(
    parameters: Option<&crate::catalog::Parameters>,
    info: &serde_json::Map<String, serde_json::Value>,
) -> Option<String> {
    match parameters {
        Some(parameters) => parameters.program.clone(),
        None => crate::catalog::program(info).ok().flatten(),
    }
}

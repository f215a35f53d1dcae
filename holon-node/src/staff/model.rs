//! What a staff holon knows of the cell, and what it learns: the pure part.
//!
//! It is built from what the holons publish anyway: each resource's state snapshot
//! (its agenda, the job it runs and since when, its services and their nominal
//! durations) and its presence. From the jobs it sees begin and end it learns how long
//! each service type takes on each resource, and what a change of program costs there
//! (a job whose program differs from the resource's last one). It also keeps the
//! intentions of the orders it advised (D-MAS): where their later steps will go and
//! when, so the next order's forecast counts them before they are booked.
//!
//! Nothing here does I/O or reads a clock: the staff's one task feeds it events with
//! the time (Unix ms) and asks it for forecasts.

use std::collections::BTreeMap;

use schemas::{CurrentJobView, HolonId, ResourceSnapshot, ResourceState};
use serde::Serialize;

/// What a service is assumed to take on a resource that says nothing of it.
pub const UNKNOWN_DURATION_MS: u64 = 1000;

/// A running mean: plain while there are few samples, then weighted to the last five
/// (a robot that slows down or is sped up is followed within a few jobs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Learned {
    /// The mean, in ms.
    pub mean_ms: f64,
    /// How many measurements it is made of.
    pub samples: u32,
}

impl Learned {
    fn add(&mut self, ms: f64) {
        self.samples = self.samples.saturating_add(1);
        let weight = (1.0 / self.samples as f64).max(0.2);
        self.mean_ms += weight * (ms - self.mean_ms);
    }

    fn known(&self) -> Option<f64> {
        (self.samples > 0).then_some(self.mean_ms)
    }
}

/// A job seen running on a resource.
#[derive(Debug, Clone, PartialEq)]
struct RunningJob {
    conversation_id: String,
    service_type: String,
    started_at: u64,
    /// The last snapshot that still showed it running (Unix ms): it takes at least
    /// this long since `started_at`.
    seen_until: u64,
    /// Its program differed from the resource's last one: it began with a changeover.
    changed_over: bool,
}

/// One resource as the staff knows it.
#[derive(Debug, Clone)]
pub struct ResourceModel {
    /// Its latest snapshot.
    pub snapshot: ResourceSnapshot,
    /// The program of the last job seen running there that named one.
    last_program: Option<String>,
    /// The jobs seen running, once their start times are known, in the order they
    /// were first seen (a resource that runs several at once shows them all).
    running: Vec<RunningJob>,
    /// Measured durations per service type (without changeovers).
    learned: BTreeMap<String, Learned>,
    /// What a change of program adds to a job, measured.
    changeover: Learned,
}

/// A step of an advised order, planned on a resource and not booked yet.
#[derive(Debug, Clone, PartialEq)]
pub struct Intention {
    pub order: HolonId,
    pub service_type: String,
    pub resource: HolonId,
    pub program: Option<String>,
    pub priority: i32,
    pub start: u64,
    pub end: u64,
    /// When the intention lapses if never booked (the order went elsewhere).
    pub expires: u64,
}

/// What the staff learned of one resource, as its state shows it.
#[derive(Debug, Clone, Serialize)]
pub struct LearnedView {
    /// Per service type: the measured mean and how many jobs it is made of.
    pub services: BTreeMap<String, Learned>,
    /// The measured cost of a change of program.
    pub changeover: Learned,
}

/// The cell as the staff knows it.
#[derive(Debug, Clone, Default)]
pub struct CellModel {
    resources: BTreeMap<HolonId, ResourceModel>,
    intentions: Vec<Intention>,
    /// The fenced resources' highest epochs: a deposed holder's states are not read.
    epochs: schemas::Epochs,
}

impl CellModel {
    /// A resource's new snapshot, published (or answered) at `snapshot.at`: a job
    /// that ended since the last one is measured, a job that began is noted.
    pub fn observe(&mut self, snapshot: ResourceSnapshot) {
        if !self.epochs.current(&snapshot) {
            return; // a deposed holder's: what it ran is not the resource's
        }
        let holon = snapshot.holon.clone();
        let model = self
            .resources
            .entry(holon.clone())
            .or_insert_with(|| ResourceModel {
                snapshot: snapshot.clone(),
                last_program: None,
                running: Vec::new(),
                learned: BTreeMap::new(),
                changeover: Learned::default(),
            });
        if snapshot.at < model.snapshot.at {
            return; // an older snapshot overtaken by a newer one
        }
        let now_running: Vec<(&CurrentJobView, u64)> = snapshot
            .current
            .iter()
            .chain(&snapshot.more_running)
            .filter_map(|c| c.started_at.map(|at| (c, at)))
            .collect();
        // A job seen running has ended if it is not among those running now.
        let (ended, still): (Vec<RunningJob>, Vec<RunningJob>) = std::mem::take(&mut model.running)
            .into_iter()
            .partition(|job| {
                !now_running
                    .iter()
                    .any(|(c, _)| c.conversation_id == job.conversation_id)
            });
        for job in &ended {
            model.measure(job, snapshot.at);
        }
        model.running = still;
        for job in &mut model.running {
            job.seen_until = job.seen_until.max(snapshot.at);
        }
        for (job, started_at) in now_running {
            if model
                .running
                .iter()
                .any(|seen| seen.conversation_id == job.conversation_id)
            {
                continue;
            }
            let changed_over = match (&job.program, &model.last_program) {
                (Some(program), Some(last)) => program != last,
                _ => false,
            };
            if job.program.is_some() {
                model.last_program = job.program.clone();
            }
            model.running.push(RunningJob {
                conversation_id: job.conversation_id.clone(),
                service_type: job.service_type.clone(),
                started_at,
                seen_until: snapshot.at.max(started_at),
                changed_over,
            });
        }
        // Intentions that became bookings are counted as bookings from now on.
        let booked: Vec<(&HolonId, &str)> = snapshot
            .agenda
            .iter()
            .map(|b| (&b.requester, b.service_type.as_str()))
            .chain(
                snapshot
                    .current
                    .iter()
                    .chain(&snapshot.more_running)
                    .map(|c| (&c.requester, c.service_type.as_str())),
            )
            .collect();
        self.intentions.retain(|i| {
            i.resource != holon
                || !booked
                    .iter()
                    .any(|(order, service)| **order == i.order && *service == i.service_type)
        });
        model.snapshot = snapshot;
    }

    /// The resource left the cell (its token vanished): it is not advised any more.
    pub fn gone(&mut self, resource: &HolonId) {
        self.resources.remove(resource);
        self.intentions.retain(|i| &i.resource != resource);
    }

    /// Keeps `intentions` as `order`'s plan (replacing what it had), and drops every
    /// intention lapsed at `now`.
    pub fn intend(&mut self, order: &HolonId, intentions: Vec<Intention>, now: u64) {
        self.intentions
            .retain(|i| &i.order != order && i.expires > now);
        self.intentions.extend(intentions);
    }

    /// The order ended or gave up: its intentions go.
    pub fn forget(&mut self, order: &HolonId) {
        self.intentions.retain(|i| &i.order != order);
    }

    pub fn intentions(&self) -> &[Intention] {
        &self.intentions
    }

    pub fn resources(&self) -> impl Iterator<Item = &ResourceModel> {
        self.resources.values()
    }

    pub fn resource(&self, resource: &HolonId) -> Option<&ResourceModel> {
        self.resources.get(resource)
    }

    /// What was learned of each resource, for the staff's published state.
    pub fn learned(&self) -> BTreeMap<String, LearnedView> {
        self.resources
            .iter()
            .map(|(holon, model)| {
                (
                    holon.to_string(),
                    LearnedView {
                        services: model.learned.clone(),
                        changeover: model.changeover,
                    },
                )
            })
            .collect()
    }
}

impl ResourceModel {
    /// Learns from a job that ran from its start until `ended_at`.
    fn measure(&mut self, job: &RunningJob, ended_at: u64) {
        let Some(took) = ended_at.checked_sub(job.started_at) else {
            return;
        };
        let took = took as f64;
        if job.changed_over {
            let base = self.duration_without_changeover(&job.service_type);
            self.changeover.add((took - base).max(0.0));
        } else {
            self.learned
                .entry(job.service_type.clone())
                .or_default()
                .add(took);
        }
    }

    /// Whether it can be advised: present, controller ready, taking work (in PackML
    /// Execute and Production, not being handed over).
    pub fn takes_work(&self) -> bool {
        let s = &self.snapshot;
        s.state != ResourceState::Init
            && s.controller == schemas::ControllerStatus::Ready
            && s.journal_fault.is_none()
            && !s.handing_over
            && s.packml.as_ref().is_none_or(|p| {
                p.state == schemas::PackmlState::Execute && p.mode == schemas::UnitMode::Production
            })
    }

    pub fn offers(&self, service_type: &str) -> bool {
        self.snapshot.services.iter().any(|s| s == service_type)
    }

    /// How long `service_type` takes here, without a changeover: measured, else the
    /// resource's nominal duration, else [`UNKNOWN_DURATION_MS`]; and at least as long
    /// as a job of it (without a changeover) has been running now: a resource slower
    /// than believed shows it before its first job ends.
    pub fn duration_without_changeover(&self, service_type: &str) -> f64 {
        let believed = self
            .learned
            .get(service_type)
            .and_then(Learned::known)
            .or_else(|| {
                self.snapshot
                    .nominal_ms
                    .get(service_type)
                    .map(|ms| *ms as f64)
            })
            .unwrap_or(UNKNOWN_DURATION_MS as f64);
        let running_for = self
            .running
            .iter()
            .filter(|job| job.service_type == service_type && !job.changed_over)
            .map(|job| job.seen_until.saturating_sub(job.started_at))
            .max()
            .unwrap_or(0);
        believed.max(running_for as f64)
    }

    /// What a change of program costs here, as measured (0 until one was seen).
    pub fn changeover_ms(&self) -> f64 {
        self.changeover.known().unwrap_or(0.0)
    }

    /// How long a job of `service_type` and `program` takes after a job of `before`.
    pub fn duration(&self, service_type: &str, program: Option<&str>, before: Option<&str>) -> Job {
        let changeover = matches!((program, before), (Some(p), Some(b)) if p != b);
        let mut ms = self.duration_without_changeover(service_type);
        if changeover {
            ms += self.changeover_ms();
        }
        Job {
            ms: ms.round() as u64,
            changeover,
        }
    }

    /// When the resource is free of the work that goes before a new booking of
    /// `priority` (the running job, and the waiting bookings of that priority or
    /// higher), at `now`; and the program it is then set up for.
    pub fn free_for(&self, priority: i32, now: u64) -> (u64, Option<String>) {
        let mut program = self.last_program.clone();
        let mut free = now;
        if let Some(job) = self.running.first() {
            let took = self.duration(&job.service_type, None, None).ms
                + if job.changed_over {
                    self.changeover_ms().round() as u64
                } else {
                    0
                };
            free = free.max(job.started_at + took);
        } else if let Some(current) = &self.snapshot.current {
            // Begun, its start time not published yet: a whole job from now.
            free += self.duration(&current.service_type, None, None).ms;
        }
        for booking in self
            .snapshot
            .agenda
            .iter()
            .filter(|b| b.priority >= priority)
        {
            let job = self.duration(
                &booking.service_type,
                booking.program.as_deref(),
                program.as_deref(),
            );
            free += job.ms;
            if booking.program.is_some() {
                program = booking.program.clone();
            }
        }
        (free, program)
    }
}

/// A job as forecast: how long, and whether it begins with a changeover.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Job {
    pub ms: u64,
    pub changeover: bool,
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use schemas::{BookingView, ControllerStatus};

    pub fn snapshot(name: &str, at: u64) -> ResourceSnapshot {
        ResourceSnapshot {
            state: ResourceState::Free,
            controller: ControllerStatus::Ready,
            services: vec!["pick_n_place".into()],
            nominal_ms: [("pick_n_place".to_string(), 1000)].into(),
            at,
            ..ResourceSnapshot::blank(HolonId::resource(name).unwrap())
        }
    }

    pub fn running(
        mut s: ResourceSnapshot,
        conversation: &str,
        program: Option<&str>,
        started_at: u64,
    ) -> ResourceSnapshot {
        s.state = ResourceState::Busy;
        s.current = Some(CurrentJobView {
            requester: HolonId::order("o-1").unwrap(),
            conversation_id: conversation.into(),
            service_type: "pick_n_place".into(),
            step: Some("pick".into()),
            program: program.map(str::to_string),
            started_at: Some(started_at),
        });
        s
    }

    pub fn booking(order: &str, priority: i32, program: Option<&str>) -> BookingView {
        BookingView {
            priority,
            program: program.map(str::to_string),
            ..BookingView::waiting(
                HolonId::order(order).unwrap(),
                &format!("{order}/1/1"),
                "pick_n_place",
            )
        }
    }

    /// Runs jobs of `program`s one after another, each taking `ms` (plus `extra` after
    /// a change of program), from time `from`; returns when the last ended.
    fn run_jobs(
        model: &mut CellModel,
        name: &str,
        programs: &[Option<&str>],
        ms: u64,
        extra: u64,
        from: u64,
    ) -> u64 {
        let mut t = from;
        let mut last: Option<&str> = None;
        for (n, program) in programs.iter().enumerate() {
            model.observe(running(snapshot(name, t), &format!("c{n}"), *program, t));
            let change = matches!((program, last), (Some(p), Some(l)) if *p != l);
            t += ms + if change { extra } else { 0 };
            if program.is_some() {
                last = *program;
            }
            model.observe(snapshot(name, t));
        }
        t
    }

    #[test]
    fn durations_and_changeovers_are_learned_from_the_jobs_seen() {
        let mut model = CellModel::default();
        let robot = HolonId::resource("robot1").unwrap();
        model.observe(snapshot("robot1", 0));
        let r = model.resource(&robot).unwrap();
        assert_eq!(
            r.duration_without_changeover("pick_n_place"),
            1000.0,
            "nominal first"
        );
        run_jobs(
            &mut model,
            "robot1",
            &[Some("a"), Some("a"), Some("b"), None, Some("b"), Some("a")],
            300,
            500,
            10,
        );
        let r = model.resource(&robot).unwrap();
        assert_eq!(r.duration_without_changeover("pick_n_place"), 300.0);
        assert_eq!(r.changeover_ms(), 500.0);
        assert_eq!(
            r.duration("pick_n_place", Some("b"), Some("a")),
            Job {
                ms: 800,
                changeover: true
            }
        );
        assert_eq!(r.duration("pick_n_place", Some("a"), Some("a")).ms, 300);
        assert_eq!(r.duration("pick_n_place", None, Some("a")).ms, 300);
        let learned = model.learned();
        assert_eq!(
            learned["resource/robot1"].services["pick_n_place"].samples,
            4
        );
        assert_eq!(learned["resource/robot1"].changeover.samples, 2);
    }

    #[test]
    fn every_job_a_resource_runs_at_once_is_measured() {
        // A transporter running two moves at once: both are timed, each from its own
        // start to the first state without it, the one that is not `current` too.
        let mut model = CellModel::default();
        let mut both = running(snapshot("monorail", 1000), "m1", None, 0);
        both.more_running = running(snapshot("monorail", 1000), "m2", None, 500)
            .current
            .into_iter()
            .collect();
        model.observe(both);
        // m2 ends at 2000 while m1 runs on.
        model.observe(running(snapshot("monorail", 2000), "m1", None, 0));
        let learned = &model.learned()["resource/monorail"].services;
        assert_eq!(learned["pick_n_place"].samples, 1, "{learned:?}");
        assert_eq!(learned["pick_n_place"].mean_ms, 1500.0);
        model.observe(snapshot("monorail", 3500));
        let learned = &model.learned()["resource/monorail"].services;
        assert_eq!(learned["pick_n_place"].samples, 2, "m1 measured too");
        assert_eq!(learned["pick_n_place"].mean_ms, 2500.0, "(1500 + 3500) / 2");
    }

    #[test]
    fn a_job_running_longer_than_believed_is_evidence_before_it_ends() {
        let mut model = CellModel::default();
        let robot = HolonId::resource("robot1").unwrap();
        model.observe(running(snapshot("robot1", 0), "c1", None, 0));
        let r = model.resource(&robot).unwrap();
        assert_eq!(r.duration_without_changeover("pick_n_place"), 1000.0);
        // Still on the job 1.6 s later (a step changed): it takes at least that.
        model.observe(running(snapshot("robot1", 1600), "c1", None, 0));
        let r = model.resource(&robot).unwrap();
        assert_eq!(r.duration_without_changeover("pick_n_place"), 1600.0);
        model.observe(snapshot("robot1", 2000));
        let r = model.resource(&robot).unwrap();
        assert_eq!(
            r.duration_without_changeover("pick_n_place"),
            2000.0,
            "measured"
        );
    }

    #[test]
    fn a_resource_is_free_after_its_running_job_and_the_bookings_ahead() {
        let mut model = CellModel::default();
        let robot = HolonId::resource("robot1").unwrap();
        run_jobs(&mut model, "robot1", &[Some("a")], 200, 0, 0);
        let mut busy = running(snapshot("robot1", 1000), "c9", Some("a"), 1000);
        busy.agenda = vec![booking("o-2", 0, Some("b")), booking("o-3", -5, Some("a"))];
        model.observe(busy);
        let r = model.resource(&robot).unwrap();
        // Running from 1000 for 200; then o-2's job (200, no changeover measured yet).
        assert_eq!(r.free_for(0, 1050), (1400, Some("b".into())));
        // A rush booking passes both waiting bookings.
        assert_eq!(r.free_for(100, 1050), (1200, Some("a".into())));
        // Later than the forecast end: free now.
        assert_eq!(r.free_for(100, 5000).0, 5000);
    }

    #[test]
    fn intentions_end_when_booked_lapse_or_their_resource_goes() {
        let mut model = CellModel::default();
        let order = HolonId::order("o-2").unwrap();
        let intention = |resource: &str, service: &str| Intention {
            order: order.clone(),
            service_type: service.into(),
            resource: HolonId::resource(resource).unwrap(),
            program: None,
            priority: 0,
            start: 100,
            end: 200,
            expires: 1000,
        };
        model.intend(
            &order,
            vec![
                intention("robot1", "pick_n_place"),
                intention("robot2", "inspect"),
            ],
            0,
        );
        assert_eq!(model.intentions().len(), 2);
        let mut booked = snapshot("robot1", 50);
        booked.agenda = vec![booking("o-2", 0, None)];
        model.observe(booked);
        assert_eq!(
            model.intentions().len(),
            1,
            "the booked step is a booking now"
        );
        model.gone(&HolonId::resource("robot2").unwrap());
        assert!(model.intentions().is_empty());
        model.intend(&order, vec![intention("robot1", "x")], 0);
        model.intend(&HolonId::order("o-9").unwrap(), vec![], 2000);
        assert!(model.intentions().is_empty(), "lapsed");
    }
}

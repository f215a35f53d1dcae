//! The dashboard's model of the cell: what it has heard (liveliness, state snapshots)
//! turned into what the page shows. Pure, like the holons' state machines: one input
//! in, the model changes; no I/O and no clock (each input carries its time).
//!
//! | input | what changes |
//! |---|---|
//! | a holon's token appears | the holon is live; a `vanished` alarm of it clears; it counts towards `restarting` |
//! | a holon's token vanishes | the holon is gone; a resource raises `vanished` |
//! | a snapshot older than the one held (`at`) | nothing |
//! | a resource's snapshot | its state, controller, agenda and job; `controller` (fault, estop), `journal` and `undelivered` alarms raise or clear; busy time accrues |
//! | an order's snapshot | its status and step; a failed or scrapped order raises an alarm (cleared at once, kept until acknowledged) |
//! | a router's or order-node's token appears (`host/<program>/<name>`) | it is live; a `vanished` alarm of it clears |
//! | a router's or order-node's token vanishes | it is gone; `vanished` is raised (an order-node's orders wait for it) |
//! | an operator's acknowledgement | the alarm is acknowledged; one that is cleared and acknowledged leaves the list |
//! | the fenced resources' reports | who holds each controller, who stands by; a new holder is an event |
//! | an order's snapshot whose part moved, left the cell, or whose order ended | its `part_waits` alarm clears |
//! | a resource's snapshot, a resource vanishing | the running schedule's bars open and close ([`schedule`]) |
//! | time passes (a tick) | a running order's part in the cell that has stayed where it is beyond the bound raises `part_waits` |
//!
//! Every change of a holon's presence or state, an order's status or step, and every
//! alarm raised or cleared is one entry of the event log (the last [`EVENTS_KEPT`]).

use std::collections::{BTreeMap, HashMap, VecDeque};

use schemas::{
    ControllerStatus, HolonId, HolonKind, OrderSnapshot, OrderStatus, ResourceSnapshot,
    ResourceState,
};
use serde::Serialize;

mod alarms;
mod counters;
mod input;
mod part_waits;
mod parts;
mod processes;
mod schedule;

pub use part_waits::DEFAULT_BOUND_MS as DEFAULT_PART_WAIT_BOUND_MS;

pub use alarms::{Alarm, AlarmKind, Event, Source};
pub use counters::{Counters, StepHistogram, STEP_BUCKETS};
pub use input::Input;
pub use processes::{ProcessId, ProcessView};
pub use schedule::{ScheduleView, WINDOW_PLANT_MS};

/// How many entries the event log keeps.
pub const EVENTS_KEPT: usize = 500;

/// Undelivered results on one resource that raise an alarm.
pub const UNDELIVERED_ALARM: usize = 5;

/// A holon whose token appears this often within [`RESTARTING_WINDOW_MS`] is restarting
/// repeatedly.
pub const RESTARTING_APPEARANCES: usize = 3;
pub const RESTARTING_WINDOW_MS: u64 = 60_000;

/// How many finished orders the model keeps (the newest heard): the page shows
/// [`crate::dashboard::FINISHED_SHOWN`] of them and reads older ones a page at a time
/// from their order-node, so a dashboard open for a month holds no more than a day's.
pub const FINISHED_KEPT: usize = 1_000;

/// One holon as the page shows it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HolonView {
    pub holon: HolonId,
    /// `resource`, `product`, `order` or `staff`.
    pub kind: &'static str,
    /// Its token is visible.
    pub live: bool,
    /// Since when it is live or gone (Unix ms).
    pub since: u64,
    /// A resource's last snapshot.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub resource: Option<ResourceSnapshot>,
}

/// The cell as the dashboard knows it.
#[derive(Debug, Clone, Default)]
pub struct Model {
    holons: BTreeMap<HolonId, HolonView>,
    /// Routers and order-nodes.
    processes: BTreeMap<ProcessId, ProcessView>,
    orders: BTreeMap<HolonId, OrderSnapshot>,
    /// The finished orders of `orders`, in the order they were heard finished: the
    /// oldest leave past [`FINISHED_KEPT`].
    finished: VecDeque<HolonId>,
    /// The order-nodes' counts, as last asked.
    node_counts: BTreeMap<String, schemas::OrderCounts>,
    /// Active alarms, and cleared ones not yet acknowledged, oldest first.
    alarms: Vec<Alarm>,
    next_alarm: u64,
    events: VecDeque<Event>,
    /// When each holon's token last appeared, within the restarting window.
    appearances: HashMap<HolonId, VecDeque<u64>>,
    /// When orders reached `done` (for the throughput).
    completions: VecDeque<u64>,
    /// Per resource: milliseconds it has been busy since the dashboard started, and
    /// since when it is busy now.
    busy: BTreeMap<HolonId, (u64, Option<u64>)>,
    /// Per resource: the job seen starting (conversation, service type) and when.
    jobs: HashMap<HolonId, (String, String, u64)>,
    /// Counters for the metrics.
    counters: Counters,
    /// The fenced resources' processes, holders and standbys, as last asked.
    fences: Vec<schemas::FenceReport>,
    /// The order-nodes' processes on etcd, holders and standbys, as last asked.
    node_fences: Vec<schemas::fence::NodeFenceReport>,
    /// The cell's layout, as last asked.
    layout: schemas::layout::CellLayout,
    /// How long each running order's part has stayed where it is (`part_waits`).
    part_waits: part_waits::PartWaits,
    /// The running schedule: each resource's jobs, drawn as a Gantt chart.
    schedule: schedule::Schedule,
}

impl Model {
    /// A model whose `part_waits` alarm is raised for a part in the cell that stays
    /// where it is longer than `bound_ms`.
    pub fn with_part_wait_bound(bound_ms: u64) -> Model {
        Model {
            part_waits: part_waits::PartWaits::new(bound_ms),
            ..Model::default()
        }
    }

    /// One input in; true if the page's view changed.
    pub fn apply(&mut self, input: Input) -> bool {
        match input {
            Input::Appeared { holon, at } => self.appeared(holon, at),
            Input::Vanished { holon, at } => self.vanished(holon, at),
            Input::Resource { snapshot, at } => self.resource(*snapshot, at),
            Input::Order { snapshot, at } => self.order(*snapshot, at),
            Input::ProcessAppeared { process, at } => self.process(process, true, at),
            Input::ProcessVanished { process, at } => self.process(process, false, at),
            Input::Acknowledge { id, by, at } => self.acknowledge(id, &by, at),
            Input::Fences { reports, at } => self.fences(reports, at),
            Input::NodeFences { reports } => self.node_fences(reports),
            Input::NodeCounts { counts } => {
                let changed = counts != self.node_counts;
                self.node_counts = counts;
                changed
            }
            Input::Layout(layout) => {
                let changed = *layout != self.layout;
                self.layout = *layout;
                changed
            }
            Input::Tick { at } => self.tick(at),
        }
    }

    /// The running schedule's rows as of `now` (each resource's jobs in the chart's
    /// window).
    pub fn schedule(&self, now: u64) -> ScheduleView {
        self.schedule.view(now)
    }

    /// The cell's layout, as last asked (empty until resources with a layout answered).
    pub fn layout(&self) -> &schemas::layout::CellLayout {
        &self.layout
    }

    /// The order-nodes' counts, as last asked (empty until one answered).
    pub fn node_counts(&self) -> &BTreeMap<String, schemas::OrderCounts> {
        &self.node_counts
    }

    /// The order-nodes' processes on etcd, holders and standbys (sorted by node).
    pub fn node_fence_reports(&self) -> &[schemas::fence::NodeFenceReport] {
        &self.node_fences
    }

    /// A new list of the order-nodes' reports: news when a role, an epoch, a lag or a
    /// lost store changed (not the reports' times).
    fn node_fences(&mut self, mut reports: Vec<schemas::fence::NodeFenceReport>) -> bool {
        use schemas::fence::NodeFenceReport as Report;
        reports
            .sort_by(|a, b| (&a.node, a.role as u8, &a.zid).cmp(&(&b.node, b.role as u8, &b.zid)));
        // The reports without their times.
        let timeless = |r: &Report| Report { at: 0, ..r.clone() };
        if reports
            .iter()
            .map(timeless)
            .eq(self.node_fences.iter().map(timeless))
        {
            return false;
        }
        self.node_fences = reports;
        true
    }

    /// The fenced resources' processes, holders and standbys (sorted by resource).
    pub fn fence_reports(&self) -> &[schemas::FenceReport] {
        &self.fences
    }

    /// A new list of fence reports: a change of holder or epoch is logged.
    fn fences(&mut self, mut reports: Vec<schemas::FenceReport>, at: u64) -> bool {
        reports.sort_by(|a, b| {
            (a.holon.name(), a.role as u8, &a.zid).cmp(&(b.holon.name(), b.role as u8, &b.zid))
        });
        // Only who holds what, and who waits, is news: the reports' times are not.
        let shape = |r: &schemas::FenceReport| (r.holon.clone(), r.role, r.epoch, r.zid.clone());
        let same = reports.len() == self.fences.len()
            && reports
                .iter()
                .zip(&self.fences)
                .all(|(a, b)| shape(a) == shape(b));
        if same {
            return false;
        }
        for report in &reports {
            let holder = report.role == schemas::FenceRole::Holder;
            let known = self
                .fences
                .iter()
                .any(|r| r.zid == report.zid && r.role == report.role && r.epoch == report.epoch);
            if holder && !known {
                self.log(
                    at,
                    &report.holon,
                    format!(
                        "holds its controller at epoch {} (on {})",
                        report.epoch.unwrap_or_default(),
                        report.host
                    ),
                );
            }
        }
        self.fences = reports;
        true
    }

    pub fn processes(&self) -> impl Iterator<Item = &ProcessView> {
        self.processes.values()
    }

    pub fn holons(&self) -> impl Iterator<Item = &HolonView> {
        self.holons.values()
    }

    pub fn orders(&self) -> impl Iterator<Item = &OrderSnapshot> {
        self.orders.values()
    }

    pub fn alarms(&self) -> &[Alarm] {
        &self.alarms
    }

    pub fn events(&self) -> impl DoubleEndedIterator<Item = &Event> {
        self.events.iter()
    }

    pub fn counters(&self) -> &Counters {
        &self.counters
    }

    /// Orders done within the hour before `now`.
    pub fn done_last_hour(&self, now: u64) -> usize {
        self.completions
            .iter()
            .filter(|at| now.saturating_sub(**at) <= 3_600_000)
            .count()
    }

    /// Per resource: milliseconds busy since the dashboard started, as of `now`.
    pub fn busy_ms(&self, now: u64) -> BTreeMap<HolonId, u64> {
        self.busy
            .iter()
            .map(|(holon, (total, since))| {
                (
                    holon.clone(),
                    total + since.map_or(0, |s| now.saturating_sub(s)),
                )
            })
            .collect()
    }

    fn log(&mut self, at: u64, source: impl Into<Source>, text: String) {
        if self.events.len() == EVENTS_KEPT {
            self.events.pop_front();
        }
        self.events.push_back(Event {
            at,
            source: source.into(),
            text,
        });
    }

    /// Raises an alarm of `kind` on `source` unless one is active already.
    fn raise(
        &mut self,
        kind: AlarmKind,
        source: impl Into<Source>,
        message: String,
        at: u64,
    ) -> bool {
        let source = source.into();
        if self
            .alarms
            .iter()
            .any(|a| a.kind == kind && a.source == source && a.active())
        {
            return false;
        }
        self.next_alarm += 1;
        self.log(at, source.clone(), format!("alarm: {message}"));
        self.alarms.push(Alarm {
            id: self.next_alarm,
            kind,
            source,
            message,
            raised: at,
            cleared: None,
            acknowledged: None,
        });
        true
    }

    /// Clears the active alarm of `kind` on `source`, if any; an acknowledged one leaves.
    fn clear(&mut self, kind: AlarmKind, source: impl Into<Source>, at: u64) -> bool {
        let source = source.into();
        let Some(alarm) = self
            .alarms
            .iter_mut()
            .find(|a| a.kind == kind && a.source == source && a.active())
        else {
            return false;
        };
        alarm.cleared = Some(at);
        let message = format!("cleared: {}", alarm.message);
        self.alarms
            .retain(|a| a.active() || a.acknowledged.is_none());
        self.log(at, source, message);
        true
    }

    /// Raises or clears the alarm of `kind` on `source` after `condition`.
    fn hold(
        &mut self,
        kind: AlarmKind,
        source: &HolonId,
        condition: Option<String>,
        at: u64,
    ) -> bool {
        match condition {
            Some(message) => self.raise(kind, source, message, at),
            None => self.clear(kind, source, at),
        }
    }

    fn appeared(&mut self, holon: HolonId, at: u64) -> bool {
        let view = self.holons.entry(holon.clone()).or_insert(HolonView {
            kind: holon.kind().as_str(),
            holon: holon.clone(),
            live: false,
            since: at,
            resource: None,
        });
        if view.live {
            return false;
        }
        view.live = true;
        view.since = at;
        self.log(at, &holon, "appeared".into());
        self.clear(AlarmKind::Vanished, &holon, at);
        let times = self.appearances.entry(holon.clone()).or_default();
        times.push_back(at);
        while times
            .front()
            .is_some_and(|t| at.saturating_sub(*t) > RESTARTING_WINDOW_MS)
        {
            times.pop_front();
        }
        if times.len() >= RESTARTING_APPEARANCES {
            let message = format!(
                "{holon} appeared {} times within {} s: its process restarts repeatedly",
                times.len(),
                RESTARTING_WINDOW_MS / 1000
            );
            self.raise(AlarmKind::Restarting, &holon, message, at);
        }
        true
    }

    /// A router's or order-node's token appeared (`live`) or vanished.
    fn process(&mut self, process: ProcessId, live: bool, at: u64) -> bool {
        let view = self
            .processes
            .entry(process.clone())
            .or_insert(ProcessView {
                process: process.clone(),
                live: !live,
                since: at,
            });
        if view.live == live {
            return false;
        }
        view.live = live;
        view.since = at;
        if live {
            self.log(at, &process, "appeared".into());
            self.clear(AlarmKind::Vanished, &process, at);
        } else {
            self.log(at, &process, "vanished".into());
            let message = match process.program.as_str() {
                "order-node" => format!(
                    "{process} vanished: its orders wait until it is back (their bookings are kept for the grace)"
                ),
                _ => format!("{process} vanished: the holons linked through it may be cut off"),
            };
            self.raise(AlarmKind::Vanished, &process, message, at);
        }
        true
    }

    fn vanished(&mut self, holon: HolonId, at: u64) -> bool {
        let Some(view) = self.holons.get_mut(&holon) else {
            return false;
        };
        if !view.live {
            return false;
        }
        view.live = false;
        view.since = at;
        if let Some((total, since)) = self.busy.get_mut(&holon) {
            *total += since.take().map_or(0, |s| at.saturating_sub(s));
        }
        self.log(at, &holon, "vanished".into());
        self.schedule.vanished(&holon, at);
        if holon.kind() == HolonKind::Resource {
            let message = format!("{holon} vanished: its process stopped or its host is cut off");
            self.raise(AlarmKind::Vanished, &holon, message, at);
        }
        true
    }

    fn resource(&mut self, snapshot: ResourceSnapshot, at: u64) -> bool {
        let holon = snapshot.holon.clone();
        let view = self.holons.entry(holon.clone()).or_insert(HolonView {
            kind: HolonKind::Resource.as_str(),
            holon: holon.clone(),
            live: true,
            since: at,
            resource: None,
        });
        // A snapshot older than the one held (a late answer to an ask) changes nothing.
        if view
            .resource
            .as_ref()
            .is_some_and(|held| snapshot.at < held.at)
        {
            return false;
        }
        let before = view.resource.replace(snapshot.clone());
        if before
            .as_ref()
            .is_some_and(|b| same_resource_state(b, &snapshot))
        {
            return false;
        }
        self.schedule.resource(&snapshot, at);
        let (was_state, was_controller, was_agenda) =
            before.as_ref().map_or((None, None, Vec::new()), |b| {
                (
                    Some(b.state),
                    Some(b.controller),
                    b.agenda.iter().map(|a| a.conversation_id.clone()).collect(),
                )
            });
        let name = holon.name().to_string();
        for booking in &snapshot.agenda {
            if !was_agenda.contains(&booking.conversation_id) {
                *self.counters.bookings.entry(name.clone()).or_default() += 1;
            }
        }
        if was_state != Some(snapshot.state) || was_controller != Some(snapshot.controller) {
            let text = match &snapshot.current {
                Some(job) => format!(
                    "{} (controller {}), working on {} for {}",
                    snapshot.state, snapshot.controller, job.service_type, job.requester
                ),
                None => format!("{} (controller {})", snapshot.state, snapshot.controller),
            };
            self.log(at, &holon, text);
        }
        let running = snapshot
            .current
            .as_ref()
            .map(|job| (job.conversation_id.clone(), job.service_type.clone()));
        let seen = self
            .jobs
            .get(&holon)
            .map(|(c, t, _)| (c.clone(), t.clone()));
        if seen != running {
            if let Some((_, service_type, started)) = self.jobs.remove(&holon) {
                let seconds = at.saturating_sub(started) as f64 / 1000.0;
                self.counters
                    .steps
                    .entry((service_type, holon.name().to_string()))
                    .or_default()
                    .observe(seconds);
            }
            // A job already running when the dashboard first saw the resource has no
            // known start: not timed.
            if let (Some((conversation, service_type)), true) = (running, before.is_some()) {
                self.jobs
                    .insert(holon.clone(), (conversation, service_type, at));
            }
        }
        let busy = self.busy.entry(holon.clone()).or_default();
        match (snapshot.state == ResourceState::Busy, busy.1) {
            (true, None) => busy.1 = Some(at),
            (false, Some(since)) => {
                busy.0 += at.saturating_sub(since);
                busy.1 = None;
            }
            _ => {}
        }
        let faulted = matches!(
            snapshot.controller,
            ControllerStatus::Fault | ControllerStatus::Estop
        );
        if faulted && was_controller != Some(snapshot.controller) {
            *self.counters.controller_faults.entry(name).or_default() += 1;
        }
        self.hold(
            AlarmKind::Controller,
            &holon,
            faulted.then(|| format!("{holon}: controller in {}", snapshot.controller)),
            at,
        );
        self.hold(
            AlarmKind::Journal,
            &holon,
            snapshot
                .journal_fault
                .as_ref()
                .map(|why| format!("{holon}: the journal cannot be written ({why})")),
            at,
        );
        self.hold(
            AlarmKind::Undelivered,
            &holon,
            (snapshot.undelivered >= UNDELIVERED_ALARM).then(|| {
                format!(
                    "{holon}: {} results not acknowledged by their orders",
                    snapshot.undelivered
                )
            }),
            at,
        );
        true
    }

    fn order(&mut self, snapshot: OrderSnapshot, at: u64) -> bool {
        let holon = snapshot.holon.clone();
        if self
            .orders
            .get(&holon)
            .is_some_and(|held| snapshot.at < held.at)
        {
            return false;
        }
        let before = self.orders.insert(holon.clone(), snapshot.clone());
        if before.as_ref() == Some(&snapshot) {
            return false;
        }
        let progressed = before.as_ref().is_none_or(|b| {
            b.status != snapshot.status
                || b.step != snapshot.step
                || b.resource != snapshot.resource
        });
        if progressed {
            let text = match (&snapshot.status, &snapshot.resource) {
                (OrderStatus::Running, Some(resource)) => format!(
                    "step {}/{} {} on {resource}",
                    snapshot.step,
                    snapshot.steps,
                    snapshot.service_type.as_deref().unwrap_or("")
                ),
                (OrderStatus::Running, None) => {
                    format!("step {}/{}", snapshot.step, snapshot.steps)
                }
                (status, _) => format!(
                    "{}{}",
                    serde_json::to_value(status)
                        .ok()
                        .and_then(|v| v.as_str().map(String::from))
                        .unwrap_or_default(),
                    snapshot
                        .reason
                        .as_deref()
                        .map(|r| format!(": {r}"))
                        .unwrap_or_default()
                ),
            };
            self.log(at, &holon, text);
        }
        self.part_alarm(&snapshot, at);
        if self.part_waits.seen(&snapshot, at) {
            self.clear(AlarmKind::PartWaits, &holon, at);
        }
        let ended_now = before.as_ref().is_none_or(|b| b.status != snapshot.status);
        if ended_now && snapshot.status.is_final() {
            self.finished.push_back(holon.clone());
            while self.finished.len() > FINISHED_KEPT {
                if let Some(oldest) = self.finished.pop_front() {
                    if self
                        .orders
                        .get(&oldest)
                        .is_some_and(|o| o.status.is_final())
                    {
                        self.orders.remove(&oldest);
                    }
                }
            }
        }
        if ended_now {
            let reason = snapshot.reason.clone().unwrap_or_default();
            match snapshot.status {
                OrderStatus::Done => {
                    self.counters.orders_done += 1;
                    self.completions.push_back(at);
                    while self
                        .completions
                        .front()
                        .is_some_and(|t| at.saturating_sub(*t) > 3_600_000)
                    {
                        self.completions.pop_front();
                    }
                }
                OrderStatus::Failed => {
                    self.counters.orders_failed += 1;
                    let message = format!("{holon} failed: {reason}");
                    self.raise(AlarmKind::OrderFailed, &holon, message, at);
                    self.clear(AlarmKind::OrderFailed, &holon, at);
                }
                OrderStatus::Scrapped => {
                    self.counters.orders_scrapped += 1;
                    let message = format!("{holon} scrapped: {reason}");
                    self.raise(AlarmKind::OrderScrapped, &holon, message, at);
                    self.clear(AlarmKind::OrderScrapped, &holon, at);
                }
                OrderStatus::Running | OrderStatus::Cancelled => {}
            }
        }
        true
    }

    fn acknowledge(&mut self, id: u64, by: &str, at: u64) -> bool {
        let Some(alarm) = self.alarms.iter_mut().find(|a| a.id == id) else {
            return false;
        };
        if alarm.acknowledged.is_some() {
            return false;
        }
        alarm.acknowledged = Some(at);
        let (source, message) = (alarm.source.clone(), alarm.message.clone());
        self.alarms
            .retain(|a| a.active() || a.acknowledged.is_none());
        self.log(at, source, format!("acknowledged by {by}: {message}"));
        true
    }
}

/// Whether two snapshots of a resource show the same (only their time differs).
fn same_resource_state(a: &ResourceSnapshot, b: &ResourceSnapshot) -> bool {
    ResourceSnapshot { at: 0, ..a.clone() } == ResourceSnapshot { at: 0, ..b.clone() }
}

#[cfg(test)]
mod tests;

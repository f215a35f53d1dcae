//! What the page shows: the view of the model, as of one moment, made by the model's
//! owner and sent whole to every page.

use schemas::OrderSnapshot;
use serde::Serialize;

use super::model::{self, Alarm, Event, HolonView, Model, ProcessView};
use super::DashboardConfig;

/// What the page shows, as of one moment.
#[derive(Debug, Clone, Serialize, Default)]
pub struct View {
    pub cell: String,
    /// Unix ms.
    pub at: u64,
    pub operator: bool,
    pub holons: Vec<HolonView>,
    /// The routers and order-nodes that announce themselves (`host/<program>/<name>`).
    pub processes: Vec<ProcessView>,
    /// The routers this dashboard's own session is linked to (zenoh ids), as zenoh
    /// tells it.
    pub linked_routers: Vec<String>,
    /// Every running order, and the last [`FINISHED_SHOWN`] finished ones, as rows (the
    /// page's memory and each update stay bounded however many orders the cell made;
    /// `cell orders --detail` has every attempt of every order).
    pub orders: Vec<OrderRow>,
    /// How many orders the cell's order-nodes host, by status.
    pub order_counts: std::collections::BTreeMap<String, usize>,
    pub alarms: Vec<Alarm>,
    /// The fenced resources' processes: who holds each controller, at which epoch, and
    /// who stands by.
    pub fences: Vec<schemas::FenceReport>,
    /// The order-nodes' processes on etcd: who holds each node's leader key, at which
    /// epoch, and its standbys with their lag.
    pub node_fences: Vec<schemas::fence::NodeFenceReport>,
    /// The newest first.
    pub events: Vec<Event>,
    pub throughput: Throughput,
    /// For `/metrics`.
    #[serde(skip)]
    pub counters: model::Counters,
    /// Samples dropped because the model's queue was full.
    pub dropped: u64,
    /// The cell's layout (docs/material-flow.md): each serving resource's part, and
    /// what is wrong with them together.
    pub layout: schemas::layout::CellLayout,
    /// The running schedule, per resource: its jobs of the last
    /// [`model::WINDOW_PLANT_MS`] of plant time, for the page's Gantt chart.
    pub schedule: model::ScheduleView,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct Throughput {
    /// Orders done within the last hour.
    pub done_last_hour: usize,
    /// Per resource: the share of time busy since the dashboard started.
    pub utilisation: Vec<(String, f64)>,
    /// Per resource: seconds busy since the dashboard started.
    pub busy_seconds: Vec<(String, f64)>,
}

/// How many finished orders the view carries (the newest).
pub const FINISHED_SHOWN: usize = 500;

/// One order as the page lists it.
#[derive(Debug, Clone, Serialize)]
pub struct OrderRow {
    pub holon: schemas::HolonId,
    pub product: String,
    pub status: schemas::OrderStatus,
    pub reason: Option<String>,
    pub step: usize,
    pub steps: usize,
    pub service_type: Option<String>,
    pub resource: Option<schemas::HolonId>,
    pub rebooks: u32,
    pub reworks: u32,
    pub failed_attempts: u32,
    /// The work order's priority (higher first).
    pub priority: i32,
    /// When the order is due (Unix ms), if it is.
    pub due: Option<u64>,
    /// Where its part is, for a plan that moves parts (drawn on the layout).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub part: Option<schemas::PartPlace>,
    /// When the order last changed (Unix ms).
    pub at: u64,
}

impl From<&OrderSnapshot> for OrderRow {
    fn from(o: &OrderSnapshot) -> OrderRow {
        OrderRow {
            holon: o.holon.clone(),
            product: o.product.clone(),
            status: o.status,
            reason: o.reason.clone(),
            step: o.step,
            steps: o.steps,
            service_type: o.service_type.clone(),
            resource: o.resource.clone(),
            rebooks: o.rebooks,
            reworks: o.reworks,
            failed_attempts: o.failed_attempts,
            priority: o.priority,
            due: o.due,
            part: o.part.clone(),
            at: o.at,
        }
    }
}

/// The rows of the view: every running order, the newest finished ones.
fn order_rows(model: &Model) -> Vec<OrderRow> {
    let mut finished: Vec<&OrderSnapshot> =
        model.orders().filter(|o| o.status.is_final()).collect();
    finished.sort_by_key(|o| std::cmp::Reverse(o.at));
    finished.truncate(FINISHED_SHOWN);
    model
        .orders()
        .filter(|o| !o.status.is_final())
        .chain(finished.into_iter().rev())
        .map(OrderRow::from)
        .collect()
}

/// How many orders the cell's order-nodes host, by status: as the nodes counted them
/// (their listings' counts, every whole history), or, until one answered, the orders
/// this dashboard heard of.
fn order_counts(model: &Model) -> std::collections::BTreeMap<String, usize> {
    use schemas::OrderStatus;
    let mut counts = std::collections::BTreeMap::new();
    if model.node_counts().is_empty() {
        for o in model.orders() {
            *counts.entry(o.status.as_str().to_string()).or_insert(0) += 1;
        }
        return counts;
    }
    let mut total = schemas::OrderCounts::default();
    for node in model.node_counts().values() {
        total.merge(node);
    }
    for status in [
        OrderStatus::Running,
        OrderStatus::Done,
        OrderStatus::Scrapped,
        OrderStatus::Failed,
        OrderStatus::Cancelled,
    ] {
        counts.insert(status.as_str().to_string(), total.of(status) as usize);
    }
    counts
}

/// The page's view of the model, now (`started`: when the dashboard began watching).
pub(super) fn view_of(config: &DashboardConfig, model: &Model, dropped: u64, started: u64) -> View {
    let now = schemas::unix_ms();
    let busy = model.busy_ms(now);
    let watched = now.saturating_sub(started).max(1) as f64;
    View {
        cell: config.keys.cell().to_string(),
        at: now,
        operator: config.operator,
        holons: model.holons().cloned().collect(),
        processes: model.processes().cloned().collect(),
        linked_routers: Vec::new(),
        orders: order_rows(model),
        order_counts: order_counts(model),
        alarms: model.alarms().to_vec(),
        fences: model.fence_reports().to_vec(),
        node_fences: model.node_fence_reports().to_vec(),
        events: model.events().rev().cloned().collect(),
        throughput: Throughput {
            done_last_hour: model.done_last_hour(now),
            utilisation: busy
                .iter()
                .map(|(h, ms)| (h.name().to_string(), (*ms as f64 / watched).min(1.0)))
                .collect(),
            busy_seconds: busy
                .iter()
                .map(|(h, ms)| (h.name().to_string(), *ms as f64 / 1000.0))
                .collect(),
        },
        counters: model.counters().clone(),
        dropped,
        layout: model.layout().clone(),
        schedule: model.schedule(now),
    }
}

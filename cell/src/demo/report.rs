//! What the demo prints of its orders: each step as it completes, and the summary.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use schemas::{HolonId, OrderSnapshot, OrderStatus, PartPlace};

/// What the demo saw, for its summary.
pub(super) struct Report {
    pub(super) orders: BTreeMap<HolonId, OrderSnapshot>,
    pub(super) failed: usize,
    pub(super) elapsed: Duration,
    pub(super) hot_added: Option<Duration>,
    /// A staff holon advised the orders.
    pub(super) staff: bool,
    /// The moves seen to end (a part from in transit to where it went), by transporter.
    pub(super) transports: BTreeMap<HolonId, usize>,
}

impl Report {
    pub(super) fn completed(&self) -> usize {
        self.orders
            .values()
            .filter(|o| matches!(o.status, OrderStatus::Done | OrderStatus::Scrapped))
            .count()
    }

    pub(super) fn print(&self, dir: &Path) {
        let count = |s: OrderStatus| self.orders.values().filter(|o| o.status == s).count();
        let mut steps: BTreeMap<String, usize> = BTreeMap::new();
        for order in self.orders.values() {
            for (_, resource) in &order.completed {
                *steps.entry(resource.to_string()).or_default() += 1;
            }
        }
        println!();
        println!("summary");
        println!("  orders done     {}", count(OrderStatus::Done));
        println!("  orders scrapped {}", count(OrderStatus::Scrapped));
        println!("  orders failed   {}", self.failed);
        for order in self
            .orders
            .values()
            .filter(|o| o.status == OrderStatus::Failed)
        {
            println!(
                "    {}: {}",
                order.holon,
                order.reason.as_ref().map_or("", |r| r.as_str())
            );
        }
        println!("  time taken      {:.2} s", self.elapsed.as_secs_f64());
        if let Some(at) = self.hot_added {
            println!("  robot3 added    at {:.2} s", at.as_secs_f64());
        }
        println!(
            "  reworks         {}",
            self.orders.values().map(|o| o.reworks).sum::<u32>()
        );
        println!(
            "  rebooks         {}",
            self.orders.values().map(|o| o.rebooks).sum::<u32>()
        );
        if self.staff {
            let steps: usize = self.orders.values().map(|o| o.completed.len()).sum();
            println!(
                "  on advice       {} of {steps} steps booked as staff/planner advised",
                self.orders.values().map(|o| o.advised).sum::<u32>()
            );
        }
        println!("  steps per resource");
        for (resource, n) in &steps {
            println!("    {resource:<20} {n:>4}");
        }
        println!("  transports");
        for (transporter, n) in &self.transports {
            println!("    {transporter:<20} {n:>4}");
        }
        // The plant's own word on where the parts are.
        let plant = std::fs::read_to_string(dir.join(super::PLANT_STATE))
            .ok()
            .and_then(|text| serde_json::from_str::<serde_json::Value>(&text).ok());
        if let Some(plant) = plant {
            let in_cell: usize = plant["locations"].as_object().map_or(0, |l| {
                l.values().filter_map(|p| p.as_array()).map(Vec::len).sum()
            });
            let moving = plant["in_transit"].as_array().map_or(0, Vec::len);
            println!(
                "  the plant says  {} parts shipped, {in_cell} in the cell, {moving} on the move",
                plant["shipped"]
            );
        }
    }

    /// Counts a move seen to end: `previous` had the part in transit, `snapshot` has it
    /// where it went.
    pub(super) fn count_move(
        &mut self,
        previous: Option<&OrderSnapshot>,
        snapshot: &OrderSnapshot,
    ) {
        if let Some(transporter) = move_ended(previous, snapshot) {
            *self.transports.entry(transporter).or_default() += 1;
        }
    }
}

/// The transporter whose move ended between `previous` and `snapshot`: the part was in
/// transit on it, and is now at a location or shipped.
fn move_ended(previous: Option<&OrderSnapshot>, snapshot: &OrderSnapshot) -> Option<HolonId> {
    let Some(PartPlace::InTransit { transporter, .. }) = previous.and_then(|p| p.part.as_ref())
    else {
        return None;
    };
    matches!(
        snapshot.part,
        Some(PartPlace::At { .. } | PartPlace::Shipped { .. })
    )
    .then(|| transporter.clone())
}

/// Prints what an order's new state says, if it progressed since `previous`: the step
/// just completed (passed, or rejected: a rework or a scrap), and its end.
pub(super) fn print_progress(
    previous: Option<&OrderSnapshot>,
    snapshot: &OrderSnapshot,
    elapsed: Duration,
    advised_shown: &mut BTreeMap<HolonId, u32>,
) {
    let elapsed = elapsed.as_secs_f64();
    if let Some(transporter) = move_ended(previous, snapshot) {
        if let Some(part) = &snapshot.part {
            println!(
                "{elapsed:7.2}s  {:<14} {:<13} part {part} ({transporter})",
                snapshot.holon.name(),
                "move"
            );
        }
    }
    let progressed = previous.is_none_or(|p| {
        p.status != snapshot.status || p.completed.len() != snapshot.completed.len()
    });
    if !progressed {
        return;
    }
    let steps_before = previous.map_or(0, |p| p.completed.len());
    let reworked = previous.is_some_and(|p| snapshot.reworks > p.reworks);
    // The step was booked on a staff holon's advice: the count grew since the last
    // step shown (it grows when a step is booked, before it is done).
    let shown = advised_shown.entry(snapshot.holon.clone()).or_default();
    let advised = if snapshot.advised > *shown && snapshot.completed.len() > steps_before {
        *shown = snapshot.advised;
        " *"
    } else {
        ""
    };
    if snapshot.completed.len() > steps_before {
        if let Some((service, resource)) = snapshot.completed.last() {
            let outcome = if reworked {
                format!("rejected by {resource} -> rework {}", snapshot.reworks)
            } else if snapshot.status == OrderStatus::Scrapped {
                format!("rejected by {resource}")
            } else {
                format!("done by {resource}{advised}")
            };
            println!(
                "{elapsed:7.2}s  {:<14} {service:<13} {outcome}",
                snapshot.holon.name()
            );
        }
    }
    if snapshot.status != OrderStatus::Running {
        println!(
            "{elapsed:7.2}s  {:<14} {:?}{}",
            snapshot.holon.name(),
            snapshot.status,
            snapshot
                .reason
                .as_deref()
                .map(|r| format!(": {r}"))
                .unwrap_or_default()
        );
    }
}

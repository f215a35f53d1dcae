//! What the demo prints of its orders: each step as it completes, and the summary.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::Duration;

use schemas::{HolonId, OrderSnapshot, OrderStatus};

/// What the demo saw, for its summary.
pub(super) struct Report {
    pub(super) orders: BTreeMap<HolonId, OrderSnapshot>,
    pub(super) failed: usize,
    pub(super) elapsed: Duration,
    pub(super) hot_added: Option<Duration>,
    /// A staff holon advised the orders.
    pub(super) staff: bool,
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
            let sim = resource.trim_start_matches("resource/");
            let counts = std::fs::read_to_string(dir.join(format!("{sim}-sim.counts.json")))
                .unwrap_or_default();
            println!("    {resource:<20} {n:>4}   controller {}", counts.trim());
        }
    }
}

/// Prints what an order's new state says, if it progressed since `previous`: the step
/// just completed (passed, or rejected: a rework or a scrap), and its end.
pub(super) fn print_progress(
    previous: Option<&OrderSnapshot>,
    snapshot: &OrderSnapshot,
    elapsed: Duration,
    advised_shown: &mut BTreeMap<HolonId, u32>,
) {
    let progressed = previous.is_none_or(|p| {
        p.status != snapshot.status || p.completed.len() != snapshot.completed.len()
    });
    if !progressed {
        return;
    }
    let elapsed = elapsed.as_secs_f64();
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

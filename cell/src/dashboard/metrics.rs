//! `/metrics`: the view in the Prometheus text format (version 0.0.4).

use std::collections::BTreeMap;

use schemas::OrderStatus;

use super::gate::Gate;
use super::View;

/// The dashboard's own door in the Prometheus text format: refused logins and live
/// sessions.
pub fn render_gate(gate: &Gate) -> String {
    format!(
        "# HELP holarchy_dashboard_logins_failed_total Logins refused (a wrong password, an unknown user, a lock-out) since the dashboard started.\n\
         # TYPE holarchy_dashboard_logins_failed_total counter\n\
         holarchy_dashboard_logins_failed_total {}\n\
         # HELP holarchy_dashboard_sessions Live login sessions.\n\
         # TYPE holarchy_dashboard_sessions gauge\n\
         holarchy_dashboard_sessions {}\n",
        gate.logins_refused(),
        gate.sessions_live()
    )
}

/// The metrics of `view`, one family after the other, each with its HELP and TYPE.
pub fn render(view: &View) -> String {
    let mut metrics = Exposition::default();
    the_cell_now(&mut metrics, view);
    per_resource(&mut metrics, view);
    metrics.family(
        "holarchy_dashboard_dropped_samples_total",
        "counter",
        "Samples the dashboard dropped because its model was behind.",
        vec![(String::new(), view.dropped as f64)],
    );
    metrics.out
}

/// The text being written: families of samples, each a label set and a value.
#[derive(Default)]
struct Exposition {
    /// The families written so far.
    out: String,
}

impl Exposition {
    /// One family: its HELP and TYPE lines, then a line per sample.
    fn family(&mut self, name: &str, kind: &str, help: &str, samples: Vec<(String, f64)>) {
        self.out
            .push_str(&format!("# HELP {name} {help}\n# TYPE {name} {kind}\n"));
        for (labels, value) in samples {
            self.out.push_str(&format!("{name}{labels} {value}\n"));
        }
    }
}

/// The cell as it is: its live holons, its orders and its alarms.
fn the_cell_now(metrics: &mut Exposition, view: &View) {
    let mut holons: BTreeMap<(String, String), f64> = BTreeMap::new();
    for holon in view.holons.iter().filter(|h| h.live) {
        let state = holon
            .resource
            .as_ref()
            .map_or("live".to_string(), |r| r.state.to_string());
        *holons.entry((holon.kind.to_string(), state)).or_default() += 1.0;
    }
    metrics.family(
        "holarchy_holons",
        "gauge",
        "Live holons by kind and state (a resource's state: init, free, busy).",
        holons
            .into_iter()
            .map(|((kind, state), n)| (format!("{{kind=\"{kind}\",state=\"{state}\"}}"), n))
            .collect(),
    );
    let mut orders: BTreeMap<String, f64> = [
        OrderStatus::Running,
        OrderStatus::Done,
        OrderStatus::Scrapped,
        OrderStatus::Failed,
        OrderStatus::Cancelled,
    ]
    .iter()
    .map(|s| (status_name(*s), 0.0))
    .collect();
    for (status, count) in &view.order_counts {
        *orders.entry(status.clone()).or_default() += *count as f64;
    }
    metrics.family(
        "holarchy_orders",
        "gauge",
        "Orders the cell's order-nodes host, by status.",
        orders
            .into_iter()
            .map(|(status, n)| (format!("{{status=\"{status}\"}}"), n))
            .collect(),
    );
    metrics.family(
        "holarchy_alarms_active",
        "gauge",
        "Alarms whose condition holds.",
        vec![(
            String::new(),
            view.alarms.iter().filter(|a| a.active()).count() as f64,
        )],
    );
    metrics.family(
        "holarchy_alarms_unacknowledged",
        "gauge",
        "Alarms no operator acknowledged yet.",
        vec![(
            String::new(),
            view.alarms
                .iter()
                .filter(|a| a.acknowledged.is_none())
                .count() as f64,
        )],
    );
}

/// What ended since the dashboard started, and each resource's work and deliveries.
fn per_resource(metrics: &mut Exposition, view: &View) {
    let counters = &view.counters;
    metrics.family(
        "holarchy_orders_ended_total",
        "counter",
        "Orders seen ending since the dashboard started, by how.",
        vec![
            ("{how=\"done\"}".into(), counters.orders_done as f64),
            ("{how=\"failed\"}".into(), counters.orders_failed as f64),
            ("{how=\"scrapped\"}".into(), counters.orders_scrapped as f64),
        ],
    );
    metrics.family(
        "holarchy_resource_busy_seconds_total",
        "counter",
        "Seconds each resource was busy since the dashboard started.",
        view.throughput
            .busy_seconds
            .iter()
            .map(|(r, s)| (format!("{{resource=\"{r}\"}}"), *s))
            .collect(),
    );
    let of_each_resource = |value: fn(&schemas::ResourceSnapshot) -> f64| {
        view.holons
            .iter()
            .filter_map(|h| h.resource.as_ref())
            .map(|r| (format!("{{resource=\"{}\"}}", r.holon.name()), value(r)))
            .collect()
    };
    metrics.family(
        "holarchy_resource_undelivered",
        "gauge",
        "Results each resource sent and its orders have not acknowledged yet.",
        of_each_resource(|r| r.undelivered as f64),
    );
    metrics.family(
        "holarchy_delivery_retries_total",
        "counter",
        "Times each resource sent a result again because it was not acknowledged, since its process started (resets when it restarts).",
        of_each_resource(|r| r.delivery_retries as f64),
    );
    metrics.family(
        "holarchy_controller_faults_total",
        "counter",
        "Times each resource's controller went into fault or estop since the dashboard started.",
        counters
            .controller_faults
            .iter()
            .map(|(r, n)| (format!("{{resource=\"{r}\"}}"), *n as f64))
            .collect(),
    );
    metrics.family(
        "holarchy_bookings_total",
        "counter",
        "Bookings seen on each resource's agenda since the dashboard started.",
        counters
            .bookings
            .iter()
            .map(|(r, n)| (format!("{{resource=\"{r}\"}}"), *n as f64))
            .collect(),
    );
    metrics.family(
        "holarchy_step_duration_seconds",
        "histogram",
        "How long jobs took on each resource, by service type (seen from start to end).",
        step_durations(view),
    );
}

/// The step-duration histograms' samples: cumulative buckets, sum and count per service
/// type and resource.
fn step_durations(view: &View) -> Vec<(String, f64)> {
    let mut steps = Vec::new();
    for ((service_type, resource), histogram) in &view.counters.steps {
        let labels = format!("service_type=\"{service_type}\",resource=\"{resource}\"");
        let mut cumulative = 0;
        for (i, count) in histogram.buckets.iter().enumerate() {
            cumulative += count;
            let le = super::model::STEP_BUCKETS
                .get(i)
                .map_or("+Inf".to_string(), |b| b.to_string());
            steps.push((
                format!("_bucket{{{labels},le=\"{le}\"}}"),
                cumulative as f64,
            ));
        }
        steps.push((format!("_sum{{{labels}}}"), histogram.sum_seconds));
        steps.push((format!("_count{{{labels}}}"), histogram.count as f64));
    }
    steps
}

fn status_name(status: OrderStatus) -> String {
    serde_json::to_value(status)
        .ok()
        .and_then(|v| v.as_str().map(String::from))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_cell_has_every_family_with_help_and_type() {
        let text = render(&View::default());
        for family in [
            "holarchy_holons",
            "holarchy_orders",
            "holarchy_alarms_active",
            "holarchy_orders_ended_total",
        ] {
            assert!(text.contains(&format!("# TYPE {family} ")), "{text}");
            assert!(text.contains(&format!("# HELP {family} ")), "{text}");
        }
        assert!(
            text.contains("holarchy_orders{status=\"done\"} 0"),
            "{text}"
        );
    }
}

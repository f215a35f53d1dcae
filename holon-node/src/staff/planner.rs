//! The staff's advice: for an order's route still ahead, which resource to book for the
//! next step, by forecasting the whole route (pure; no I/O, no clock).
//!
//! For each resource that could take the next step, the planner forecasts the route to
//! its end: the next step on that resource, each later step on whichever resource would
//! finish it first. A step on a resource starts when the resource is free of the work
//! that goes before it (its running job and the waiting bookings of the order's
//! priority or higher, each as long as the staff measured, with a changeover where the
//! program changes) and of the other orders' intentions of that priority or higher (the
//! later steps the staff planned for them), and not before the order's previous step
//! ends. The advice is the candidate whose route is least late for the order's due time,
//! then done soonest, then frees the next step soonest. Its route becomes the order's
//! intentions, so orders that ask together are spread over the resources.

use schemas::layout::CellLayout;
use schemas::{Advice, AdviceRequest, ForecastStep, HolonId, RouteStep, ADVICE_VERSION};

use crate::staff::model::{CellModel, Intention, ResourceModel};
use crate::staff::travel::{self, Reach};

/// A route as forecast from one candidate for the next step.
#[derive(Debug, Clone)]
struct Forecast {
    route: Vec<ForecastStep>,
    /// Every step found a resource.
    complete: bool,
}

impl Forecast {
    fn done(&self) -> u64 {
        self.route.last().map_or(0, |s| s.end)
    }

    fn first_end(&self) -> u64 {
        self.route.first().map_or(0, |s| s.end)
    }
}

/// The advice for `request` at `now`, and the order's intentions (its forecast route,
/// each step lapsing `intention_ttl_ms` after its forecast end unless booked).
pub fn advise(
    model: &CellModel,
    layout: Option<&CellLayout>,
    staff: &HolonId,
    request: &AdviceRequest,
    now: u64,
    intention_ttl_ms: u64,
) -> (Advice, Vec<Intention>) {
    let mut advice = Advice {
        v: ADVICE_VERSION,
        staff: staff.clone(),
        order: request.order.clone(),
        conversation_id: request.conversation_id.clone(),
        resource: None,
        forecast_done: None,
        late_by_ms: None,
        route: vec![],
        why: String::new(),
    };
    let next = &request.steps[0];
    let mut forecasts: Vec<Forecast> = model
        .resources()
        .filter(|r| can_take(r, next) && !request.avoid.contains(&r.snapshot.holon))
        .filter_map(|first| forecast(model, layout, request, first, now))
        .collect();
    if forecasts.is_empty() {
        advice.why = match &request.at {
            Some(at) => format!(
                "no resource alive and ready offers {} where the part can get from {at}",
                next.service_type
            ),
            None => format!("no resource alive and ready offers {}", next.service_type),
        };
        return (advice, vec![]);
    }
    let late = |f: &Forecast| match request.due {
        Some(due) if f.complete => f.done().saturating_sub(due),
        _ => 0,
    };
    forecasts.sort_by(|a, b| {
        (
            !a.complete,
            late(a),
            a.done(),
            a.first_end(),
            &a.route[0].resource,
        )
            .cmp(&(
                !b.complete,
                late(b),
                b.done(),
                b.first_end(),
                &b.route[0].resource,
            ))
    });
    let best = &forecasts[0];
    advice.resource = Some(best.route[0].resource.clone());
    advice.forecast_done = best.complete.then(|| best.done());
    advice.late_by_ms = Some(late(best)).filter(|ms| *ms > 0);
    advice.why = forecasts
        .iter()
        .take(4)
        .map(|f| {
            let when = f.done().saturating_sub(now) as f64 / 1000.0;
            let done = if f.complete { "done" } else { "partly planned" };
            let travel = f.route.iter().map(|s| s.travel_ms).sum::<u64>();
            let travel = match travel {
                0 => String::new(),
                ms => format!(" (travel {:.1} s)", ms as f64 / 1000.0),
            };
            format!("{} {done} at +{when:.1} s{travel}", f.route[0].resource)
        })
        .collect::<Vec<_>>()
        .join("; ");
    let intentions = best
        .route
        .iter()
        .zip(&request.steps)
        .map(|(step, route_step)| Intention {
            order: request.order.clone(),
            service_type: step.service_type.clone(),
            resource: step.resource.clone(),
            program: route_step.program.clone(),
            priority: request.priority,
            start: step.start,
            end: step.end,
            expires: step.end.saturating_add(intention_ttl_ms),
        })
        .collect();
    advice.route = best.route.clone();
    (advice, intentions)
}

fn can_take(resource: &ResourceModel, step: &RouteStep) -> bool {
    resource.takes_work() && resource.offers(&step.service_type)
}

/// The route with the next step on `first` and every later step where it ends soonest,
/// each step after the part's move to it (travel times from the layout, from where the
/// part is). `None` when the part cannot get to `first`.
fn forecast(
    model: &CellModel,
    layout: Option<&CellLayout>,
    request: &AdviceRequest,
    first: &ResourceModel,
    now: u64,
) -> Option<Forecast> {
    let mut own: Vec<Intention> = Vec::new();
    let mut route = Vec::new();
    let mut ready = now;
    let mut at = request.at.clone();
    for (index, step) in request.steps.iter().enumerate() {
        let candidates: Vec<&ResourceModel> = if index == 0 {
            vec![first]
        } else {
            model.resources().filter(|r| can_take(r, step)).collect()
        };
        let placed = candidates
            .into_iter()
            .filter_map(|r| {
                let (to, travel_ms) =
                    match travel::reach(layout, at.as_ref(), r.snapshot.holon.name()) {
                        Reach::There => (None, 0),
                        Reach::Move { to, travel_ms } => (Some(to), travel_ms),
                        Reach::Unreachable => return None,
                    };
                let placed = place(model, r, step, request, ready + travel_ms, now, &own);
                Some(ForecastStep {
                    to,
                    travel_ms,
                    ..placed
                })
            })
            .min_by(|a, b| (a.end, &a.resource).cmp(&(b.end, &b.resource)));
        let Some(placed) = placed else {
            return (index > 0).then_some(Forecast {
                route,
                complete: false,
            });
        };
        ready = placed.end;
        if let Some(to) = placed.to.clone() {
            at = Some(travel::departure(layout, placed.resource.name(), to));
        }
        own.push(Intention {
            order: request.order.clone(),
            service_type: step.service_type.clone(),
            resource: placed.resource.clone(),
            program: step.program.clone(),
            priority: request.priority,
            start: placed.start,
            end: placed.end,
            expires: u64::MAX,
        });
        route.push(placed);
    }
    Some(Forecast {
        route,
        complete: true,
    })
}

/// The earliest a step can run on `resource`: after `ready`, once the resource is free
/// of the work ahead of the order's priority, in the first gap between the intentions
/// of that priority or higher (the other orders', and this order's earlier steps) long
/// enough for it, changeover included.
fn place(
    model: &CellModel,
    resource: &ResourceModel,
    step: &RouteStep,
    request: &AdviceRequest,
    ready: u64,
    now: u64,
    own: &[Intention],
) -> ForecastStep {
    let holon = &resource.snapshot.holon;
    let (free, mut before) = resource.free_for(request.priority, now);
    let mut reserved: Vec<&Intention> = model
        .intentions()
        .iter()
        .filter(|i| &i.resource == holon && i.order != request.order)
        .filter(|i| i.priority >= request.priority)
        .chain(own.iter().filter(|i| &i.resource == holon))
        .collect();
    reserved.sort_by_key(|i| (i.start, i.end));
    let job_after = |before: &Option<String>| {
        resource.duration(
            &step.service_type,
            step.program.as_deref(),
            before.as_deref(),
        )
    };
    let mut start = ready.max(free);
    for interval in reserved {
        // An interval that ends by then sets the program the step follows; one that
        // the step (changeover included) would overlap pushes the step past its end.
        let ends_before = interval.end <= start;
        if !ends_before && interval.start >= start + job_after(&before).ms {
            break; // fits before it
        }
        if !ends_before {
            start = interval.end;
        }
        if interval.program.is_some() {
            before = interval.program.clone();
        }
    }
    let job = job_after(&before);
    ForecastStep {
        service_type: step.service_type.clone(),
        resource: holon.clone(),
        start,
        end: start + job.ms,
        changeover: job.changeover,
        to: None,
        travel_ms: 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::staff::model::tests::{booking, running, snapshot};

    fn request(order: &str, steps: &[(&str, Option<&str>)]) -> AdviceRequest {
        AdviceRequest {
            v: ADVICE_VERSION,
            order: HolonId::order(order).unwrap(),
            conversation_id: format!("{order}/1/1"),
            priority: 0,
            due: None,
            steps: steps
                .iter()
                .map(|(service, program)| RouteStep {
                    service_type: service.to_string(),
                    program: program.map(str::to_string),
                })
                .collect(),
            avoid: vec![],
            at: None,
        }
    }

    fn staff() -> HolonId {
        HolonId::staff("planner").unwrap()
    }

    /// A model where `fast` and `slow` both offer pick_n_place, measured at 200 and
    /// 800 ms, and `inspect1` offers inspect (nominal 500).
    fn cell() -> CellModel {
        let mut model = CellModel::default();
        for (name, ms) in [("fast", 200), ("slow", 800)] {
            let mut t = 0;
            for n in 0..3 {
                model.observe(running(snapshot(name, t), &format!("c{n}"), None, t));
                t += ms;
                model.observe(snapshot(name, t));
            }
        }
        let mut inspect = snapshot("inspect1", 0);
        inspect.services = vec!["inspect".into()];
        inspect.nominal_ms = [("inspect".to_string(), 500)].into();
        model.observe(inspect);
        model
    }

    fn advised(advice: &Advice) -> &str {
        advice.resource.as_ref().map(|r| r.name()).unwrap_or("-")
    }

    #[test]
    fn the_resource_that_finishes_the_route_first_is_advised() {
        let model = cell();
        let ask = request("o-1", &[("pick_n_place", None), ("inspect", None)]);
        let (advice, intentions) = advise(&model, None, &staff(), &ask, 10_000, 5000);
        assert_eq!(advised(&advice), "fast", "{advice:?}");
        assert_eq!(advice.forecast_done, Some(10_000 + 200 + 500));
        assert_eq!(advice.route.len(), 2);
        assert_eq!(advice.route[1].resource.name(), "inspect1");
        assert!(
            advice.why.starts_with("resource/fast done at +0.7 s"),
            "{}",
            advice.why
        );
        assert_eq!(intentions.len(), 2);
        assert_eq!(intentions[1].expires, 10_700 + 5000);
    }

    #[test]
    fn orders_that_ask_together_are_spread_by_their_intentions() {
        let mut model = cell();
        let mut chosen = Vec::new();
        for n in 0..5 {
            let ask = request(&format!("o-{n}"), &[("pick_n_place", None)]);
            let (advice, intentions) = advise(&model, None, &staff(), &ask, 10_000, 5000);
            chosen.push(advised(&advice).to_string());
            model.intend(&ask.order, intentions, 10_000);
        }
        // Each advice is the next one's intention: fast would end them at +200,
        // +400, +600, +800 (slow: +800, a tie that goes to the lower name); the fifth
        // ends sooner on slow (+800) than on fast (+1000).
        assert_eq!(
            chosen,
            ["fast", "fast", "fast", "fast", "slow"],
            "{chosen:?}"
        );
    }

    #[test]
    fn a_changeover_is_avoided_when_it_costs_more_than_it_saves() {
        let mut model = CellModel::default();
        // Two equal robots; a change of program costs 1 s on each. `a` last ran
        // program x, `b` program y.
        for (name, last) in [("a", "x"), ("b", "y")] {
            let mut t = 0;
            for (n, program) in [last, "z", last].iter().enumerate() {
                model.observe(running(
                    snapshot(name, t),
                    &format!("c{n}"),
                    Some(program),
                    t,
                ));
                t += 300 + if n > 0 { 1000 } else { 0 };
                model.observe(snapshot(name, t));
            }
        }
        let ask = request("o-1", &[("pick_n_place", Some("y"))]);
        let (advice, _) = advise(&model, None, &staff(), &ask, 10_000, 5000);
        assert_eq!(advised(&advice), "b", "{advice:?}");
        assert!(!advice.route[0].changeover);
        let ask = request("o-2", &[("pick_n_place", Some("x"))]);
        let (advice, _) = advise(&model, None, &staff(), &ask, 10_000, 5000);
        assert_eq!(advised(&advice), "a", "{advice:?}");
    }

    #[test]
    fn a_rush_order_is_not_held_up_by_ordinary_work() {
        let mut model = cell();
        let mut busy = running(snapshot("fast", 9_900), "c9", None, 9_900);
        busy.agenda = (0..5)
            .map(|n| booking(&format!("o-{n}"), 0, None))
            .collect();
        model.observe(busy);
        let ordinary = request("o-8", &[("pick_n_place", None)]);
        let (advice, _) = advise(&model, None, &staff(), &ordinary, 10_000, 5000);
        assert_eq!(advised(&advice), "slow", "behind five jobs, fast is later");
        let mut rush = request("o-9", &[("pick_n_place", None)]);
        rush.priority = 100;
        rush.due = Some(10_150);
        let (advice, _) = advise(&model, None, &staff(), &rush, 10_000, 5000);
        assert_eq!(advised(&advice), "fast", "{advice:?}");
        assert_eq!(advice.forecast_done, Some(10_300));
        assert_eq!(advice.late_by_ms, Some(150));
    }

    #[test]
    fn no_advice_without_a_resource_that_could_take_the_step() {
        let model = cell();
        let ask = request("o-1", &[("weld", None)]);
        let (advice, intentions) = advise(&model, None, &staff(), &ask, 0, 5000);
        assert_eq!(advice.resource, None);
        assert!(advice.why.contains("weld"), "{}", advice.why);
        assert!(intentions.is_empty());
        let mut ask = request("o-1", &[("pick_n_place", None)]);
        ask.avoid = vec![HolonId::resource("fast").unwrap()];
        let (advice, _) = advise(&model, None, &staff(), &ask, 0, 5000);
        assert_eq!(
            advised(&advice),
            "slow",
            "an avoided resource is never advised"
        );
    }

    /// conveyor1: a 4 m loop at 1 m/s, its load point at 0; `slow`'s port at 1 m,
    /// `fast`'s at 3 m, `inspect1`'s at 2 m.
    fn layout() -> CellLayout {
        let part = |holon: &str, text: &str| {
            schemas::layout::part_from_toml(holon, text).unwrap_or_else(|e| panic!("{e}"))
        };
        let station = |holon: &str, dock: &str| {
            part(
                holon,
                &format!(
                    "[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"{dock}\"\n"
                ),
            )
        };
        CellLayout::assemble([
            part(
                "conveyor1",
                "[[layout.locations]]\nname = \"load\"\nrole = \"entry_exit\"\ndock = \"conveyor1.load\"\n[layout.conveyor]\nlength_mm = 4000\nspeed_mm_s = 1000\npallets = 2\nstoppers = [{ name = \"load\", at_mm = 0 }, { name = \"s1\", at_mm = 1000 }, { name = \"s2\", at_mm = 2000 }, { name = \"s3\", at_mm = 3000 }]\n",
            ),
            station("slow", "conveyor1.s1"),
            station("inspect1", "conveyor1.s2"),
            station("fast", "conveyor1.s3"),
        ])
    }

    #[test]
    fn the_travel_to_each_station_counts_and_the_advice_names_the_move() {
        let model = cell();
        let layout = layout();
        assert!(layout.problems.is_empty(), "{:?}", layout.problems);
        let mut ask = request("o-1", &[("pick_n_place", None), ("inspect", None)]);
        ask.at = Some(schemas::layout::LocationId::new("conveyor1", "load").unwrap());
        let (advice, _) = advise(&model, Some(&layout), &staff(), &ask, 10_000, 5000);
        // fast works in 200 ms but is 3 s away; slow in 800 ms, 1 s away.
        assert_eq!(advised(&advice), "slow", "{advice:?}");
        let first = &advice.route[0];
        assert_eq!(first.to.as_ref().map(|l| l.as_str()), Some("slow.port"));
        assert!(first.travel_ms >= 1000, "{first:?}");
        assert_eq!(first.start, 10_000 + first.travel_ms);
        // Then on to inspect1, 1 m further on.
        let second = &advice.route[1];
        assert_eq!(
            second.to.as_ref().map(|l| l.as_str()),
            Some("inspect1.port")
        );
        assert!(second.travel_ms >= 1000, "{second:?}");
        assert_eq!(second.start, first.end + second.travel_ms);
        assert!(advice.why.contains("travel"), "{}", advice.why);
        // Without the part's place, as before: the fastest worker.
        ask.at = None;
        let (advice, _) = advise(&model, Some(&layout), &staff(), &ask, 10_000, 5000);
        assert_eq!(advised(&advice), "fast");
        assert_eq!(advice.route[0].travel_ms, 0);
    }

    #[test]
    fn a_station_the_part_cannot_get_to_is_not_advised() {
        let model = cell();
        let layout = layout();
        let mut ask = request("o-1", &[("pick_n_place", None)]);
        // A place no transporter serves: neither station can be reached.
        ask.at = Some(schemas::layout::LocationId::new("nowhere", "shelf").unwrap());
        let (advice, _) = advise(&model, Some(&layout), &staff(), &ask, 10_000, 5000);
        // Unknown to the layout: the staff cannot tell, and counts no travel.
        assert_eq!(advised(&advice), "fast");
        // At a station's port with no route onward (an exit-only place): unreachable.
        let mut cut = layout.clone();
        cut.parts.remove("conveyor1");
        ask.at = Some(schemas::layout::LocationId::new("inspect1", "port").unwrap());
        let (advice, _) = advise(&model, Some(&cut), &staff(), &ask, 10_000, 5000);
        assert_eq!(advice.resource, None, "{advice:?}");
        assert!(
            advice
                .why
                .contains("where the part can get from inspect1.port"),
            "{}",
            advice.why
        );
    }
}

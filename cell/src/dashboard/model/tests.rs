//! The dashboard model's tests: each input and what it changes.

use super::*;
use schemas::{BookingView, CurrentJobView};

fn robot() -> HolonId {
    HolonId::resource("robot1").unwrap()
}

fn snapshot(
    state: ResourceState,
    controller: ControllerStatus,
    agenda: &[&str],
) -> ResourceSnapshot {
    ResourceSnapshot {
        state,
        controller,
        agenda: agenda
            .iter()
            .map(|c| BookingView::waiting(HolonId::order("o-1").unwrap(), c, "pick_n_place"))
            .collect(),
        current: (state == ResourceState::Busy).then(|| CurrentJobView {
            requester: HolonId::order("o-1").unwrap(),
            conversation_id: "o-1/1/1".into(),
            service_type: "pick_n_place".into(),
            step: Some("pick".into()),
            program: None,
            started_at: None,
        }),
        services: vec!["pick_n_place".into()],
        ..ResourceSnapshot::blank(robot())
    }
}

fn order(name: &str, status: OrderStatus, reason: Option<&str>) -> OrderSnapshot {
    serde_json::from_value(serde_json::json!({
        "holon": format!("order/{name}"), "product": "breaker", "status": status,
        "reason": reason, "step": 1, "steps": 3, "service_type": "transport",
        "resource": null, "attempt": 1, "completed": [], "reworks": 0, "rebooks": 0,
        "failed_attempts": 0, "attempts": [], "at": 0
    }))
    .unwrap()
}

fn active(model: &Model) -> Vec<AlarmKind> {
    model
        .alarms()
        .iter()
        .filter(|a| a.active())
        .map(|a| a.kind)
        .collect()
}

#[test]
fn a_vanished_resource_raises_an_alarm_that_its_return_clears() {
    let mut m = Model::default();
    assert!(m.apply(Input::Appeared {
        holon: robot(),
        at: 1
    }));
    assert!(
        !m.apply(Input::Appeared {
            holon: robot(),
            at: 2
        }),
        "a repeat is no news"
    );
    assert!(m.apply(Input::Vanished {
        holon: robot(),
        at: 3
    }));
    assert_eq!(active(&m), vec![AlarmKind::Vanished]);
    assert!(!m.holons().next().unwrap().live);
    m.apply(Input::Appeared {
        holon: robot(),
        at: 4,
    });
    assert_eq!(active(&m), vec![]);
    // Cleared but not acknowledged: it stays listed until an operator acknowledges.
    let id = m.alarms()[0].id;
    assert_eq!(m.alarms().len(), 1);
    assert!(m.apply(Input::Acknowledge {
        id,
        by: "anna".into(),
        at: 5
    }));
    assert!(m.alarms().is_empty());
}

#[test]
fn an_acknowledged_alarm_stays_while_its_condition_lasts() {
    let mut m = Model::default();
    let fault = snapshot(ResourceState::Init, ControllerStatus::Fault, &[]);
    m.apply(Input::Resource {
        snapshot: Box::new(fault),
        at: 1,
    });
    let id = m.alarms()[0].id;
    m.apply(Input::Acknowledge {
        id,
        by: "anna".into(),
        at: 2,
    });
    assert_eq!(active(&m), vec![AlarmKind::Controller]);
    assert!(m.alarms()[0].acknowledged.is_some());
    let ready = snapshot(ResourceState::Free, ControllerStatus::Ready, &[]);
    m.apply(Input::Resource {
        snapshot: Box::new(ready),
        at: 3,
    });
    assert!(m.alarms().is_empty(), "cleared and acknowledged: gone");
    assert_eq!(m.counters().controller_faults["robot1"], 1);
}

#[test]
fn repeated_snapshots_change_nothing_and_busy_time_accrues() {
    let mut m = Model::default();
    let busy = snapshot(ResourceState::Busy, ControllerStatus::Ready, &["o-2/1/1"]);
    assert!(m.apply(Input::Resource {
        snapshot: Box::new(busy.clone()),
        at: 1_000
    }));
    let mut again = busy.clone();
    again.at = 99;
    assert!(!m.apply(Input::Resource {
        snapshot: Box::new(again),
        at: 1_500
    }));
    let free = ResourceSnapshot {
        at: 100,
        ..snapshot(ResourceState::Free, ControllerStatus::Ready, &[])
    };
    m.apply(Input::Resource {
        snapshot: Box::new(free),
        at: 3_000,
    });
    assert_eq!(m.busy_ms(10_000)[&robot()], 2_000);
    assert_eq!(m.counters().bookings["robot1"], 1);
}

#[test]
fn a_job_seen_from_its_start_to_its_end_is_timed() {
    let mut m = Model::default();
    let free = snapshot(ResourceState::Free, ControllerStatus::Ready, &[]);
    let busy = snapshot(ResourceState::Busy, ControllerStatus::Ready, &[]);
    m.apply(Input::Resource {
        snapshot: Box::new(free.clone()),
        at: 1_000,
    });
    m.apply(Input::Resource {
        snapshot: Box::new(busy),
        at: 2_000,
    });
    m.apply(Input::Resource {
        snapshot: Box::new(free),
        at: 2_700,
    });
    let histogram = &m.counters().steps[&("pick_n_place".to_string(), "robot1".to_string())];
    assert_eq!(histogram.count, 1);
    assert_eq!(
        histogram.buckets[3], 1,
        "0.7 s falls in the (0.5, 1] bucket"
    );
    assert!((histogram.sum_seconds - 0.7).abs() < 1e-9);
}

#[test]
fn a_job_running_when_first_seen_is_not_timed() {
    let mut m = Model::default();
    let busy = snapshot(ResourceState::Busy, ControllerStatus::Ready, &[]);
    let free = snapshot(ResourceState::Free, ControllerStatus::Ready, &[]);
    m.apply(Input::Resource {
        snapshot: Box::new(busy),
        at: 1_000,
    });
    m.apply(Input::Resource {
        snapshot: Box::new(free),
        at: 2_000,
    });
    assert!(m.counters().steps.is_empty());
}

#[test]
fn a_snapshot_older_than_the_one_held_changes_nothing() {
    let mut m = Model::default();
    let free = ResourceSnapshot {
        at: 20,
        ..snapshot(ResourceState::Free, ControllerStatus::Ready, &[])
    };
    let init = ResourceSnapshot {
        at: 10,
        ..snapshot(ResourceState::Init, ControllerStatus::Disconnected, &[])
    };
    assert!(m.apply(Input::Resource {
        snapshot: Box::new(free),
        at: 21
    }));
    assert!(!m.apply(Input::Resource {
        snapshot: Box::new(init),
        at: 22
    }));
    let shown = m.holons().next().unwrap().resource.as_ref().unwrap();
    assert_eq!(shown.state, ResourceState::Free);
    let done = OrderSnapshot {
        at: 20,
        ..order("o-1", OrderStatus::Done, None)
    };
    let running = OrderSnapshot {
        at: 10,
        ..order("o-1", OrderStatus::Running, None)
    };
    assert!(m.apply(Input::Order {
        snapshot: Box::new(done),
        at: 21
    }));
    assert!(!m.apply(Input::Order {
        snapshot: Box::new(running),
        at: 22
    }));
    assert_eq!(m.orders().next().unwrap().status, OrderStatus::Done);
}

#[test]
fn a_router_or_order_node_shows_live_or_gone_and_raises_vanished() {
    let mut m = Model::default();
    let node = ProcessId {
        program: "order-node".into(),
        name: "orders1".into(),
    };
    let appeared = || Input::ProcessAppeared {
        process: node.clone(),
        at: 1,
    };
    assert!(m.apply(appeared()));
    assert!(!m.apply(appeared()), "a repeat is no news");
    assert!(m.processes().next().unwrap().live);
    assert!(m.apply(Input::ProcessVanished {
        process: node.clone(),
        at: 2
    }));
    assert!(!m.processes().next().unwrap().live);
    assert_eq!(active(&m), vec![AlarmKind::Vanished]);
    let alarm = serde_json::to_value(&m.alarms()[0]).unwrap();
    assert_eq!(alarm["source"], "order-node/orders1");
    assert!(m.apply(Input::ProcessAppeared {
        process: node,
        at: 3
    }));
    assert_eq!(active(&m), vec![]);
}

#[test]
fn undelivered_results_piling_up_raise_an_alarm_until_they_drain() {
    let mut m = Model::default();
    let mut piling = snapshot(ResourceState::Free, ControllerStatus::Ready, &[]);
    piling.undelivered = UNDELIVERED_ALARM;
    m.apply(Input::Resource {
        snapshot: Box::new(piling),
        at: 1,
    });
    assert_eq!(active(&m), vec![AlarmKind::Undelivered]);
    let drained = snapshot(ResourceState::Free, ControllerStatus::Ready, &[]);
    m.apply(Input::Resource {
        snapshot: Box::new(drained),
        at: 2,
    });
    assert_eq!(active(&m), vec![]);
}

#[test]
fn the_model_keeps_the_running_orders_and_only_the_newest_finished_ones() {
    let mut m = Model::default();
    m.apply(Input::Order {
        snapshot: Box::new(order("o-0", OrderStatus::Running, None)),
        at: 1,
    });
    for n in 1..=FINISHED_KEPT + 10 {
        m.apply(Input::Order {
            snapshot: Box::new(order(&format!("o-{n}"), OrderStatus::Done, None)),
            at: 2,
        });
    }
    assert_eq!(m.orders().count(), FINISHED_KEPT + 1);
    assert!(
        m.orders().any(|o| o.holon.name() == "o-0"),
        "the running one stays"
    );
    assert!(
        !m.orders().any(|o| o.holon.name() == "o-1"),
        "the oldest finished left"
    );
    assert_eq!(m.counters().orders_done, (FINISHED_KEPT + 10) as u64);
}

#[test]
fn a_part_that_stays_where_it_is_beyond_the_bound_raises_part_waits_until_it_moves() {
    let mut m = Model::with_part_wait_bound(60_000);
    let at = |location: &str, t: u64| {
        let mut o = order("o-1", OrderStatus::Running, None);
        o.part = Some(schemas::PartPlace::At {
            location: location.to_string().try_into().unwrap(),
        });
        o.at = t;
        Input::Order {
            snapshot: Box::new(o),
            at: t,
        }
    };
    m.apply(at("conveyor1.buffer", 1_000));
    // Another snapshot with the part where it was does not restart its wait.
    m.apply(at("conveyor1.buffer", 30_000));
    assert!(!m.apply(Input::Tick { at: 61_000 }), "within the bound");
    assert!(active(&m).is_empty());
    assert!(m.apply(Input::Tick { at: 61_001 }));
    assert_eq!(active(&m), [AlarmKind::PartWaits]);
    assert!(
        m.alarms()[0]
            .message
            .contains("at conveyor1.buffer for 60 s"),
        "{}",
        m.alarms()[0].message
    );
    // Raised once, however long it waits.
    assert!(!m.apply(Input::Tick { at: 90_000 }));
    // It moves: cleared, and its new wait starts then.
    m.apply(at("robot1.port", 100_000));
    assert!(active(&m).is_empty());
    assert!(!m.apply(Input::Tick { at: 150_000 }));
    // An order that ends (its part shipped) waits no more.
    let mut shipped = order("o-1", OrderStatus::Done, None);
    shipped.part = Some(schemas::PartPlace::Shipped {
        exit: "conveyor1.load".to_string().try_into().unwrap(),
    });
    shipped.at = 151_000;
    m.apply(Input::Order {
        snapshot: Box::new(shipped),
        at: 151_000,
    });
    assert!(!m.apply(Input::Tick { at: 1_000_000 }));
    assert!(active(&m).is_empty());
}

#[test]
fn a_lost_part_raises_an_alarm_until_it_is_found() {
    let mut m = Model::default();
    let mut lost = order("o-1", OrderStatus::Running, None);
    lost.part = Some(schemas::PartPlace::Lost {
        transporter: HolonId::resource("conveyor1").unwrap(),
        from: "robot1.port".to_string().try_into().unwrap(),
        to: "conveyor1.buffer".to_string().try_into().unwrap(),
        why: "the resource vanished".into(),
    });
    lost.at = 1;
    m.apply(Input::Order {
        snapshot: Box::new(lost),
        at: 1,
    });
    assert_eq!(m.alarms().len(), 1);
    assert_eq!(m.alarms()[0].kind, AlarmKind::PartLost);
    assert!(m.alarms()[0].active());
    assert!(
        m.alarms()[0]
            .message
            .contains("last seen at robot1.port (the resource vanished)"),
        "{}",
        m.alarms()[0].message
    );
    let mut found = order("o-1", OrderStatus::Running, None);
    found.part = Some(schemas::PartPlace::At {
        location: "conveyor1.buffer".to_string().try_into().unwrap(),
    });
    found.at = 2;
    m.apply(Input::Order {
        snapshot: Box::new(found),
        at: 2,
    });
    assert!(!m.alarms()[0].active(), "cleared once the part is found");
}

#[test]
fn a_failed_order_leaves_an_alarm_to_acknowledge_and_done_ones_count() {
    let mut m = Model::default();
    m.apply(Input::Order {
        snapshot: Box::new(order("o-1", OrderStatus::Running, None)),
        at: 1,
    });
    m.apply(Input::Order {
        snapshot: Box::new(order("o-1", OrderStatus::Failed, Some("no resource"))),
        at: 2,
    });
    assert_eq!(m.alarms().len(), 1);
    assert_eq!(m.alarms()[0].kind, AlarmKind::OrderFailed);
    assert!(
        !m.alarms()[0].active(),
        "an event: cleared at once, kept until acknowledged"
    );
    m.apply(Input::Order {
        snapshot: Box::new(order("o-2", OrderStatus::Done, None)),
        at: 3,
    });
    assert_eq!(m.done_last_hour(4), 1);
    assert_eq!(m.done_last_hour(3 + 3_600_001), 0);
    assert_eq!(m.counters().orders_failed, 1);
    assert!(m.events().any(|e| e.text == "failed: no resource"));
}

#[test]
fn a_holon_that_keeps_reappearing_is_restarting() {
    let mut m = Model::default();
    for (i, at) in [0u64, 10_000, 20_000].iter().enumerate() {
        m.apply(Input::Appeared {
            holon: robot(),
            at: *at,
        });
        if i < 2 {
            m.apply(Input::Vanished {
                holon: robot(),
                at: at + 1,
            });
        }
    }
    assert!(active(&m).contains(&AlarmKind::Restarting));
}

#[test]
fn the_event_log_keeps_the_last_entries() {
    let mut m = Model::default();
    for at in 0..(EVENTS_KEPT as u64 + 10) {
        m.apply(Input::Appeared {
            holon: robot(),
            at: at * 2,
        });
        m.apply(Input::Vanished {
            holon: robot(),
            at: at * 2 + 1,
        });
    }
    assert_eq!(m.events().count(), EVENTS_KEPT);
}

#[test]
fn an_order_node_report_is_news_when_its_lag_changes_not_its_time() {
    let mut m = Model::default();
    let report = |lag, at| schemas::fence::NodeFenceReport {
        node: "orders".into(),
        role: schemas::FenceRole::Standby,
        epoch: None,
        holder_epoch: Some(3),
        lag: Some(lag),
        store_lost: false,
        host: "b".into(),
        zid: "z".into(),
        at,
    };
    assert!(m.apply(Input::NodeFences {
        reports: vec![report(0, 1)]
    }));
    assert!(!m.apply(Input::NodeFences {
        reports: vec![report(0, 2)]
    }));
    assert!(m.apply(Input::NodeFences {
        reports: vec![report(4, 3)]
    }));
    assert_eq!(m.node_fence_reports()[0].lag, Some(4));
}

#[test]
fn a_new_holder_of_a_fenced_resource_is_news_and_the_same_list_is_not() {
    let report = |role, epoch, zid: &str| schemas::FenceReport {
        holon: HolonId::resource("robot1").unwrap(),
        role,
        epoch,
        holder_epoch: None,
        host: "host-a".into(),
        zid: zid.into(),
        at: 1,
    };
    let mut m = Model::default();
    let first = vec![
        report(schemas::FenceRole::Standby, None, "b"),
        report(schemas::FenceRole::Holder, Some(1), "a"),
    ];
    assert!(m.apply(Input::Fences {
        reports: first.clone(),
        at: 5
    }));
    assert_eq!(m.fence_reports()[0].role, schemas::FenceRole::Holder);
    assert!(
        !m.apply(Input::Fences {
            reports: first,
            at: 6
        }),
        "no news"
    );
    // The standby took over at epoch 2.
    let taken = vec![report(schemas::FenceRole::Holder, Some(2), "b")];
    assert!(m.apply(Input::Fences {
        reports: taken,
        at: 7
    }));
    let said: Vec<&str> = m.events().map(|e| e.text.as_str()).collect();
    assert!(
        said.contains(&"holds its controller at epoch 1 (on host-a)"),
        "{said:?}"
    );
    assert!(
        said.contains(&"holds its controller at epoch 2 (on host-a)"),
        "{said:?}"
    );
}

use super::*;

#[test]
fn orders_sort_by_number_within_their_node() {
    let mut names = vec!["orders1-10", "orders2-1", "orders1-2", "orders1-1"];
    names.sort_by_key(|n| crate::client::listing::order_sort_key(n));
    assert_eq!(names, ["orders1-1", "orders1-2", "orders1-10", "orders2-1"]);
}

#[test]
fn bookings_of_absent_requesters_are_counted() {
    let row = HolonStatus {
        holon: HolonId::resource("robot1").unwrap(),
        snapshot: Some(serde_json::json!({
            "state": "free", "controller": "ready", "undelivered": 0,
            "agenda": [
                {"requester": "order/o-1", "conversation_id": "o-1/1/1", "service_type": "pick_n_place"},
                {"requester": "order/o-2", "conversation_id": "o-2/1/1", "service_type": "pick_n_place",
                 "requester_absent_since": 1},
            ],
        })),
    };
    let table = render("demo", std::slice::from_ref(&row));
    let fenced = |role, epoch, holder_epoch, host: &str| schemas::FenceReport {
        holon: "resource/robot1".parse().unwrap(),
        role,
        epoch,
        holder_epoch,
        host: host.into(),
        zid: "z".into(),
        at: 0,
    };
    let fences = render_fences(&[
        fenced(schemas::FenceRole::Holder, Some(2), None, "host-a"),
        fenced(schemas::FenceRole::Standby, None, Some(2), "host-b"),
    ]);
    assert!(fences.contains("holder        2  host-a"), "{fences}");
    assert!(fences.contains("standby       2  host-b"), "{fences}");
    assert!(!fences.contains('!'), "{fences}");
    let unheld = render_fences(&[fenced(schemas::FenceRole::Standby, None, None, "host-b")]);
    assert!(unheld.contains("! resource/robot1: no process"), "{unheld}");
    assert_eq!(render_fences(&[]), "");
    assert!(table.contains("2 (1 absent)"), "{table}");
    let mut faulty = row;
    faulty.snapshot.as_mut().unwrap()["journal_fault"] = "No space left on device".into();
    let table = render("demo", &[faulty]);
    assert!(table.contains("free!"), "{table}");
    assert!(
        table.contains("resource/robot1: the journal cannot be written (No space left on device)"),
        "{table}"
    );
}

#[test]
fn the_order_node_fence_table_shows_holder_standby_lag_and_flags() {
    let report =
        |role, epoch, holder_epoch, lag, store_lost, host: &str| schemas::fence::NodeFenceReport {
            node: "orders".into(),
            role,
            epoch,
            holder_epoch,
            lag,
            store_lost,
            host: host.into(),
            zid: format!("z-{host}"),
            at: 0,
        };
    use schemas::FenceRole::{Holder, Standby};
    let table = render_node_fences(&[
        report(Holder, Some(9), None, None, false, "host-a"),
        report(Standby, None, Some(9), Some(0), false, "host-b"),
    ]);
    assert!(table.starts_with("FENCED ORDER-NODE"), "{table}");
    assert!(
        table.contains("orders                       holder        9      -  host-a"),
        "{table}"
    );
    assert!(
        table.contains("orders                       standby       9      0  host-b"),
        "{table}"
    );
    assert!(!table.contains('!'), "{table}");
    let lost = render_node_fences(&[report(Standby, None, Some(9), Some(4), true, "host-b")]);
    assert!(lost.contains("standby       9   lost"), "{lost}");
    assert!(lost.contains("! order-node orders: no process"), "{lost}");
    assert!(lost.contains("cannot reach etcd (store lost"), "{lost}");
    assert_eq!(render_node_fences(&[]), "");
}

/// An order snapshot with everything at its start values.
fn order(name: &str, status: schemas::OrderStatus) -> schemas::OrderSnapshot {
    schemas::OrderSnapshot {
        holon: HolonId::order(name).unwrap(),
        product: "breaker".into(),
        status,
        reason: None,
        step: 1,
        steps: 3,
        service_type: None,
        resource: None,
        attempt: 1,
        completed: vec![],
        reworks: 0,
        rebooks: 0,
        failed_attempts: 0,
        attempts: vec![],
        priority: 0,
        due: None,
        advised: 0,
        version: None,
        part: None,
        part_found: vec![],
        at: 0,
    }
}

#[test]
fn the_orders_table_says_where_each_part_in_the_cell_is() {
    let mut moving = order("o-1", schemas::OrderStatus::Running);
    moving.part = Some(schemas::PartPlace::InTransit {
        transporter: HolonId::resource("conveyor1").unwrap(),
        from: "conveyor1.load".to_string().try_into().unwrap(),
        to: "robot1.port".to_string().try_into().unwrap(),
    });
    let mut shipped = order("o-2", schemas::OrderStatus::Done);
    shipped.part = Some(schemas::PartPlace::Shipped {
        exit: "conveyor1.load".to_string().try_into().unwrap(),
    });
    shipped.part_found = vec![schemas::PartFound {
        conversation_id: "o-2/m2/1".into(),
        transporter: HolonId::resource("conveyor1").unwrap(),
        location: "robot1.port".to_string().try_into().unwrap(),
        by: "cell operator.default on host1 (user kim)".into(),
        at: 0,
    }];
    let table = render_orders_at("demo", &[moving.clone(), shipped.clone()], false, 0);
    assert!(
        table.contains(
            "    part in transit on resource/conveyor1 from conveyor1.load to robot1.port\n"
        ),
        "{table}"
    );
    assert!(
        !table.contains("shipped"),
        "only parts in the cell: {table}"
    );
    let detailed = render_orders_at("demo", &[moving, shipped], true, 0);
    assert!(
        detailed.contains("    part shipped at conveyor1.load\n"),
        "{detailed}"
    );
    assert!(
        detailed.contains("    part found at robot1.port by cell operator.default on host1 (user kim) (lost on resource/conveyor1, move o-2/m2/1)\n"),
        "the operator's word, in the order's audit trail: {detailed}"
    );
}

#[test]
fn the_orders_table_shows_failures_and_with_detail_every_attempt() {
    let robot = HolonId::resource("robot1").unwrap();
    let order = schemas::OrderSnapshot {
        step: 3,
        rebooks: 1,
        failed_attempts: 1,
        attempts: vec![schemas::AttemptRecord {
            conversation_id: "orders1-2/2/1".into(),
            step: 2,
            service_type: "pick_n_place".into(),
            resource: Some(robot),
            end: schemas::AttemptEnd::Failed,
            detail: "failed on resource/robot1: interrupted".into(),
            at: 0,
        }],
        ..order("orders1-2", schemas::OrderStatus::Done)
    };
    let table = render_orders("demo", std::slice::from_ref(&order), false);
    let row: Vec<&str> = table.lines().nth(2).unwrap().split_whitespace().collect();
    assert_eq!(
        row,
        [
            "orders1-2",
            "breaker",
            "done",
            "0",
            "-",
            "3/3",
            "-",
            "1",
            "1",
            "0"
        ]
    );
    assert_eq!(table.lines().count(), 3, "{table}");
    let detailed = render_orders("demo", &[order], true);
    let trail = detailed.lines().nth(3).unwrap();
    assert_eq!(
        trail.split_whitespace().collect::<Vec<_>>().join(" "),
        "orders1-2/2/1 pick_n_place failed failed on resource/robot1: interrupted"
    );
}

#[test]
fn order_nodes_show_their_counts_or_why_not() {
    let nodes = [
        OrderNodeStatus {
            name: "orders1".into(),
            counts: Ok(schemas::OrderCounts {
                running: 1,
                done: 7,
                failed: 2,
                ..Default::default()
            }),
        },
        OrderNodeStatus {
            name: "orders2".into(),
            counts: Err("no answer within 5s".into()),
        },
    ];
    let table = render_order_nodes(&nodes);
    let row =
        |n: usize| -> Vec<&str> { table.lines().nth(n).unwrap().split_whitespace().collect() };
    assert_eq!(row(1), ["orders1", "1", "7", "2"], "{table}");
    assert!(
        table
            .lines()
            .nth(2)
            .unwrap()
            .contains("no answer within 5s"),
        "{table}"
    );
    assert_eq!(render_order_nodes(&[]), "no order-node alive\n");
}

#[test]
fn the_orders_table_shows_priority_and_time_to_due() {
    let now = 1_000_000_000;
    let rush = schemas::OrderSnapshot {
        priority: 100,
        due: Some(now + 250_000),
        ..order("orders1-1", schemas::OrderStatus::Running)
    };
    let late = schemas::OrderSnapshot {
        priority: -5,
        due: Some(now - 30_000),
        ..order("orders1-2", schemas::OrderStatus::Running)
    };
    let table = render_orders_at("demo", &[rush, late], false, now);
    let cells = |n: usize| -> Vec<String> {
        let row: Vec<&str> = table.lines().nth(n).unwrap().split_whitespace().collect();
        vec![row[3].to_string(), row[4].to_string()]
    };
    assert_eq!(cells(2), ["100", "4m10s"], "{table}");
    assert_eq!(cells(3), ["-5", "-30s"], "{table}");
    assert_eq!(
        due_text(Some(now + 7_200_000), schemas::OrderStatus::Running, now),
        "2h00m"
    );
    assert_eq!(
        due_text(Some(now), schemas::OrderStatus::Done, now),
        "(ended)"
    );
}

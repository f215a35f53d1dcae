use super::*;
use serde_json::json;

fn order() -> OrderProgress {
    let mut o = OrderProgress::new(HolonId::order("n1-1").unwrap(), "breaker", 2);
    o.plan = Some(
        serde_json::from_value(json!({"product": "breaker", "steps": [
            {"service_type": "transport"},
            {"service_type": "pick_n_place"},
            {"service_type": "inspect", "reject_results": ["inspect_fail"],
             "on_reject": {"rework": {"from_step": 2, "max_reworks": 1}}}
        ]}))
        .unwrap(),
    );
    o
}

fn robot(n: &str) -> HolonId {
    HolonId::resource(n).unwrap()
}

fn done(provider: &str, result: &str) -> StepOutcome {
    StepOutcome::Done {
        provider: robot(provider),
        results: json!({ "x": result }).as_object().unwrap().clone(),
    }
}

#[test]
fn walks_the_plan_to_done() {
    let mut o = order();
    assert_eq!(o.conversation_id(), "n1-1/1/1");
    o.record(done("conveyor1", "arrived"));
    assert_eq!(o.step, 1);
    assert_eq!(o.conversation_id(), "n1-1/2/1");
    o.record(done("robot1", "placing_done"));
    o.record(done("inspect1", "inspect_pass"));
    assert_eq!(o.status, OrderStatus::Done);
    assert_eq!(o.current_step(), None);
    assert_eq!(o.completed.len(), 3);
    assert_eq!(o.snapshot().status, OrderStatus::Done);
}

#[test]
fn every_ended_attempt_is_in_the_history() {
    let mut o = order();
    o.record(StepOutcome::Lost {
        provider: robot("conveyor1"),
        why: "withdrawn".into(),
    });
    o.record(done("conveyor1", "arrived"));
    o.record(StepOutcome::Failed {
        provider: robot("robot1"),
        reason: "interrupted".into(),
        detail: None,
    });
    o.record(done("robot2", "placing_done"));
    o.record(done("inspect1", "inspect_fail"));
    let history: Vec<(String, AttemptEnd)> = o
        .snapshot()
        .attempts
        .iter()
        .map(|a| (a.conversation_id.clone(), a.end))
        .collect();
    assert_eq!(
        history,
        [
            ("n1-1/1/1".to_string(), AttemptEnd::Lost),
            ("n1-1/1/2".to_string(), AttemptEnd::Done),
            ("n1-1/2/1".to_string(), AttemptEnd::Failed),
            ("n1-1/2/2".to_string(), AttemptEnd::Done),
            ("n1-1/3/1".to_string(), AttemptEnd::Rejected),
        ]
    );
    let failed = &o.history[2];
    assert_eq!(failed.resource, Some(robot("robot1")));
    assert_eq!(failed.detail, "failed on resource/robot1: interrupted");
    let snapshot = o.snapshot();
    assert_eq!(
        (snapshot.rebooks, snapshot.failed_attempts, snapshot.reworks),
        (1, 1, 1)
    );
}

#[test]
fn the_history_keeps_the_latest_attempts() {
    let mut o = order();
    o.max_attempts = u32::MAX;
    for _ in 0..MAX_ATTEMPT_HISTORY + 5 {
        o.record(StepOutcome::Lost {
            provider: robot("conveyor1"),
            why: "withdrawn".into(),
        });
    }
    assert_eq!(o.history.len(), MAX_ATTEMPT_HISTORY);
    assert_eq!(
        o.history.last().unwrap().conversation_id,
        format!("n1-1/1/{}", MAX_ATTEMPT_HISTORY + 5)
    );
}

#[test]
fn a_rejected_part_is_reworked_then_scrapped() {
    let mut o = order();
    o.record(done("conveyor1", "arrived"));
    o.record(done("robot1", "placing_done"));
    o.record(done("inspect1", "inspect_fail"));
    assert_eq!(o.status, OrderStatus::Running);
    assert_eq!(o.step, 1, "back to step 2");
    assert_eq!(o.reworks, 1);
    assert_eq!(
        o.conversation_id(),
        "n1-1/2/2",
        "the reworked step is a new conversation"
    );
    o.record(done("robot1", "placing_done"));
    assert_eq!(o.conversation_id(), "n1-1/3/2");
    o.record(done("inspect1", "inspect_fail"));
    assert_eq!(o.status, OrderStatus::Scrapped);
    assert!(o.reason.as_deref().unwrap().contains("after 1 reworks"));
}

#[test]
fn a_rejected_part_is_recovered_then_checked_again_then_scrapped() {
    let mut o = order();
    o.plan.as_mut().unwrap().steps[2].on_reject = Some(OnReject::Recover {
        service_type: "recovery".into(),
        then_step: 3,
        max_recoveries: 1,
    });
    o.plan.as_mut().unwrap().steps[2].info = json!({"program": "b"}).as_object().unwrap().clone();
    o.record(done("conveyor1", "arrived"));
    o.record(done("robot1", "placing_done"));
    assert_eq!(o.last_worked_for(), Some("pick_n_place"));
    o.record(done("inspect1", "inspect_fail"));
    assert_eq!(o.status, OrderStatus::Running);
    let recovery = o.current_step().unwrap().clone();
    assert_eq!(recovery.service_type, "recovery");
    assert_eq!(recovery.info["program"], "b", "the rejected step's info");
    assert_eq!(o.conversation_id(), "n1-1/3/2", "its own conversation");
    let ahead: Vec<String> = o
        .route_ahead()
        .into_iter()
        .map(|s| s.service_type)
        .collect();
    assert_eq!(ahead, ["recovery", "inspect"]);
    assert_eq!(o.snapshot().service_type.as_deref(), Some("recovery"));
    // A failed recovery is tried again, as any step.
    o.record(StepOutcome::Failed {
        provider: robot("m6"),
        reason: "interrupted".into(),
        detail: None,
    });
    assert_eq!(o.current_step().unwrap().service_type, "recovery");
    assert_eq!(o.conversation_id(), "n1-1/3/3");
    o.record(done("m6", "placing_done"));
    assert_eq!(o.last_worked_for(), Some("recovery"));
    assert_eq!(o.current_step().unwrap().service_type, "inspect");
    assert_eq!(o.conversation_id(), "n1-1/3/4", "checked again, a new one");
    o.record(done("inspect1", "inspect_fail"));
    assert_eq!(o.status, OrderStatus::Scrapped);
    assert!(o.reason.as_deref().unwrap().contains("after 1 recoveries"));
    assert!(o.recovering.is_none());
}

#[test]
fn a_recovered_part_goes_on_to_the_end() {
    let mut o = order();
    o.plan.as_mut().unwrap().steps[2].on_reject = Some(OnReject::Recover {
        service_type: "recovery".into(),
        then_step: 3,
        max_recoveries: 2,
    });
    o.step = 2;
    o.record(done("inspect1", "inspect_fail"));
    o.record(done("m6", "placing_done"));
    o.record(done("inspect1", "inspect_pass"));
    assert_eq!(o.status, OrderStatus::Done);
    assert_eq!(o.reworks, 1);
    // The journal's copy reads back the same, mid-recovery included.
    let mut mid = order();
    mid.plan = o.plan.clone();
    mid.step = 2;
    mid.record(done("inspect1", "inspect_fail"));
    let back: OrderProgress = serde_json::from_str(&serde_json::to_string(&mid).unwrap()).unwrap();
    assert_eq!(back, mid);
}

#[test]
fn scrap_on_reject_ends_the_order_with_the_plan_reason() {
    let mut o = order();
    o.plan.as_mut().unwrap().steps[2].on_reject = Some(OnReject::Scrap {
        reason: "cracked housing".into(),
    });
    o.step = 2;
    o.record(done("inspect1", "inspect_fail"));
    assert_eq!(o.status, OrderStatus::Scrapped);
    assert_eq!(o.reason.as_deref(), Some("cracked housing"));
}

#[test]
fn failures_retry_elsewhere_then_fail_the_order() {
    let mut o = order();
    o.record(StepOutcome::Failed {
        provider: robot("conveyor1"),
        reason: "controller_error".into(),
        detail: None,
    });
    assert_eq!(o.status, OrderStatus::Running);
    assert_eq!(o.conversation_id(), "n1-1/1/2");
    assert!(o.avoid.contains(&robot("conveyor1")));
    o.record(StepOutcome::Failed {
        provider: robot("conveyor2"),
        reason: "controller_timeout".into(),
        detail: None,
    });
    assert_eq!(o.status, OrderStatus::Failed);
    let reason = o.reason.clone().unwrap();
    assert!(
        reason.contains("step 1 (transport) failed 2 times"),
        "{reason}"
    );
    assert!(reason.contains("controller_timeout"), "{reason}");
}

#[test]
fn lost_bookings_rebook_without_counting_as_failures() {
    let mut o = order();
    for _ in 0..5 {
        o.record(StepOutcome::Lost {
            provider: robot("robot1"),
            why: "withdrawn".into(),
        });
    }
    assert_eq!(o.status, OrderStatus::Running);
    assert_eq!(o.rebooks, 5);
    assert_eq!(o.attempt, 6);
    assert_eq!(o.failures, 0);
    o.record(done("conveyor1", "arrived"));
    assert_eq!(o.attempt, 1, "a new step starts at attempt 1");
}

#[test]
fn failures_that_never_reached_the_controller_rebook_without_counting() {
    // max_attempts is 2 here: four of these would have failed the order twice over.
    let mut o = order();
    for reason in ["unavailable", "busy", "withdrawn", "not_begun"] {
        o.record(StepOutcome::Failed {
            provider: robot("robot1"),
            reason: reason.into(),
            detail: Some("the controller is not ready".into()),
        });
        assert_eq!(o.status, OrderStatus::Running, "{reason}");
    }
    assert_eq!((o.rebooks, o.failures, o.failed_attempts), (4, 0, 0));
    assert!(
        o.avoid.contains(&robot("robot1")),
        "others preferred while it recovers"
    );
    assert_eq!(o.conversation_id(), "n1-1/1/5");
    // Each is in the audit trail as the resource said it.
    assert_eq!(o.history[0].end, AttemptEnd::Lost);
    assert_eq!(
        o.history[0].detail,
        "failed on resource/robot1: unavailable (the controller is not ready)"
    );
}

#[test]
fn no_resource_fails_the_order() {
    let mut o = order();
    o.record(StepOutcome::NoResource);
    assert_eq!(o.status, OrderStatus::Failed);
    assert!(o.reason.unwrap().contains("no resource"));
}

#[test]
fn outcomes_read_as_an_operator_reads_them() {
    assert_eq!(
        done("inspect1", "inspect_fail").to_string(),
        "done by resource/inspect1 (x=inspect_fail)"
    );
    let failed = StepOutcome::Failed {
        provider: robot("robot2"),
        reason: "controller_error".into(),
        detail: None,
    };
    assert_eq!(
        failed.to_string(),
        "failed on resource/robot2: controller_error"
    );
}

#[test]
fn a_failure_in_the_controllers_words_reaches_the_attempt_and_the_order() {
    // What the operator reads (`cell orders --detail`): not the reason alone, but
    // what the controller said (issue 41: "every failure reason shown to the
    // operator in the controller's own words").
    let mut o = order();
    o.max_attempts = 1;
    o.record(done("conveyor1", "arrived"));
    o.record(StepOutcome::Failed {
        provider: robot("robot1"),
        reason: "controller_error".into(),
        detail: Some("pick failed: gripper open".into()),
    });
    assert_eq!(o.status, OrderStatus::Failed);
    let said = "failed on resource/robot1: controller_error (pick failed: gripper open)";
    assert_eq!(o.history.last().unwrap().detail, said);
    assert!(
        o.reason
            .as_ref()
            .unwrap()
            .ends_with("last on resource/robot1: controller_error (pick failed: gripper open)"),
        "{:?}",
        o.reason
    );
}

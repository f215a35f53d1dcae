//! The execution machine's transitions, one event at a time.

use super::*;
use crate::catalog::pick_n_place;
use schemas::{HolonId, Pose};
use serde_json::json;

pub(super) fn job(service_type: &str) -> Job {
    Job {
        requester: HolonId::order("o-1").unwrap(),
        conversation_id: "c1".into(),
        service_type: service_type.into(),
        reply_to: "holarchy/t/order/o-1/inbox".into(),
        info: json!({"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}})
            .as_object()
            .unwrap()
            .clone(),
        parameters: None,
        operator: None,
    }
}

fn ready() -> ExecutionEvent {
    ExecutionEvent::Controller(ControllerEvent::Status(ControllerStatus::Ready, None))
}

pub(super) fn status(s: ControllerStatus) -> ExecutionEvent {
    ExecutionEvent::Controller(ControllerEvent::Status(s, None))
}

pub(super) fn reply(id: u64, result: &str) -> ExecutionEvent {
    ExecutionEvent::Controller(ControllerEvent::Reply {
        id,
        result: result.into(),
        message: None,
    })
}

fn ready_execution() -> ExecutionMachine {
    let mut e = ExecutionMachine::new(Arc::new(pick_n_place()));
    assert_eq!(e.handle(ready()), vec![ExecutionAction::Ready]);
    e
}

fn command(actions: &[ExecutionAction]) -> RobotCommand {
    match actions.first() {
        Some(ExecutionAction::Command(c)) => c.clone(),
        other => panic!("expected a command, got {other:?}"),
    }
}

fn failed_with(actions: &[ExecutionAction], why: impl AsRef<str>) {
    let why = why.as_ref();
    match actions.first() {
        Some(ExecutionAction::Finished {
            outcome: Outcome::Failed { reason, .. },
            ..
        }) => assert_eq!(reason.as_str(), why),
        other => panic!("expected failed {why}, got {other:?}"),
    }
}

#[test]
fn init_to_ready_when_the_controller_is_ready() {
    let mut e = ExecutionMachine::new(Arc::new(pick_n_place()));
    assert_eq!(e.state(), &ExecutionState::Init);
    assert_eq!(
        e.handle(status(ControllerStatus::Disconnected)),
        vec![ExecutionAction::StateChanged]
    );
    // A fault before it was ever ready is news for the agenda (PackML aborts).
    assert_eq!(
        e.handle(status(ControllerStatus::Fault)),
        vec![ExecutionAction::Unavailable(ControllerStatus::Fault, None)]
    );
    assert_eq!(
        e.handle(status(ControllerStatus::Fault)),
        vec![ExecutionAction::StateChanged]
    );
    assert_eq!(e.handle(ready()), vec![ExecutionAction::Ready]);
    assert_eq!(e.state(), &ExecutionState::Ready);
}

#[test]
fn every_command_of_a_job_carries_its_program() {
    let mut e = ready_execution();
    let mut variant = job("pick_n_place");
    variant
        .info
        .insert(crate::catalog::PROGRAM_KEY.into(), json!("b2"));
    let pick = command(&e.handle(ExecutionEvent::Start(variant)));
    assert_eq!(pick.program.as_deref(), Some("b2"));
    let place = command(&e.handle(reply(pick.id, "picking_done")));
    assert_eq!(place.program.as_deref(), Some("b2"));
    assert_eq!(e.current_conversation(), Some("c1"));
    let mut plain = ready_execution();
    let pick = command(&plain.handle(ExecutionEvent::Start(job("pick_n_place"))));
    assert_eq!(pick.program, None);
}

#[test]
fn pick_n_place_runs_picking_then_placing_then_ready() {
    let mut e = ready_execution();
    let actions = e.handle(ExecutionEvent::Start(job("pick_n_place")));
    let pick = command(&actions);
    assert_eq!(pick.action, "pick");
    assert_eq!(
        pick.pos,
        Some(Pose {
            x: 1.0,
            y: 2.0,
            z: 3.0,
            ..Pose::default()
        })
    );
    assert_eq!(actions[1], ExecutionAction::StateChanged);
    assert_eq!(e.current_step().as_deref(), Some("pick"));
    let place = command(&e.handle(reply(pick.id, "picking_done")));
    assert_eq!(place.action, "place");
    assert_eq!(place.pos.unwrap().x, 4.0);
    assert_ne!(place.id, pick.id);
    assert_eq!(e.current_step().as_deref(), Some("place"));
    let actions = e.handle(reply(place.id, "placing_done"));
    assert_eq!(
        actions,
        vec![ExecutionAction::Finished {
            conversation_id: "c1".into(),
            outcome: Outcome::Done {
                results: json!({"pick": "picking_done", "place": "placing_done"})
                    .as_object()
                    .unwrap()
                    .clone()
            }
        }]
    );
    assert_eq!(e.state(), &ExecutionState::Ready);
}

#[test]
fn a_step_may_end_with_any_of_its_results() {
    let mut e = ready_execution();
    let inspect = command(&e.handle(ExecutionEvent::Start(job("inspect"))));
    assert_eq!(inspect.pos, None);
    let actions = e.handle(reply(inspect.id, "inspect_fail"));
    assert!(matches!(
        &actions[0],
        ExecutionAction::Finished { outcome: Outcome::Done { results }, .. } if results["inspect"] == "inspect_fail"
    ));
}

#[test]
fn an_error_result_fails_the_job() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    let actions = e.handle(ExecutionEvent::Controller(ControllerEvent::Reply {
        id: pick.id,
        result: "error".into(),
        message: Some("gripper empty".into()),
    }));
    failed_with(&actions, "controller_error");
    assert!(
        matches!(&actions[0], ExecutionAction::Finished { outcome: Outcome::Failed { detail, .. }, .. } if detail.contains("gripper empty"))
    );
    assert_eq!(e.state(), &ExecutionState::Ready);
}

#[test]
fn an_unexpected_result_fails_the_job() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    failed_with(
        &e.handle(reply(pick.id, "placing_done")),
        "unexpected_result",
    );
}

#[test]
fn command_failures_fail_the_job_with_their_reason() {
    let cases = [
        (
            CommandFailure::Timeout(std::time::Duration::from_secs(1)),
            "controller_timeout",
        ),
        (CommandFailure::Disconnected, "controller_disconnected"),
        (CommandFailure::NotConnected, "controller_disconnected"),
        (
            CommandFailure::Protocol("x".into()),
            "controller_protocol_error",
        ),
    ];
    for (failure, why) in cases {
        let mut e = ready_execution();
        let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
        let actions = e.handle(ExecutionEvent::Controller(ControllerEvent::CommandFailed {
            id: pick.id,
            failure,
        }));
        failed_with(&actions, why);
    }
}

#[test]
fn losing_the_controller_mid_step_fails_the_job_and_goes_to_init() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    let actions = e.handle(status(ControllerStatus::Disconnected));
    failed_with(&actions, "controller_disconnected");
    assert_eq!(
        actions[1],
        ExecutionAction::Unavailable(ControllerStatus::Disconnected, None)
    );
    assert_eq!(e.state(), &ExecutionState::Init);
    // The command's own failure, arriving after, changes nothing.
    assert_eq!(
        e.handle(ExecutionEvent::Controller(ControllerEvent::CommandFailed {
            id: pick.id,
            failure: CommandFailure::Disconnected
        })),
        vec![]
    );
    assert_eq!(e.handle(ready()), vec![ExecutionAction::Ready]);
}

#[test]
fn a_fault_or_estop_mid_step_fails_the_job() {
    for state in [ControllerStatus::Fault, ControllerStatus::Estop] {
        let mut e = ready_execution();
        e.handle(ExecutionEvent::Start(job("pick_n_place")));
        let actions = e.handle(status(state));
        failed_with(&actions, "controller_fault");
        assert_eq!(actions[1], ExecutionAction::Unavailable(state, None));
    }
}

#[test]
fn the_controllers_words_reach_the_failure_and_the_agenda() {
    let fault = |said: &str| {
        ExecutionEvent::Controller(ControllerEvent::Status(
            ControllerStatus::Fault,
            Some(said.to_string()),
        ))
    };
    let mut e = ready_execution();
    e.handle(ExecutionEvent::Start(job("pick_n_place")));
    let actions = e.handle(fault("overtravel axis 3"));
    match &actions[0] {
        ExecutionAction::Finished {
            outcome: Outcome::Failed { reason, detail },
            ..
        } => {
            assert_eq!(reason.as_str(), "controller_fault");
            assert_eq!(detail, "the controller reported fault: overtravel axis 3");
        }
        other => panic!("{other:?}"),
    }
    let said = |s: &str| Some(s.to_string());
    assert_eq!(
        actions[1],
        ExecutionAction::Unavailable(ControllerStatus::Fault, said("overtravel axis 3"))
    );
    // Other words, the same state: the agenda is told them; the same words again: not.
    assert_eq!(
        e.handle(fault("overtravel axis 4")),
        vec![ExecutionAction::Unavailable(
            ControllerStatus::Fault,
            said("overtravel axis 4")
        )]
    );
    assert_eq!(
        e.handle(fault("overtravel axis 4")),
        vec![ExecutionAction::StateChanged]
    );
}

#[test]
fn a_step_not_sent_to_a_stopped_controller_fails_as_a_fault() {
    let mut e = ready_execution();
    let actions = e.handle(ExecutionEvent::Start(job("pick_n_place")));
    let id = command(&actions).id;
    let actions = e.handle(ExecutionEvent::Controller(ControllerEvent::CommandFailed {
        id,
        failure: CommandFailure::Stopped(ControllerStatus::Estop),
    }));
    failed_with(&actions, "controller_fault");
}

#[test]
fn a_fault_while_ready_makes_it_unavailable() {
    let mut e = ready_execution();
    assert_eq!(
        e.handle(status(ControllerStatus::Estop)),
        vec![ExecutionAction::Unavailable(ControllerStatus::Estop, None)]
    );
    let actions = e.handle(ExecutionEvent::Start(job("pick_n_place")));
    failed_with(&actions, "unavailable");
}

#[test]
fn start_while_running_is_refused_without_disturbing_the_job() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    let mut other = job("pick_n_place");
    other.conversation_id = "c2".into();
    let actions = e.handle(ExecutionEvent::Start(other));
    assert!(
        matches!(&actions[0], ExecutionAction::Finished { conversation_id, .. } if conversation_id == "c2")
    );
    failed_with(&actions, "busy");
    assert_eq!(
        command(&e.handle(reply(pick.id, "picking_done"))).action,
        "place"
    );
}

#[test]
fn an_abort_tells_the_controller_and_the_step_ends_aborted() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    assert_eq!(
        e.handle(ExecutionEvent::Abort),
        vec![
            ExecutionAction::AbortController,
            ExecutionAction::StateChanged
        ]
    );
    assert_eq!(e.state().to_string(), "step 1, aborting");
    // A second abort changes nothing.
    assert_eq!(e.handle(ExecutionEvent::Abort), vec![]);
    // The controller answers the aborted command with its error.
    let actions = e.handle(ExecutionEvent::Controller(ControllerEvent::Reply {
        id: pick.id,
        result: "error".into(),
        message: Some("aborted".into()),
    }));
    failed_with(&actions, "aborted");
    assert_eq!(e.state(), &ExecutionState::Ready);
    // Nothing runs: nothing to abort.
    assert_eq!(e.handle(ExecutionEvent::Abort), vec![]);
}

#[test]
fn an_aborted_step_that_completes_a_middle_step_still_ends_aborted() {
    for end in [
        reply(0, "picking_done"),
        ExecutionEvent::Controller(ControllerEvent::CommandFailed {
            id: 0,
            failure: CommandFailure::Aborted,
        }),
        status(ControllerStatus::Estop),
    ] {
        let mut e = ready_execution();
        let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
        e.handle(ExecutionEvent::Abort);
        let end = match end {
            ExecutionEvent::Controller(ControllerEvent::Reply {
                result, message, ..
            }) => ExecutionEvent::Controller(ControllerEvent::Reply {
                id: pick.id,
                result,
                message,
            }),
            ExecutionEvent::Controller(ControllerEvent::CommandFailed { failure, .. }) => {
                ExecutionEvent::Controller(ControllerEvent::CommandFailed {
                    id: pick.id,
                    failure,
                })
            }
            other => other,
        };
        let actions = e.handle(end);
        failed_with(&actions, "aborted");
        assert!(
            !actions
                .iter()
                .any(|a| matches!(a, ExecutionAction::Command(_))),
            "no next step after an abort: {actions:?}"
        );
    }
}

#[test]
fn a_last_step_that_completes_before_the_abort_took_is_done() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    let place = command(&e.handle(reply(pick.id, "picking_done")));
    e.handle(ExecutionEvent::Abort);
    let actions = e.handle(reply(place.id, "placing_done"));
    assert!(
        matches!(
            &actions[0],
            ExecutionAction::Finished {
                outcome: Outcome::Done { .. },
                ..
            }
        ),
        "a completed step is never reported failed: {actions:?}"
    );
}

#[test]
fn stale_and_unknown_replies_are_ignored() {
    let mut e = ready_execution();
    assert_eq!(e.handle(reply(99, "picking_done")), vec![]);
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    assert_eq!(e.handle(reply(pick.id + 100, "picking_done")), vec![]);
    assert_eq!(e.current_step().as_deref(), Some("pick"));
}

#[test]
fn a_job_read_at_booking_is_not_read_again() {
    let mut e = ready_execution();
    let mut booked = job("pick_n_place");
    let catalog = crate::catalog::pick_n_place();
    let mut parameters = catalog
        .parameters(&booked.service_type, &booked.info)
        .unwrap();
    parameters.program = Some("read-at-booking".into());
    booked.parameters = Some(Arc::new(parameters));
    // What the steps use comes from the parameters, not from the info.
    booked.info.clear();
    let pick = command(&e.handle(ExecutionEvent::Start(booked)));
    assert_eq!(pick.pos.unwrap().x, 1.0);
    assert_eq!(pick.program.as_deref(), Some("read-at-booking"));
    let place = command(&e.handle(reply(pick.id, "picking_done")));
    assert_eq!(place.pos.unwrap().x, 4.0);
    assert_eq!(place.program.as_deref(), Some("read-at-booking"));
}

#[test]
fn a_job_whose_info_does_not_fit_fails_without_a_command() {
    let mut e = ready_execution();
    let mut bad = job("pick_n_place");
    bad.info.remove("place");
    failed_with(&e.handle(ExecutionEvent::Start(bad)), "invalid_info");
    assert_eq!(e.state(), &ExecutionState::Ready);
}

#[test]
fn a_stale_epoch_refusal_ends_the_job_deposed_with_no_result() {
    let deposed = |actions: &[ExecutionAction]| match actions.first() {
        Some(ExecutionAction::Finished {
            outcome: Outcome::Deposed { .. },
            ..
        }) => {}
        other => panic!("expected the job ended deposed, got {other:?}"),
    };
    let mut e = ready_execution();
    let actions = e.handle(ExecutionEvent::Start(job("pick_n_place")));
    let id = command(&actions).id;
    assert_eq!(e.current_step_index().map(|(_, i)| i), Some(0));
    let actions = e.handle(ExecutionEvent::Controller(ControllerEvent::CommandFailed {
        id,
        failure: CommandFailure::StaleEpoch {
            current: Some(robot_bridge::client::Epoch(2)),
        },
    }));
    deposed(&actions);
    assert_eq!(e.state(), &ExecutionState::Ready);
    // Refused at its second step: the same (the new holder may go on with it).
    let id = command(&e.handle(ExecutionEvent::Start(job("pick_n_place")))).id;
    let id = command(&e.handle(reply(id, "picking_done"))).id;
    let actions = e.handle(ExecutionEvent::Controller(ControllerEvent::CommandFailed {
        id,
        failure: CommandFailure::StaleEpoch { current: None },
    }));
    deposed(&actions);
}

mod fenced {
    use super::*;
    use robot_bridge::client::StepId;

    fn fenced_running() -> (ExecutionMachine, RobotCommand) {
        let mut e = ExecutionMachine::new(Arc::new(pick_n_place())).fenced(true);
        e.handle(ready());
        let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
        (e, pick)
    }

    fn lost(id: u64) -> ExecutionEvent {
        ExecutionEvent::Controller(ControllerEvent::CommandFailed {
            id,
            failure: CommandFailure::Disconnected,
        })
    }

    fn step_state(step: &str, status: Result<StepStatus, FenceError>) -> ExecutionEvent {
        ExecutionEvent::Controller(ControllerEvent::StepStatus {
            step: StepId::new(step).unwrap(),
            status,
        })
    }

    /// The connection breaks: the step's state is asked once the controller is back.
    fn unsettled() -> (ExecutionMachine, RobotCommand) {
        let (mut e, pick) = fenced_running();
        let asked = e.handle(lost(pick.id));
        assert_eq!(
            asked,
            vec![
                ExecutionAction::AskStepStatus,
                ExecutionAction::StateChanged
            ]
        );
        // The client could not ask: not connected. The status says so next.
        assert!(e
            .handle(step_state("c1#0", Err(FenceError::NotConnected)))
            .is_empty());
        assert_eq!(
            e.handle(status(ControllerStatus::Disconnected)),
            Vec::<ExecutionAction>::new()
        );
        assert_eq!(e.state().to_string(), "step 1, unsettled");
        assert_eq!(e.handle(ready()), vec![ExecutionAction::AskStepStatus]);
        (e, pick)
    }

    #[test]
    fn a_step_the_controller_completed_goes_on_as_if_it_had_answered() {
        let (mut e, _) = unsettled();
        let done = Ok(StepStatus::Done {
            result: "picking_done".into(),
        });
        // An answer for another step changes nothing.
        assert!(e.handle(step_state("c0#0", done.clone())).is_empty());
        let place = command(&e.handle(step_state("c1#0", done)));
        assert_eq!(place.action, "place");
        assert_eq!(e.state().to_string(), "step 2");
        let actions = e.handle(reply(place.id, "placing_done"));
        assert!(matches!(
            actions.first(),
            Some(ExecutionAction::Finished {
                outcome: Outcome::Done { .. },
                ..
            })
        ));
    }

    #[test]
    fn a_first_step_the_controller_never_began_fails_not_begun() {
        let (mut e, _) = unsettled();
        let actions = e.handle(step_state("c1#0", Ok(StepStatus::Unknown)));
        // Nothing of the job ran: the order may book it again (a part has not moved).
        failed_with(&actions, "not_begun");
        assert_eq!(e.state(), &ExecutionState::Ready);
    }

    #[test]
    fn a_later_step_the_controller_never_began_fails_disconnected() {
        let (mut e, _) = unsettled();
        let done = Ok(StepStatus::Done {
            result: "picking_done".into(),
        });
        let place = command(&e.handle(step_state("c1#0", done)));
        assert_eq!(
            e.handle(lost(place.id)),
            vec![
                ExecutionAction::AskStepStatus,
                ExecutionAction::StateChanged
            ]
        );
        // Step 1 ran: the job ran in part, not "not begun".
        let actions = e.handle(step_state("c1#1", Ok(StepStatus::Unknown)));
        failed_with(&actions, "controller_disconnected");
        assert_eq!(e.state(), &ExecutionState::Ready);
    }

    #[test]
    fn a_step_the_controller_failed_fails_with_its_message() {
        let (mut e, _) = unsettled();
        let failed = Ok(StepStatus::Failed {
            message: "gripper".into(),
        });
        failed_with(&e.handle(step_state("c1#0", failed)), "controller_error");
    }

    #[test]
    fn a_running_step_or_no_answer_waits_and_a_timeout_asks_again() {
        let (mut e, _) = unsettled();
        assert!(e
            .handle(step_state("c1#0", Ok(StepStatus::Running)))
            .is_empty());
        let timeout = Err(FenceError::Timeout(std::time::Duration::from_secs(1)));
        assert_eq!(
            e.handle(step_state("c1#0", timeout)),
            vec![ExecutionAction::AskStepStatus]
        );
        let cannot = Err(FenceError::Refused("no".into()));
        failed_with(
            &e.handle(step_state("c1#0", cannot)),
            "controller_disconnected",
        );
    }

    #[test]
    fn an_unfenced_machine_still_fails_a_lost_step_at_once() {
        let mut e = ready_execution();
        let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
        failed_with(&e.handle(lost(pick.id)), "controller_disconnected");
    }
}

fn departed(id: u64) -> ExecutionEvent {
    ExecutionEvent::Controller(ControllerEvent::Departed { id })
}

#[test]
fn a_departed_move_tells_its_requester_and_the_step_goes_on() {
    let mut e = ready_execution();
    let pick = command(&e.handle(ExecutionEvent::Start(job("pick_n_place"))));
    // Another command's departure (late, or a lane's) says nothing.
    assert_eq!(e.handle(departed(pick.id + 7)), vec![]);
    assert_eq!(
        e.handle(departed(pick.id)),
        vec![ExecutionAction::Departed {
            conversation_id: "c1".into(),
            requester: HolonId::order("o-1").unwrap(),
            service_type: "pick_n_place".into(),
            reply_to: "holarchy/t/order/o-1/inbox".into(),
        }]
    );
    // The step still waits for its reply, and ends with it as ever.
    assert!(e.is_waiting_for(pick.id));
    assert_eq!(e.current_step().as_deref(), Some("pick"));
    let place = command(&e.handle(reply(pick.id, "picking_done")));
    assert_eq!(place.action, "place");
    // Once its step has ended, a repeat of the old command's departure says nothing.
    assert_eq!(e.handle(departed(pick.id)), vec![]);
}

#[test]
fn an_operators_job_has_nobody_to_tell_of_a_departure() {
    let mut e = ready_execution();
    let mut operators = job("pick_n_place");
    operators.reply_to = String::new();
    operators.operator = Some("ada".into());
    let pick = command(&e.handle(ExecutionEvent::Start(operators)));
    assert_eq!(e.handle(departed(pick.id)), vec![]);
    assert!(e.is_waiting_for(pick.id));
}

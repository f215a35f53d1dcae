//! Several jobs at once on one controller: each lane's commands and replies its own.

use std::sync::Arc;

use robot_bridge::client::{CommandFailure, ControllerEvent, StepId, StepStatus};
use schemas::ControllerStatus;

use super::Executions;
use crate::catalog::pick_n_place;
use crate::machine::agenda::{Job, Outcome};
use crate::machine::execution::tests::{reply, status};
use crate::machine::execution::{ExecutionAction, ExecutionEvent};

/// A pick_n_place job of conversation `conversation`.
fn job(conversation: &str) -> Job {
    Job {
        conversation_id: conversation.into(),
        ..crate::machine::execution::tests::job("pick_n_place")
    }
}

/// The command ids (and lanes) among `actions`.
fn commands(actions: &[(usize, ExecutionAction)]) -> Vec<(usize, u64)> {
    actions
        .iter()
        .filter_map(|(lane, a)| match a {
            ExecutionAction::Command(c) => Some((*lane, c.id)),
            _ => None,
        })
        .collect()
}

fn finished(actions: &[(usize, ExecutionAction)]) -> Vec<(String, bool)> {
    actions
        .iter()
        .filter_map(|(_, a)| match a {
            ExecutionAction::Finished {
                conversation_id,
                outcome,
            } => Some((
                conversation_id.clone(),
                matches!(outcome, Outcome::Done { .. }),
            )),
            _ => None,
        })
        .collect()
}

fn ready_lanes(n: usize, fenced: bool) -> Executions {
    let mut e = Executions::new(Arc::new(pick_n_place()), fenced, n);
    let actions = e.handle(status(ControllerStatus::Ready));
    // The agenda is told once, whatever the number of lanes.
    assert_eq!(actions, vec![(0, ExecutionAction::Ready)]);
    e
}

#[test]
fn two_jobs_run_at_once_each_lane_with_its_own_command_ids() {
    let mut e = ready_lanes(2, false);
    assert_eq!(
        commands(&e.handle(ExecutionEvent::Start(job("a")))),
        [(0, 1)]
    );
    assert_eq!(
        commands(&e.handle(ExecutionEvent::Start(job("b")))),
        [(1, 2)]
    );
    // A third finds every lane running: refused busy, nothing sent.
    let third = e.handle(ExecutionEvent::Start(job("c")));
    assert!(commands(&third).is_empty());
    match &third[..] {
        [(
            _,
            ExecutionAction::Finished {
                conversation_id,
                outcome: Outcome::Failed { reason, .. },
            },
        )] => {
            assert_eq!(conversation_id, "c");
            assert_eq!(reason.as_str(), "busy");
        }
        other => panic!("expected c refused busy, got {other:?}"),
    }
    // b's pick is answered first: b's place goes out from its lane, a's is untouched.
    assert_eq!(commands(&e.handle(reply(2, "picking_done"))), [(1, 4)]);
    assert_eq!(commands(&e.handle(reply(1, "picking_done"))), [(0, 3)]);
    let running: Vec<String> = e.running().map(|j| j.conversation_id.into()).collect();
    assert_eq!(running, ["a", "b"]);
    assert_eq!(
        finished(&e.handle(reply(4, "placing_done"))),
        [("b".to_string(), true)]
    );
    assert_eq!(e.describe(), "step 2 | ready");
    // The freed lane takes the next job.
    assert_eq!(
        commands(&e.handle(ExecutionEvent::Start(job("c")))),
        [(1, 6)]
    );
    // A reply nobody waits for (late, or another lane's already answered): nothing.
    assert!(e.handle(reply(4, "placing_done")).is_empty());
}

#[test]
fn a_lost_controller_ends_every_running_job_and_the_agenda_hears_it_once() {
    let mut e = ready_lanes(3, false);
    e.handle(ExecutionEvent::Start(job("a")));
    e.handle(ExecutionEvent::Start(job("b")));
    let actions = e.handle(status(ControllerStatus::Estop));
    let mut ended = finished(&actions);
    ended.sort();
    assert_eq!(ended, [("a".to_string(), false), ("b".to_string(), false)]);
    let unavailable = actions
        .iter()
        .filter(|(_, a)| matches!(a, ExecutionAction::Unavailable(..)))
        .count();
    assert_eq!(unavailable, 1);
    assert_eq!(e.describe(), "init | init | init");
    assert_eq!(
        e.handle(status(ControllerStatus::Ready)),
        [(0, ExecutionAction::Ready)]
    );
}

#[test]
fn an_abort_is_told_to_the_controller_once_and_ends_each_running_job() {
    let mut e = ready_lanes(2, false);
    e.handle(ExecutionEvent::Start(job("a")));
    e.handle(ExecutionEvent::Start(job("b")));
    let actions = e.handle(ExecutionEvent::Abort);
    let aborts = actions
        .iter()
        .filter(|(_, a)| *a == ExecutionAction::AbortController)
        .count();
    assert_eq!(aborts, 1);
    let failure = |id| {
        ExecutionEvent::Controller(ControllerEvent::CommandFailed {
            id,
            failure: CommandFailure::Aborted,
        })
    };
    assert_eq!(finished(&e.handle(failure(2))), [("b".to_string(), false)]);
    assert_eq!(finished(&e.handle(failure(1))), [("a".to_string(), false)]);
}

#[test]
fn a_fenced_lane_asks_its_own_step_and_the_answer_reaches_it() {
    let mut e = ready_lanes(2, true);
    e.handle(ExecutionEvent::Start(job("a")));
    e.handle(ExecutionEvent::Start(job("b")));
    // The connection breaks: both steps are unsettled, asked once it is back.
    e.handle(status(ControllerStatus::Disconnected));
    let asked = e.handle(status(ControllerStatus::Ready));
    let asks: Vec<usize> = asked
        .iter()
        .filter(|(_, a)| *a == ExecutionAction::AskStepStatus)
        .map(|(lane, _)| *lane)
        .collect();
    assert_eq!(asks, [0, 1]);
    // b's pick was done: its lane goes on to its place; a's is untouched.
    let settled = e.handle(ExecutionEvent::Controller(ControllerEvent::StepStatus {
        step: StepId::of("b", 0).unwrap(),
        status: Ok(StepStatus::Done {
            result: "picking_done".into(),
        }),
    }));
    assert_eq!(commands(&settled), [(1, 4)]);
    assert_eq!(e.describe(), "step 1, unsettled | step 2");
}

#[test]
fn one_lane_is_the_machine_itself() {
    let mut e = ready_lanes(1, false);
    assert_eq!(
        commands(&e.handle(ExecutionEvent::Start(job("a")))),
        [(0, 1)]
    );
    assert_eq!(commands(&e.handle(reply(1, "picking_done"))), [(0, 2)]);
    assert_eq!(
        finished(&e.handle(reply(2, "placing_done"))),
        [("a".to_string(), true)]
    );
}

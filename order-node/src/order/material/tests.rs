//! What a move's outcome means for its part ([`super::move_end`]).

use schemas::HolonId;

use super::move_end;
use crate::part::MoveEnd;
use crate::progress::StepOutcome;

fn failed(reason: &str) -> StepOutcome {
    StepOutcome::Failed {
        provider: HolonId::resource("conveyor1").unwrap(),
        reason: reason.into(),
        detail: None,
    }
}

#[test]
fn a_move_refused_or_never_begun_moved_nothing() {
    // Refused by its controller, or never sent to it: the transporter's execution
    // refuses a move whose turn comes while its controller is not ready (a reconnect
    // after another move's timeout) or another job runs, and a transporter shutting
    // down hands back the moves it never began.
    let never_ran = [
        "controller_error",
        "invalid_info",
        "not_begun",
        "unavailable",
        "busy",
        "withdrawn",
    ];
    for reason in never_ran {
        assert_eq!(
            move_end(&failed(reason), true),
            MoveEnd::Unattempted,
            "{reason}"
        );
    }
}

#[test]
fn a_move_that_failed_on_its_way_may_have_moved_the_part() {
    let may_have_run = [
        "controller_disconnected",
        "controller_timeout",
        "controller_fault",
        "controller_protocol_error",
        "unexpected_result",
        "interrupted",
        "aborted",
    ];
    for reason in may_have_run {
        assert!(
            matches!(move_end(&failed(reason), true), MoveEnd::Unknown { .. }),
            "{reason}"
        );
    }
    let lost = StepOutcome::Lost {
        provider: HolonId::resource("conveyor1").unwrap(),
        why: "vanished".into(),
    };
    assert!(matches!(move_end(&lost, true), MoveEnd::Unknown { .. }));
    assert_eq!(move_end(&lost, false), MoveEnd::Unattempted);
}

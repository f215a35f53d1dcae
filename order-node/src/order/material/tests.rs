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
    for reason in ["controller_error", "invalid_info", "not_begun"] {
        assert_eq!(
            move_end(&failed(reason), true),
            MoveEnd::Unattempted,
            "{reason}"
        );
    }
}

#[test]
fn a_move_that_failed_on_its_way_may_have_moved_the_part() {
    for reason in ["controller_disconnected", "controller_fault", "interrupted"] {
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

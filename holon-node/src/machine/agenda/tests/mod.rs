use super::*;
use crate::catalog::pick_n_place;
use schemas::unix_ms;
use schemas::MessageType;
use serde_json::json;

mod at_once;
mod carriers;
mod epoch;
mod on_turn;
mod packml;
mod places;
mod queue;
mod refusals;
mod restore;
mod travel;

const INBOX: &str = "holarchy/t/order/o-1/inbox";

fn manager() -> AgendaMachine {
    let mut m = AgendaMachine::new(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        unix_ms(),
    );
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    m
}

fn poses() -> Map<String, Value> {
    json!({"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}})
        .as_object()
        .unwrap()
        .clone()
}

fn msg(kind: MessageType, order: &str, conversation: &str) -> Service {
    Service::request(
        kind,
        "pick_n_place",
        conversation,
        HolonId::order(order).unwrap(),
    )
    .with_reply_to(INBOX)
}

fn book(order: &str, conversation: &str) -> Service {
    msg(MessageType::BookingReq, order, conversation)
}

fn start(order: &str, conversation: &str) -> Service {
    msg(MessageType::Start, order, conversation).with_info(poses())
}

fn reply(actions: &[AgendaAction]) -> &Service {
    match actions.first() {
        Some(AgendaAction::Reply(r)) => r,
        other => panic!("expected a reply first, got {other:?}"),
    }
}

fn assert_refused(actions: &[AgendaAction], why: impl AsRef<str>) {
    let r = reply(actions);
    assert_eq!(r.result, Some(false), "{r:?}");
    assert_eq!(r.reason.as_ref().map(|r| r.as_str()), Some(why.as_ref()));
    assert_eq!(actions.len(), 1, "a refusal changes nothing: {actions:?}");
}

fn assert_accepted(actions: &[AgendaAction]) {
    let r = reply(actions);
    assert_eq!(r.result, Some(true), "{r:?}");
    assert_eq!(r.provider, Some(HolonId::resource("robot1").unwrap()));
}

fn done(conversation: &str) -> AgendaEvent {
    AgendaEvent::ExecutionFinished {
        conversation_id: conversation.into(),
        outcome: Outcome::Done {
            results: Map::new(),
        },
    }
}

#[test]
fn starts_in_init_until_execution_is_ready() {
    let mut m = AgendaMachine::new(
        HolonId::resource("robot1").unwrap(),
        Arc::new(pick_n_place()),
        3,
        unix_ms(),
    );
    assert_eq!(m.status(), Status::Init);
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms()),
        "unavailable",
    );
    assert_eq!(
        m.handle(AgendaEvent::ExecutionReady, unix_ms()),
        vec![AgendaAction::StateChanged]
    );
    assert_eq!(m.status(), Status::Free);
    assert_eq!(m.handle(AgendaEvent::ExecutionReady, unix_ms()), vec![]);
}

#[test]
fn free_empty_to_free_booked_on_booking_request() {
    let mut m = manager();
    let actions = m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    assert_accepted(&actions);
    assert_eq!(reply(&actions).info["queue_position"], 1);
    assert_eq!(actions[1], AgendaAction::StateChanged);
    assert_eq!(m.bookings().len(), 1);
    let actions = m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    assert_eq!(reply(&actions).info["queue_position"], 2);
    assert_eq!(m.status(), Status::Free);
}

#[test]
fn a_repeated_booking_request_books_once() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    let again = m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    assert_accepted(&again);
    assert_eq!(again.len(), 1);
    assert_eq!(m.bookings().len(), 1);
}

#[test]
fn free_booked_to_busy_on_start_from_a_booked_requester() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    let actions = m.handle(AgendaEvent::Request(start("o-2", "c2")), unix_ms());
    assert_accepted(&actions);
    match &actions[1] {
        AgendaAction::Execute(job) => {
            assert_eq!(job.conversation_id, "c2");
            assert_eq!(job.reply_to, INBOX);
            assert_eq!(job.info, poses());
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(actions[2], AgendaAction::StateChanged);
    assert!(matches!(m.status(), Status::Busy(ref j) if j.conversation_id == "c2"));
    assert_eq!(m.bookings().len(), 1, "the started booking left the list");
}

fn book_on_turn(order: &str, conversation: &str) -> Service {
    book(order, conversation)
        .with_info(poses())
        .with_start_on_turn()
}

fn executed(actions: &[AgendaAction]) -> Vec<String> {
    actions
        .iter()
        .filter_map(|a| match a {
            AgendaAction::Execute(job) => Some(job.conversation_id.clone()),
            _ => None,
        })
        .collect()
}

#[test]
fn a_resource_may_not_book() {
    let mut m = manager();
    let by_a_resource = Service::request(
        MessageType::BookingReq,
        "pick_n_place",
        "c1",
        HolonId::resource("robot2").unwrap(),
    )
    .with_reply_to(INBOX);
    let actions = m.handle(AgendaEvent::Request(by_a_resource), unix_ms());
    assert_refused(&actions, Reason::NotARequester);
    assert!(m.bookings().is_empty());
}

#[test]
fn start_by_the_last_booked_client_leaves_busy_with_no_bookings() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert!(matches!(m.status(), Status::Busy(_)));
    assert!(m.bookings().is_empty());
}

#[test]
fn start_uses_the_booking_info_when_it_has_none() {
    let mut m = manager();
    m.handle(
        AgendaEvent::Request(book("o-1", "c1").with_info(poses())),
        unix_ms(),
    );
    let actions = m.handle(
        AgendaEvent::Request(msg(MessageType::Start, "o-1", "c1")),
        unix_ms(),
    );
    assert!(matches!(&actions[1], AgendaAction::Execute(job) if job.info == poses()));
}

#[test]
fn a_jobs_info_is_read_at_booking_and_carried_to_its_execution() {
    let mut m = manager();
    let booking = book("o-1", "c1").with_info(poses());
    m.handle(AgendaEvent::Request(booking), unix_ms());
    let read = m.bookings()[0].parameters.clone();
    assert!(
        read.as_ref().is_some_and(|p| p.poses.len() == 2),
        "{read:?}"
    );
    let actions = m.handle(
        AgendaEvent::Request(msg(MessageType::Start, "o-1", "c1")),
        unix_ms(),
    );
    assert!(matches!(&actions[1], AgendaAction::Execute(job) if job.parameters == read));
    // A start with an info of its own is read when it comes.
    m.handle(done("c1"), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    let mut own = poses();
    own.insert("program".into(), serde_json::json!("b2"));
    let start = msg(MessageType::Start, "o-2", "c2").with_info(own);
    let actions = m.handle(AgendaEvent::Request(start), unix_ms());
    assert!(
        matches!(&actions[1], AgendaAction::Execute(job) if job.parameters.as_ref().and_then(|p| p.program.as_deref()) == Some("b2")),
        "{actions:?}"
    );
}

#[test]
fn start_while_busy_is_refused_and_keeps_the_booking() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-2", "c2")), unix_ms()),
        "busy",
    );
    assert_eq!(m.bookings().len(), 1);
}

#[test]
fn start_without_a_booking_is_refused() {
    let mut m = manager();
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()),
        "not_booked",
    );
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    // Another requester, or another conversation of the same requester.
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-2", "c1")), unix_ms()),
        "not_booked",
    );
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-1", "c9")), unix_ms()),
        "not_booked",
    );
    // Not booked beats busy: a stranger is told it holds no booking.
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-3", "c3")), unix_ms()),
        "not_booked",
    );
}

#[test]
fn start_while_unavailable_is_refused_and_keeps_the_booking() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(
        AgendaEvent::ExecutionUnavailable(ControllerStatus::Disconnected, None),
        unix_ms(),
    );
    assert_eq!(m.status(), Status::Init);
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()),
        "unavailable",
    );
    assert_eq!(m.bookings().len(), 1);
    m.handle(AgendaEvent::ExecutionReady, unix_ms());
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()));
}

#[test]
fn start_without_what_the_steps_need_is_refused() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    let actions = m.handle(
        AgendaEvent::Request(msg(MessageType::Start, "o-1", "c1")),
        unix_ms(),
    );
    assert_refused(&actions, "invalid_info");
    assert!(reply(&actions).info["detail"]
        .as_str()
        .unwrap()
        .contains("info.pick"));
    let mut booking_without_reply_to = book("o-2", "c2");
    booking_without_reply_to.reply_to = None;
    m.handle(AgendaEvent::Request(booking_without_reply_to), unix_ms());
    let mut no_reply_to = start("o-2", "c2");
    no_reply_to.reply_to = None;
    assert_refused(
        &m.handle(AgendaEvent::Request(no_reply_to), unix_ms()),
        "invalid_info",
    );
    assert_eq!(m.bookings().len(), 2);
    assert_eq!(m.status(), Status::Free);
}

#[test]
fn a_repeated_start_of_the_running_job_is_accepted_without_a_second_execution() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    let again = m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_accepted(&again);
    assert_eq!(again.len(), 1);
}

#[test]
fn unknown_service_types_are_refused() {
    let mut m = manager();
    let mut weld = book("o-1", "c1");
    weld.service_type = "weld".into();
    assert_refused(
        &m.handle(AgendaEvent::Request(weld.clone()), unix_ms()),
        "unknown_service",
    );
    weld.message_type = MessageType::Start;
    assert_refused(
        &m.handle(AgendaEvent::Request(weld.clone()), unix_ms()),
        "unknown_service",
    );
    weld.message_type = MessageType::ProposalReq;
    let proposal = m.handle(AgendaEvent::Request(weld), unix_ms());
    assert_eq!(reply(&proposal).message_type, MessageType::Proposal);
    assert_eq!(
        reply(&proposal).reason.as_ref().map(|r| r.as_str()),
        Some("unknown_service")
    );
    assert!(m.bookings().is_empty());
}

#[test]
fn start_for_a_booking_of_another_service_type_is_refused() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    let mut inspect = start("o-1", "c1");
    inspect.service_type = "inspect".into();
    assert_refused(
        &m.handle(AgendaEvent::Request(inspect), unix_ms()),
        "not_booked",
    );
}

#[test]
fn booking_cancel_removes_the_booking() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    let actions = m.handle(
        AgendaEvent::Request(msg(MessageType::BookingCancel, "o-1", "c1")),
        unix_ms(),
    );
    assert_accepted(&actions);
    assert_eq!(actions[1], AgendaAction::StateChanged);
    assert_eq!(m.bookings().len(), 1);
    assert_eq!(m.bookings()[0].conversation_id, "c2");
    // Cancel by the last booked client leaves an empty agenda.
    m.handle(
        AgendaEvent::Request(msg(MessageType::BookingCancel, "o-2", "c2")),
        unix_ms(),
    );
    assert!(m.bookings().is_empty());
    assert_eq!(m.status(), Status::Free);
}

#[test]
fn booking_cancel_without_a_booking_is_refused() {
    let mut m = manager();
    assert_refused(
        &m.handle(
            AgendaEvent::Request(msg(MessageType::BookingCancel, "o-1", "c1")),
            unix_ms(),
        ),
        "not_booked",
    );
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    assert_refused(
        &m.handle(
            AgendaEvent::Request(msg(MessageType::BookingCancel, "o-2", "c1")),
            unix_ms(),
        ),
        "not_booked",
    );
    assert_eq!(m.bookings().len(), 1);
}

#[test]
fn bookings_and_cancels_while_busy_keep_it_busy() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_accepted(&m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms()));
    assert!(matches!(m.status(), Status::Busy(_)));
    assert_accepted(&m.handle(
        AgendaEvent::Request(msg(MessageType::BookingCancel, "o-2", "c2")),
        unix_ms(),
    ));
    assert!(matches!(m.status(), Status::Busy(_)));
    // The running job cannot be booked again.
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms()),
        "busy",
    );
}

#[test]
fn done_from_execution_frees_the_resource_and_delivers_the_result() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    let actions = m.handle(done("c1"), unix_ms());
    let AgendaAction::Deliver(result) = &actions[0] else {
        panic!("{actions:?}")
    };
    assert_eq!(result.message_type, MessageType::Done);
    assert_eq!(result.result, Some(true));
    assert_eq!(result.conversation_id, "c1");
    assert_eq!(result.reply_to.as_deref(), Some(INBOX));
    assert_eq!(result.provider, Some(HolonId::resource("robot1").unwrap()));
    assert_eq!(actions[1], AgendaAction::StateChanged);
    assert_eq!(m.status(), Status::Free);
    assert_eq!(m.bookings().len(), 1, "busy_booked goes to free_booked");
    assert_eq!(m.undelivered().len(), 1);
}

#[test]
fn failed_from_execution_carries_the_reason() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    let actions = m.handle(
        AgendaEvent::ExecutionFinished {
            conversation_id: "c1".into(),
            outcome: Outcome::Failed {
                reason: Reason::ControllerDisconnected,
                detail: "the connection broke".into(),
            },
        },
        unix_ms(),
    );
    let AgendaAction::Deliver(result) = &actions[0] else {
        panic!("{actions:?}")
    };
    assert_eq!(result.message_type, MessageType::Failed);
    assert_eq!(result.result, Some(false));
    assert_eq!(
        result.reason.as_ref().map(|r| r.as_str()),
        Some("controller_disconnected")
    );
    assert_eq!(result.info["detail"], "the connection broke");
}

#[test]
fn a_stale_finish_changes_nothing() {
    let mut m = manager();
    assert_eq!(m.handle(done("c1"), unix_ms()), vec![]);
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_eq!(m.handle(done("c9"), unix_ms()), vec![]);
    assert!(matches!(m.status(), Status::Busy(_)));
}

#[test]
fn unavailable_while_busy_returns_to_init_after_the_job_ends() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    m.handle(
        AgendaEvent::ExecutionUnavailable(ControllerStatus::Disconnected, None),
        unix_ms(),
    );
    assert!(matches!(m.status(), Status::Busy(_)));
    m.handle(done("c1"), unix_ms());
    assert_eq!(m.status(), Status::Init);
}

#[test]
fn acknowledgement_removes_the_undelivered_result() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    m.handle(done("c1"), unix_ms());
    let ack = |c: &str| AgendaEvent::ResultAcknowledged {
        conversation_id: c.into(),
    };
    assert_eq!(m.handle(ack("c9"), unix_ms()), vec![]);
    assert_eq!(
        m.handle(ack("c1"), unix_ms()),
        vec![AgendaAction::StateChanged]
    );
    assert!(m.undelivered().is_empty());
    assert_eq!(m.handle(ack("c1"), unix_ms()), vec![]);
}

#[test]
fn withdraw_hands_every_booking_back_and_lets_the_running_job_finish() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms());
    let mut silent = book("o-3", "c3");
    silent.reply_to = None;
    m.handle(AgendaEvent::Request(silent), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    let actions = m.handle(AgendaEvent::Withdraw, unix_ms());
    let handed_back: Vec<&Service> = actions
        .iter()
        .filter_map(|a| match a {
            AgendaAction::Deliver(s) => Some(s),
            _ => None,
        })
        .collect();
    assert_eq!(
        handed_back.len(),
        1,
        "only bookings with a reply_to can be told"
    );
    assert_eq!(handed_back[0].conversation_id, "c2");
    assert_eq!(handed_back[0].message_type, MessageType::Failed);
    assert_eq!(
        handed_back[0].reason.as_ref().map(|r| r.as_str()),
        Some("withdrawn")
    );
    assert!(m.bookings().is_empty());
    assert!(
        !m.is_drained(),
        "the running job and the hand-back are pending"
    );
    assert_eq!(m.handle(AgendaEvent::Withdraw, unix_ms()), vec![]);
    // No new work.
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-4", "c4")), unix_ms()),
        "unavailable",
    );
    let mut proposal = book("o-4", "p");
    proposal.message_type = MessageType::ProposalReq;
    assert_eq!(
        reply(&m.handle(AgendaEvent::Request(proposal), unix_ms())).reason,
        Some(Reason::Unavailable)
    );
    // The running job finishes and is delivered.
    m.handle(done("c1"), unix_ms());
    for c in ["c1", "c2"] {
        m.handle(
            AgendaEvent::ResultAcknowledged {
                conversation_id: c.into(),
            },
            unix_ms(),
        );
    }
    assert!(m.is_drained());
}

#[test]
fn a_start_of_a_finished_job_whose_result_is_undelivered_is_accepted_again() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    m.handle(done("c1"), unix_ms());
    let again = m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    assert_accepted(&again);
    assert_eq!(again.len(), 1, "no second execution");
    m.handle(
        AgendaEvent::ResultAcknowledged {
            conversation_id: "c1".into(),
        },
        unix_ms(),
    );
    assert_refused(
        &m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()),
        "not_booked",
    );
}

/// The agenda of a busy resource with two bookings on turn behind the running job,
/// journalled and restored as `inheritance` says, its controller ready again: the
/// restored agenda and the jobs that started.
#[test]
fn a_requester_gone_for_good_loses_its_bookings_not_its_running_job() {
    let mut m = manager();
    m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-1", "c2")), unix_ms());
    m.handle(AgendaEvent::Request(book("o-2", "c3")), unix_ms());
    m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms());
    let actions = m.handle(
        AgendaEvent::RequesterGone {
            requester: HolonId::order("o-1").unwrap(),
        },
        unix_ms(),
    );
    assert_eq!(actions, vec![AgendaAction::StateChanged]);
    let left: Vec<_> = m
        .bookings()
        .iter()
        .map(|b| b.conversation_id.as_str())
        .collect();
    assert_eq!(left, vec!["c3"], "o-2's booking stays");
    assert_eq!(m.current().map(|j| j.conversation_id.as_str()), Some("c1"));
    let again = m.handle(
        AgendaEvent::RequesterGone {
            requester: HolonId::order("o-1").unwrap(),
        },
        unix_ms(),
    );
    assert!(again.is_empty(), "nothing left to release: {again:?}");
}

#[test]
fn a_deposed_agenda_drops_its_bookings_without_a_word_and_takes_no_work() {
    let mut m = agenda_for_record();
    let actions = m.handle(AgendaEvent::Deposed, unix_ms());
    assert_eq!(
        actions,
        vec![AgendaAction::StateChanged],
        "no withdrawn result"
    );
    assert!(m.record().bookings.is_empty());
    assert_eq!(m.handle(AgendaEvent::Deposed, unix_ms()), vec![]);
    assert_refused(
        &m.handle(AgendaEvent::Request(book("o-4", "c4")), unix_ms()),
        "unavailable",
    );
}

#[test]
fn a_job_ended_deposed_leaves_no_result() {
    let mut m = manager();
    assert_accepted(&m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms()));
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()));
    let actions = m.handle(
        AgendaEvent::ExecutionFinished {
            conversation_id: "c1".into(),
            outcome: Outcome::Deposed {
                detail: "stale_epoch".into(),
            },
        },
        unix_ms(),
    );
    assert_eq!(actions, vec![AgendaAction::StateChanged]);
    assert!(m.current().is_none());
    assert!(m.undelivered().is_empty(), "nothing to deliver");
}

/// An agenda with a job running, a booking waiting and a result undelivered: every
/// part of the journal's record (for `record`'s tests).
pub(super) fn agenda_for_record() -> AgendaMachine {
    let mut m = manager();
    assert_accepted(&m.handle(AgendaEvent::Request(book("o-1", "c1")), unix_ms()));
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-1", "c1")), unix_ms()));
    m.handle(done("c1"), unix_ms());
    assert_accepted(&m.handle(AgendaEvent::Request(book("o-2", "c2")), unix_ms()));
    assert_accepted(&m.handle(AgendaEvent::Request(start("o-2", "c2")), unix_ms()));
    assert_accepted(&m.handle(AgendaEvent::Request(book("o-3", "c3")), unix_ms()));
    m
}

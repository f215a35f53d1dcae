//! Answers `resource/<name>/outcome`: what became of a conversation, for the order that
//! booked it and heard nothing (docs/reliability.md, "Standby resources").
//!
//! The resource answers from what its agenda holds (its journal's): a result not yet
//! acknowledged is `done` or `failed` as it says (`withdrawn`: `never_reached`), the job
//! running or a booking waiting is `running`. A fenced resource that does not know the
//! conversation (a standby that took over from a dead holder, which has no journal of
//! the holder's), or whose journal says only `interrupted`, asks its controller the
//! state of each step id `<conversation>#<index>` of the service type's steps
//! (`STEP_STATUS`) and answers by [`from_steps`]. An unfenced resource that does not
//! know it answers `unknown`. Each question is answered by a task of its own, so a
//! controller slow to answer holds up no other request.

use std::sync::Arc;
use std::time::Duration;

use robot_bridge::client::{FenceError, StepId, StepStatus};
use schemas::{
    bounded_detail, ErrorReply, HolonId, MessageType, Outcome, OutcomeReply, OutcomeRequest,
    OutcomeSource, Reason,
};
use tracing::{debug, info, warn};

use crate::component::question::Question;
use crate::views::{AgendaView, FenceView};

/// What an answer is made of: the resource's name and catalog, what its components
/// publish, and its fence (the communication component's links give them).
pub trait Sources: Send + Sync + 'static {
    fn config(&self) -> &crate::config::ResourceConfig;
    fn views(&self) -> &crate::views::Views;
    fn fence(&self) -> Option<&robot_bridge::client::FenceHandle>;
}

/// The longest a question waits for the controller's step states, in all.
pub const CONTROLLER_WAIT: Duration = Duration::from_secs(2);

/// What the agenda (and so the journal) knows of the conversation: `None` when it
/// knows nothing of it, or (`fenced`) only that it was interrupted, which the
/// controller can tell better.
pub fn from_agenda(
    view: &AgendaView,
    request: &OutcomeRequest,
    holon: &HolonId,
    fenced: bool,
) -> Option<OutcomeReply> {
    let ours = |requester: &HolonId, conversation_id: &str| {
        *requester == request.requester && conversation_id == request.conversation_id
    };
    let mut reply = request.answer(holon, Outcome::Running);
    reply.source = OutcomeSource::Journal;
    if let Some(result) = view
        .deliverable
        .iter()
        .find(|r| ours(&r.requester, &r.conversation_id))
    {
        match (result.message_type, &result.reason) {
            (MessageType::Done, _) => {
                reply.outcome = Outcome::Done;
                reply.results = result
                    .info
                    .get("results")
                    .and_then(|r| r.as_object())
                    .cloned()
                    .unwrap_or_default();
            }
            (_, Some(Reason::Interrupted)) if fenced => return None,
            (_, Some(Reason::Withdrawn | Reason::NotBegun)) => {
                reply.outcome = Outcome::NeverReached
            }
            (_, reason) => {
                reply.outcome = Outcome::Failed;
                reply.reason = Some(reason.clone().unwrap_or(Reason::Other("failed".into())));
                reply.detail = result
                    .info
                    .get("detail")
                    .and_then(|d| d.as_str())
                    .map(str::to_string);
            }
        }
        return Some(reply);
    }
    let snapshot = &view.snapshot;
    let running = snapshot
        .current
        .iter()
        .chain(&snapshot.more_running)
        .any(|c| ours(&c.requester, &c.conversation_id));
    let waiting = snapshot
        .agenda
        .iter()
        .any(|b| ours(&b.requester, &b.conversation_id));
    (running || waiting).then_some(reply)
}

/// The outcome of a job from its steps' states on the controller, step by step in
/// order (`actions[i]` is step `i`'s action, `states[i]` what the controller said of
/// step id `<conversation>#<i>`):
///
/// | states | outcome |
/// |---|---|
/// | every step `done` | `done`, each step's result by its action |
/// | a step `failed` (before any not done) | `failed` `controller_error`, its message |
/// | a step `running` | `running` |
/// | the first step unknown | `never_reached` (nothing ran: book it again) |
/// | steps done, then one unknown | `failed` `interrupted` (it ran in part: the order decides) |
/// | the controller not asked (no connection, a timeout) | `unknown` |
pub fn from_steps(
    request: &OutcomeRequest,
    holon: &HolonId,
    actions: &[String],
    states: &[Result<StepStatus, FenceError>],
) -> OutcomeReply {
    let mut reply = request.answer(holon, Outcome::Done);
    reply.source = OutcomeSource::Controller;
    for (index, (action, state)) in actions.iter().zip(states).enumerate() {
        match state {
            Ok(StepStatus::Done { result }) => {
                reply
                    .results
                    .insert(action.clone(), serde_json::Value::String(result.clone()));
            }
            Ok(StepStatus::Failed { message }) => {
                reply.outcome = Outcome::Failed;
                reply.reason = Some(Reason::ControllerError);
                reply.detail = Some(bounded_detail(message.clone()));
                reply.results.clear();
                return reply;
            }
            Ok(StepStatus::Running) => {
                reply.outcome = Outcome::Running;
                reply.results.clear();
                return reply;
            }
            Ok(StepStatus::Unknown) if index == 0 => {
                reply.outcome = Outcome::NeverReached;
                return reply;
            }
            Ok(StepStatus::Unknown) => {
                reply.outcome = Outcome::Failed;
                reply.reason = Some(Reason::Interrupted);
                reply.detail = Some(format!(
                    "steps 1 to {index} ran on the controller; step {} never reached it",
                    index + 1
                ));
                reply.results.clear();
                return reply;
            }
            Err(e) => {
                let mut unknown = request.answer(holon, Outcome::Unknown);
                unknown.detail = Some(format!("the controller did not say: {e}"));
                return unknown;
            }
        }
    }
    if states.len() < actions.len() || actions.is_empty() {
        let mut unknown = request.answer(holon, Outcome::Unknown);
        unknown.detail = Some("the controller did not say of every step".into());
        return unknown;
    }
    reply
}

/// Answers one question on `resource/<name>/outcome` (in a task of its own).
pub async fn answer<L: Sources>(links: Arc<L>, question: Question) {
    let holon = &links.config().holon;
    let request = match OutcomeRequest::from_json(&question.payload()) {
        Ok(request) => request,
        Err(e) => {
            let refusal = ErrorReply::for_schema_error(&e);
            question.reject(holon, refusal.code, refusal.message).await;
            return;
        }
    };
    let fence = *links.views().fence.borrow();
    let epoch = match fence {
        FenceView::Holding(epoch) => Some(epoch),
        FenceView::Unfenced | FenceView::Standby => None,
    };
    let known = {
        let view = links.views().agenda.borrow();
        from_agenda(&view, &request, holon, epoch.is_some())
    };
    let mut reply = match (known, links.fence(), epoch) {
        (Some(reply), _, _) => reply,
        (None, Some(handle), Some(_)) => ask_controller(links.as_ref(), handle, &request).await,
        (None, _, _) => {
            let mut unknown = request.answer(holon, Outcome::Unknown);
            unknown.detail = Some("this resource does not know the conversation".into());
            unknown
        }
    };
    reply.epoch = epoch;
    info!(%holon, conversation_id = %request.conversation_id, requester = %request.requester, outcome = %reply.outcome, source = ?reply.source, reason = reply.reason.as_ref().map_or("", |r| r.as_str()), "outcome asked");
    question
        .answer_bytes(holon, "outcome", reply.to_json())
        .await;
}

/// Asks the controller the state of each step of the conversation's job.
async fn ask_controller(
    links: &impl Sources,
    fence: &robot_bridge::client::FenceHandle,
    request: &OutcomeRequest,
) -> OutcomeReply {
    let holon = &links.config().holon;
    let Some(definition) = links.config().catalog.get(&request.service_type) else {
        let mut unknown = request.answer(holon, Outcome::Unknown);
        unknown.detail = Some(format!(
            "this resource does not offer {}",
            request.service_type
        ));
        return unknown;
    };
    let actions: Vec<String> = definition.steps.iter().map(|s| s.action.clone()).collect();
    let asked = tokio::time::timeout(CONTROLLER_WAIT, async {
        let mut states = Vec::with_capacity(actions.len());
        for index in 0..actions.len() {
            let state = match StepId::of(&request.conversation_id, index) {
                Ok(step) => fence.step_status(&step).await,
                Err(e) => Err(e),
            };
            debug!(%holon, conversation_id = %request.conversation_id, index, ?state, "a step's state, as the controller knows it");
            // Past a step that is not done, the later ones cannot change the answer.
            let settled = !matches!(state, Ok(StepStatus::Done { .. }));
            states.push(state);
            if settled {
                break;
            }
        }
        states
    })
    .await;
    match asked {
        Ok(states) => from_steps(request, holon, &actions, &states),
        Err(_) => {
            warn!(%holon, conversation_id = %request.conversation_id, within = ?CONTROLLER_WAIT, "the controller did not say the steps' states in time");
            let mut unknown = request.answer(holon, Outcome::Unknown);
            unknown.detail = Some(format!(
                "the controller did not answer within {CONTROLLER_WAIT:?}"
            ));
            unknown
        }
    }
}

#[cfg(test)]
mod tests {
    use schemas::{CurrentJobView, ResourceSnapshot, Service};

    use super::*;

    fn request() -> OutcomeRequest {
        OutcomeRequest::new(
            "orders1-1/1/1",
            "pick_n_place",
            HolonId::order("orders1-1").unwrap(),
        )
    }

    fn robot() -> HolonId {
        HolonId::resource("robot1").unwrap()
    }

    fn view(deliverable: Vec<Service>, current: Option<&str>) -> AgendaView {
        let mut snapshot: ResourceSnapshot = serde_json::from_value(serde_json::json!({
            "holon": "resource/robot1", "state": "free", "controller": "ready",
            "agenda": [], "current": null, "undelivered": 0, "services": [], "v": 1, "at": 0
        }))
        .unwrap();
        snapshot.current = current.map(|conversation| CurrentJobView {
            requester: HolonId::order("orders1-1").unwrap(),
            conversation_id: conversation.into(),
            service_type: "pick_n_place".into(),
            step: None,
            program: None,
            started_at: None,
        });
        AgendaView {
            snapshot,
            deliverable,
            accepting: true,
            drained: false,
        }
    }

    fn result(kind: MessageType, reason: Option<Reason>) -> Service {
        let booking = Service::request(
            MessageType::BookingReq,
            "pick_n_place",
            "orders1-1/1/1",
            HolonId::order("orders1-1").unwrap(),
        );
        let mut result = booking.accepted(&robot());
        result.message_type = kind;
        result.reason = reason;
        if kind == MessageType::Done {
            result.info.insert(
                "results".into(),
                serde_json::json!({"pick": "picking_done", "place": "placing_done"}),
            );
        }
        result
    }

    #[test]
    fn the_agenda_answers_what_it_knows() {
        let asked = request();
        let done = from_agenda(
            &view(vec![result(MessageType::Done, None)], None),
            &asked,
            &robot(),
            false,
        )
        .unwrap();
        assert_eq!(done.outcome, Outcome::Done);
        assert_eq!(done.results["place"], "placing_done");
        assert_eq!(done.source, OutcomeSource::Journal);
        let failed = from_agenda(
            &view(
                vec![result(MessageType::Failed, Some(Reason::ControllerFault))],
                None,
            ),
            &asked,
            &robot(),
            true,
        )
        .unwrap();
        assert_eq!(
            (failed.outcome, failed.reason),
            (Outcome::Failed, Some(Reason::ControllerFault))
        );
        let withdrawn = from_agenda(
            &view(
                vec![result(MessageType::Failed, Some(Reason::Withdrawn))],
                None,
            ),
            &asked,
            &robot(),
            false,
        )
        .unwrap();
        assert_eq!(withdrawn.outcome, Outcome::NeverReached);
        // Failed before the controller began its first step: nothing ran either.
        let not_begun = from_agenda(
            &view(
                vec![result(MessageType::Failed, Some(Reason::NotBegun))],
                None,
            ),
            &asked,
            &robot(),
            true,
        )
        .unwrap();
        assert_eq!(not_begun.outcome, Outcome::NeverReached);
        let running = from_agenda(&view(vec![], Some("orders1-1/1/1")), &asked, &robot(), true);
        assert_eq!(running.unwrap().outcome, Outcome::Running);
        // Another conversation, or nothing: the agenda does not know it.
        assert!(
            from_agenda(&view(vec![], Some("orders1-1/1/2")), &asked, &robot(), true).is_none()
        );
        assert!(from_agenda(&view(vec![], None), &asked, &robot(), false).is_none());
    }

    #[test]
    fn an_interrupted_job_is_the_controllers_to_tell_when_fenced() {
        let interrupted = view(
            vec![result(MessageType::Failed, Some(Reason::Interrupted))],
            None,
        );
        assert!(from_agenda(&interrupted, &request(), &robot(), true).is_none());
        let unfenced = from_agenda(&interrupted, &request(), &robot(), false).unwrap();
        assert_eq!(unfenced.reason, Some(Reason::Interrupted));
    }

    #[test]
    fn the_controllers_step_states_make_the_outcome() {
        let actions = vec!["pick".to_string(), "place".to_string()];
        let done = |r: &str| {
            Ok(StepStatus::Done {
                result: r.to_string(),
            })
        };
        let outcome = |states: Vec<Result<StepStatus, FenceError>>| {
            from_steps(&request(), &robot(), &actions, &states)
        };
        let all = outcome(vec![done("picking_done"), done("placing_done")]);
        assert_eq!(all.outcome, Outcome::Done);
        assert_eq!(all.source, OutcomeSource::Controller);
        assert_eq!(all.results["pick"], "picking_done");
        assert_eq!(all.results["place"], "placing_done");
        assert_eq!(
            outcome(vec![Ok(StepStatus::Unknown)]).outcome,
            Outcome::NeverReached
        );
        assert_eq!(
            outcome(vec![done("picking_done"), Ok(StepStatus::Running)]).outcome,
            Outcome::Running
        );
        let partly = outcome(vec![done("picking_done"), Ok(StepStatus::Unknown)]);
        assert_eq!(
            (partly.outcome, partly.reason),
            (Outcome::Failed, Some(Reason::Interrupted))
        );
        assert!(partly.results.is_empty());
        let failed = outcome(vec![Ok(StepStatus::Failed {
            message: "gripper empty".into(),
        })]);
        assert_eq!(
            (failed.outcome, failed.reason, failed.detail.as_deref()),
            (
                Outcome::Failed,
                Some(Reason::ControllerError),
                Some("gripper empty")
            )
        );
        let silent = outcome(vec![done("picking_done"), Err(FenceError::NotConnected)]);
        assert_eq!(silent.outcome, Outcome::Unknown);
        // Fewer states than steps (asking stopped): not done.
        assert_eq!(
            outcome(vec![done("picking_done")]).outcome,
            Outcome::Unknown
        );
    }
}

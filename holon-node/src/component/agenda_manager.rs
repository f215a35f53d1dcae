//! The agenda manager component: the one owner of the agenda.
//!
//! Every event reaches it through its mailbox, each as an [`AgendaMessage`]: requests
//! from the communication component (with the [`Question`] to answer), `ready`,
//! `unavailable` and finished jobs from the execution component, acknowledgements from
//! the communication component, requesters gone from the requesters component, and
//! `withdraw` when the holon stops. The events waiting in the mailbox are taken together
//! (up to [`BATCH`]), so that requests arriving at once (eight orders booking at the
//! same moment) share one journal write and its fsync. For each batch, in this order:
//!
//! 1. the pure state machine ([`crate::machine::agenda`]) makes the transition of each event;
//! 2. the journal records what changed, once, before anything is answered or done; when
//!    that write fails, the agenda goes back to where it was and the events are taken
//!    one at a time (a request that cannot be recorded is refused and changes nothing);
//! 3. the agenda view is set ([`crate::views`]), so a state read after the answer sees
//!    the change;
//! 4. the actions are carried out, here and nowhere else: `Reply` answers the question,
//!    `Execute` goes to the execution component, `Deliver` to the delivery machine
//!    ([`crate::machine::delivery`]), whose attempts this task sends out and owns
//!    ([`courier::Courier`]) until the requester acknowledges;
//! 5. the view's watchers are woken (the snapshot's publisher among them): after the
//!    answers, so that the publication does not take a CPU from them, and before a job
//!    goes to the execution, which is then the next task to run ([`Unannounced`]).
//!
//! It owns the undelivered results alone: the agenda holds them (journalled), the
//! delivery machine their attempts; an acknowledgement goes straight into the agenda.
//! It never waits on another component: a job goes to the execution component's
//! mailbox with `try_send` (that mailbox holds at most a job and an abort, see
//! [`send_job`]), and an attempt is a future of its own, not a task behind a channel.
//! Every other component sends to its mailbox, and none of them is waited on by it, so
//! no cycle of waiting can form.

use std::sync::Arc;
use std::time::Duration;

use holon::ChildError;
use schemas::HolonId;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use crate::component::question::Question;
use crate::config::DeliverySettings;
use crate::fault_injection::Faults;
use crate::handover::{Handover, Mailbox};
use crate::machine::agenda::{AgendaAction, AgendaEvent};
use crate::machine::delivery::{
    repeat_worth_logging, DeliveryAction, DeliveryEvent, DeliveryMachine,
};
use crate::machine::execution::ExecutionRequest;
use crate::views::Views;
use courier::Courier;

pub mod courier;
mod journalled;

pub use journalled::JournalledAgenda;
use journalled::NotRecorded;

/// At most this many waiting events go through the state machine before one journal
/// write (their answers wait for it).
const BATCH: usize = 32;

/// How often a journal that cannot be written is tried again.
const JOURNAL_RETRY: Duration = Duration::from_secs(1);

/// One event for the agenda manager.
pub struct AgendaMessage {
    pub event: AgendaEvent,
    /// For a request: the query to answer. Other events have nobody to answer.
    pub question: Option<Question>,
}

impl From<AgendaEvent> for AgendaMessage {
    fn from(event: AgendaEvent) -> AgendaMessage {
        AgendaMessage {
            event,
            question: None,
        }
    }
}

/// What the agenda manager is linked to.
pub struct Links {
    pub holon: HolonId,
    /// The agenda it owns.
    pub agenda: Handover<JournalledAgenda>,
    /// Every event for it.
    pub mailbox: Mailbox<AgendaMessage>,
    /// The execution component's job mailbox (jobs and aborts), never waited on.
    pub jobs: mpsc::Sender<ExecutionRequest>,
    /// The session results are delivered on.
    pub session: zenoh::Session,
    /// The pauses between attempts to deliver a result, and their timeout.
    pub delivery: DeliverySettings,
    /// Where it publishes its view.
    pub views: Arc<Views>,
    pub faults: Arc<Faults>,
}

/// The delivery of the agenda's results, held by the running task: the machine that
/// schedules the attempts and the attempts out. A successor starts both afresh from the
/// agenda's undelivered results (an attempt lost with its predecessor goes out again).
struct Delivery {
    /// When each result goes out (again).
    deliveries: DeliveryMachine,
    /// The attempts out.
    courier: Courier,
}

/// The component's task: drains the mailbox, the events waiting at once together, and
/// delivers the results, until cancelled.
pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let holon = &links.holon;
    let mut agenda = links.agenda.take().await;
    let mut mailbox = links.mailbox.take().await;
    // A successor publishes at once: its predecessor may have died between a change and
    // its publication.
    links.views.agenda.send_replace(agenda.view());
    let mut delivery = Delivery {
        deliveries: DeliveryMachine::new(links.delivery, *links.views.delivery_retries.borrow()),
        courier: Courier::new(links.session.clone(), links.delivery.attempt_timeout),
    };
    // Results not yet acknowledged (from before a restart of the process or of this
    // component) go out as soon as the resource serves.
    for result in agenda.deliverable() {
        deliver(&links, &mut delivery, DeliveryEvent::Result(result));
    }
    // A fenced resource delivers nothing until it holds its controller
    // (docs/reliability.md, "Standby resources"), and no resource before it answers
    // questions about its results (its queryables are declared).
    let mut fence = links.views.fence.subscribe();
    let mut answering = links.views.answering.subscribe();
    let mut serving = false;
    let mut journal_retry = tokio::time::interval(JOURNAL_RETRY);
    journal_retry.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        // Both read (and marked seen) every time: a change of either wakes the loop once.
        let (serves, answers) = (
            fence.borrow_and_update().serves(),
            *answering.borrow_and_update(),
        );
        if !serving && serves && answers {
            serving = true;
            deliver(&links, &mut delivery, DeliveryEvent::Serving);
        }
        let next_due = delivery.deliveries.next_due();
        let batch = tokio::select! {
            _ = token.cancelled() => return Ok(()),
            _ = links.faults.agenda.notified() => panic!("fault injection: agenda manager crashed"),
            _ = journal_retry.tick() => {
                let mut actions = retry(&mut agenda, holon);
                if agenda.wants_tick() {
                    if let Ok(more) = record(&mut agenda, holon, AgendaEvent::Tick, schemas::unix_ms()) {
                        actions.extend(more);
                    }
                }
                let mut view = Unannounced::set(&links, &agenda, actions.contains(&AgendaAction::StateChanged));
                carry_out(&links, &mut delivery, actions, None, &mut view).await?;
                view.announce(&links);
                continue;
            }
            (conversation_id, outcome) = delivery.courier.next_end() => {
                let ended = DeliveryEvent::AttemptEnded { conversation_id, outcome };
                for conversation_id in deliver(&links, &mut delivery, ended) {
                    // Recorded lazily (see `JournalledAgenda::apply`); never refused.
                    let acknowledged = AgendaEvent::ResultAcknowledged { conversation_id };
                    if let Ok(actions) = record(&mut agenda, holon, acknowledged, schemas::unix_ms()) {
                        let mut view = Unannounced::set(&links, &agenda, actions.contains(&AgendaAction::StateChanged));
                        carry_out(&links, &mut delivery, actions, None, &mut view).await?;
                        view.announce(&links);
                    }
                }
                continue;
            }
            _ = tokio::time::sleep_until(next_due.unwrap_or_else(Instant::now)), if next_due.is_some() => {
                deliver(&links, &mut delivery, DeliveryEvent::Tick);
                continue;
            }
            changed = fence.changed(), if !serving => {
                changed.map_err(|_| "the fence view closed")?;
                continue;
            }
            changed = answering.changed(), if !serving => {
                changed.map_err(|_| "the answering view closed")?;
                continue;
            }
            message = mailbox.recv() => {
                let mut batch = vec![message.ok_or("agenda mailbox closed")?];
                while batch.len() < BATCH {
                    match mailbox.try_recv() {
                        Ok(message) => batch.push(message),
                        Err(_) => break,
                    }
                }
                batch
            }
        };
        let (events, questions): (Vec<_>, Vec<_>) = batch
            .into_iter()
            .map(|AgendaMessage { event, question }| (event, question))
            .unzip();
        let outcomes = record_batch(&mut agenda, holon, events, schemas::unix_ms());
        // The view is set once, before any answer (a state read after an answer sees it),
        // and announced after the answers (see `Unannounced`).
        let changed = outcomes.iter().any(|outcome| match outcome {
            Ok(actions) => actions.contains(&AgendaAction::StateChanged),
            Err(NotRecorded) => true,
        });
        let mut view = Unannounced::set(&links, &agenda, changed);
        for (outcome, question) in outcomes.into_iter().zip(questions) {
            match outcome {
                Ok(actions) => {
                    carry_out(&links, &mut delivery, actions, question, &mut view).await?
                }
                Err(NotRecorded) => {
                    if let Some(question) = question {
                        question
                            .reject(
                                holon,
                                schemas::ErrorCode::Unavailable,
                                "the journal could not record the request; nothing changed".into(),
                            )
                            .await;
                    }
                }
            }
        }
        view.announce(&links);
    }
}

/// One event through the agenda at `now` (Unix ms), and the journal write it asks for:
/// the actions to carry out, or [`NotRecorded`] (see [`JournalledAgenda::settle`]).
fn record(
    agenda: &mut JournalledAgenda,
    holon: &HolonId,
    event: AgendaEvent,
    now: u64,
) -> Result<Vec<AgendaAction>, NotRecorded> {
    let pending = agenda.apply(holon, event, now);
    let written = pending.must_write().then(|| agenda.write());
    agenda.settle(holon, pending, written)
}

/// The events that arrived together through the agenda at `now`, with one journal
/// write (or each with its own, see [`JournalledAgenda::apply_batch`]): the outcome of
/// each, in order.
fn record_batch(
    agenda: &mut JournalledAgenda,
    holon: &HolonId,
    events: Vec<AgendaEvent>,
    now: u64,
) -> Vec<Result<Vec<AgendaAction>, NotRecorded>> {
    if let Some(batch) = agenda.apply_batch(&events, now) {
        let written = batch.undo.is_some().then(|| agenda.write());
        if let Some(actions) = agenda.settle_batch(holon, batch, written) {
            return actions.into_iter().map(Ok).collect();
        }
    }
    events
        .into_iter()
        .map(|event| record(agenda, holon, event, now))
        .collect()
}

/// While the journal is failing: the agenda written as it is now, and what that
/// releases.
fn retry(agenda: &mut JournalledAgenda, holon: &HolonId) -> Vec<AgendaAction> {
    if !agenda.failing() {
        return vec![];
    }
    let written = agenda.write();
    agenda.retried(holon, written)
}

/// An agenda view set for readers ([`Views::set_agenda_quietly`]) whose watchers are not
/// woken yet. They are woken once the answers are out, so that the snapshot's
/// publication does not take a CPU from them; but before a job goes to the execution
/// component, so that the execution is the task woken last, and the next to run.
struct Unannounced(bool);

impl Unannounced {
    /// Sets the view of `agenda` when it `changed`.
    fn set(links: &Links, agenda: &JournalledAgenda, changed: bool) -> Unannounced {
        if changed {
            links.views.set_agenda_quietly(agenda.view());
        }
        Unannounced(changed)
    }

    /// Wakes the view's watchers, once.
    fn announce(&mut self, links: &Links) {
        if std::mem::take(&mut self.0) {
            links.views.announce_agenda();
        }
    }
}

/// One event through the delivery machine, its actions carried out: attempts go out,
/// the count of retries is republished when it changed. Returns the conversations
/// whose results were acknowledged (for the agenda).
fn deliver(links: &Links, delivery: &mut Delivery, event: DeliveryEvent) -> Vec<String> {
    let holon = &links.holon;
    let mut acknowledged = Vec::new();
    for action in delivery.deliveries.handle(event, Instant::now()) {
        match action {
            DeliveryAction::Attempt { message, attempt } => {
                if repeat_worth_logging(attempt) {
                    info!(%holon, conversation_id = %message.conversation_id, message_type = %message.message_type, reply_to = message.reply_to.as_deref().unwrap_or(""), attempt, "sending result");
                } else {
                    debug!(%holon, conversation_id = %message.conversation_id, attempt, "sending result again");
                }
                delivery.courier.send(message);
            }
            DeliveryAction::Retry {
                conversation_id,
                attempt,
                refused,
                pause,
            } => match refused {
                Some(why) if repeat_worth_logging(attempt) => {
                    warn!(%holon, %conversation_id, attempt, reason = %why, retry_in = ?pause, "result refused; it is sent again until acknowledged");
                }
                _ => {
                    debug!(%holon, %conversation_id, retry_in = ?pause, "result not acknowledged yet")
                }
            },
            DeliveryAction::Acknowledged {
                conversation_id,
                message_type,
                attempts,
            } => {
                info!(%holon, %conversation_id, %message_type, attempts, "result acknowledged");
                acknowledged.push(conversation_id);
            }
        }
    }
    // Retries back off (doubling), so publishing the count with each is cheap.
    let retries = delivery.deliveries.retries();
    links.views.delivery_retries.send_if_modified(|count| {
        let changed = *count != retries;
        *count = retries;
        changed
    });
    acknowledged
}

/// Hands a job or an abort to the execution component without waiting for room: the
/// agenda begins a job only after it learnt the end of the last one, and aborts the
/// running one at most once, so the mailbox holds at most a job and an abort and is
/// never full. Full would be a bug: the component fails and is restarted.
fn send_job(links: &Links, request: ExecutionRequest) -> Result<(), ChildError> {
    links.jobs.try_send(request).map_err(|e| match e {
        mpsc::error::TrySendError::Full(_) => ChildError::from(
            "the execution mailbox is full (it holds at most a job and an abort: a bug)",
        ),
        mpsc::error::TrySendError::Closed(_) => ChildError::from("execution mailbox closed"),
    })
}

/// Carries out the actions of one transition.
async fn carry_out(
    links: &Links,
    delivery: &mut Delivery,
    actions: Vec<AgendaAction>,
    mut question: Option<Question>,
    view: &mut Unannounced,
) -> Result<(), ChildError> {
    let holon = &links.holon;
    for action in actions {
        match action {
            AgendaAction::Reply(answer) => match question.take() {
                Some(question) => question.answer(holon, &answer).await,
                None => {
                    warn!(%holon, conversation_id = %answer.conversation_id, "an answer without a question is dropped (a bug: only requests are answered)")
                }
            },
            AgendaAction::Execute(job) => {
                info!(%holon, component = "agenda", conversation_id = %job.conversation_id, requester = %job.requester, "starting execution");
                view.announce(links);
                send_job(links, ExecutionRequest::Start(job))?;
            }
            AgendaAction::Abort => {
                info!(%holon, component = "agenda", "PackML abort: the running step is aborted");
                view.announce(links);
                send_job(links, ExecutionRequest::Abort)?;
            }
            AgendaAction::PackmlReply(reply) => match question.take() {
                Some(question) => {
                    let payload = serde_json::to_vec(&reply).expect("a reply serializes");
                    question.answer_bytes(holon, "packml", payload).await;
                }
                None => {
                    warn!(%holon, "a PackML answer without a question is dropped (a bug: only requests are answered)")
                }
            },
            AgendaAction::CarrierAnswer(answer) => match question.take() {
                Some(question) => match answer {
                    Ok(reply) => {
                        let payload = serde_json::to_vec(&reply).expect("a reply serializes");
                        question.answer_bytes(holon, "carriers", payload).await;
                    }
                    Err((code, why)) => question.reject(holon, code, why).await,
                },
                None => {
                    warn!(%holon, "an answer on a carrier without a question is dropped (a bug: only words are answered)")
                }
            },
            AgendaAction::Deliver(result) => {
                // A new result is not acknowledged yet: nothing comes back for the agenda.
                let acknowledged = deliver(links, delivery, DeliveryEvent::Result(result));
                debug_assert!(acknowledged.is_empty());
            }
            // The view is set before the actions (see `Unannounced`).
            AgendaAction::StateChanged => {}
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use schemas::{unix_ms, MessageType, Service};

    use super::*;
    use crate::config::ResourceConfig;
    use crate::identity::Overrides;
    use crate::machine::agenda::Inheritance;

    const DEMO: &str = include_str!("../../../deploy/cells/demo/robot1.toml");

    fn config(data: &Path) -> ResourceConfig {
        let overrides = Overrides {
            common: holon::session::CommandLine {
                data_dir: Some(data.to_path_buf()),
                ..Default::default()
            },
            ..Overrides::default()
        };
        ResourceConfig::parse(DEMO, "robot1.toml", overrides).unwrap()
    }

    /// The demo's robot1 with its journal in `data`, its controller ready.
    fn journalled(config: &ResourceConfig) -> JournalledAgenda {
        let mut agenda = JournalledAgenda::open(config, Inheritance::Restarted).unwrap();
        record(
            &mut agenda,
            &config.holon,
            AgendaEvent::ExecutionReady,
            unix_ms(),
        )
        .unwrap();
        agenda
    }

    fn booking(order: &str) -> AgendaEvent {
        AgendaEvent::Request(
            Service::request(
                MessageType::BookingReq,
                "pick_n_place",
                &format!("{order}/1/1"),
                HolonId::order(order).unwrap(),
            )
            .with_reply_to("holarchy/demo/order/x/inbox"),
        )
    }

    fn accepted(outcome: &Result<Vec<AgendaAction>, NotRecorded>) -> bool {
        matches!(outcome, Ok(actions) if matches!(actions.first(), Some(AgendaAction::Reply(r)) if r.result == Some(true)))
    }

    #[test]
    fn bookings_that_arrive_together_share_one_journal_write() {
        let dir = tempfile::tempdir().unwrap();
        let config = config(dir.path());
        let mut agenda = journalled(&config);
        let commits = agenda.journal.as_ref().unwrap().commits();
        let eight = (0..8).map(|i| booking(&format!("o{i}"))).collect();
        let outcomes = record_batch(&mut agenda, &config.holon, eight, unix_ms());
        assert!(outcomes.iter().all(accepted), "{outcomes:?}");
        assert_eq!(agenda.journal.as_ref().unwrap().commits(), commits + 1);
        drop(agenda);
        let reopened = JournalledAgenda::open(&config, Inheritance::Restarted).unwrap();
        assert_eq!(reopened.agenda.bookings().len(), 8, "all eight recorded");
    }

    #[test]
    fn a_batch_the_journal_refuses_is_taken_one_request_at_a_time() {
        let dir = tempfile::tempdir().unwrap();
        let config = config(dir.path());
        drop(JournalledAgenda::open(&config, Inheritance::Restarted).unwrap());
        // The journal refuses any agenda that holds order o5's booking.
        let file = dir.path().join("resource-robot1.sqlite");
        rusqlite::Connection::open(&file)
            .unwrap()
            .execute_batch(
                "CREATE TRIGGER no_o5 BEFORE UPDATE ON records WHEN NEW.body LIKE '%o5/1/1%' \
                 BEGIN SELECT RAISE(ABORT, 'refused'); END;",
            )
            .unwrap();
        let mut agenda = journalled(&config);
        let eight = (0..8).map(|i| booking(&format!("o{i}"))).collect();
        let outcomes = record_batch(&mut agenda, &config.holon, eight, unix_ms());
        for (i, outcome) in outcomes.iter().enumerate() {
            if i == 5 {
                assert!(matches!(outcome, Err(NotRecorded)), "{outcome:?}");
            } else {
                assert!(accepted(outcome), "o{i}: {outcome:?}");
            }
        }
        drop(agenda);
        let reopened = JournalledAgenda::open(&config, Inheritance::Restarted).unwrap();
        let booked: Vec<String> = reopened
            .agenda
            .bookings()
            .iter()
            .map(|b| b.requester.name().to_string())
            .collect();
        assert_eq!(booked, ["o0", "o1", "o2", "o3", "o4", "o6", "o7"]);
    }

    #[test]
    fn a_job_whose_start_the_journal_cannot_record_does_not_begin_on_its_turn() {
        let dir = tempfile::tempdir().unwrap();
        let config = config(dir.path());
        drop(JournalledAgenda::open(&config, Inheritance::Restarted).unwrap());
        // The journal refuses any agenda with o2's job running.
        rusqlite::Connection::open(dir.path().join("resource-robot1.sqlite"))
            .unwrap()
            .execute_batch(
                r#"CREATE TRIGGER no_o2 BEFORE UPDATE ON records WHEN NEW.body LIKE '%"current":{"requester":"order/o2"%'
                 BEGIN SELECT RAISE(ABORT, 'refused'); END;"#,
            )
            .unwrap();
        let mut agenda = journalled(&config);
        let on_turn = |order: &str| {
            let AgendaEvent::Request(request) = booking(order) else {
                unreachable!()
            };
            let poses = serde_json::json!({"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}});
            AgendaEvent::Request(
                request
                    .with_info(poses.as_object().unwrap().clone())
                    .with_start_on_turn(),
            )
        };
        let first = record(&mut agenda, &config.holon, on_turn("o1"), unix_ms()).unwrap();
        assert!(
            matches!(&first[0], AgendaAction::Reply(r) if r.started()),
            "{first:?}"
        );
        record(&mut agenda, &config.holon, on_turn("o2"), unix_ms()).unwrap();
        let finished = AgendaEvent::ExecutionFinished {
            conversation_id: "o1/1/1".into(),
            outcome: crate::machine::agenda::Outcome::Done {
                results: Default::default(),
            },
        };
        let actions = record(&mut agenda, &config.holon, finished, unix_ms()).unwrap();
        assert!(
            !actions
                .iter()
                .any(|a| matches!(a, AgendaAction::Execute(_))),
            "o2 must not begin unrecorded: {actions:?}"
        );
        // The fact is kept: o1 finished, o2 still waits on the agenda.
        assert!(agenda.agenda.current().is_none());
        assert_eq!(agenda.agenda.bookings().len(), 1);
        assert_eq!(agenda.agenda.undelivered().len(), 1);
    }
}

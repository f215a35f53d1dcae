//! The orders' inboxes: one queryable for all the orders of a node, and what a result
//! reported there means for the attempt that waits on it ([`judge`]).
//!
//! A resource delivers `done` / `failed` with a `get` on `holarchy/<cell>/order/<name>/inbox`,
//! and a transporter its move's `departed` the same way (once, never repeated: the order
//! may release the place at the move's origin early, docs/material-flow.md,
//! "Departure"). The node declares one queryable, `order/<node>-$*/inbox`, and
//! [`Inboxes::route`] hands each result to the task of the running order it names;
//! results for orders that are not running (finished, or waiting to be restarted) go to
//! the node, which acknowledges those of finished orders (and every `departed`: never
//! a result). An order waiting for a resource therefore costs the cell no
//! declaration of its own (thousands of them used to mean thousands of queryables on
//! every router and peer).

use std::collections::HashMap;
use std::sync::Arc;

use schemas::{HolonId, MessageType, Reason, Service};
use tokio::sync::{mpsc, watch};
use tracing::{info, warn};
use zenoh::query::Query;

use crate::progress::StepOutcome;

/// A result reported to an order (or a move's departure), with the query to
/// acknowledge once it is recorded.
pub struct ResultReport {
    /// The result (`done` or `failed`), or a transporter's `departed`.
    pub message: Service,
    /// The resource's delivery, answered with the acknowledgement (or a refusal).
    pub query: Query,
}

impl ResultReport {
    /// Acknowledges the result: the resource stops delivering it.
    pub async fn acknowledge(self) {
        let mut ack = self.message.clone();
        ack.result = Some(true);
        if let Err(e) = self
            .query
            .reply(self.query.key_expr().clone(), ack.to_json())
            .await
        {
            warn!(conversation_id = %self.message.conversation_id, error = %e, "cannot acknowledge a result: the resource delivers it again");
        }
    }

    /// Refuses the result with an error reply (the resource logs it and retries).
    pub async fn refuse(self, code: schemas::ErrorCode, message: String) {
        if let Err(e) = self
            .query
            .reply_err(schemas::ErrorReply::new(code, message).to_json())
            .await
        {
            warn!(conversation_id = %self.message.conversation_id, error = %e, "cannot refuse a result");
        }
    }
}

/// How many results may wait in one order's inbox; more are refused `unavailable` (the
/// resource sends them again after its pause).
pub const INBOX_CAPACITY: usize = 16;

/// The open inboxes, by order name: where to send each running order's results.
type Open = HashMap<String, mpsc::Sender<ResultReport>>;

/// The inboxes of the running orders, by order name.
pub struct Inboxes {
    /// The open inboxes: each order's task opens and closes its own (one change at a
    /// time, in place); the zenoh callbacks ([`Inboxes::route`], [`Inboxes::held`]),
    /// which must answer without waiting for any task, read the latest.
    open: watch::Sender<Open>,
}

impl Default for Inboxes {
    fn default() -> Inboxes {
        Inboxes {
            open: watch::Sender::new(Open::new()),
        }
    }
}

/// An open inbox: results for its order arrive here until it is dropped.
pub struct Inbox {
    /// The order's name.
    name: String,
    /// Where it is listed while open.
    inboxes: Arc<Inboxes>,
    /// Results for the order, at most [`INBOX_CAPACITY`] waiting.
    pub reports: mpsc::Receiver<ResultReport>,
}

impl Drop for Inbox {
    fn drop(&mut self) {
        self.inboxes.open.send_modify(|open| {
            open.remove(&self.name);
        });
    }
}

impl Inboxes {
    /// Opens the inbox of `order` (replacing one left by an earlier task of it).
    pub fn open(self: &Arc<Self>, order: &HolonId) -> Inbox {
        let (sender, reports) = mpsc::channel(INBOX_CAPACITY);
        self.open.send_modify(|open| {
            open.insert(order.name().to_string(), sender);
        });
        Inbox {
            name: order.name().to_string(),
            inboxes: self.clone(),
            reports,
        }
    }

    /// Those of `names` whose order is running here (its inbox is open): the orders the
    /// node holds ([`schemas::held`]).
    pub fn held(&self, names: &[String]) -> Vec<String> {
        let open = self.open.borrow();
        names
            .iter()
            .filter(|name| open.contains_key(name.as_str()))
            .cloned()
            .collect()
    }

    /// Hands a query on `order/<name>/inbox` to the running order it names; an
    /// undecodable or misaddressed message is refused here. Returns the query when no
    /// running order has that name (the node decides).
    pub fn route(&self, query: Query) -> Option<Query> {
        use zenoh::Wait;
        let name = order_name(query.key_expr().as_str())?.to_string();
        let sender = self.open.borrow().get(&name).cloned();
        let Some(sender) = sender else {
            return Some(query);
        };
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let (query, refusal) = match Service::from_json(&payload) {
            Ok(message)
                if HolonId::order(&name).ok().as_ref() == Some(&message.requester)
                    && matches!(
                        message.message_type,
                        MessageType::Done | MessageType::Failed | MessageType::Departed
                    ) =>
            {
                info!(holon = %message.requester, conversation_id = %message.conversation_id, message_type = %message.message_type, provider = %message.provider.as_ref().map(|p| p.to_string()).unwrap_or_default(), reason = message.reason.as_ref().map_or("", |r| r.as_str()), "received");
                match sender.try_send(ResultReport { message, query }) {
                    Ok(()) => return None,
                    // The order's task ended between the lookup and the send: the node
                    // answers as for an order that is not running.
                    Err(mpsc::error::TrySendError::Closed(returned)) => {
                        return Some(returned.query)
                    }
                    // The order is far behind (a resource repeating results faster than
                    // the order records them): refused, the resource sends it again.
                    Err(mpsc::error::TrySendError::Full(returned)) => {
                        warn!(order = %name, conversation_id = %returned.message.conversation_id, message_type = %returned.message.message_type, "the order's inbox is full: refused, the resource sends a result again (a departure is not: its place is released at done)");
                        (returned.query, schemas::ErrorReply::new(schemas::ErrorCode::Unavailable, format!("{INBOX_CAPACITY} results are waiting for this order; send it again later")))
                    }
                }
            }
            Ok(other) => (
                query,
                schemas::ErrorReply::new(
                    schemas::ErrorCode::WrongKey,
                    format!(
                        "{} for {} is not for this inbox",
                        other.message_type, other.requester
                    ),
                ),
            ),
            Err(err) => {
                warn!(order = %name, bytes = payload.len(), error = %err, "undecodable message in the inbox refused");
                (query, schemas::ErrorReply::for_schema_error(&err))
            }
        };
        if let Err(e) = query.reply_err(refusal.to_json()).wait() {
            warn!(order = %name, error = %e, "cannot refuse a message in the inbox");
        }
        None
    }
}

/// The order named by an inbox key (`.../order/<name>/inbox`).
pub fn order_name(key: &str) -> Option<&str> {
    key.strip_suffix("/inbox")?.rsplit('/').next()
}

/// What a message in the inbox means for the attempt waiting on `provider` with
/// `conversation_id` ([`verdict`]), with the report where the attempt has more to do
/// with it.
pub enum Judged {
    /// The attempt's result: it ends (the report acknowledged once the outcome is
    /// recorded).
    Ended(StepOutcome, ResultReport),
    /// The attempt's provider says its move has left the move's origin (`departed`):
    /// the attempt goes on, waiting for the move's result. A move's task releases the
    /// origin's place, then acknowledges the report; any other acknowledges it.
    Departed(ResultReport),
}

/// What a message in the inbox means for the attempt waiting on `provider` with
/// `conversation_id`, having booked `worked_with` over the order's life. Pure:
///
/// | message | condition, in order | verdict |
/// |---|---|---|
/// | `departed` | another conversation, or another provider | acknowledged, ignored (never repeated by its sender) |
/// | `departed` | this attempt's, from its provider | [`Verdict::Departed`]: the attempt goes on |
/// | `done` / `failed` | another conversation, from a resource the order booked | acknowledged, ignored (a duplicate, or a late report of an abandoned attempt) |
/// | `done` / `failed` | another conversation, from any other | refused `not_booked` |
/// | `done` / `failed` | this conversation, from another provider | refused `not_booked` |
/// | `done` | this attempt's | [`StepOutcome::Done`] with its results |
/// | `failed` | this attempt's | [`StepOutcome::Failed`] with its reason and detail (one that never reached the controller, `withdrawn` say, is booked again, not counted: [`crate::progress`]) |
/// | anything else | | refused `wrong_key` ([`Inboxes::route`] lets no other through) |
#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    /// The attempt's result: it ends.
    Ended(StepOutcome),
    /// The attempt's transporter says the move left its origin: the attempt goes on.
    Departed,
    /// Not this attempt's: acknowledged (its sender stops delivering it) and ignored,
    /// for the reason given.
    Ignored(String),
    /// Refused with an error reply (the resource logs it and retries).
    Refused(schemas::ErrorCode, String),
}

/// The verdict on `message` (see [`Verdict`]'s table).
pub fn verdict(
    message: &Service,
    provider: &HolonId,
    worked_with: &std::collections::BTreeSet<HolonId>,
    conversation_id: &str,
) -> Verdict {
    let from = message
        .provider
        .as_ref()
        .map(|p| p.to_string())
        .unwrap_or_default();
    match message.message_type {
        MessageType::Departed => {
            // Never repeated, never a result: a departure not of this attempt (a late
            // one of an earlier move, one from a transporter this attempt did not
            // book) is only acknowledged, whoever sent it.
            return if message.conversation_id != conversation_id {
                Verdict::Ignored(format!(
                    "a departure of {} while waiting on {conversation_id}",
                    message.conversation_id
                ))
            } else if message.provider.as_ref() != Some(provider) {
                Verdict::Ignored(format!(
                    "a departure from {from:?}, while {conversation_id} is booked on {provider}"
                ))
            } else {
                Verdict::Departed
            };
        }
        MessageType::Done | MessageType::Failed => {}
        other => {
            return Verdict::Refused(
                schemas::ErrorCode::WrongKey,
                format!("{other} is not for this inbox"),
            )
        }
    }
    if message.conversation_id != conversation_id {
        // A duplicate of a recorded result, or a late report of an abandoned attempt:
        // acknowledged (no effect) if it comes from a resource this order booked,
        // refused otherwise.
        return if message
            .provider
            .as_ref()
            .is_some_and(|p| worked_with.contains(p))
        {
            Verdict::Ignored("a result of an earlier conversation".into())
        } else {
            Verdict::Refused(
                schemas::ErrorCode::NotBooked,
                "this order never booked that resource".into(),
            )
        };
    }
    if message.provider.as_ref() != Some(provider) {
        // Only the resource this attempt booked reports its result.
        return Verdict::Refused(
            schemas::ErrorCode::NotBooked,
            format!("{conversation_id} is booked on {provider}, not {from:?}"),
        );
    }
    let from = provider.clone();
    Verdict::Ended(match message.message_type {
        MessageType::Done => StepOutcome::Done {
            provider: from,
            results: message
                .info
                .get("results")
                .and_then(|r| r.as_object())
                .cloned()
                .unwrap_or_default(),
        },
        _ => StepOutcome::Failed {
            provider: from,
            reason: message
                .reason
                .as_ref()
                .map_or_else(|| "failed".to_string(), Reason::to_string),
            // The resource's words beyond the reason (the controller's, where it had
            // any): what the operator reads of the attempt and of a failed order.
            detail: message
                .info
                .get("detail")
                .and_then(|d| d.as_str())
                .filter(|d| !d.is_empty())
                .map(|d| schemas::bounded_detail(d.to_string())),
        },
    })
}

/// What a message in the inbox means for the attempt waiting on `provider` with
/// `conversation_id` ([`verdict`]): its outcome (with the report, to acknowledge once
/// recorded), a departure of its move (the attempt goes on), or `None` when it is not
/// this attempt's (then it was acknowledged or refused here).
pub async fn judge(
    report: ResultReport,
    provider: &HolonId,
    worked_with: &std::collections::BTreeSet<HolonId>,
    conversation_id: &str,
) -> Option<Judged> {
    match verdict(&report.message, provider, worked_with, conversation_id) {
        Verdict::Ended(outcome) => Some(Judged::Ended(outcome, report)),
        Verdict::Departed => Some(Judged::Departed(report)),
        Verdict::Ignored(why) => {
            let message = &report.message;
            info!(holon = %message.requester, conversation_id = %message.conversation_id, message_type = %message.message_type, current = %conversation_id, "{why}: acknowledged and ignored");
            report.acknowledge().await;
            None
        }
        Verdict::Refused(code, why) => {
            let message = &report.message;
            warn!(holon = %message.requester, conversation_id = %message.conversation_id, message_type = %message.message_type, current = %conversation_id, booked = %provider, "refused: {why}");
            report.refuse(code, why).await;
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_the_order_of_an_inbox_key() {
        assert_eq!(
            order_name("holarchy/demo/order/orders1-7/inbox"),
            Some("orders1-7")
        );
        assert_eq!(order_name("holarchy/demo/order/orders1-7/state"), None);
    }

    fn conveyor() -> HolonId {
        HolonId::resource("conveyor1").unwrap()
    }

    /// A report to order `o-1` of `kind` for `conversation`, from `provider`.
    fn report(kind: MessageType, conversation: &str, provider: &HolonId) -> Service {
        let mut message = Service::request(
            kind,
            "transport",
            conversation,
            HolonId::order("o-1").unwrap(),
        );
        message.provider = Some(provider.clone());
        message
    }

    fn booked() -> std::collections::BTreeSet<HolonId> {
        [conveyor()].into_iter().collect()
    }

    #[test]
    fn a_departure_of_the_attempts_move_lets_it_go_on() {
        let departed = report(MessageType::Departed, "o-1/m1/1", &conveyor());
        assert_eq!(
            verdict(&departed, &conveyor(), &booked(), "o-1/m1/1"),
            Verdict::Departed
        );
    }

    #[test]
    fn a_departure_is_never_a_result_nor_refused() {
        let other = HolonId::resource("mover1").unwrap();
        // Of an earlier move, from a transporter the order never booked, or not from
        // the attempt's: acknowledged and ignored (its sender does not send it again).
        for (departed, provider) in [
            (
                report(MessageType::Departed, "o-1/m0/1", &conveyor()),
                conveyor(),
            ),
            (
                report(MessageType::Departed, "o-1/m0/1", &other),
                conveyor(),
            ),
            (
                report(MessageType::Departed, "o-1/m1/1", &other),
                conveyor(),
            ),
            (
                report(MessageType::Departed, "o-1/m1/1", &conveyor()),
                other.clone(),
            ),
        ] {
            let judged = verdict(&departed, &provider, &booked(), "o-1/m1/1");
            assert!(matches!(judged, Verdict::Ignored(_)), "{judged:?}");
        }
        // Waiting on a station's step, a departure ends nothing.
        let robot = HolonId::resource("robot1").unwrap();
        let departed = report(MessageType::Departed, "o-1/m1/1", &conveyor());
        assert!(matches!(
            verdict(&departed, &robot, &booked(), "o-1/2/1"),
            Verdict::Ignored(_)
        ));
    }

    #[test]
    fn results_are_judged_as_before() {
        let done = report(MessageType::Done, "o-1/m1/1", &conveyor());
        assert!(matches!(
            verdict(&done, &conveyor(), &booked(), "o-1/m1/1"),
            Verdict::Ended(StepOutcome::Done { .. })
        ));
        let mut failed = report(MessageType::Failed, "o-1/m1/1", &conveyor());
        failed.reason = Some(Reason::ControllerError);
        assert!(matches!(
            verdict(&failed, &conveyor(), &booked(), "o-1/m1/1"),
            Verdict::Ended(StepOutcome::Failed { .. })
        ));
        failed.reason = Some(Reason::Withdrawn);
        assert!(matches!(
            verdict(&failed, &conveyor(), &booked(), "o-1/m1/1"),
            Verdict::Ended(StepOutcome::Failed { reason, .. }) if reason == "withdrawn"
        ));
        // A duplicate of an earlier conversation from a booked resource: ignored;
        // from one never booked, or from another than the attempt's: refused.
        assert!(matches!(
            verdict(&done, &conveyor(), &booked(), "o-1/m2/1"),
            Verdict::Ignored(_)
        ));
        let stranger = HolonId::resource("mover1").unwrap();
        let foreign = report(MessageType::Done, "o-1/m1/1", &stranger);
        assert!(matches!(
            verdict(&foreign, &conveyor(), &booked(), "o-1/m2/1"),
            Verdict::Refused(schemas::ErrorCode::NotBooked, _)
        ));
        assert!(matches!(
            verdict(&foreign, &conveyor(), &booked(), "o-1/m1/1"),
            Verdict::Refused(schemas::ErrorCode::NotBooked, _)
        ));
        // Nothing else is a result (the inbox lets none through: checked here too).
        let status = report(MessageType::Status, "o-1/m1/1", &conveyor());
        assert!(matches!(
            verdict(&status, &conveyor(), &booked(), "o-1/m1/1"),
            Verdict::Refused(schemas::ErrorCode::WrongKey, _)
        ));
    }
}

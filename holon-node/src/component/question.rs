//! A query waiting for its answer: the zenoh query and the key its answer goes out on.
//!
//! The communication component answers what it can itself (malformed or misaddressed
//! requests, state reads); a request for the agenda travels with its question to the
//! agenda manager, which answers it once the agenda has changed and the change is
//! recorded. Whoever answers logs a failed reply with what it means: the requester
//! gets no answer and asks again after its timeout.

use schemas::{ErrorCode, ErrorReply, HolonId, MessageType, Service};
use tracing::{debug, info, warn};
use zenoh::query::Query;

pub struct Question {
    /// The query, answered once.
    query: Query,
    /// The key of the queryable it came to (e.g. `resource/robot1/service`): answers go
    /// out on it, so a client with zenoh's default consolidation keeps one answer per
    /// resource, and access control can check that an answer comes from the resource
    /// whose key it carries.
    key: String,
}

impl Question {
    pub fn new(query: Query, key: String) -> Question {
        Question { query, key }
    }

    /// The key the query was sent to (may be a wildcard).
    pub fn asked_key(&self) -> &str {
        self.query.key_expr().as_str()
    }

    /// Who asks, as the query's attachment says ([`schemas::requested_by`]).
    pub fn requested_by(&self) -> Option<String> {
        self.query
            .attachment()
            .and_then(|a| schemas::requested_by(&a.to_bytes()))
    }

    /// The request's bytes (empty when it has none).
    pub fn payload(&self) -> Vec<u8> {
        self.query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default()
    }

    /// Answers with a Service message.
    pub async fn answer(self, holon: &HolonId, message: &Service) {
        // One line at `info` per commitment (a booking made or cancelled, a job started);
        // proposals, refusals and status reads are many and go at `debug`. Logging every
        // request at `info` cost about a tenth of a booking's CPU (profiled).
        let commitment = message.result == Some(true)
            && matches!(
                message.message_type,
                MessageType::BookingReq | MessageType::BookingCancel | MessageType::Start
            );
        macro_rules! sent {
            ($level:ident) => {
                $level!(
                    holon = %holon,
                    conversation_id = %message.conversation_id,
                    message_type = %message.message_type,
                    requester = %message.requester,
                    result = message.result.map_or("", |r| if r { "true" } else { "false" }),
                    reason = message.reason.as_ref().map_or("", |r| r.as_str()),
                    "sent"
                )
            };
        }
        // Sent first, then logged: the line is not in the requester's round trip.
        if let Err(e) = self.query.reply(self.key.as_str(), message.to_json()).await {
            warn!(%holon, conversation_id = %message.conversation_id, message_type = %message.message_type, error = %e, "cannot send the reply; the requester asks again after its timeout");
            return;
        }
        if commitment {
            sent!(info);
        } else {
            sent!(debug);
        }
    }

    /// Answers with raw bytes (a state snapshot, a fault-injection acknowledgement).
    pub async fn answer_bytes(self, holon: &HolonId, what: &str, payload: Vec<u8>) {
        if let Err(e) = self.query.reply(self.key.as_str(), payload).await {
            warn!(%holon, what, error = %e, "cannot send the reply; the asker gets none");
        }
    }

    /// Rejects the query with an error reply (`{"code", "message"}`).
    pub async fn reject(self, holon: &HolonId, code: ErrorCode, message: String) {
        warn!(%holon, key = %self.query.key_expr(), %code, error = %message, "request rejected");
        if let Err(e) = self
            .query
            .reply_err(ErrorReply::new(code.clone(), message).to_json())
            .await
        {
            warn!(%holon, %code, error = %e, "cannot send the error reply; the requester asks again after its timeout");
        }
    }
}

impl Question {
    /// Rejects the query at once, without awaiting: for a queryable's callback, which
    /// must not block (the queue behind it is full).
    pub fn reject_now(self, holon: &HolonId, code: ErrorCode, message: String) {
        use zenoh::Wait;
        warn!(%holon, key = %self.query.key_expr(), %code, error = %message, "request rejected");
        if let Err(e) = self
            .query
            .reply_err(ErrorReply::new(code.clone(), message).to_json())
            .wait()
        {
            warn!(%holon, %code, error = %e, "cannot send the error reply; the requester asks again after its timeout");
        }
    }
}

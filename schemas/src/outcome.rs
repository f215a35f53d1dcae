//! What became of a conversation: an order asks the resource it booked, on
//! `resource/<name>/outcome`, before it gives up on a step that may have run
//! (docs/reliability.md, "Standby resources"; docs/architecture.md, "Conversations").
//!
//! The resource answers from its own agenda and journal when it knows the conversation,
//! and a fenced resource that does not (a standby that took over from a dead holder)
//! asks its controller the state of each step id `<conversation>#<index>` of the
//! service type's steps. The answer is one of [`Outcome`]'s words.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::id::{validate_name, HolonId};
use crate::service::{MAX_CONVERSATION_ID_LEN, MAX_SERVICE_BYTES, SERVICE_VERSION};
use crate::vocabulary::Reason;
use crate::SchemaError;

/// What became of a conversation, as the resource asked knows it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Outcome {
    /// The job ran to its end: `results` holds each step's result, as a `done` would.
    Done,
    /// The job ended failed (`reason`, `detail`), or ran in part and was interrupted.
    Failed,
    /// Not ended: it runs (on the resource or, after a failover, on the controller), or
    /// waits its turn on the agenda. Its result is still to come: ask again later.
    Running,
    /// No step of it reached the controller: nothing ran, it is safe to book it again.
    NeverReached,
    /// The resource cannot tell (it does not know the conversation and has no fenced
    /// controller to ask, or the controller did not answer): the order goes on as it
    /// would without an answer.
    Unknown,
}

impl Outcome {
    pub fn as_str(self) -> &'static str {
        match self {
            Outcome::Done => "done",
            Outcome::Failed => "failed",
            Outcome::Running => "running",
            Outcome::NeverReached => "never_reached",
            Outcome::Unknown => "unknown",
        }
    }
}

impl std::fmt::Display for Outcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Where an [`OutcomeReply`] comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum OutcomeSource {
    /// The resource's own agenda and journal (bookings, the job running, results not
    /// yet acknowledged).
    Journal,
    /// The controller's step states (`STEP_STATUS`), for a fenced resource that does
    /// not know the conversation.
    Controller,
    /// Nowhere: the outcome is `unknown`.
    Nowhere,
}

/// The question, on `resource/<name>/outcome`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct OutcomeRequest {
    /// Schema version, 1.
    pub v: u32,
    /// The conversation asked about, e.g. `orders1-3/2/1`.
    pub conversation_id: String,
    /// Its service type: the resource counts the steps (and their step ids) by it.
    pub service_type: String,
    /// Who asks (the order that booked it).
    pub requester: HolonId,
}

impl OutcomeRequest {
    pub fn new(conversation_id: &str, service_type: &str, requester: HolonId) -> OutcomeRequest {
        OutcomeRequest {
            v: SERVICE_VERSION,
            conversation_id: conversation_id.to_string(),
            service_type: service_type.to_string(),
            requester,
        }
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("an OutcomeRequest always serializes")
    }

    /// Decodes and checks a request (version, service type, conversation id).
    pub fn from_json(payload: &[u8]) -> Result<OutcomeRequest, SchemaError> {
        if payload.len() > MAX_SERVICE_BYTES {
            return Err(SchemaError::TooLarge {
                size: payload.len(),
                limit: MAX_SERVICE_BYTES,
            });
        }
        let request: OutcomeRequest =
            serde_json::from_slice(payload).map_err(|e| SchemaError::Json(e.to_string()))?;
        if request.v != SERVICE_VERSION {
            return Err(SchemaError::UnsupportedVersion(request.v));
        }
        validate_name("service type", &request.service_type)?;
        let id = &request.conversation_id;
        if id.is_empty() || id.len() > MAX_CONVERSATION_ID_LEN || id.chars().any(|c| c.is_control())
        {
            return Err(SchemaError::InvalidField {
                field: "conversation_id",
                why: "must be 1 to 128 bytes, no control characters".into(),
            });
        }
        Ok(request)
    }

    /// The answer `outcome`, from `provider`, with nothing else said.
    pub fn answer(&self, provider: &HolonId, outcome: Outcome) -> OutcomeReply {
        OutcomeReply {
            v: SERVICE_VERSION,
            conversation_id: self.conversation_id.clone(),
            provider: provider.clone(),
            outcome,
            results: serde_json::Map::new(),
            reason: None,
            detail: None,
            source: OutcomeSource::Nowhere,
            epoch: None,
        }
    }
}

/// The answer to an [`OutcomeRequest`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct OutcomeReply {
    /// Schema version, 1.
    pub v: u32,
    /// The conversation asked about.
    pub conversation_id: String,
    /// The resource that answers.
    pub provider: HolonId,
    pub outcome: Outcome,
    /// With `done`: each step's result by its action, as a `done`'s `info.results`.
    #[serde(default, skip_serializing_if = "serde_json::Map::is_empty")]
    pub results: serde_json::Map<String, serde_json::Value>,
    /// With `failed`: why, as a `failed`'s `reason`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "Option<String>")]
    pub reason: Option<Reason>,
    /// With `failed`: the controller's message, if any (bounded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detail: Option<String>,
    /// Whether the resource knew it (`journal`) or asked its controller (`controller`).
    pub source: OutcomeSource,
    /// A fenced resource's epoch (the holder that answers).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub epoch: Option<u64>,
}

impl OutcomeReply {
    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("an OutcomeReply always serializes")
    }

    pub fn from_json(payload: &[u8]) -> Result<OutcomeReply, SchemaError> {
        if payload.len() > MAX_SERVICE_BYTES {
            return Err(SchemaError::TooLarge {
                size: payload.len(),
                limit: MAX_SERVICE_BYTES,
            });
        }
        serde_json::from_slice(payload).map_err(|e| SchemaError::Json(e.to_string()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request() -> OutcomeRequest {
        OutcomeRequest::new(
            "orders1-3/1/1",
            "pick_n_place",
            HolonId::order("orders1-3").unwrap(),
        )
    }

    #[test]
    fn outcomes_are_snake_case_words() {
        for (outcome, word) in [
            (Outcome::Done, "done"),
            (Outcome::Failed, "failed"),
            (Outcome::Running, "running"),
            (Outcome::NeverReached, "never_reached"),
            (Outcome::Unknown, "unknown"),
        ] {
            assert_eq!(serde_json::to_value(outcome).unwrap(), word);
            assert_eq!(outcome.as_str(), word);
            let back: Outcome = serde_json::from_value(word.into()).unwrap();
            assert_eq!(back, outcome);
        }
        assert!(serde_json::from_value::<Outcome>("maybe".into()).is_err());
    }

    #[test]
    fn a_request_round_trips_and_bad_ones_are_refused() {
        let asked = request();
        assert_eq!(OutcomeRequest::from_json(&asked.to_json()).unwrap(), asked);
        let good = serde_json::to_value(&asked).unwrap();
        for (field, value) in [
            ("v", serde_json::json!(2)),
            ("conversation_id", serde_json::json!("")),
            ("conversation_id", serde_json::json!("a\nb")),
            ("service_type", serde_json::json!("Pick")),
            ("requester", serde_json::json!("nobody")),
            ("extra", serde_json::json!(1)),
        ] {
            let mut bad = good.clone();
            bad[field] = value.clone();
            let bytes = serde_json::to_vec(&bad).unwrap();
            assert!(
                OutcomeRequest::from_json(&bytes).is_err(),
                "{field} = {value} accepted"
            );
        }
    }

    #[test]
    fn a_reply_says_only_what_it_has() {
        let robot = HolonId::resource("robot1").unwrap();
        let mut done = request().answer(&robot, Outcome::Done);
        done.results.insert("pick".into(), "picking_done".into());
        done.source = OutcomeSource::Controller;
        done.epoch = Some(2);
        let value: serde_json::Value = serde_json::from_slice(&done.to_json()).unwrap();
        assert_eq!(value["outcome"], "done");
        assert_eq!(value["source"], "controller");
        assert_eq!(value["results"]["pick"], "picking_done");
        assert!(value.get("reason").is_none());
        assert_eq!(OutcomeReply::from_json(&done.to_json()).unwrap(), done);
        let mut failed = request().answer(&robot, Outcome::Failed);
        failed.reason = Some(Reason::Interrupted);
        let value: serde_json::Value = serde_json::from_slice(&failed.to_json()).unwrap();
        assert_eq!(value["reason"], "interrupted");
        assert!(value.get("results").is_none());
    }
}

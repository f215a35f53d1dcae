//! The Service message (the seed's `#service{}` record) and the error reply.

use std::fmt;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::id::{validate_name, HolonId};
use crate::keys::validate_reply_key;
use crate::vocabulary::{ErrorCode, Reason};
use crate::SchemaError;

/// The schema version this crate reads and writes.
pub const SERVICE_VERSION: u32 = 1;

/// The largest Service payload a holon accepts.
pub const MAX_SERVICE_BYTES: usize = 64 * 1024;

/// The longest `conversation_id` we accept.
pub const MAX_CONVERSATION_ID_LEN: usize = 128;

/// The most bytes of free text (a controller's error message, in `info.detail`) a holon
/// puts in a message; longer text is cut at a character boundary and marked.
pub const MAX_DETAIL_BYTES: usize = 1024;

/// `text` bounded to [`MAX_DETAIL_BYTES`]: unchanged when it fits, else cut and ending
/// in `... [truncated: N bytes in all]`.
pub fn bounded_detail(text: String) -> String {
    if text.len() <= MAX_DETAIL_BYTES {
        return text;
    }
    let total = text.len();
    let mark = format!("... [truncated: {total} bytes in all]");
    let mut cut = MAX_DETAIL_BYTES - mark.len();
    while !text.is_char_boundary(cut) {
        cut -= 1;
    }
    format!("{}{mark}", &text[..cut])
}

/// What a Service message asks or answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum MessageType {
    /// Contract net: asks a resource for a proposal (sent to `offer/<type>/*`).
    ProposalReq,
    /// A resource's answer to `proposal_req`: `info` holds its expected wait.
    Proposal,
    /// Asks a resource to add a booking to its agenda.
    BookingReq,
    /// Removes the requester's booking.
    BookingCancel,
    /// Asks a resource to execute a booked service now.
    Start,
    /// The service was executed: sent to `reply_to` until acknowledged.
    Done,
    /// The service failed (`reason` says why): sent to `reply_to` until acknowledged.
    Failed,
    /// Asks a resource for its state; the reply's `info` holds the snapshot.
    Status,
    /// A transporter's move has left its origin (its controller said so): sent once to
    /// `reply_to`, acknowledged there but never repeated; the order may then release
    /// the place it held at the move's `from` (docs/material-flow.md, "Departure").
    Departed,
}

impl MessageType {
    pub fn as_str(self) -> &'static str {
        match self {
            MessageType::ProposalReq => "proposal_req",
            MessageType::Proposal => "proposal",
            MessageType::BookingReq => "booking_req",
            MessageType::BookingCancel => "booking_cancel",
            MessageType::Start => "start",
            MessageType::Done => "done",
            MessageType::Failed => "failed",
            MessageType::Status => "status",
            MessageType::Departed => "departed",
        }
    }
}

impl fmt::Display for MessageType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// Keys of `info` with a meaning to the agenda itself (every other key is service data).
pub mod info_key {
    /// On a `booking_req`: `true` asks the resource to start the job by itself when its
    /// turn comes (at once if it is free and nothing is booked ahead), so one request
    /// books and starts. Such a booking must carry `reply_to` and the info its steps
    /// need. A resource that does not know the key books as usual and waits for `start`.
    pub const START_ON_TURN: &str = "start_on_turn";
    /// On a booking reply: `true` when the job has begun (a `start` would be answered
    /// true again); absent when it waits for its turn.
    pub const STARTED: &str = "started";
    /// On a `proposal_req` or `booking_req`: the order's priority, an integer from
    /// [`super::MIN_PRIORITY`] to [`super::MAX_PRIORITY`] (absent: 0; higher is more
    /// urgent). A booking not yet started goes ahead of waiting bookings of lower
    /// priority, each of which it may pass only while it has been passed fewer than
    /// `agenda.max_overtakes` times (no starvation); a proposal's figures say where it
    /// would stand.
    pub const PRIORITY: &str = "priority";
    /// On a `proposal_req` or `booking_req`: when the order is due, in Unix
    /// milliseconds. The agenda keeps and shows it; a staff holon plans by it.
    pub const DUE: &str = "due";
    /// On a refusal `unavailable`: when to ask again, in ms (set while the resource is
    /// handed over to its successor during an upgrade).
    pub const RETRY_AFTER_MS: &str = "retry_after_ms";
    /// On a `booking_req`, `start` or `booking_cancel` of an order hosted by an
    /// order-node on etcd: the epoch at which that order-node holds its leader key (a
    /// `start` is journalled at that epoch before it is sent). The resource keeps the
    /// highest it has seen with the booking and refuses `stale_epoch` a request of a
    /// lower one: it comes from a deposed holder of the order-node.
    pub const EPOCH: &str = "epoch";
    /// On a booking of a move (a transporter's) or of a place ([`super::PLACE_SERVICE`]):
    /// the part, by its order's name (`o-1-3`).
    pub const PART: &str = "part";
    /// On a booking of a move: where the part is (a location id, `robot1.port`).
    pub const FROM: &str = "from";
    /// On a booking of a move: where the part goes.
    pub const TO: &str = "to";
    /// On a booking of a place ([`super::PLACE_SERVICE`]): the location, one of the
    /// resource's own.
    pub const LOCATION: &str = "location";
}

/// The service every resource that states locations in its layout answers, without
/// offering it: a booking of `place` with `info.part` and `info.location` reserves a
/// place for the part at that location (one of the resource's own), refused
/// `no_place` when all its places are held; its `booking_cancel` releases it. A place
/// is never started, and it outlasts its requester's absence, a withdrawal and a
/// restart (the part is physically there): only its requester (or an operator)
/// releases it (docs/material-flow.md, "Reservations").
pub const PLACE_SERVICE: &str = "place";

/// The most urgent priority a work order may have.
pub const MAX_PRIORITY: i32 = 1000;
/// The least urgent priority a work order may have.
pub const MIN_PRIORITY: i32 = -1000;

/// The Service message: one per zenoh payload, JSON, UTF-8.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
#[schemars(
    title = "Service",
    description = "holarchy's Service message (the seed's #service{} record), schema version 1."
)]
pub struct Service {
    /// Schema version, 1.
    pub v: u32,
    pub message_type: MessageType,
    /// The service type, e.g. `pick_n_place`, `inspect`, `transport`.
    #[schemars(regex(pattern = r"^[a-z0-9][a-z0-9_-]*$"), length(max = 64))]
    pub service_type: String,
    /// One per order step and attempt, e.g. `o-17/2/1`; replies carry it back.
    #[schemars(length(min = 1, max = 128))]
    pub conversation_id: String,
    /// The holon that asks (the seed's requester_pid), e.g. `order/o-17`.
    pub requester: HolonId,
    /// The holon that provides (the seed's provider_pid), e.g. `resource/robot1`.
    #[serde(default)]
    pub provider: Option<HolonId>,
    /// Where later results (`done`, `failed`) go: the requester's inbox key expression.
    #[serde(default)]
    #[schemars(regex(pattern = r"^holarchy/[^*$?#\s]+$"), length(max = 512))]
    pub reply_to: Option<String>,
    /// The seed's Boolean result; null in requests.
    #[serde(default)]
    pub result: Option<bool>,
    /// Why `result` is false: `not_booked`, `busy`, `unavailable`, `unknown_service`, ...
    #[serde(default)]
    #[schemars(with = "Option<String>")]
    pub reason: Option<Reason>,
    /// Service data, e.g. `{"pick": {"x":..}, "place": {..}}`; on replies, e.g. queue position.
    #[serde(default)]
    pub info: serde_json::Map<String, serde_json::Value>,
}

impl Service {
    /// A request with the fields every request has; the rest defaults to null / `{}`.
    pub fn request(
        message_type: MessageType,
        service_type: &str,
        conversation_id: &str,
        requester: HolonId,
    ) -> Service {
        Service {
            v: SERVICE_VERSION,
            message_type,
            service_type: service_type.to_string(),
            conversation_id: conversation_id.to_string(),
            requester,
            provider: None,
            reply_to: None,
            result: None,
            reason: None,
            info: serde_json::Map::new(),
        }
    }

    pub fn with_reply_to(mut self, reply_to: impl Into<String>) -> Self {
        self.reply_to = Some(reply_to.into());
        self
    }

    pub fn with_info(mut self, info: serde_json::Map<String, serde_json::Value>) -> Self {
        self.info = info;
        self
    }

    /// Asks, on a `booking_req`, for the job to start by itself on its turn
    /// ([`info_key::START_ON_TURN`]).
    pub fn with_start_on_turn(mut self) -> Self {
        self.info.insert(
            info_key::START_ON_TURN.into(),
            serde_json::Value::Bool(true),
        );
        self
    }

    /// The same request carrying an order's priority (when not 0) and due time
    /// ([`info_key::PRIORITY`], [`info_key::DUE`]).
    pub fn with_urgency(mut self, priority: i32, due: Option<u64>) -> Self {
        if priority != 0 {
            self.info
                .insert(info_key::PRIORITY.into(), serde_json::Value::from(priority));
        }
        if let Some(due) = due {
            self.info
                .insert(info_key::DUE.into(), serde_json::Value::from(due));
        }
        self
    }

    /// When a refusal asks to be asked again ([`info_key::RETRY_AFTER_MS`], set by a
    /// resource being handed over), clamped to 10 ms..5 s; `None` when it does not say.
    pub fn retry_after(&self) -> Option<std::time::Duration> {
        self.info
            .get(info_key::RETRY_AFTER_MS)
            .and_then(|v| v.as_u64())
            .map(|ms| std::time::Duration::from_millis(ms.clamp(10, 5000)))
    }

    /// The request's priority ([`info_key::PRIORITY`]): 0 when absent, an error
    /// saying why when it is not an integer in range.
    pub fn priority(&self) -> Result<i32, String> {
        match self.info.get(info_key::PRIORITY) {
            None => Ok(0),
            Some(value) => value
                .as_i64()
                .filter(|p| (MIN_PRIORITY as i64..=MAX_PRIORITY as i64).contains(p))
                .map(|p| p as i32)
                .ok_or_else(|| {
                    format!(
                        "info.priority must be an integer from {MIN_PRIORITY} to {MAX_PRIORITY}, not {value}"
                    )
                }),
        }
    }

    /// The request's due time in Unix milliseconds ([`info_key::DUE`]), if it has
    /// one; an error saying why when it is not a whole number.
    pub fn due(&self) -> Result<Option<u64>, String> {
        match self.info.get(info_key::DUE) {
            None => Ok(None),
            Some(value) => value.as_u64().map(Some).ok_or_else(|| {
                format!("info.due must be a time in Unix milliseconds, not {value}")
            }),
        }
    }

    /// The epoch of the order-node that sent this request ([`info_key::EPOCH`]), if it
    /// says; an error saying why when it is not a whole number.
    pub fn epoch(&self) -> Result<Option<u64>, String> {
        match self.info.get(info_key::EPOCH) {
            None => Ok(None),
            Some(value) => value
                .as_u64()
                .map(Some)
                .ok_or_else(|| format!("info.epoch must be a whole number, not {value}")),
        }
    }

    /// The same request carrying the epoch of the order-node that sends it, when it has
    /// one ([`info_key::EPOCH`]).
    pub fn with_epoch(mut self, epoch: Option<u64>) -> Self {
        if let Some(epoch) = epoch {
            self.info
                .insert(info_key::EPOCH.into(), serde_json::Value::from(epoch));
        }
        self
    }

    /// Whether this request's `info` holds service data, not only the epoch of its
    /// sender: a `start` without any runs with its booking's.
    pub fn has_service_data(&self) -> bool {
        self.info.keys().any(|key| key != info_key::EPOCH)
    }

    /// Whether this `booking_req` asks to start on its turn.
    pub fn start_on_turn(&self) -> bool {
        self.info.get(info_key::START_ON_TURN) == Some(&serde_json::Value::Bool(true))
    }

    /// Whether this booking reply says the job has begun ([`info_key::STARTED`]).
    pub fn started(&self) -> bool {
        self.result == Some(true)
            && self.info.get(info_key::STARTED) == Some(&serde_json::Value::Bool(true))
    }

    /// The answer to this message: same conversation, `provider` set, `result` true.
    pub fn accepted(&self, provider: &HolonId) -> Service {
        let mut reply = self.clone();
        reply.provider = Some(provider.clone());
        reply.result = Some(true);
        reply.reason = None;
        reply
    }

    /// The answer to this message with `result` false and a reason.
    pub fn refused(&self, provider: &HolonId, reason: Reason) -> Service {
        let mut reply = self.accepted(provider);
        reply.result = Some(false);
        reply.reason = Some(reason);
        reply
    }

    /// Decodes and validates a payload. Errors say what is wrong, for the error reply.
    pub fn from_json(payload: &[u8]) -> Result<Service, SchemaError> {
        if payload.len() > MAX_SERVICE_BYTES {
            return Err(SchemaError::TooLarge {
                size: payload.len(),
                limit: MAX_SERVICE_BYTES,
            });
        }
        let service: Service =
            serde_json::from_slice(payload).map_err(|e| SchemaError::Json(e.to_string()))?;
        service.validate()?;
        Ok(service)
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("a Service always serializes")
    }

    /// Checks what serde cannot: version, names, lengths, the reply key.
    pub fn validate(&self) -> Result<(), SchemaError> {
        if self.v != SERVICE_VERSION {
            return Err(SchemaError::UnsupportedVersion(self.v));
        }
        validate_name("service type", &self.service_type)?;
        let id = &self.conversation_id;
        if id.is_empty() || id.len() > MAX_CONVERSATION_ID_LEN {
            return Err(SchemaError::InvalidField {
                field: "conversation_id",
                why: "must be 1 to 128 bytes".into(),
            });
        }
        if id.chars().any(|c| c.is_control()) {
            return Err(SchemaError::InvalidField {
                field: "conversation_id",
                why: "control characters are not allowed".into(),
            });
        }
        if let Some(key) = &self.reply_to {
            validate_reply_key(key)?;
        }
        Ok(())
    }
}

/// The body of an error reply (`reply_err`): a request that could not be decoded or is
/// not allowed. The holon changes nothing.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct ErrorReply {
    /// A stable code: `malformed`, `unsupported_version`, `invalid`, `wrong_key`,
    /// `internal`, `unavailable`, ...
    #[schemars(with = "String")]
    pub code: ErrorCode,
    /// What was wrong, for a person.
    pub message: String,
    /// With `unavailable`: when to ask again, in ms (e.g. while the holon is handed over
    /// to its successor during an upgrade).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub retry_after_ms: Option<u64>,
}

impl ErrorReply {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        ErrorReply {
            code,
            message: message.into(),
            retry_after_ms: None,
        }
    }

    /// `unavailable`, to be asked again after `retry_after`.
    pub fn unavailable(message: impl Into<String>, retry_after: std::time::Duration) -> Self {
        ErrorReply {
            retry_after_ms: Some(retry_after.as_millis() as u64),
            ..ErrorReply::new(ErrorCode::Unavailable, message)
        }
    }

    /// The code for a message that `from_json` refused: `unsupported_version` when it
    /// speaks another schema version, `malformed` when it cannot be read, `invalid`
    /// when a field is wrong.
    pub fn for_schema_error(error: &crate::SchemaError) -> Self {
        let code = match error {
            crate::SchemaError::UnsupportedVersion(_) => ErrorCode::UnsupportedVersion,
            crate::SchemaError::Json(_) | crate::SchemaError::TooLarge { .. } => {
                ErrorCode::Malformed
            }
            _ => ErrorCode::Invalid,
        };
        ErrorReply::new(code, error.to_string())
    }

    /// Reads an error reply's body (None when it is not one).
    pub fn from_json(payload: &[u8]) -> Option<Self> {
        serde_json::from_slice(payload).ok()
    }

    pub fn to_json(&self) -> Vec<u8> {
        serde_json::to_vec(self).expect("an ErrorReply always serializes")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn booking() -> Service {
        Service::request(
            MessageType::BookingReq,
            "pick_n_place",
            "o-17/2/1",
            HolonId::order("o-17").unwrap(),
        )
        .with_reply_to("holarchy/demo/order/o-17/inbox")
    }

    #[test]
    fn round_trips_through_json() {
        let msg = booking();
        let bytes = msg.to_json();
        assert_eq!(Service::from_json(&bytes).unwrap(), msg);
        let value: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(value["message_type"], "booking_req");
        assert_eq!(value["requester"], "order/o-17");
        assert_eq!(value["provider"], serde_json::Value::Null);
        assert_eq!(value["result"], serde_json::Value::Null);
    }

    #[test]
    fn optional_fields_may_be_left_out() {
        let msg = Service::from_json(
            br#"{"v":1,"message_type":"status","service_type":"pick_n_place",
                 "conversation_id":"c1","requester":"staff/ops"}"#,
        )
        .unwrap();
        assert_eq!(msg.message_type, MessageType::Status);
        assert!(msg.info.is_empty());
    }

    #[test]
    fn rejects_invalid_messages() {
        let good = serde_json::to_value(booking()).unwrap();
        let cases: Vec<(&str, serde_json::Value)> = vec![
            ("v", json!(2)),
            ("message_type", json!("book")),
            ("service_type", json!("Pick")),
            ("conversation_id", json!("")),
            ("conversation_id", json!("x".repeat(129))),
            ("conversation_id", json!("a\nb")),
            ("requester", json!("o-17")),
            ("provider", json!("robot")),
            ("reply_to", json!("holarchy/demo/order/*/inbox")),
            ("reply_to", json!("elsewhere/inbox")),
            ("result", json!("yes")),
            ("info", json!([1, 2])),
            ("extra", json!(1)),
        ];
        for (field, value) in cases {
            let mut msg = good.clone();
            msg[field] = value.clone();
            let bytes = serde_json::to_vec(&msg).unwrap();
            assert!(
                Service::from_json(&bytes).is_err(),
                "{field} = {value} was accepted"
            );
        }
        for missing in [
            "v",
            "message_type",
            "service_type",
            "conversation_id",
            "requester",
        ] {
            let mut msg = good.clone();
            msg.as_object_mut().unwrap().remove(missing);
            let bytes = serde_json::to_vec(&msg).unwrap();
            assert!(Service::from_json(&bytes).is_err(), "without {missing}");
        }
        assert!(Service::from_json(b"not json").is_err());
        assert!(Service::from_json(&vec![b' '; MAX_SERVICE_BYTES + 1]).is_err());
    }

    #[test]
    fn replies_keep_the_conversation() {
        let robot = HolonId::resource("robot1").unwrap();
        let msg = booking();
        let yes = msg.accepted(&robot);
        assert_eq!(yes.result, Some(true));
        assert_eq!(yes.provider.as_ref(), Some(&robot));
        assert_eq!(yes.conversation_id, msg.conversation_id);
        let no = msg.refused(&robot, Reason::Busy);
        assert_eq!(no.result, Some(false));
        assert_eq!(no.reason, Some(Reason::Busy));
    }

    #[test]
    fn detail_text_is_bounded_and_marked() {
        assert_eq!(bounded_detail("gripper empty".into()), "gripper empty");
        let long = "\"é".repeat(40_000);
        let bounded = bounded_detail(long.clone());
        assert!(bounded.len() <= MAX_DETAIL_BYTES, "{}", bounded.len());
        assert!(
            bounded.ends_with(&format!("[truncated: {} bytes in all]", long.len())),
            "{bounded}"
        );
        assert!(long.starts_with(bounded.split("...").next().unwrap()));
    }
}

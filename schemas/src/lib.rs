//! The language-neutral contract of holarchy: the Service message, holon ids, the key
//! space, state snapshots and the robot controller protocol's messages.
//!
//! JSON Schema for the Service message is exported to `schemas/json/service.schema.json`
//! (see [`service_json_schema`]); a test fails when that file is stale.

pub mod advice;
pub mod carrier;
pub mod fence;
pub mod held;
pub mod id;
pub mod keys;
pub mod layout;
pub mod listing;
pub mod outcome;
pub mod packml;
pub mod part;
pub mod plan;
pub mod robot;
pub mod service;
pub mod state;
pub mod time_scale;
pub mod vocabulary;

pub use advice::{Advice, AdviceRequest, ForecastStep, RouteStep, ADVICE_VERSION};
pub use carrier::{carrier_name, CarrierReply, CarrierWord};
pub use fence::{FenceReport, FenceRole};
pub use held::{HeldReply, HeldRequest, MAX_HELD_ASKED};
pub use id::{validate_name, HolonId, HolonKind};
pub use keys::{validate_reply_key, CellKeys};
pub use listing::{
    OrderCounts, OrderFilter, OrderListRequest, OrderPage, PageCursor, LISTING_VERSION,
    MAX_PAGE_BYTES, MAX_PAGE_ORDERS,
};
pub use outcome::{Outcome, OutcomeReply, OutcomeRequest, OutcomeSource};
pub use packml::{
    PackmlCommand, PackmlReply, PackmlRequest, PackmlState, PackmlStatus, Refusal, StopReason,
    UnitMode,
};
pub use part::{PartFound, PartPlace, PartWord, PartWordReply};
pub use plan::{
    requested_by, AttemptEnd, AttemptRecord, CancelReply, OnReject, OrderSnapshot, OrderStatus,
    Plan, PlanStep, SubmitReply, WorkOrder, MAX_ATTEMPT_HISTORY, MAX_REQUESTED_BY,
};
pub use robot::{ControllerState, Pose, RobotCommand, RobotMessage, RobotReply};
pub use service::{
    bounded_detail, info_key, ErrorReply, MessageType, Service, MAX_DETAIL_BYTES, MAX_PRIORITY,
    MIN_PRIORITY, PLACE_SERVICE, SERVICE_VERSION,
};
pub use state::{
    unix_ms, BookingView, ControllerStatus, CurrentJobView, Epochs, ResourceSnapshot, ResourceState,
};
pub use time_scale::TimeScale;
pub use vocabulary::{ErrorCode, Reason};

/// Everything that can be wrong with a message, an id or a key.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SchemaError {
    #[error("invalid {what} {name:?}: {why}")]
    InvalidName {
        what: &'static str,
        name: String,
        why: String,
    },
    #[error("invalid holon id {id:?}: {why}")]
    InvalidHolonId { id: String, why: String },
    #[error("invalid key expression {key:?}: {why}")]
    InvalidKeyExpr { key: String, why: String },
    #[error("invalid {field}: {why}")]
    InvalidField { field: &'static str, why: String },
    #[error("unsupported schema version {0} (this holon speaks version {speaks})", speaks = crate::SERVICE_VERSION)]
    UnsupportedVersion(u32),
    #[error("payload of {size} bytes is over the {limit}-byte limit")]
    TooLarge { size: usize, limit: usize },
    #[error("not a valid message: {0}")]
    Json(String),
}

/// The JSON Schema of the Service message, as checked in at `schemas/json/service.schema.json`.
pub fn service_json_schema() -> String {
    let schema = schemars::schema_for!(Service);
    let mut text = serde_json::to_string_pretty(&schema).expect("a schema serializes");
    text.push('\n');
    text
}

/// The JSON Schema of a staff holon's advice request and reply
/// (`staff/<name>/advice`), checked in as `schemas/json/advice.schema.json`.
pub fn advice_json_schema() -> String {
    let schema = serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "holarchy advice",
        "description": "A staff holon's advice: the request an order sends on staff/<name>/advice, and the reply.",
        "$defs": {
            "AdviceRequest": schemars::schema_for!(AdviceRequest),
            "Advice": schemars::schema_for!(Advice),
        },
    });
    let mut text = serde_json::to_string_pretty(&schema).expect("a schema serializes");
    text.push('\n');
    text
}

/// The JSON Schema of the question on `resource/<name>/outcome` and its answer (what
/// became of a conversation), checked in as `schemas/json/outcome.schema.json`.
pub fn outcome_json_schema() -> String {
    let schema = serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "holarchy outcome",
        "description": "What became of a conversation: the request an order sends on resource/<name>/outcome, and the reply.",
        "$defs": {
            "OutcomeRequest": schemars::schema_for!(OutcomeRequest),
            "OutcomeReply": schemars::schema_for!(OutcomeReply),
        },
    });
    let mut text = serde_json::to_string_pretty(&schema).expect("a schema serializes");
    text.push('\n');
    text
}

/// The JSON Schema of a listing of an order-node's orders (`host/order-node/<name>/orders`,
/// [`listing`]): the request and the page, checked in as
/// `schemas/json/listing.schema.json`.
pub fn listing_json_schema() -> String {
    let schema = serde_json::json!({
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "holarchy order listing",
        "description": "A page of an order-node's orders: the request a reader sends on host/order-node/<name>/orders (an empty payload asks for the first page of every order), and the page the node answers; and which orders a node holds: the question a resource sends on host/order-node/<name>/held (HeldRequest) and the node's answer (HeldReply).",
        "$defs": {
            "OrderListRequest": schemars::schema_for!(OrderListRequest),
            "OrderPage": schemars::schema_for!(OrderPage),
            "HeldRequest": schemars::schema_for!(HeldRequest),
            "HeldReply": schemars::schema_for!(HeldReply),
        },
    });
    let mut text = serde_json::to_string_pretty(&schema).expect("a schema serializes");
    text.push('\n');
    text
}

/// The JSON Schema of a resource's part of the cell's layout
/// (`resource/<name>/layout`, [`layout::LayoutPart`]), checked in as
/// `schemas/json/layout.schema.json`.
pub fn layout_json_schema() -> String {
    let schema = schemars::schema_for!(layout::LayoutPart);
    let mut text = serde_json::to_string_pretty(&schema).expect("a schema serializes");
    text.push('\n');
    text
}

/// The JSON Schema of a resource's state snapshot (`resource/<name>/state`), checked in
/// as `schemas/json/resource-state.schema.json`: it names the values `state` and
/// `controller` take.
pub fn resource_state_json_schema() -> String {
    let schema = schemars::schema_for!(ResourceSnapshot);
    let mut text = serde_json::to_string_pretty(&schema).expect("a schema serializes");
    text.push('\n');
    text
}

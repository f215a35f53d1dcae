//! Process plans (from product holons), work orders and order snapshots.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::id::{validate_name, HolonId};
use crate::SchemaError;

/// What an order does when a step's result says the part is rejected.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum OnReject {
    /// Go back to step `from_step` (1-based) and redo the steps from there, at most
    /// `max_reworks` times for this order; past that, scrap the part.
    Rework { from_step: usize, max_reworks: u32 },
    /// Scrap the part: the order ends `scrapped` with `reason`.
    Scrap { reason: String },
    /// Send the part to be recovered: one extra step of `service_type` (on any
    /// resource that offers it, e.g. a manual recovery station), with the rejected
    /// step's `info`; then go on from step `then_step` (1-based: the rejected step
    /// itself to check the part again, or a later one). At most `max_recoveries` times
    /// for this order, reworks included; past that, scrap the part.
    Recover {
        service_type: String,
        then_step: usize,
        max_recoveries: u32,
    },
}

/// One step of a process plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PlanStep {
    /// The service the step needs, e.g. `pick_n_place`.
    pub service_type: String,
    /// The Service message's `info` for the step: coordinates, an inspection program,
    /// a transport destination.
    #[serde(default)]
    pub info: serde_json::Map<String, serde_json::Value>,
    /// Controller results (in `done`'s `info.results`) that mean the part is rejected,
    /// e.g. `["inspect_fail"]`.
    #[serde(default)]
    pub reject_results: Vec<String>,
    /// What to do with a rejected part (required when `reject_results` is not empty).
    #[serde(default)]
    pub on_reject: Option<OnReject>,
}

/// A product's process plan, answered on `product/<product>/plan`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Plan {
    pub product: String,
    pub steps: Vec<PlanStep>,
    /// The product's parts are moved through the cell's layout: each step is worked
    /// where the part is, at a station's port, and the order books the moves between
    /// them (docs/material-flow.md). Absent: no part is moved (a cell without a layout).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub moves_parts: bool,
}

impl Plan {
    /// Checks the plan: names, at least one step, rework targets inside the plan.
    pub fn validate(&self) -> Result<(), SchemaError> {
        validate_name("product", &self.product)?;
        if self.steps.is_empty() {
            return Err(SchemaError::InvalidField {
                field: "steps",
                why: "a plan needs at least one step".into(),
            });
        }
        for (i, step) in self.steps.iter().enumerate() {
            validate_name("service type", &step.service_type)?;
            if !step.reject_results.is_empty() && step.on_reject.is_none() {
                return Err(SchemaError::InvalidField {
                    field: "on_reject",
                    why: format!("step {} has reject_results but no on_reject", i + 1),
                });
            }
            if let Some(OnReject::Recover {
                service_type,
                then_step,
                ..
            }) = &step.on_reject
            {
                validate_name("service type", service_type)?;
                if *then_step == 0 || *then_step > self.steps.len() {
                    return Err(SchemaError::InvalidField {
                        field: "on_reject",
                        why: format!(
                            "step {}: recover then_step must be between 1 and {}",
                            i + 1,
                            self.steps.len()
                        ),
                    });
                }
            }
            if let Some(OnReject::Rework { from_step, .. }) = &step.on_reject {
                if *from_step == 0 || *from_step > i + 1 {
                    return Err(SchemaError::InvalidField {
                        field: "on_reject",
                        why: format!(
                            "step {}: rework from_step must be between 1 and {}",
                            i + 1,
                            i + 1
                        ),
                    });
                }
            }
        }
        Ok(())
    }
}

/// A work order, sent to `orders/submit`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct WorkOrder {
    /// The product to make (its product holon serves the plan).
    pub product: String,
    /// How many orders to create (default 1; at most `orders.max_orders_per_submit`).
    #[serde(default = "one")]
    pub count: u32,
    /// How urgent the orders are, from -1000 to 1000 (default 0; higher is more
    /// urgent, e.g. 100 for a rush order). Each booking carries it: a resource serves
    /// waiting bookings by priority, with a bound on how often one may be passed (see
    /// `agenda.max_overtakes`).
    #[serde(default)]
    pub priority: i32,
    /// When the orders are due, in Unix milliseconds (optional). Kept with each order
    /// and shown; a staff holon plans by it. A due time in the past is accepted (the
    /// order is late already).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub due: Option<u64>,
    /// Accept the work order even when no product holon of that name is alive (its
    /// orders wait for the plan); without it such a work order is refused
    /// `unknown_product`, since a misspelt product would otherwise fail only later.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub queue: bool,
    /// A name the submitter gives the work order (optional; 1 to 64 of a-z, 0-9, '_'
    /// and '-', e.g. an MES's work-order number), so that asking again is safe: an
    /// order-node that already made a work order of this name answers with the orders
    /// it made then and makes none, and refuses `invalid` one of another product or
    /// count. Remembered with its orders (through a restart or a standby's takeover)
    /// as long as finished orders are kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub submit_id: Option<String>,
}

fn one() -> u32 {
    1
}

/// The most orders one work order may create.
pub const MAX_ORDERS_PER_SUBMIT: u32 = 10_000;

impl WorkOrder {
    pub fn validate(&self) -> Result<(), SchemaError> {
        validate_name("product", &self.product)?;
        if let Some(id) = &self.submit_id {
            validate_name("submit_id", id)?;
        }
        if self.count == 0 || self.count > MAX_ORDERS_PER_SUBMIT {
            return Err(SchemaError::InvalidField {
                field: "count",
                why: format!("must be 1 to {MAX_ORDERS_PER_SUBMIT}"),
            });
        }
        if !(crate::MIN_PRIORITY..=crate::MAX_PRIORITY).contains(&self.priority) {
            return Err(SchemaError::InvalidField {
                field: "priority",
                why: format!("must be {} to {}", crate::MIN_PRIORITY, crate::MAX_PRIORITY),
            });
        }
        Ok(())
    }
}

/// The longest "who asks" a work order or a cancel may carry.
pub const MAX_REQUESTED_BY: usize = 200;

/// Who asks for a work order or a cancel (`cell submit on host`, a dashboard's user,
/// an OPC UA user), as the zenoh attachment of the query, so that the order-node's log
/// names them. It is not part of the payload, so an order-node that does not read it
/// still takes the query; what is not UTF-8, or longer than [`MAX_REQUESTED_BY`], or
/// holds control characters, is not read.
pub fn requested_by(attachment: &[u8]) -> Option<String> {
    let text = std::str::from_utf8(attachment).ok()?;
    (!text.is_empty() && text.len() <= MAX_REQUESTED_BY && !text.chars().any(char::is_control))
        .then(|| text.to_string())
}

/// The answer to a work order: the new orders' names.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct SubmitReply {
    pub orders: Vec<String>,
}

/// The answer to `order/<name>/cancel` (an operator's `cell cancel`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct CancelReply {
    pub order: String,
    /// True when the order was running and will end as `cancelled`.
    pub cancelled: bool,
    /// Its status when the request arrived.
    pub status: OrderStatus,
    /// What happens next, for the operator.
    pub detail: String,
}

/// An order's status.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum OrderStatus {
    Running,
    /// The product was made.
    Done,
    /// The part was rejected and scrapped (`reason` says why).
    Scrapped,
    /// The order could not be completed (`reason` says why).
    Failed,
    /// An operator cancelled the order (`cell cancel`): its bookings were cancelled; a
    /// step already running was let finish.
    Cancelled,
}

impl OrderStatus {
    pub fn is_final(self) -> bool {
        self != OrderStatus::Running
    }

    /// The name on the wire (`running`, `done`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            OrderStatus::Running => "running",
            OrderStatus::Done => "done",
            OrderStatus::Scrapped => "scrapped",
            OrderStatus::Failed => "failed",
            OrderStatus::Cancelled => "cancelled",
        }
    }
}

impl std::fmt::Display for OrderStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How one attempt of a step ended, as its order recorded it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum AttemptEnd {
    /// The resource reported `done`, and the results passed.
    Done,
    /// The resource reported `done` with one of the step's `reject_results`: reworked or
    /// scrapped as the plan says.
    Rejected,
    /// The resource reported `failed` (controller error, interrupted, ...): counts
    /// against `max_attempts`, tried again elsewhere.
    Failed,
    /// The booking ended without a result (the resource vanished or handed it back):
    /// booked again, not counted as a failure (a rebook).
    Lost,
    /// No resource could be booked in time: the order failed.
    NoResource,
    /// An operator cancelled the order.
    Cancelled,
}

impl AttemptEnd {
    /// The name on the wire (`done`, `rejected`, ...).
    pub fn as_str(self) -> &'static str {
        match self {
            AttemptEnd::Done => "done",
            AttemptEnd::Rejected => "rejected",
            AttemptEnd::Failed => "failed",
            AttemptEnd::Lost => "lost",
            AttemptEnd::NoResource => "no_resource",
            AttemptEnd::Cancelled => "cancelled",
        }
    }
}

impl std::fmt::Display for AttemptEnd {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// One ended attempt of a step: an order's audit trail (`cell orders --detail`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct AttemptRecord {
    /// `<order>/<step>/<attempt>`: the conversation the resource saw.
    pub conversation_id: String,
    /// The step, 1-based.
    pub step: usize,
    pub service_type: String,
    /// The resource the attempt was booked on (none when nothing could be booked).
    pub resource: Option<HolonId>,
    pub end: AttemptEnd,
    /// As an operator reads it: `done by resource/robot1 (pick=picking_done ...)`,
    /// `failed on resource/robot2: interrupted`, `lost resource/robot1: withdrawn`.
    pub detail: String,
    /// When the order recorded it (Unix ms).
    pub at: u64,
}

/// The most attempts an order keeps in its history (the oldest go first); the counters
/// (`failed_attempts`, `rebooks`, `reworks`) count them all.
pub const MAX_ATTEMPT_HISTORY: usize = 100;

/// An order's state, published on `order/<name>/state` after every change.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct OrderSnapshot {
    pub holon: HolonId,
    pub product: String,
    pub status: OrderStatus,
    pub reason: Option<String>,
    /// The current step, 1-based (0 before the plan is known).
    pub step: usize,
    pub steps: usize,
    pub service_type: Option<String>,
    /// The resource the current step is booked on.
    pub resource: Option<HolonId>,
    /// The current step's attempt, from 1.
    pub attempt: u32,
    /// Steps completed, with the resource that executed each: `[["transport", "resource/conveyor1"], ...]`.
    pub completed: Vec<(String, HolonId)>,
    pub reworks: u32,
    /// Attempts that ended without the step being done or failed (the resource vanished
    /// or handed the booking back) and were booked again.
    pub rebooks: u32,
    /// Attempts that failed (all steps).
    #[serde(default)]
    pub failed_attempts: u32,
    /// Every ended attempt, oldest first (at most [`MAX_ATTEMPT_HISTORY`]).
    #[serde(default)]
    pub attempts: Vec<AttemptRecord>,
    /// The work order's priority (0 unless given; higher is more urgent).
    #[serde(default)]
    pub priority: i32,
    /// When the order is due, in Unix milliseconds, if its work order said.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub due: Option<u64>,
    /// Steps booked on a staff holon's advice.
    #[serde(default)]
    pub advised: u32,
    /// The release of the order-node hosting the order (absent from older nodes).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub version: Option<String>,
    /// Where the order's part is, for a plan that moves parts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part: Option<crate::PartPlace>,
    /// Operators' words on where the part was while it was lost, oldest first (at most
    /// [`MAX_ATTEMPT_HISTORY`]).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub part_found: Vec<crate::PartFound>,
    pub at: u64,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn plan(v: serde_json::Value) -> Result<Plan, String> {
        let plan: Plan = serde_json::from_value(v).map_err(|e| e.to_string())?;
        plan.validate().map_err(|e| e.to_string())?;
        Ok(plan)
    }

    #[test]
    fn plans_validate() {
        plan(json!({"product": "breaker", "steps": [
            {"service_type": "transport", "info": {"destination": {"x": 1, "y": 2, "z": 0}}},
            {"service_type": "inspect", "reject_results": ["inspect_fail"],
             "on_reject": {"rework": {"from_step": 1, "max_reworks": 2}}}
        ]}))
        .unwrap();
        assert!(plan(json!({"product": "breaker", "steps": []})).is_err());
        assert!(plan(json!({"product": "Breaker", "steps": [{"service_type": "x"}]})).is_err());
        assert!(plan(json!({"product": "b", "steps": [{"service_type": "inspect", "reject_results": ["inspect_fail"]}]})).is_err());
        assert!(plan(
            json!({"product": "b", "steps": [{"service_type": "inspect", "reject_results": ["f"],
            "on_reject": {"rework": {"from_step": 2, "max_reworks": 1}}}]})
        )
        .is_err());
        assert!(
            plan(json!({"product": "b", "steps": [{"service_type": "x", "colour": 1}]})).is_err()
        );
    }

    #[test]
    fn a_recovery_names_a_service_and_a_step_of_the_plan() {
        let recover = |service: &str, then_step: usize| {
            plan(json!({"product": "b", "steps": [
                {"service_type": "axis"},
                {"service_type": "inspection", "reject_results": ["inspect_fail"],
                 "on_reject": {"recover": {"service_type": service, "then_step": then_step,
                                           "max_recoveries": 1}}},
                {"service_type": "unload"}
            ]}))
        };
        recover("recovery", 2).unwrap();
        recover("recovery", 3).unwrap();
        let beyond = recover("recovery", 4).unwrap_err();
        assert!(beyond.contains("between 1 and 3"), "{beyond}");
        assert!(recover("recovery", 0).is_err());
        assert!(recover("Recovery", 2).is_err());
    }

    #[test]
    fn work_orders_validate() {
        let order: WorkOrder =
            serde_json::from_value(json!({"product": "breaker", "count": 3, "priority": 0}))
                .unwrap();
        order.validate().unwrap();
        let order: WorkOrder = serde_json::from_value(json!({"product": "breaker"})).unwrap();
        assert_eq!(order.count, 1);
        let zero: WorkOrder =
            serde_json::from_value(json!({"product": "breaker", "count": 0})).unwrap();
        assert!(zero.validate().is_err());
        assert!(serde_json::from_value::<WorkOrder>(json!({"product": "b", "count": -1})).is_err());
        // A name, when given, is a name; none is written when there is none.
        let named: WorkOrder =
            serde_json::from_value(json!({"product": "b", "submit_id": "mes-4711"})).unwrap();
        named.validate().unwrap();
        for bad in ["", "MES 4711", &"x".repeat(65)] {
            let work: WorkOrder =
                serde_json::from_value(json!({"product": "b", "submit_id": bad})).unwrap();
            assert!(work.validate().is_err(), "{bad:?}");
        }
        assert!(!serde_json::to_string(&order).unwrap().contains("submit_id"));
    }
}

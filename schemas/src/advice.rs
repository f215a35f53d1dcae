//! A staff holon's advice: what an order asks on `staff/<name>/advice` and what it is
//! told. The staff only advises (PROSA's staff is advisory): the order still asks for
//! proposals and books for itself, and takes the advice only when the advised resource
//! proposed. JSON Schema: `schemas/json/advice.schema.json`.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::layout::LocationId;
use crate::{HolonId, SchemaError, MAX_PRIORITY, MIN_PRIORITY};

/// The version of the advice messages.
pub const ADVICE_VERSION: u32 = 1;

/// The most steps an advice request may name (a route longer than this is cut).
pub const MAX_ADVICE_STEPS: usize = 64;

/// The most resources an advice request may ask to avoid.
pub const MAX_AVOIDED: usize = 64;

/// One step of the route still ahead of an order.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RouteStep {
    /// The service the step needs, e.g. `pick_n_place`.
    pub service_type: String,
    /// The step's program (product variant), from its `info.program`, if it names one:
    /// a resource whose last job ran another program changes over first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
}

/// An order asks which resource to book for its next step (`get` on
/// `staff/<name>/advice` with this as payload).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AdviceRequest {
    /// Always [`ADVICE_VERSION`].
    pub v: u32,
    /// The order asking, e.g. `order/orders1-3`.
    pub order: HolonId,
    /// The conversation of the attempt it is for; the advice repeats it, and an order
    /// ignores advice for another conversation (a late answer to an earlier ask).
    pub conversation_id: String,
    /// The order's priority (its bookings carry it; the agenda serves by it).
    #[serde(default)]
    pub priority: i32,
    /// When the order is due (Unix ms), if it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub due: Option<u64>,
    /// The route still ahead: the next step first (at least one step).
    pub steps: Vec<RouteStep>,
    /// Resources that failed the next step for this order: not to be advised.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub avoid: Vec<HolonId>,
    /// Where the order's part is (a plan that moves parts), e.g. `conveyor1.buffer`:
    /// the staff counts the travel from there to each station, and between the
    /// stations of the route, from the cell's layout. Absent: no part to move (or an
    /// order-node of an earlier release).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "Option<String>")]
    pub at: Option<LocationId>,
}

impl AdviceRequest {
    /// Checks what serde cannot: the version, the order's kind, the bounds.
    pub fn validate(&self) -> Result<(), SchemaError> {
        if self.v != ADVICE_VERSION {
            return Err(SchemaError::UnsupportedVersion(self.v));
        }
        let invalid = |field, why: &str| SchemaError::InvalidField {
            field,
            why: why.to_string(),
        };
        if self.order.kind() != crate::HolonKind::Order {
            return Err(invalid("order", "must be an order holon"));
        }
        if self.conversation_id.is_empty() || self.conversation_id.len() > 256 {
            return Err(invalid("conversation_id", "must be 1 to 256 bytes"));
        }
        if !(MIN_PRIORITY..=MAX_PRIORITY).contains(&self.priority) {
            return Err(invalid("priority", "must be -1000 to 1000"));
        }
        if self.steps.is_empty() || self.steps.len() > MAX_ADVICE_STEPS {
            return Err(invalid("steps", "must name 1 to 64 steps"));
        }
        for step in &self.steps {
            crate::validate_name("service type", &step.service_type)?;
            if let Some(program) = &step.program {
                if program.is_empty() || program.len() > 64 {
                    return Err(invalid("steps", "a program must be 1 to 64 bytes"));
                }
            }
        }
        if self.avoid.len() > MAX_AVOIDED {
            return Err(invalid("avoid", "must name at most 64 resources"));
        }
        Ok(())
    }
}

/// One step of the route as the staff forecasts it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ForecastStep {
    pub service_type: String,
    /// The resource the forecast puts the step on.
    pub resource: HolonId,
    /// When the step is forecast to start and end (Unix ms).
    pub start: u64,
    pub end: u64,
    /// The forecast counts a changeover before the step.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub changeover: bool,
    /// The move before the step, for a part that is elsewhere: the station's port it
    /// goes to ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[schemars(with = "Option<String>")]
    pub to: Option<LocationId>,
    /// ... and its travel, as the layout times it (ms), counted before the step starts.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub travel_ms: u64,
}

fn is_zero(ms: &u64) -> bool {
    *ms == 0
}

/// The staff's answer.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Advice {
    /// Always [`ADVICE_VERSION`].
    pub v: u32,
    /// The staff holon advising, e.g. `staff/planner`.
    pub staff: HolonId,
    /// The request's order and conversation, repeated.
    pub order: HolonId,
    pub conversation_id: String,
    /// The resource to book for the next step; `None` when the staff knows of none
    /// that could take it (the order then goes by contract net alone).
    pub resource: Option<HolonId>,
    /// When the whole order is forecast to be done (Unix ms), with this advice.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub forecast_done: Option<u64>,
    /// How much later than its due time that is (absent: on time, or no due time).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub late_by_ms: Option<u64>,
    /// The forecast route, the advised step first.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub route: Vec<ForecastStep>,
    /// Why, for people: e.g. `resource/robot1 done at +1.2 s (resource/robot2: +2.9 s)`.
    pub why: String,
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn request(v: serde_json::Value) -> Result<AdviceRequest, String> {
        let request: AdviceRequest = serde_json::from_value(v).map_err(|e| e.to_string())?;
        request.validate().map_err(|e| e.to_string())?;
        Ok(request)
    }

    #[test]
    fn advice_requests_validate() {
        let good = json!({"v": 1, "order": "order/o-1", "conversation_id": "o-1/1/1",
            "priority": 100, "due": 1_800_000_000_000u64,
            "steps": [{"service_type": "pick_n_place", "program": "b2"},
                      {"service_type": "inspect"}]});
        let parsed = request(good.clone()).unwrap();
        assert_eq!(parsed.steps[0].program.as_deref(), Some("b2"));
        let bad = |change: &dyn Fn(&mut serde_json::Value)| {
            let mut v = good.clone();
            change(&mut v);
            request(v)
        };
        assert!(bad(&|v| v["v"] = json!(2)).unwrap_err().contains("version"));
        assert!(bad(&|v| v["order"] = json!("resource/r1")).is_err());
        assert!(bad(&|v| v["steps"] = json!([])).is_err());
        assert!(bad(&|v| v["priority"] = json!(5000)).is_err());
        assert!(bad(&|v| v["steps"][0]["service_type"] = json!("Bad Type")).is_err());
        assert!(bad(&|v| v["extra"] = json!(1)).is_err());
        assert!(bad(&|v| v["conversation_id"] = json!("")).is_err());
    }

    #[test]
    fn advice_round_trips() {
        let advice = Advice {
            v: ADVICE_VERSION,
            staff: HolonId::new(crate::HolonKind::Staff, "planner").unwrap(),
            order: HolonId::order("o-1").unwrap(),
            conversation_id: "o-1/1/1".into(),
            resource: Some(HolonId::resource("robot1").unwrap()),
            forecast_done: Some(10),
            late_by_ms: None,
            route: vec![ForecastStep {
                service_type: "pick_n_place".into(),
                resource: HolonId::resource("robot1").unwrap(),
                start: 1,
                end: 5,
                changeover: true,
                to: Some(crate::layout::LocationId::new("robot1", "port").unwrap()),
                travel_ms: 1200,
            }],
            why: "fastest".into(),
        };
        let text = serde_json::to_string(&advice).unwrap();
        assert_eq!(serde_json::from_str::<Advice>(&text).unwrap(), advice);
    }
}

//! What an OPC UA method call leaves in the cell's audit trail: one record per call,
//! accepted or refused, as the dashboard records its actions (who, from where, what,
//! on what, how it ended). A PackML method is a `packml` action on its resource, with
//! the method (and a unit mode's number) as the detail; SubmitWorkOrder is a `submit`
//! with the work order and, when done, the new orders.

use opcua::types::{StatusCode, Variant};

use super::address_space::{MethodTarget, SET_UNIT_MODE};
use crate::security::audit::{AuditAction, AuditOutcome, AuditRecord};

/// The longest text of an argument the trail keeps (a client may send a megabyte).
const LONGEST_ARGUMENT: usize = 200;

/// An argument as the trail shows it.
fn shown(argument: &Variant) -> serde_json::Value {
    match argument {
        Variant::Int32(n) => serde_json::json!(n),
        Variant::String(s) => {
            let text = s.as_ref();
            if text.len() <= LONGEST_ARGUMENT {
                serde_json::json!(text)
            } else {
                let mut end = LONGEST_ARGUMENT;
                while !text.is_char_boundary(end) {
                    end -= 1;
                }
                serde_json::json!(format!("{}... ({} bytes)", &text[..end], text.len()))
            }
        }
        other => serde_json::json!(format!("{:?}", other.type_id())),
    }
}

/// How a call's status ends in the trail: done, refused (the cell did not change: a
/// role, a state, an argument) or failed (the cell could not be asked, or did not
/// answer: it may or may not have taken).
fn outcome(status: StatusCode) -> AuditOutcome {
    if status.is_good() {
        return AuditOutcome::Done;
    }
    let why = format!("{status}");
    match status {
        StatusCode::BadTimeout
        | StatusCode::BadCommunicationError
        | StatusCode::BadInternalError
        | StatusCode::BadResourceUnavailable => AuditOutcome::Failed(why),
        _ => AuditOutcome::Refused(why),
    }
}

/// The record of a call of `target` (None: no method of ours) by the user `who` from
/// `from`, with `arguments`, that ended with `result`.
pub fn call_record(
    who: &str,
    from: &str,
    target: Option<&MethodTarget>,
    arguments: &[Variant],
    result: &Result<Vec<Variant>, StatusCode>,
) -> AuditRecord {
    let status = match result {
        Ok(_) => StatusCode::Good,
        Err(status) => *status,
    };
    let arguments: Vec<serde_json::Value> = arguments.iter().map(shown).collect();
    let (action, on, mut detail) = match target {
        Some(MethodTarget::Resource { resource, method }) => {
            let mut detail = serde_json::json!({ "method": method });
            if method == SET_UNIT_MODE {
                detail["mode"] = arguments.first().cloned().unwrap_or_default();
            }
            (AuditAction::Packml, Some(resource.clone()), detail)
        }
        Some(MethodTarget::Cell { method }) => (
            AuditAction::Submit,
            None,
            serde_json::json!({ "method": method, "arguments": arguments }),
        ),
        None => (
            AuditAction::Packml,
            None,
            serde_json::json!({ "method": "unknown", "arguments": arguments }),
        ),
    };
    if let (Some(MethodTarget::Cell { .. }), Ok(outputs)) = (target, result) {
        if let Some(Variant::Array(orders)) = outputs.first() {
            detail["orders"] = orders.values.iter().map(shown).collect();
        }
    }
    let mut record = AuditRecord::now(who, from, action, outcome(status)).with(detail);
    record.target = on;
    record
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_call_is_done_refused_or_failed_with_its_particulars() {
        let hold = MethodTarget::Resource {
            resource: "robot1".into(),
            method: "Hold".into(),
        };
        let done = call_record("anna", "10.0.0.9:5000", Some(&hold), &[], &Ok(vec![]));
        assert_eq!(done.action, AuditAction::Packml);
        assert_eq!(done.target.as_deref(), Some("robot1"));
        assert_eq!(done.outcome, AuditOutcome::Done);
        let refused = call_record(
            "wall",
            "10.0.0.9:5000",
            Some(&hold),
            &[],
            &Err(StatusCode::BadUserAccessDenied),
        );
        assert!(
            matches!(refused.outcome, AuditOutcome::Refused(ref why) if why.contains("BadUserAccessDenied"))
        );
        let submit = MethodTarget::Cell {
            method: "SubmitWorkOrder".into(),
        };
        let long = "x".repeat(1 << 20);
        let failed = call_record(
            "anna",
            "10.0.0.9:5000",
            Some(&submit),
            &[
                Variant::from(long.as_str()),
                Variant::Int32(1),
                Variant::Int32(0),
            ],
            &Err(StatusCode::BadTimeout),
        );
        assert_eq!(failed.action, AuditAction::Submit);
        assert!(matches!(failed.outcome, AuditOutcome::Failed(_)));
        let line = serde_json::to_string(&failed).unwrap();
        assert!(
            line.len() < 1000,
            "the trail keeps no megabyte argument: {} bytes",
            line.len()
        );
    }
}

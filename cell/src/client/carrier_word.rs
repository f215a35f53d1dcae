//! `cell carrier RESOURCE CARRIER --out|--back`: an operator's word on a conveyor's
//! carrier, taken out of service or put back (docs/material-flow.md, "Carriers out of
//! service"). The conveyor's holon journals it and grants a home at its buffers only
//! while fewer are held than carriers are in service.

use std::time::Duration;

use schemas::keys::CellKeys;

use crate::client::ask::AskError;

/// Tells the conveyor `resource` that `carrier` (`p3`) is out of service, or back
/// (`in_service`); `by` says who tells, for its log. Asked until the conveyor answers
/// (one that is restarting answers nothing); the same word again changes nothing.
pub async fn tell(
    session: &zenoh::Session,
    keys: &CellKeys,
    resource: &str,
    carrier: &str,
    in_service: bool,
    by: &str,
    timeout: Duration,
) -> Result<schemas::CarrierReply, AskError> {
    let failed = |e: &dyn std::fmt::Display| AskError::Failed(format!("{e:#}"));
    let word = schemas::CarrierWord {
        carrier: carrier.to_string(),
        in_service,
    };
    let payload = serde_json::to_vec(&word).expect("serializes");
    let key = keys.carriers(resource);
    let asked = crate::client::ask::until_answered(session, &key, Some(payload), by, timeout)
        .await
        .map_err(|e| failed(&e))?;
    crate::client::ask::answer_of(asked, || {
        format!(
            "{key} ({resource}: not a conveyor, not running, or this identity may not take \
             carriers out)"
        )
    })
}

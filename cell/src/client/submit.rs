//! Submitting a work order to a cell, as `cell submit`, the demo and the dashboard's
//! form do: one order-node answers with the new orders' names, or why it refused.

use std::time::Duration;

use schemas::{CellKeys, SubmitReply, WorkOrder};

use crate::client::ask::AskError;

/// Submits a work order to the cell's order-nodes (a default `get` reaches one); `by`
/// says who asks, for the order-node's log.
pub async fn submit(
    session: &zenoh::Session,
    keys: &CellKeys,
    work: &WorkOrder,
    by: &str,
    timeout: Duration,
) -> Result<Vec<String>, AskError> {
    let key = keys.orders_submit();
    let failed = |e: &dyn std::fmt::Display| AskError::Failed(format!("{e:#}"));
    let work = serde_json::to_vec(work).map_err(|e| failed(&e))?;
    let Some(reply) = crate::client::ask::until_answered(session, &key, Some(work), by, timeout)
        .await
        .map_err(|e| failed(&e))?
    else {
        return Err(AskError::NoAnswer(key));
    };
    crate::client::ask::answer_of::<SubmitReply>(Some(reply), || key.clone())
        .map(|reply| reply.orders)
}

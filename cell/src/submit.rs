//! Submitting a work order to a cell, as `cell submit`, the demo and the dashboard's
//! form do: one order-node answers with the new orders' names, or why it refused.

use std::time::Duration;

use anyhow::{bail, Result};
use schemas::{CellKeys, SubmitReply, WorkOrder};

/// Submits a work order to the cell's order-nodes (a default `get` reaches one); `by`
/// says who asks, for the order-node's log.
pub async fn submit(
    session: &zenoh::Session,
    keys: &CellKeys,
    work: &WorkOrder,
    by: &str,
    timeout: Duration,
) -> Result<Vec<String>> {
    let key = keys.orders_submit();
    let Some(reply) =
        crate::ask::until_answered(session, &key, Some(serde_json::to_vec(work)?), by, timeout)
            .await?
    else {
        bail!("no order-node answered on {key}");
    };
    match reply.result() {
        Ok(sample) => {
            Ok(serde_json::from_slice::<SubmitReply>(&sample.payload().to_bytes())?.orders)
        }
        Err(err) => {
            let text = err.payload().try_to_string().unwrap_or_default();
            match serde_json::from_str::<schemas::ErrorReply>(&text) {
                Ok(e) => bail!(
                    "the order-node refused the work order ({}): {}",
                    e.code,
                    e.message
                ),
                Err(_) => bail!("the order-node refused the work order: {text}"),
            }
        }
    }
}

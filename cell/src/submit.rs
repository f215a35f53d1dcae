//! Submitting a work order to a cell, as `cell submit`, the demo and the dashboard's
//! form do: one order-node answers with the new orders' names, or why it refused.

use std::time::Duration;

use schemas::{CellKeys, SubmitReply, WorkOrder};

/// Why a work order made no orders.
#[derive(Debug, thiserror::Error)]
pub enum SubmitError {
    /// An order-node answered and refused it (nothing was made).
    #[error("the order-node refused the work order ({code}): {message}")]
    Refused {
        code: schemas::ErrorCode,
        message: String,
    },
    /// No order-node answered within the time.
    #[error("no order-node answered on {0}")]
    NoAnswer(String),
    /// The question could not be asked, or the answer not read.
    #[error("{0}")]
    Failed(String),
}

/// Submits a work order to the cell's order-nodes (a default `get` reaches one); `by`
/// says who asks, for the order-node's log.
pub async fn submit(
    session: &zenoh::Session,
    keys: &CellKeys,
    work: &WorkOrder,
    by: &str,
    timeout: Duration,
) -> Result<Vec<String>, SubmitError> {
    let key = keys.orders_submit();
    let failed = |e: &dyn std::fmt::Display| SubmitError::Failed(format!("{e:#}"));
    let work = serde_json::to_vec(work).map_err(|e| failed(&e))?;
    let Some(reply) = crate::ask::until_answered(session, &key, Some(work), by, timeout)
        .await
        .map_err(|e| failed(&e))?
    else {
        return Err(SubmitError::NoAnswer(key));
    };
    match reply.result() {
        Ok(sample) => serde_json::from_slice::<SubmitReply>(&sample.payload().to_bytes())
            .map(|reply| reply.orders)
            .map_err(|e| failed(&e)),
        Err(err) => {
            let text = err.payload().try_to_string().unwrap_or_default();
            Err(match serde_json::from_str::<schemas::ErrorReply>(&text) {
                Ok(e) => SubmitError::Refused {
                    code: e.code,
                    message: e.message,
                },
                Err(_) => SubmitError::Refused {
                    code: schemas::ErrorCode::Other("unknown".into()),
                    message: text.to_string(),
                },
            })
        }
    }
}

//! `cell status`: the live holons of a cell, with their state and agenda length.

use std::time::Duration;

use anyhow::{anyhow, Result};
use schemas::{CellKeys, HolonId};

/// One line of the status table.
#[derive(Debug, Clone, PartialEq)]
pub struct HolonStatus {
    pub holon: HolonId,
    /// The holon's last snapshot, if it answered.
    pub snapshot: Option<serde_json::Value>,
}

/// Asks the cell who is alive, then each holon for its state.
pub async fn collect(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<HolonStatus>> {
    let holons = holon::presence::alive_holons(session, keys, timeout)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut rows = Vec::new();
    for holon in holons {
        let snapshot = match session.get(keys.state(&holon)).timeout(timeout).await {
            Ok(replies) => match replies.recv_async().await {
                Ok(reply) => reply
                    .result()
                    .ok()
                    .and_then(|s| serde_json::from_slice(&s.payload().to_bytes()).ok()),
                Err(_) => None,
            },
            Err(_) => None,
        };
        rows.push(HolonStatus { holon, snapshot });
    }
    Ok(rows)
}

/// The table `cell status` prints.
pub fn render(cell: &str, rows: &[HolonStatus]) -> String {
    let mut out = format!(
        "cell {cell}: {} live holon{}\n",
        rows.len(),
        if rows.len() == 1 { "" } else { "s" }
    );
    out.push_str(&format!(
        "{:<28} {:<9} {:<8} {:<13} {:>6} {:>11}\n",
        "HOLON", "KIND", "STATE", "CONTROLLER", "AGENDA", "UNDELIVERED"
    ));
    for row in rows {
        let field = |name: &str| {
            row.snapshot
                .as_ref()
                .and_then(|s| s.get(name))
                .map(|v| match v {
                    serde_json::Value::String(s) => s.clone(),
                    serde_json::Value::Array(a) => a.len().to_string(),
                    other => other.to_string(),
                })
                .unwrap_or_else(|| "-".into())
        };
        out.push_str(&format!(
            "{:<28} {:<9} {:<8} {:<13} {:>6} {:>11}\n",
            row.holon.to_string(),
            row.holon.kind().to_string(),
            if row.holon.kind() == schemas::HolonKind::Order {
                field("status")
            } else {
                field("state")
            },
            field("controller"),
            field("agenda"),
            field("undelivered"),
        ));
    }
    out
}

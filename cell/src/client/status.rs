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

/// Asks the cell who is alive, then every holon for its state with one query (all
/// answer at once; one that is slow or cut off does not hold up or blank the others,
/// and is marked as not having answered).
pub async fn collect(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<HolonStatus>> {
    let holons = holon::presence::alive_holons(session, keys, timeout)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut snapshots = std::collections::HashMap::new();
    if !holons.is_empty() {
        let mut replies = session
            .get(keys.state_all())
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(timeout)
            .with(holon::query::replies())
            .await
            .map_err(|e| anyhow!("{e}"))?;
        while let Some(reply) = replies.recv().await {
            let Ok(sample) = reply.result() else { continue };
            let Ok(snapshot) =
                serde_json::from_slice::<serde_json::Value>(&sample.payload().to_bytes())
            else {
                continue;
            };
            if let Some(holon) = snapshot
                .get("holon")
                .and_then(|h| h.as_str())
                .and_then(|h| h.parse::<HolonId>().ok())
            {
                snapshots.insert(holon, snapshot);
            }
            if holons.iter().all(|h| snapshots.contains_key(h)) {
                break;
            }
        }
    }
    Ok(holons
        .into_iter()
        .map(|holon| HolonStatus {
            snapshot: snapshots.remove(&holon),
            holon,
        })
        .collect())
}

/// Every answer to a query of `key` that reads as a `T`, whatever answers within
/// `timeout` (each process answers for itself: no consolidation).
async fn gather<T: serde::de::DeserializeOwned>(
    session: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Result<Vec<T>> {
    let mut replies = session
        .get(key)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(timeout)
        .with(holon::query::replies())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut found = Vec::new();
    while let Some(reply) = replies.recv().await {
        let Ok(sample) = reply.result() else { continue };
        if let Ok(value) = serde_json::from_slice::<T>(&sample.payload().to_bytes()) {
            found.push(value);
        }
    }
    Ok(found)
}

/// The fenced resources' processes (`resource/*/fence/*`, docs/reliability.md): each
/// one's place at the controller, holder or standby, whatever answers within `timeout`.
pub async fn fences(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<schemas::FenceReport>> {
    let mut reports: Vec<schemas::FenceReport> =
        gather(session, &keys.fence_all(), timeout).await?;
    reports.sort_by(|a, b| {
        (a.holon.name(), a.role as u8, &a.host).cmp(&(b.holon.name(), b.role as u8, &b.host))
    });
    Ok(reports)
}

/// The fence table `cell status` prints below the holons (nothing without fenced
/// resources): who holds each fenced resource's controller, at which epoch, and its
/// standbys.
pub fn render_fences(reports: &[schemas::FenceReport]) -> String {
    if reports.is_empty() {
        return String::new();
    }
    let mut out = format!(
        "{:<28} {:<8} {:>6}  {:<20} ZID\n",
        "FENCED RESOURCE", "ROLE", "EPOCH", "HOST"
    );
    for report in reports {
        let (role, epoch) = match report.role {
            schemas::FenceRole::Holder => ("holder", report.epoch),
            schemas::FenceRole::Standby => ("standby", report.holder_epoch),
        };
        let epoch = epoch.map_or_else(|| "-".to_string(), |e| e.to_string());
        out.push_str(&format!(
            "{:<28} {:<8} {:>6}  {:<20} {}\n",
            report.holon.to_string(),
            role,
            epoch,
            report.host,
            report.zid
        ));
    }
    let held: std::collections::BTreeSet<&str> = reports
        .iter()
        .filter(|r| r.role == schemas::FenceRole::Holder)
        .map(|r| r.holon.name())
        .collect();
    let unheld: std::collections::BTreeSet<String> = reports
        .iter()
        .filter(|r| !held.contains(r.holon.name()))
        .map(|r| r.holon.to_string())
        .collect();
    for holon in unheld {
        out.push_str(&format!(
            "! {holon}: no process that answered holds its controller (a standby's EPOCH is the holder's it last heard of)\n"
        ));
    }
    out
}

/// The processes of the order-nodes whose journal is on etcd
/// (`host/order-node/*/fence/*`, docs/reliability.md): each one's place, holder or
/// standby, with a standby's lag; whatever answers within `timeout`.
pub async fn node_fences(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<schemas::fence::NodeFenceReport>> {
    let mut reports: Vec<schemas::fence::NodeFenceReport> =
        gather(session, &keys.node_fence_all(), timeout).await?;
    reports.sort_by(|a, b| (&a.node, a.role as u8, &a.host).cmp(&(&b.node, b.role as u8, &b.host)));
    Ok(reports)
}

/// The order-nodes' fence table `cell status` prints below the resources' (nothing
/// without an order-node on etcd): who holds each node's leader key at which epoch, and
/// its standbys with the holder's epoch they last saw and their lag (`lost`: it cannot
/// reach etcd). A node nobody who answered holds is flagged, and so is a lost store.
pub fn render_node_fences(reports: &[schemas::fence::NodeFenceReport]) -> String {
    use schemas::FenceRole;
    if reports.is_empty() {
        return String::new();
    }
    let mut out = format!(
        "{:<28} {:<8} {:>6} {:>6}  {:<20} ZID\n",
        "FENCED ORDER-NODE", "ROLE", "EPOCH", "LAG", "HOST"
    );
    let dash = |n: Option<u64>| n.map_or_else(|| "-".to_string(), |n| n.to_string());
    for report in reports {
        let (role, epoch, lag) = match report.role {
            FenceRole::Holder => ("holder", report.epoch, "-".to_string()),
            FenceRole::Standby if report.store_lost => {
                ("standby", report.holder_epoch, "lost".to_string())
            }
            FenceRole::Standby => ("standby", report.holder_epoch, dash(report.lag)),
        };
        out.push_str(&format!(
            "{:<28} {:<8} {:>6} {:>6}  {:<20} {}\n",
            report.node,
            role,
            dash(epoch),
            lag,
            report.host,
            report.zid
        ));
    }
    let held: std::collections::BTreeSet<&str> = reports
        .iter()
        .filter(|r| r.role == FenceRole::Holder)
        .map(|r| r.node.as_str())
        .collect();
    let unheld: std::collections::BTreeSet<&str> = reports
        .iter()
        .filter(|r| !held.contains(r.node.as_str()))
        .map(|r| r.node.as_str())
        .collect();
    for node in unheld {
        out.push_str(&format!(
            "! order-node {node}: no process that answered holds its leader key on etcd (a standby's EPOCH is the holder's it last saw)\n"
        ));
    }
    for lost in reports.iter().filter(|r| r.store_lost) {
        out.push_str(&format!(
            "! order-node {}: the standby on {} cannot reach etcd (store lost; LAG as of its last read)\n",
            lost.node, lost.host
        ));
    }
    out
}

/// The table `cell status` prints.
pub fn render(cell: &str, rows: &[HolonStatus]) -> String {
    let mut out = format!(
        "cell {cell}: {} live holon{}\n",
        rows.len(),
        if rows.len() == 1 { "" } else { "s" }
    );
    out.push_str(&format!(
        "{:<28} {:<9} {:<8} {:<14} {:<13} {:>6} {:>11}  VERSION\n",
        "HOLON", "KIND", "STATE", "PACKML", "CONTROLLER", "AGENDA", "UNDELIVERED"
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
        // Bookings whose requester is absent (released after the resource's grace).
        let absent = row
            .snapshot
            .as_ref()
            .and_then(|s| s.get("agenda"))
            .and_then(|a| a.as_array())
            .map_or(0, |a| {
                a.iter()
                    .filter(|b| b.get("requester_absent_since").is_some())
                    .count()
            });
        // A journal that cannot be written marks the state (and is explained below).
        let journal_fault = row
            .snapshot
            .as_ref()
            .and_then(|s| s.get("journal_fault"))
            .and_then(|f| f.as_str());
        let agenda = if absent > 0 {
            format!("{} ({absent} absent)", field("agenda"))
        } else {
            field("agenda")
        };
        // The holon's release and the message version it speaks, for rolling upgrades.
        let version = match (
            field("version"),
            row.snapshot.as_ref().and_then(|s| s["v"].as_u64()),
        ) {
            (release, Some(v)) if v > 0 => format!("{release}/v{v}"),
            (release, _) => release,
        };
        // A resource's PackML state and number; its mode when not Production.
        let packml = row
            .snapshot
            .as_ref()
            .and_then(|s| s.get("packml"))
            .and_then(|p| serde_json::from_value::<schemas::PackmlStatus>(p.clone()).ok())
            .map_or_else(
                || "-".to_string(),
                |p| match p.mode {
                    schemas::UnitMode::Production => {
                        format!("{}({})", p.state.name(), p.state_number)
                    }
                    mode => format!("{}({})/{}", p.state.name(), p.state_number, mode.name()),
                },
            );
        out.push_str(&format!(
            "{:<28} {:<9} {:<8} {:<14} {:<13} {:>6} {:>11}  {}\n",
            row.holon.to_string(),
            row.holon.kind().to_string(),
            if row.holon.kind() == schemas::HolonKind::Order {
                field("status")
            } else if journal_fault.is_some() {
                format!("{}!", field("state"))
            } else {
                field("state")
            },
            packml,
            field("controller"),
            agenda,
            field("undelivered"),
            version,
        ));
    }
    let silent: Vec<String> = rows
        .iter()
        .filter(|r| r.snapshot.is_none())
        .map(|r| r.holon.to_string())
        .collect();
    if !silent.is_empty() {
        out.push_str(&format!(
            "? alive but no state within the timeout (slow, or cut off from this host): {}\n",
            silent.join(", ")
        ));
    }
    for row in rows {
        if let Some(why) = row
            .snapshot
            .as_ref()
            .and_then(|s| s.get("journal_fault"))
            .and_then(|f| f.as_str())
        {
            out.push_str(&format!(
                "! {}: the journal cannot be written ({why}); no new work is taken, results are held until it can\n",
                row.holon
            ));
        }
        let carriers_out: Vec<&str> = row
            .snapshot
            .as_ref()
            .and_then(|s| s.get("carriers_out"))
            .and_then(|c| c.as_array())
            .map(|c| c.iter().filter_map(|v| v.as_str()).collect())
            .unwrap_or_default();
        if !carriers_out.is_empty() {
            out.push_str(&format!(
                "~ {}: carriers out of service: {} (it lets in only as many parts as carriers are in service; `cell carrier ... --back`)\n",
                row.holon,
                carriers_out.join(", ")
            ));
        }
    }
    out
}

/// One order-node of the cell and how many of its orders stand where.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OrderNodeStatus {
    pub name: String,
    /// Its counts, or why it did not give them.
    pub counts: Result<schemas::OrderCounts, String>,
}

/// The live order-nodes (their `host/order-node/<name>` tokens) with their orders'
/// counts, each asked for a page of none ([`crate::client::listing::counts`]).
pub async fn order_nodes(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<OrderNodeStatus>> {
    let counts = crate::client::listing::counts(session, keys, timeout)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    Ok(counts
        .into_iter()
        .map(|(name, counts)| OrderNodeStatus {
            name,
            counts: counts.map_err(|e| e.to_string()),
        })
        .collect())
}

/// The order-node lines of `cell status`.
pub fn render_order_nodes(nodes: &[OrderNodeStatus]) -> String {
    if nodes.is_empty() {
        return "no order-node alive\n".into();
    }
    let mut out = format!(
        "{:<28} {:>8} {:>8} {:>8}\n",
        "ORDER-NODE", "RUNNING", "DONE", "ENDED"
    );
    for node in nodes {
        match &node.counts {
            Ok(c) => out.push_str(&format!(
                "{:<28} {:>8} {:>8} {:>8}\n",
                node.name,
                c.running,
                c.done,
                c.finished() - c.done
            )),
            Err(why) => out.push_str(&format!(
                "{:<28} {:>8} {:>8} {:>8}  (its counts: {why})\n",
                node.name, "?", "?", "?"
            )),
        }
    }
    out
}

/// Asks the order-node hosting `order` to cancel it; `by` says who asks, for the
/// order-node's log.
pub async fn cancel(
    session: &zenoh::Session,
    keys: &CellKeys,
    order: &str,
    by: &str,
    timeout: Duration,
) -> Result<schemas::CancelReply, crate::client::ask::AskError> {
    use crate::client::ask::AskError;
    let failed = |e: &dyn std::fmt::Display| AskError::Failed(format!("{e:#}"));
    // A cancel is idempotent (journalled before its reply; asked again it answers the
    // order's state), so it is asked until an order-node answers.
    let asked = crate::client::ask::until_answered(session, &keys.cancel(order), None, by, timeout)
        .await
        .map_err(|e| failed(&e))?;
    crate::client::ask::answer_of(asked, || {
        format!(
            "{} ({order}: unknown order, its order-node is down, or this identity may not cancel)",
            keys.cancel(order)
        )
    })
}

/// The table `cell orders` prints, with a summary line first; with `detail`, each
/// order's ended attempts below it (its audit trail).
pub fn render_orders(cell: &str, orders: &[schemas::OrderSnapshot], detail: bool) -> String {
    render_orders_at(cell, orders, detail, schemas::unix_ms())
}

/// The orders table as it reads at `now` (Unix ms): due times are shown from then.
pub fn render_orders_at(
    cell: &str,
    orders: &[schemas::OrderSnapshot],
    detail: bool,
    now: u64,
) -> String {
    let mut counts = schemas::OrderCounts::default();
    for order in orders {
        counts.add(order.status);
    }
    let mut out = orders_summary(cell, &counts);
    out.push_str(&orders_header());
    out.push_str(&order_rows(orders, detail, now));
    out
}

/// The summary line of the orders table.
pub fn orders_summary(cell: &str, counts: &schemas::OrderCounts) -> String {
    format!(
        "cell {cell}: {} orders: {} done, {} running, {} scrapped, {} failed, {} cancelled\n",
        counts.total(),
        counts.done,
        counts.running,
        counts.scrapped,
        counts.failed,
        counts.cancelled
    )
}

/// The header of the orders table.
pub fn orders_header() -> String {
    format!(
        "{:<22} {:<10} {:<9} {:>5} {:>9} {:>5} {:<22} {:>6} {:>7} {:>7}  REASON\n",
        "ORDER",
        "PRODUCT",
        "STATUS",
        "PRIO",
        "DUE",
        "STEP",
        "RESOURCE",
        "FAILED",
        "REBOOKS",
        "REWORKS"
    )
}

/// The orders table's rows for `orders` (with `detail`, each one's ended attempts).
pub fn order_rows(orders: &[schemas::OrderSnapshot], detail: bool, now: u64) -> String {
    let mut out = String::new();
    for o in orders {
        out.push_str(&format!(
            "{:<22} {:<10} {:<9} {:>5} {:>9} {:>5} {:<22} {:>6} {:>7} {:>7}  {}\n",
            o.holon.name(),
            o.product,
            o.status.as_str(),
            o.priority,
            due_text(o.due, o.status, now),
            format!("{}/{}", o.step, o.steps),
            o.resource
                .as_ref()
                .map(|r| r.to_string())
                .unwrap_or_else(|| "-".into()),
            o.failed_attempts,
            o.rebooks,
            o.reworks,
            o.reason.as_ref().map_or("", |r| r.as_str())
        ));
        // Where its part is (a plan that moves parts): while it is in the cell, and
        // always with detail.
        if let Some(part) = &o.part {
            let in_cell = !matches!(
                part,
                schemas::PartPlace::Outside | schemas::PartPlace::Shipped { .. }
            );
            if in_cell || detail {
                out.push_str(&format!("    part {part}\n"));
            }
        }
        if detail {
            for found in &o.part_found {
                out.push_str(&format!("    part {found}\n"));
            }
            for a in &o.attempts {
                out.push_str(&format!(
                    "    {:<24} {:<14} {:<10} {}\n",
                    a.conversation_id,
                    a.service_type,
                    a.end.as_str(),
                    a.detail
                ));
            }
        }
    }
    out
}

/// An order's due time as the table shows it: `-` without one; for a running order
/// the time left (`4m10s`) or, past it, how late (`-30s`).
fn due_text(due: Option<u64>, status: schemas::OrderStatus, now: u64) -> String {
    let Some(due) = due else {
        return "-".into();
    };
    if status != schemas::OrderStatus::Running {
        return "(ended)".into();
    }
    let span = |ms: u64| {
        let s = ms / 1000;
        match s {
            0..60 => format!("{s}s"),
            60..3600 => format!("{}m{:02}s", s / 60, s % 60),
            _ => format!("{}h{:02}m", s / 3600, (s % 3600) / 60),
        }
    };
    if due >= now {
        span(due - now)
    } else {
        format!("-{}", span(now - due))
    }
}

#[cfg(test)]
mod tests;

//! `cell orders`: the table of the cell's orders, printed a page at a time as each
//! order-node answers ([`crate::client::listing`]): each node's running orders (oldest first),
//! then its newest finished ones, as many as asked. Neither the node nor this command
//! holds the whole history at once, and a listing that could not be had whole says so
//! (and the command exits 1).

use std::io::Write;
use std::time::Duration;

use schemas::{CellKeys, OrderCounts, OrderFilter, OrderListRequest, OrderStatus};

/// What `cell orders` lists.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OrdersOptions {
    /// Which orders (`--status`).
    pub filter: OrderFilter,
    /// How many finished orders of each node, newest first (`--finished`); every one
    /// with `None` (`--all`).
    pub finished: Option<usize>,
    /// Each order's ended attempts below it (`--detail`).
    pub detail: bool,
}

/// Prints the cell's orders to `out`; true when the listing was complete.
pub async fn print(
    session: &zenoh::Session,
    keys: &CellKeys,
    cell: &str,
    options: &OrdersOptions,
    timeout: Duration,
    out: &mut dyn Write,
) -> anyhow::Result<bool> {
    // The counts first, for the summary line: a page of none from each node.
    let counted = crate::client::listing::counts(session, keys, timeout).await?;
    if counted.is_empty() {
        writeln!(
            out,
            "cell {cell}: no order-node alive: no orders can be listed (is the cell up, and is this the right --connect and --cell?)"
        )?;
        return Ok(false);
    }
    let mut total = OrderCounts::default();
    let mut incomplete: Vec<String> = Vec::new();
    let mut nodes = Vec::new();
    for (node, counts) in counted {
        match counts {
            Ok(counts) => total.merge(&counts),
            Err(e) => incomplete.push(format!("{node}: its counts: {e}")),
        }
        nodes.push(node);
    }
    out.write_all(crate::client::status::orders_summary(cell, &total).as_bytes())?;
    if !incomplete.is_empty() {
        writeln!(
            out,
            "(not counted above: {}; the listing below is incomplete)",
            incomplete.join("; ")
        )?;
    }
    out.write_all(crate::client::status::orders_header().as_bytes())?;
    let now = schemas::unix_ms();
    let mut shown_finished_total = 0u64;
    for node in &nodes {
        // The running orders (all of them), then the finished ones up to the limit.
        let mut shown_finished = 0usize;
        let limit = options.finished;
        let first = OrderListRequest::first(options.filter, schemas::MAX_PAGE_ORDERS);
        let mut failed_write = None;
        let listing =
            crate::client::listing::node_orders(session, keys, node, &first, timeout, |page| {
                let mut rows = Vec::with_capacity(page.len());
                for order in page {
                    if order.status.is_final() {
                        if limit.is_some_and(|l| shown_finished >= l) {
                            break;
                        }
                        shown_finished += 1;
                    }
                    rows.push(order);
                }
                if let Err(e) = out.write_all(
                    crate::client::status::order_rows(&rows, options.detail, now).as_bytes(),
                ) {
                    failed_write = Some(e);
                    return 0;
                }
                match limit {
                    Some(l) if shown_finished >= l => 0,
                    _ => usize::MAX,
                }
            })
            .await;
        if let Some(e) = failed_write {
            return Err(e.into());
        }
        shown_finished_total += shown_finished as u64;
        if let Some(why) = listing.incomplete {
            incomplete.push(format!("{node}: {why}"));
        }
    }
    let finished_matching = match options.filter {
        OrderFilter::Running | OrderFilter::Status(OrderStatus::Running) => 0,
        OrderFilter::All | OrderFilter::Finished => total.finished(),
        OrderFilter::Status(s) => total.of(s),
    };
    if finished_matching > shown_finished_total && incomplete.is_empty() {
        writeln!(
            out,
            "(the newest {shown_finished_total} of {finished_matching} finished orders shown: --finished N for more, --all for every one, --status for one kind)"
        )?;
    }
    if !incomplete.is_empty() {
        writeln!(
            out,
            "INCOMPLETE: not every order could be listed: {}",
            incomplete.join("; ")
        )?;
        return Ok(false);
    }
    Ok(true)
}

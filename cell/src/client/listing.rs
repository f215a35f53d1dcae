//! Listing the cell's orders a page at a time (`host/order-node/<node>/orders`,
//! [`schemas::listing`]): `cell orders`, `cell status`'s order-node lines, the
//! dashboard's and the OPC UA server's order figures, and tests that need every order.
//!
//! The order-nodes are found two ways at once ([`first_pages`]): every node that
//! answers the first page's `get` on `host/order-node/*/orders`, and every node whose
//! token (`host/order-node/*`) is alive. A node known by its token that did not answer
//! is asked again by name until the timeout; each node is then asked its further pages
//! one after the other, every page within the timeout. A node that does not answer a
//! page (busy past the timeout, gone, or a release without listings) makes the listing
//! [`incomplete`](NodeListing::incomplete), and the reader says so: a listing never
//! passes a silent "0 orders" off as the cell's.

use std::time::Duration;

use schemas::{CellKeys, OrderCounts, OrderListRequest, OrderPage, OrderSnapshot};

/// Why a page was not had.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PageError {
    /// No answer within the timeout (the node is busy, cut off or gone; or it does not
    /// serve listings: a release before them).
    #[error("no answer within {0:?}")]
    NoAnswer(Duration),
    /// The node refused the request.
    #[error("refused: {0}")]
    Refused(String),
    /// The reply could not be read.
    #[error("unreadable reply: {0}")]
    Unreadable(String),
    /// The query could not be sent.
    #[error("cannot ask: {0}")]
    Query(String),
}

/// The order-nodes whose tokens are alive, by name, sorted.
pub async fn live_nodes(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<String>, PageError> {
    let prefix = keys.host("order-node", "");
    let mut names: Vec<String> = holon::presence::tokens(session, &format!("{prefix}*"), timeout)
        .await
        .map_err(|e| PageError::Query(e.to_string()))?
        .into_iter()
        .filter_map(|key| key.strip_prefix(&prefix).map(String::from))
        .collect();
    names.sort();
    names.dedup();
    Ok(names)
}

/// The first page of `request` from every order-node of the cell, by node name, sorted:
/// those that answered the one `get` on every node's listing, and those whose token is
/// alive, each of which did not answer asked again by name ([`page`]).
pub async fn first_pages(
    session: &zenoh::Session,
    keys: &CellKeys,
    request: &OrderListRequest,
    timeout: Duration,
) -> Result<Vec<(String, Result<OrderPage, PageError>)>, PageError> {
    let payload = serde_json::to_vec(request).expect("a request serializes");
    let asked = async {
        let replies = session
            .get(keys.node_listing_all())
            .payload(payload)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(timeout)
            .await
            .map_err(|e| PageError::Query(e.to_string()))?;
        let mut pages = std::collections::BTreeMap::new();
        while let Ok(reply) = replies.recv_async().await {
            // Only pages are taken: a refusal names no node, and the node is then
            // asked again by its token.
            if let Ok(sample) = reply.result() {
                let page = serde_json::from_slice::<OrderPage>(&sample.payload().to_bytes())
                    .map_err(|e| PageError::Unreadable(e.to_string()));
                let node = sample
                    .key_expr()
                    .as_str()
                    .strip_suffix("/orders")
                    .and_then(|k| k.rsplit('/').next())
                    .unwrap_or_default()
                    .to_string();
                pages.insert(node, page);
            }
        }
        Ok::<_, PageError>(pages)
    };
    let (answered, alive) = tokio::join!(asked, live_nodes(session, keys, timeout));
    let mut pages = answered?;
    for node in alive? {
        if let std::collections::btree_map::Entry::Vacant(unanswered) = pages.entry(node) {
            let node = unanswered.key().clone();
            unanswered.insert(page(session, keys, &node, request, timeout).await);
        }
    }
    Ok(pages.into_iter().collect())
}

/// Asks `node` for one page. A node whose token is up but whose queryable has not
/// reached this session yet answers nothing at once: asked again until `timeout`.
pub async fn page(
    session: &zenoh::Session,
    keys: &CellKeys,
    node: &str,
    request: &OrderListRequest,
    timeout: Duration,
) -> Result<OrderPage, PageError> {
    let deadline = tokio::time::Instant::now() + timeout;
    let payload = serde_json::to_vec(request).expect("a request serializes");
    loop {
        let left = deadline.saturating_duration_since(tokio::time::Instant::now());
        let replies = session
            .get(keys.node_listing(node))
            .payload(payload.clone())
            .timeout(left.max(Duration::from_millis(1)))
            .await
            .map_err(|e| PageError::Query(e.to_string()))?;
        if let Ok(reply) = replies.recv_async().await {
            return match reply.result() {
                Ok(sample) => serde_json::from_slice::<OrderPage>(&sample.payload().to_bytes())
                    .map_err(|e| PageError::Unreadable(e.to_string())),
                Err(err) => Err(PageError::Refused(
                    err.payload()
                        .try_to_string()
                        .unwrap_or_default()
                        .to_string(),
                )),
            };
        }
        if tokio::time::Instant::now() + Duration::from_millis(50) >= deadline {
            return Err(PageError::NoAnswer(timeout));
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// What one node's listing gave.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct NodeListing {
    /// The node.
    pub node: String,
    /// Its counts by status, from its first page (none when it did not answer).
    pub counts: Option<OrderCounts>,
    /// How many orders the listing went through (all pages, shown or not).
    pub listed: u64,
    /// Why the listing of this node is incomplete, if it is.
    pub incomplete: Option<String>,
}

/// Runs through `node`'s pages for `request`, handing each page's orders to `each`
/// (which returns how many more it wants; 0 ends the listing early, which is not
/// incomplete). At most `pages` pages.
pub async fn node_orders<F>(
    session: &zenoh::Session,
    keys: &CellKeys,
    node: &str,
    request: &OrderListRequest,
    timeout: Duration,
    each: F,
) -> NodeListing
where
    F: FnMut(Vec<OrderSnapshot>) -> usize,
{
    let first = page(session, keys, node, request, timeout).await;
    node_orders_from(session, keys, node, request, first, timeout, each).await
}

/// [`node_orders`] from a first page already asked (`first`, [`first_pages`]).
pub async fn node_orders_from<F>(
    session: &zenoh::Session,
    keys: &CellKeys,
    node: &str,
    request: &OrderListRequest,
    first: Result<OrderPage, PageError>,
    timeout: Duration,
    mut each: F,
) -> NodeListing
where
    F: FnMut(Vec<OrderSnapshot>) -> usize,
{
    let mut listing = NodeListing {
        node: node.to_string(),
        ..NodeListing::default()
    };
    let mut request = request.clone();
    let mut next = Some(first);
    loop {
        let answer = match next.take() {
            Some(answer) => answer,
            None => page(session, keys, node, &request, timeout).await,
        };
        match answer {
            Ok(page) => {
                if listing.counts.is_none() {
                    listing.counts = Some(page.counts);
                }
                if page.unreadable > 0 {
                    listing.incomplete = Some(format!(
                        "{} finished orders could not be read from its journal (its log says why)",
                        page.unreadable
                    ));
                }
                listing.listed += page.orders.len() as u64;
                let wanted = if page.orders.is_empty() {
                    usize::MAX
                } else {
                    each(page.orders)
                };
                match page.next {
                    Some(next) if wanted > 0 => {
                        request = request.after(next);
                        if (wanted as u64) < request.limit as u64 {
                            request.limit = wanted as u32;
                        }
                    }
                    _ => return listing,
                }
            }
            Err(e) => {
                listing.incomplete = Some(match &request.after {
                    None => format!("its orders: {e}"),
                    Some(_) => format!("its orders after the {}th: {e}", listing.listed),
                });
                return listing;
            }
        }
    }
}

/// Every order of the cell (every node, every page), sorted by node and number; an
/// error naming the nodes when the listing is incomplete. For tests and tools that
/// need the whole history at once (`cell orders` prints page by page instead).
pub async fn all_orders(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> anyhow::Result<Vec<OrderSnapshot>> {
    let request = OrderListRequest::first(schemas::OrderFilter::All, schemas::MAX_PAGE_ORDERS);
    let firsts = first_pages(session, keys, &request, timeout).await?;
    if firsts.is_empty() {
        anyhow::bail!(
            "no order-node alive in cell {}: no orders can be listed",
            keys.cell()
        );
    }
    let mut orders = std::collections::BTreeMap::new();
    let mut missing = Vec::new();
    for (node, first) in firsts {
        let listing = node_orders_from(session, keys, &node, &request, first, timeout, |page| {
            for order in page {
                // Listed running, then again finished: the later copy wins.
                orders.insert(order.holon.clone(), order);
            }
            usize::MAX
        })
        .await;
        if let Some(why) = listing.incomplete {
            missing.push(format!("{node}: {why}"));
        }
    }
    if !missing.is_empty() {
        anyhow::bail!(
            "the listing of orders is incomplete: {}",
            missing.join("; ")
        );
    }
    let mut orders: Vec<OrderSnapshot> = orders.into_values().collect();
    orders.sort_by_key(|o| order_sort_key(o.holon.name()));
    Ok(orders)
}

/// Orders sort by node, then by number: `orders1-2` before `orders1-10`.
pub fn order_sort_key(name: &str) -> (String, u64) {
    name.rsplit_once('-')
        .and_then(|(node, n)| Some((node.to_string(), n.parse::<u64>().ok()?)))
        .unwrap_or_else(|| (name.to_string(), 0))
}

/// Every order-node's counts (a page of none each, [`first_pages`]), or why a node
/// did not give them.
pub async fn counts(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Vec<(String, Result<OrderCounts, PageError>)>, PageError> {
    let request = OrderListRequest::first(schemas::OrderFilter::All, 0);
    Ok(first_pages(session, keys, &request, timeout)
        .await?
        .into_iter()
        .map(|(node, page)| (node, page.map(|p| p.counts)))
        .collect())
}

/// The counts of every order-node that gave them ([`counts`]); a node that did not is
/// left out (logged at debug: a reader that polls asks again soon).
pub async fn answered_counts(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<std::collections::BTreeMap<String, OrderCounts>, PageError> {
    Ok(counts(session, keys, timeout)
        .await?
        .into_iter()
        .filter_map(|(node, counts)| match counts {
            Ok(counts) => Some((node, counts)),
            Err(e) => {
                tracing::debug!(%node, error = %e, "an order-node did not give its counts");
                None
            }
        })
        .collect())
}

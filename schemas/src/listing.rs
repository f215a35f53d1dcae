//! Listing an order-node's orders a page at a time (`host/order-node/<node>/orders`).
//!
//! A node may hold a day of finished orders in its journal; no reply carries them all.
//! A reader asks for a page ([`OrderListRequest`]) and gets at most [`MAX_PAGE_ORDERS`]
//! orders and about [`MAX_PAGE_BYTES`] of them in one reply ([`OrderPage`]), with the
//! node's counts by status and the cursor of the next page. A listing runs through the
//! running orders first (oldest first), then the finished ones (newest first); a
//! reader that wants only the counts asks for `limit: 0`.
//!
//! A listing is complete when the last page came (`next: None`); a reader that gives up
//! before then (a page not answered in time) says the listing is incomplete.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::plan::{OrderSnapshot, OrderStatus};

/// The version of the listing's messages.
pub const LISTING_VERSION: u32 = 1;

/// The most orders one page holds (a request asking for more gets this many).
pub const MAX_PAGE_ORDERS: u32 = 200;

/// A page stops growing once its orders take this many bytes as JSON (a page always
/// holds at least one order when one is left): one reply never fills a link's queue.
pub const MAX_PAGE_BYTES: usize = 128 * 1024;

/// The page size when a request does not say.
pub const DEFAULT_PAGE_ORDERS: u32 = 100;

/// Which orders a listing runs through.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum OrderFilter {
    /// Every order: the running ones, then the finished ones.
    #[default]
    All,
    /// The running orders only.
    Running,
    /// The finished orders only (done, scrapped, failed, cancelled).
    Finished,
    /// The orders of one status only.
    Status(OrderStatus),
}

impl OrderFilter {
    /// Whether an order of `status` is listed.
    pub fn admits(self, status: OrderStatus) -> bool {
        match self {
            OrderFilter::All => true,
            OrderFilter::Running => status == OrderStatus::Running,
            OrderFilter::Finished => status.is_final(),
            OrderFilter::Status(s) => s == status,
        }
    }

    /// Whether any running order can be listed.
    pub fn admits_running(self) -> bool {
        self.admits(OrderStatus::Running)
    }

    /// Whether any finished order can be listed.
    pub fn admits_finished(self) -> bool {
        !matches!(
            self,
            OrderFilter::Running | OrderFilter::Status(OrderStatus::Running)
        )
    }

    /// Parses the filter's name: `all`, `running`, `finished` or a status (`done`,
    /// `scrapped`, `failed`, `cancelled`).
    pub fn parse(text: &str) -> Result<OrderFilter, String> {
        Ok(match text {
            "all" => OrderFilter::All,
            "running" => OrderFilter::Running,
            "finished" => OrderFilter::Finished,
            "done" => OrderFilter::Status(OrderStatus::Done),
            "scrapped" => OrderFilter::Status(OrderStatus::Scrapped),
            "failed" => OrderFilter::Status(OrderStatus::Failed),
            "cancelled" => OrderFilter::Status(OrderStatus::Cancelled),
            other => {
                return Err(format!(
                    "unknown order filter {other:?} (all, running, finished, done, scrapped, failed, cancelled)"
                ))
            }
        })
    }
}

/// Where a page begins: after this order of the running orders, or after this order of
/// the finished ones (the order numbers of `<node>-<number>`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum PageCursor {
    /// The running orders numbered above this one, then every finished order.
    AfterRunning(u64),
    /// The finished orders numbered below this one (newest first).
    AfterFinished(u64),
}

/// A request for a page of a node's orders (the query's payload; an empty payload asks
/// for the first page of every order, [`DEFAULT_PAGE_ORDERS`] long).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct OrderListRequest {
    /// [`LISTING_VERSION`].
    pub v: u32,
    /// Which orders.
    #[serde(default)]
    pub filter: OrderFilter,
    /// Where the page begins (the previous page's `next`); none for the first page.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub after: Option<PageCursor>,
    /// At most this many orders (at most [`MAX_PAGE_ORDERS`]); 0 asks for the counts
    /// only.
    #[serde(default = "default_limit")]
    pub limit: u32,
}

fn default_limit() -> u32 {
    DEFAULT_PAGE_ORDERS
}

impl Default for OrderListRequest {
    fn default() -> OrderListRequest {
        OrderListRequest {
            v: LISTING_VERSION,
            filter: OrderFilter::All,
            after: None,
            limit: DEFAULT_PAGE_ORDERS,
        }
    }
}

impl OrderListRequest {
    /// A request for the first page of `filter`'s orders, `limit` long.
    pub fn first(filter: OrderFilter, limit: u32) -> OrderListRequest {
        OrderListRequest {
            filter,
            limit,
            ..OrderListRequest::default()
        }
    }

    /// The same request for the page after `cursor`.
    pub fn after(&self, cursor: PageCursor) -> OrderListRequest {
        OrderListRequest {
            after: Some(cursor),
            ..self.clone()
        }
    }

    /// The page's size as the node serves it (at most [`MAX_PAGE_ORDERS`]).
    pub fn page_size(&self) -> usize {
        self.limit.min(MAX_PAGE_ORDERS) as usize
    }

    /// Reads a request from a query's payload: empty is the default.
    pub fn from_json(payload: &[u8]) -> Result<OrderListRequest, String> {
        if payload.is_empty() {
            return Ok(OrderListRequest::default());
        }
        let request: OrderListRequest = serde_json::from_slice(payload)
            .map_err(|e| format!("malformed listing request: {e}"))?;
        if request.v != LISTING_VERSION {
            return Err(format!(
                "listing version {} is not spoken here (version {LISTING_VERSION})",
                request.v
            ));
        }
        Ok(request)
    }
}

/// How many of a node's orders stand where, as of the page.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
pub struct OrderCounts {
    pub running: u64,
    pub done: u64,
    pub scrapped: u64,
    pub failed: u64,
    pub cancelled: u64,
}

impl OrderCounts {
    /// Counts one more order of `status`.
    pub fn add(&mut self, status: OrderStatus) {
        *self.slot(status) += 1;
    }

    /// How many orders of `status`.
    pub fn of(&self, status: OrderStatus) -> u64 {
        match status {
            OrderStatus::Running => self.running,
            OrderStatus::Done => self.done,
            OrderStatus::Scrapped => self.scrapped,
            OrderStatus::Failed => self.failed,
            OrderStatus::Cancelled => self.cancelled,
        }
    }

    fn slot(&mut self, status: OrderStatus) -> &mut u64 {
        match status {
            OrderStatus::Running => &mut self.running,
            OrderStatus::Done => &mut self.done,
            OrderStatus::Scrapped => &mut self.scrapped,
            OrderStatus::Failed => &mut self.failed,
            OrderStatus::Cancelled => &mut self.cancelled,
        }
    }

    /// Every order.
    pub fn total(&self) -> u64 {
        self.running + self.finished()
    }

    /// The finished orders (every status but running).
    pub fn finished(&self) -> u64 {
        self.done + self.scrapped + self.failed + self.cancelled
    }

    /// How many orders `filter` admits.
    pub fn matching(&self, filter: OrderFilter) -> u64 {
        match filter {
            OrderFilter::All => self.total(),
            OrderFilter::Running => self.running,
            OrderFilter::Finished => self.finished(),
            OrderFilter::Status(s) => self.of(s),
        }
    }

    /// Adds another node's counts.
    pub fn merge(&mut self, other: &OrderCounts) {
        self.running += other.running;
        self.done += other.done;
        self.scrapped += other.scrapped;
        self.failed += other.failed;
        self.cancelled += other.cancelled;
    }
}

/// One page of a node's orders (the reply on `host/order-node/<node>/orders`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct OrderPage {
    /// [`LISTING_VERSION`].
    pub v: u32,
    /// The order-node.
    pub node: String,
    /// Its orders by status, when the page was made.
    pub counts: OrderCounts,
    /// The page's orders: running ones oldest first, then finished ones newest first.
    pub orders: Vec<OrderSnapshot>,
    /// Where the next page begins; none when this is the last.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub next: Option<PageCursor>,
    /// Finished orders the page passed over because the journal could not read them
    /// (the listing is then incomplete; the node logs why).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub unreadable: u64,
}

fn is_zero(n: &u64) -> bool {
    *n == 0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_request_reads_from_empty_or_json_and_checks_its_version() {
        assert_eq!(
            OrderListRequest::from_json(b"").unwrap(),
            OrderListRequest::default()
        );
        let r = OrderListRequest::from_json(
            br#"{"v":1,"filter":{"status":"failed"},"after":{"after_finished":40},"limit":5000}"#,
        )
        .unwrap();
        assert_eq!(r.filter, OrderFilter::Status(OrderStatus::Failed));
        assert_eq!(r.after, Some(PageCursor::AfterFinished(40)));
        assert_eq!(r.page_size(), MAX_PAGE_ORDERS as usize);
        assert!(OrderListRequest::from_json(br#"{"v":2}"#)
            .unwrap_err()
            .contains("version 2"));
        assert!(
            OrderListRequest::from_json(br#"{"v":1,"filter":"everything"}"#)
                .unwrap_err()
                .contains("malformed")
        );
    }

    #[test]
    fn filters_admit_their_statuses() {
        use OrderStatus::*;
        assert!(OrderFilter::All.admits(Running) && OrderFilter::All.admits(Failed));
        assert!(!OrderFilter::Finished.admits(Running) && OrderFilter::Finished.admits(Done));
        assert!(!OrderFilter::Running.admits_finished());
        assert!(!OrderFilter::Status(Done).admits_running());
        assert_eq!(
            OrderFilter::parse("scrapped"),
            Ok(OrderFilter::Status(Scrapped))
        );
        assert!(OrderFilter::parse("lost").is_err());
        let mut c = OrderCounts::default();
        c.add(Running);
        c.add(Done);
        c.add(Failed);
        assert_eq!(
            (
                c.total(),
                c.finished(),
                c.matching(OrderFilter::Status(Failed))
            ),
            (3, 2, 1)
        );
    }
}

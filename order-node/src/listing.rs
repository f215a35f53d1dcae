//! A page of an order-node's orders ([`schemas::listing`], `host/order-node/<node>/orders`):
//! the running orders from memory, the finished ones from the journal, only those of
//! the page, with the node's counts by status.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

use tracing::warn;

use crate::host::Host;
use crate::progress::OrderProgress;

impl Host {
    /// A page of this node's orders ([`schemas::listing`]): the running orders oldest
    /// first, then the finished ones newest first, as `request` filters them, at most
    /// [`schemas::MAX_PAGE_ORDERS`] and about [`schemas::MAX_PAGE_BYTES`] of them, with
    /// the node's counts. Finished orders are read from the journal, only those of the
    /// page; what the journal cannot read is counted in `unreadable` and passed over.
    pub fn page(&self, request: &schemas::OrderListRequest) -> schemas::OrderPage {
        use schemas::{OrderCounts, OrderStatus, PageCursor};
        let filter = request.filter;
        let size = request.page_size();
        // What memory holds: (number, status, progress), numbered orders only.
        let mut in_memory: Vec<(u64, OrderStatus, Arc<Mutex<OrderProgress>>)> = {
            let orders = self.orders.lock().unwrap_or_else(|e| e.into_inner());
            orders
                .iter()
                .filter_map(|(name, hosted)| {
                    let status = hosted
                        .progress
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .status;
                    Some((self.number(name)?, status, hosted.progress.clone()))
                })
                .collect()
        };
        in_memory.sort_by_key(|(number, ..)| *number);
        let mut counts = OrderCounts::default();
        for (_, status, _) in &in_memory {
            counts.add(*status);
        }
        let mut page = schemas::OrderPage {
            v: schemas::LISTING_VERSION,
            node: self.config.name.clone(),
            counts,
            orders: Vec::new(),
            next: None,
            unreadable: 0,
        };
        // The finished orders of the journal: counted, and the page's candidates.
        let below = match request.after {
            Some(PageCursor::AfterFinished(n)) => n,
            _ => u64::MAX,
        };
        let mut from_journal: Vec<u64> = Vec::new();
        {
            let finished = self.finished.lock().unwrap_or_else(|e| e.into_inner());
            for ended in finished.values() {
                page.counts.add(ended.status);
            }
            if size > 0 && filter.admits_finished() {
                from_journal = finished
                    .range(..below)
                    .rev()
                    .filter(|(_, ended)| filter.admits(ended.status))
                    .map(|(number, _)| *number)
                    .take(size + 1)
                    .collect();
            }
        }
        if size == 0 {
            return page;
        }
        let mut bytes = 0usize;
        // Whether the page takes another order.
        let room = |page: &schemas::OrderPage, bytes: usize| {
            page.orders.len() < size && (page.orders.is_empty() || bytes < schemas::MAX_PAGE_BYTES)
        };
        let push =
            |page: &mut schemas::OrderPage, bytes: &mut usize, snapshot: schemas::OrderSnapshot| {
                *bytes += serde_json::to_vec(&snapshot).map_or(0, |b| b.len());
                page.orders.push(snapshot);
            };
        // The running orders, oldest first.
        if filter.admits_running() && !matches!(request.after, Some(PageCursor::AfterFinished(_))) {
            let after = match request.after {
                Some(PageCursor::AfterRunning(n)) => Some(n),
                _ => None,
            };
            let running = in_memory.iter().filter(|(number, status, _)| {
                *status == OrderStatus::Running && after.is_none_or(|a| *number > a)
            });
            let mut last = None;
            for (number, _, progress) in running {
                if !room(&page, bytes) {
                    break;
                }
                let snapshot = progress
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .snapshot();
                push(&mut page, &mut bytes, snapshot);
                last = Some(*number);
            }
            if !room(&page, bytes) {
                // Full: the next page goes on after the last running order (at worst
                // it finds nothing more to list).
                page.next = last.map(PageCursor::AfterRunning);
                return page;
            }
        }
        if !filter.admits_finished() {
            return page;
        }
        // The finished orders, newest first: those memory holds (no journal) and those
        // the journal holds, merged by number.
        enum Source {
            Memory(Arc<Mutex<OrderProgress>>),
            Journal,
        }
        let mut candidates: Vec<(u64, Source)> = in_memory
            .into_iter()
            .filter(|(number, status, _)| {
                status.is_final() && filter.admits(*status) && *number < below
            })
            .map(|(number, _, progress)| (number, Source::Memory(progress)))
            .chain(from_journal.into_iter().map(|n| (n, Source::Journal)))
            .collect();
        candidates.sort_by_key(|c| std::cmp::Reverse(c.0));
        let left = size - page.orders.len();
        let more = candidates.len() > left;
        candidates.truncate(left);
        let names: Vec<String> = candidates
            .iter()
            .filter(|(_, source)| matches!(source, Source::Journal))
            .map(|(number, _)| format!("{}-{number}", self.config.name))
            .collect();
        let mut read: BTreeMap<String, OrderProgress> = match self.read_finished(&names) {
            Ok(read) => read.into_iter().collect(),
            Err(e) => {
                warn!(node = %self.config.name, orders = names.len(), error = %e, "cannot read finished orders from the journal for a listing; the page says how many it passed over");
                BTreeMap::new()
            }
        };
        let mut last = None;
        for (number, source) in candidates {
            if !room(&page, bytes) {
                page.next = last.map(PageCursor::AfterFinished);
                return page;
            }
            let snapshot = match source {
                Source::Memory(progress) => Some(
                    progress
                        .lock()
                        .unwrap_or_else(|e| e.into_inner())
                        .snapshot(),
                ),
                Source::Journal => read
                    .remove(&format!("{}-{number}", self.config.name))
                    .map(|progress| progress.snapshot()),
            };
            match snapshot {
                Some(snapshot) => push(&mut page, &mut bytes, snapshot),
                None => page.unreadable += 1,
            }
            last = Some(number);
        }
        if more {
            page.next = last.map(PageCursor::AfterFinished);
        }
        page
    }
}

//! A page of an order-node's orders ([`schemas::listing`], `host/order-node/<node>/orders`):
//! the running orders from memory, the finished ones from the journal, only those of
//! the page, with the node's counts by status.

use std::collections::BTreeMap;

use schemas::{OrderPage, OrderSnapshot, OrderStatus, PageCursor};
use tracing::warn;

use crate::context::ProgressView;
use crate::host::Host;
use crate::progress::OrderProgress;

/// A page being filled: at most `size` orders, and about [`schemas::MAX_PAGE_BYTES`].
struct Filling {
    /// The page so far.
    page: OrderPage,
    /// How many orders it takes at most.
    size: usize,
    /// The bytes of the orders on it so far.
    bytes: usize,
}

impl Filling {
    /// Whether the page takes another order.
    fn room(&self) -> bool {
        self.page.orders.len() < self.size
            && (self.page.orders.is_empty() || self.bytes < schemas::MAX_PAGE_BYTES)
    }

    fn push(&mut self, snapshot: OrderSnapshot) {
        self.bytes += serde_json::to_vec(&snapshot).map_or(0, |b| b.len());
        self.page.orders.push(snapshot);
    }
}

/// Where a finished order on the page is read from.
enum Source<'a> {
    /// Memory (no journal, or its end could not be recorded).
    Memory(&'a ProgressView),
    /// The journal.
    Journal,
}

impl Host {
    /// A page of this node's orders ([`schemas::listing`]): the running orders oldest
    /// first, then the finished ones newest first, as `request` filters them, at most
    /// [`schemas::MAX_PAGE_ORDERS`] and about [`schemas::MAX_PAGE_BYTES`] of them, with
    /// the node's counts. Finished orders are read from the journal, only those of the
    /// page; what the journal cannot read is counted in `unreadable` and passed over.
    pub fn page(&self, request: &schemas::OrderListRequest) -> OrderPage {
        let filter = request.filter;
        let size = request.page_size();
        // What memory holds: (number, status, progress), numbered orders only.
        let mut in_memory: Vec<(u64, OrderStatus, &ProgressView)> = self
            .orders
            .iter()
            .filter_map(|(name, hosted)| {
                let status = hosted.progress.borrow().status;
                Some((self.number(name)?, status, &hosted.progress))
            })
            .collect();
        in_memory.sort_by_key(|(number, ..)| *number);
        let mut counts = schemas::OrderCounts::default();
        for (_, status, _) in &in_memory {
            counts.add(*status);
        }
        for ended in self.finished.values() {
            counts.add(ended.status);
        }
        let mut filling = Filling {
            page: OrderPage {
                v: schemas::LISTING_VERSION,
                node: self.config.name.clone(),
                counts,
                orders: Vec::new(),
                next: None,
                unreadable: 0,
            },
            size,
            bytes: 0,
        };
        if size == 0 {
            return filling.page;
        }
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
                if !filling.room() {
                    break;
                }
                filling.push(progress.borrow().snapshot());
                last = Some(*number);
            }
            if !filling.room() {
                // Full: the next page goes on after the last running order (at worst
                // it finds nothing more to list).
                filling.page.next = last.map(PageCursor::AfterRunning);
                return filling.page;
            }
        }
        if !filter.admits_finished() {
            return filling.page;
        }
        self.finished_part(request, in_memory, &mut filling);
        filling.page
    }

    /// The finished orders of the page, newest first: those memory holds (no journal)
    /// and those the journal holds, merged by number.
    fn finished_part(
        &self,
        request: &schemas::OrderListRequest,
        in_memory: Vec<(u64, OrderStatus, &ProgressView)>,
        filling: &mut Filling,
    ) {
        let filter = request.filter;
        let below = match request.after {
            Some(PageCursor::AfterFinished(n)) => n,
            _ => u64::MAX,
        };
        let left = filling.size - filling.page.orders.len();
        let from_journal = self
            .finished
            .range(..below)
            .rev()
            .filter(|(_, ended)| filter.admits(ended.status))
            .map(|(number, _)| (*number, Source::Journal))
            .take(left + 1);
        let mut candidates: Vec<(u64, Source)> = in_memory
            .into_iter()
            .filter(|(number, status, _)| {
                status.is_final() && filter.admits(*status) && *number < below
            })
            .map(|(number, _, progress)| (number, Source::Memory(progress)))
            .chain(from_journal)
            .collect();
        candidates.sort_by_key(|c| std::cmp::Reverse(c.0));
        let more = candidates.len() > left;
        candidates.truncate(left);
        let names: Vec<String> = candidates
            .iter()
            .filter(|(_, source)| matches!(source, Source::Journal))
            .map(|(number, _)| crate::host::order_name_of(&self.config.name, *number))
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
            if !filling.room() {
                filling.page.next = last.map(PageCursor::AfterFinished);
                return;
            }
            let snapshot = match source {
                Source::Memory(progress) => Some(progress.borrow().snapshot()),
                Source::Journal => read
                    .remove(&crate::host::order_name_of(&self.config.name, number))
                    .map(|progress| progress.snapshot()),
            };
            match snapshot {
                Some(snapshot) => filling.push(snapshot),
                None => filling.page.unreadable += 1,
            }
            last = Some(number);
        }
        if more {
            filling.page.next = last.map(PageCursor::AfterFinished);
        }
    }
}

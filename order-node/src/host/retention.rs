//! The retention sweep of a node's orders: the finished orders and the named work
//! orders older than `keep_finished` leave the journal, then memory.

use std::time::Duration;

use tracing::{info, warn};

use super::{Host, FORGET_AT_ONCE};
use crate::context::ORDER_RECORD;
use crate::submits::SUBMIT_RECORD;

impl Host {
    /// Forgets the orders that finished more than `keep` ago (at most
    /// [`FORGET_AT_ONCE`]): out of the journal first, in one commit, then out of memory
    /// (and out of [`Host::finished`]). When the delete fails they stay until the next
    /// sweep. Returns how many went.
    pub fn forget_finished(&mut self, keep: Duration) -> usize {
        let now = schemas::unix_ms();
        let keep_ms = keep.as_millis() as u64;
        let expired_at = |at: u64| now.saturating_sub(at) > keep_ms;
        self.forget_submits_before(now.saturating_sub(keep_ms));
        let mut expired: Vec<String> = self
            .orders
            .iter()
            .filter(|(_, hosted)| {
                let p = hosted.progress.borrow();
                p.status.is_final() && p.finished_at.is_some_and(expired_at)
            })
            .map(|(name, _)| name.clone())
            .take(FORGET_AT_ONCE)
            .collect();
        let in_journal: Vec<u64> = self
            .finished
            .iter()
            .filter(|(_, ended)| expired_at(ended.at))
            .map(|(number, _)| *number)
            .take(FORGET_AT_ONCE - expired.len())
            .collect();
        expired.extend(
            in_journal
                .iter()
                .map(|number| super::order_name_of(&self.config.name, *number)),
        );
        if expired.is_empty() {
            return 0;
        }
        if let Some(journal) = &self.context.journal {
            if let Err(e) = holon::journal::blocking(|| journal.delete(ORDER_RECORD, &expired)) {
                warn!(node = %self.config.name, orders = expired.len(), error = %e, "cannot remove finished orders from the journal; tried again at the next sweep");
                return 0;
            }
        }
        for name in &expired {
            self.orders.remove(name);
        }
        for number in &in_journal {
            self.finished.remove(number);
        }
        info!(node = %self.config.name, orders = expired.len(), ?keep, "finished orders left the journal");
        expired.len()
    }

    /// Forgets the named work orders made before `before` (Unix ms), from the journal
    /// first; those it could not remove there are tried again at the next sweep.
    fn forget_submits_before(&mut self, before: u64) {
        let old = self.submits.made_before(before, FORGET_AT_ONCE);
        if old.is_empty() {
            return;
        }
        if let Some(journal) = &self.context.journal {
            if let Err(e) = holon::journal::blocking(|| journal.delete(SUBMIT_RECORD, &old)) {
                warn!(node = %self.config.name, names = old.len(), error = %e, "cannot remove named work orders from the journal; tried again at the next sweep");
                return;
            }
        }
        self.submits.forget(&old);
    }
}

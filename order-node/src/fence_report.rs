//! Where this process of an order-node on etcd stands, holder or standby, for `cell
//! status` and the dashboard: `holarchy/<cell>/host/order-node/<name>/fence/<zid>`,
//! one key per process, answered to a query (docs/reliability.md, "Order-node standby
//! on etcd"). A standby declares this queryable and nothing else.

use schemas::fence::NodeFenceReport;
use schemas::FenceRole;
use tokio::sync::watch;
use tracing::warn;

/// This process's report: its key's queryable and its latest value.
pub struct Reporter {
    /// The latest report, read by the queryable's callback.
    report: watch::Sender<NodeFenceReport>,
    /// Answers queries while the process lives (None if it could not be declared).
    _queryable: Option<zenoh::query::Queryable<()>>,
}

/// A standby's report before its first read: it has heard of no holder.
pub fn first_report(node: &str, host: String, zid: String, at: u64) -> NodeFenceReport {
    NodeFenceReport {
        node: node.to_string(),
        role: FenceRole::Standby,
        epoch: None,
        holder_epoch: None,
        lag: None,
        store_lost: false,
        host,
        zid,
        at,
    }
}

impl Reporter {
    /// Declares this process's report under `prefix` (`CellKeys::node_fence`), a
    /// standby that has read nothing yet. A report that cannot be declared (e.g. an
    /// access control that does not allow it) is logged: the fence does not depend on
    /// it.
    pub async fn declare(node: &str, prefix: &str, session: &zenoh::Session) -> Reporter {
        let zid = session.zid().to_string();
        let key = format!("{prefix}/{zid}");
        let report = watch::Sender::new(first_report(
            node,
            holon::presence::host_name(),
            zid,
            schemas::unix_ms(),
        ));
        let queryable = holon::query::answer_latest(session, &key, report.subscribe()).await;
        let queryable = match queryable {
            Ok(queryable) => Some(queryable),
            Err(e) => {
                warn!(%node, %key, error = %e, "cannot declare where this order-node stands: cell status will not list it");
                None
            }
        };
        Reporter {
            report,
            _queryable: queryable,
        }
    }

    /// A holder at `epoch`.
    pub fn holder(&self, epoch: u64) {
        self.report.send_modify(|report| {
            report.role = FenceRole::Holder;
            report.epoch = Some(epoch);
            report.holder_epoch = None;
            report.lag = None;
            report.store_lost = false;
            report.at = schemas::unix_ms();
        });
    }

    /// A standby that read the journal: the holder's epoch (none while the key is
    /// free) and the revisions it has not read.
    pub fn following(&self, holder_epoch: Option<u64>, lag: u64) {
        self.report.send_modify(|report| {
            report.role = FenceRole::Standby;
            report.holder_epoch = holder_epoch;
            report.lag = Some(lag);
            report.store_lost = false;
            report.at = schemas::unix_ms();
        });
    }

    /// A standby that cannot reach etcd: what it last read stands, marked lost.
    pub fn store_lost(&self) {
        self.report.send_modify(|report| {
            report.store_lost = true;
            report.at = schemas::unix_ms();
        });
    }

    /// The report as it stands.
    pub fn now(&self) -> NodeFenceReport {
        self.report.borrow().clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_report_follows_the_standby_then_the_holder() {
        let reporter = Reporter {
            report: watch::Sender::new(first_report("orders", "b".into(), "z".into(), 1)),
            _queryable: None,
        };
        assert_eq!(reporter.now().role, FenceRole::Standby);
        reporter.following(Some(7), 0);
        reporter.store_lost();
        let lost = reporter.now();
        assert_eq!(
            (lost.holder_epoch, lost.lag, lost.store_lost),
            (Some(7), Some(0), true)
        );
        reporter.following(Some(7), 3);
        assert!(!reporter.now().store_lost);
        reporter.holder(9);
        let held = reporter.now();
        assert_eq!(held.role, FenceRole::Holder);
        assert_eq!(
            (held.epoch, held.holder_epoch, held.lag),
            (Some(9), None, None)
        );
    }
}

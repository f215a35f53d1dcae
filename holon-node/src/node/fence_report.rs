//! What a fenced resource says of itself, so that watchers tell holders apart:
//! `holarchy/<cell>/resource/<name>/fence/<zid>`, one key per process (a holder and its
//! standbys side by side), answered to a query and put on every change.

use schemas::{FenceReport, FenceRole};
use tokio::sync::watch;
use tracing::{debug, warn};

use crate::config::ResourceConfig;

/// The report of this process: its key's queryable and its latest value.
pub struct Reporter {
    /// `.../resource/<name>/fence/<zid>`.
    key: String,
    /// Where it is put on each change.
    session: zenoh::Session,
    /// The latest report, read by the queryable's callback.
    report: watch::Sender<FenceReport>,
    /// Answers queries while the process lives (None if it could not be declared).
    _queryable: Option<zenoh::query::Queryable<()>>,
}

/// `holarchy/<cell>/resource/<name>/fence`: every process's report is under it.
pub fn fence_prefix(config: &ResourceConfig) -> String {
    config.keys.fence(config.holon.name())
}

impl Reporter {
    /// Declares this process's report (a standby that has heard of no holder yet). A
    /// report that cannot be declared (e.g. an access control that does not allow
    /// it) is logged: the fence does not depend on it.
    pub async fn declare(config: &ResourceConfig, session: &zenoh::Session) -> Reporter {
        let zid = session.zid().to_string();
        let key = format!("{}/{zid}", fence_prefix(config));
        let report = watch::Sender::new(FenceReport {
            holon: config.holon.clone(),
            role: FenceRole::Standby,
            epoch: None,
            holder_epoch: None,
            host: holon::presence::host_name(),
            zid,
            at: schemas::unix_ms(),
        });
        let queryable = holon::query::answer_latest(session, &key, report.subscribe()).await;
        let queryable = match queryable {
            Ok(queryable) => Some(queryable),
            Err(e) => {
                warn!(holon = %config.holon, %key, error = %e, "cannot declare the fence report; watchers see the holder's token only");
                None
            }
        };
        Reporter {
            key,
            session: session.clone(),
            report,
            _queryable: queryable,
        }
    }

    /// A holder with `epoch`.
    pub async fn holder(&self, epoch: u64) {
        self.set(FenceRole::Holder, Some(epoch), None).await;
    }

    /// A standby; `holder_epoch` when the controller said it.
    pub async fn standby(&self, holder_epoch: Option<u64>) {
        self.set(FenceRole::Standby, None, holder_epoch).await;
    }

    async fn set(&self, role: FenceRole, epoch: Option<u64>, holder_epoch: Option<u64>) {
        self.report.send_modify(|report| {
            report.role = role;
            report.epoch = epoch;
            report.holder_epoch = holder_epoch;
            report.at = schemas::unix_ms();
        });
        let payload = serde_json::to_vec(&*self.report.borrow()).expect("a report serializes");
        if let Err(e) = self.session.put(&self.key, payload).await {
            debug!(key = %self.key, error = %e, "cannot put the fence report");
        }
    }
}

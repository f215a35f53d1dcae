//! The life cycle every holon process shares, written once: resources, products, staff
//! holons and order-nodes each say who they are ([`Life`]), what is their own
//! ([`Behaviour`], [`Work`]) and who may serve ([`Leadership`]), and [`run`] drives
//! their whole life, along the phases of [`machine`]:
//!
//! | step | what happens | here |
//! |---|---|---|
//! | open | the zenoh session, as the process's TLS identity | [`Life::open`] |
//! | take over | with `--take-over`, the running process of the name hands over first ([`crate::takeover`]) | [`Life::open`] |
//! | claim | the leadership: a twin refused ([`LivelinessClaim`]), the etcd leader key campaigned for | [`Leadership::win`] |
//! | start | the holon's own work: its components, its queryables, its journal | [`Behaviour::start`] |
//! | hold | the leadership once the work runs: a fenced resource claims its controller | [`Leadership::hold`] |
//! | announce | the liveliness token, and the listener for successors | [`Life::announce`] |
//! | serve | the holon's events; a successor refused, or prepared for ([`Work::prepare`]) | [`run`] |
//! | stand in | handing over: the stand-in declared, the work stopped and its journal closed; then the token and the claim go, the successor is released, and the process stands in until the successor serves | [`run`] |
//! | leave | stopped: work handed back, token withdrawn, work stopped; deposed: the same, then claim again or end | [`run`] |
//! | close | the session, bounded | [`close`] |

use std::path::PathBuf;
use std::time::Duration;

use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::presence::{Claim, ClaimError, Holder};
use crate::session::{SessionError, ZenohSettings};
use crate::takeover::{self, Listener, NoSuccessor, TakenOver, TakeoverError};

pub mod driver;
#[cfg(test)]
mod driver_tests;
pub mod machine;

pub use driver::{
    run, unavailable_answer, Behaviour, Held, Leadership, Leaving, LivelinessClaim, Next, Process,
    StandInSpec, Start, Work, HANDOVER_RETRY,
};

/// How long closing a session may take before the process goes on without it.
const CLOSE_WITHIN: Duration = Duration::from_secs(5);

/// Who a holon process is, for its life cycle.
#[derive(Debug, Clone)]
pub struct Life {
    /// The key of its liveliness token (`holarchy/<cell>/alive/<kind>/<name>`, or
    /// `holarchy/<cell>/host/order-node/<name>`): claimed, announced, taken over on.
    pub presence_key: String,
    /// How it is named in logs and in the claim's refusal (`resource/robot1`,
    /// `order-node orders1`).
    pub holder: String,
    /// This build's release, told to a predecessor and to successors.
    pub version: &'static str,
    /// `--take-over`: start as the successor of the running process of the name,
    /// waiting at most this long for it to hand over.
    pub take_over: Option<Duration>,
    /// Its data directory, if it keeps a journal: a predecessor refuses a successor
    /// that would not open its journal.
    pub data_dir: Option<PathBuf>,
    /// How long the session's opening and the claim may take.
    pub startup_timeout: Duration,
}

/// Why a step of the life cycle failed.
#[derive(Debug, thiserror::Error)]
pub enum LifeError {
    #[error(transparent)]
    Session(#[from] SessionError),
    #[error(transparent)]
    Claim(#[from] ClaimError),
    /// Shown as the take-over's own error, which stays in the chain (its exit code).
    #[error("{0}")]
    Takeover(#[from] TakeoverError),
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// Handed over, and no successor served: the supervisor starts this process again.
    #[error(transparent)]
    NoSuccessor(#[from] NoSuccessor),
}

/// A session opened, and the predecessor's hand-over if there was one.
pub struct Opened {
    /// The session, as the process's identity.
    pub session: zenoh::Session,
    /// `Some` when the process was started with `--take-over`: the predecessor's
    /// answer, or `Nobody` when no process held the name.
    pub taken_over: Option<TakenOver>,
}

/// What the holon shows the cell while it serves: its token, and the listener that
/// hears a successor ask to take over.
pub struct Announced {
    /// The name's liveliness token: withdrawn when the holon leaves.
    pub token: zenoh::liveliness::LivelinessToken,
    /// The take-over queryable, when the holon takes successors.
    pub successors: Option<Listener>,
}

impl Life {
    /// Opens the session as `tls_identity` and, with `--take-over`, takes over from the
    /// running process. `None` when `shutdown` came while it was taking over (the
    /// session is then closed); on an error the session is closed too.
    pub async fn open(
        &self,
        zenoh: &ZenohSettings,
        tls_identity: &str,
        shutdown: &CancellationToken,
    ) -> Result<Option<Opened>, LifeError> {
        let session = zenoh.open(tls_identity, self.startup_timeout).await?;
        info!(holon = %self.holder, zid = %session.zid(), "zenoh session open");
        let Some(wait) = self.take_over else {
            return Ok(Some(Opened {
                session,
                taken_over: None,
            }));
        };
        let request = takeover::Request {
            successor: Holder::this_process(&session),
            version: self.version.to_string(),
            data_dir: self
                .data_dir
                .as_deref()
                .map(|d| std::fs::canonicalize(d).unwrap_or_else(|_| d.to_path_buf())),
            wait_ms: wait.as_millis() as u64,
        };
        let taken = tokio::select! {
            taken = takeover::take_over(&session, &self.presence_key, &self.holder, &request) => taken,
            _ = shutdown.cancelled() => {
                warn!(holon = %self.holder, "told to stop while taking over; the running process may hand over to nobody (it then exits, and its supervisor starts it again)");
                close(&self.holder, session).await;
                return Ok(None);
            }
        };
        match taken {
            Ok(taken) => Ok(Some(Opened {
                session,
                taken_over: Some(taken),
            })),
            Err(e) => {
                close(&self.holder, session).await;
                Err(e.into())
            }
        }
    }

    /// Claims the name: a twin is refused, naming the process that holds it. Keep the
    /// claim for as long as the holon serves.
    pub async fn claim(&self, session: &zenoh::Session) -> Result<Claim, LifeError> {
        Ok(crate::presence::claim(
            session,
            &self.presence_key,
            &self.holder,
            self.startup_timeout,
        )
        .await?)
    }

    /// Declares the token (the holon serves: others may book it, ask it, watch it) and,
    /// if it takes successors, listens for them.
    pub async fn announce(
        &self,
        session: &zenoh::Session,
        takes_successors: bool,
    ) -> Result<Announced, LifeError> {
        let described = |e: zenoh::Error| LifeError::Zenoh(crate::zenoh_error::describe(&e));
        let token = session
            .liveliness()
            .declare_token(&self.presence_key)
            .await
            .map_err(described)?;
        if !takes_successors {
            return Ok(Announced {
                token,
                successors: None,
            });
        }
        let successors = takeover::listen(session, &self.presence_key)
            .await
            .map_err(described)?;
        info!(holon = %self.holder, key = %self.presence_key, "holon ready");
        Ok(Announced {
            token,
            successors: Some(successors),
        })
    }
}

/// Whether two data directories are one (canonicalized where they exist): a successor
/// whose is not its predecessor's would not open its journal.
pub fn same_data_dir(mine: Option<&std::path::Path>, theirs: Option<&std::path::Path>) -> bool {
    let canonical =
        |d: &std::path::Path| std::fs::canonicalize(d).unwrap_or_else(|_| d.to_path_buf());
    mine.map(canonical) == theirs.map(canonical)
}

/// Closes `session`, waiting at most [`CLOSE_WITHIN`]: a process that stops does not
/// hang on a link that does not answer.
pub async fn close(holon: &str, session: zenoh::Session) {
    match tokio::time::timeout(CLOSE_WITHIN, session.close()).await {
        Ok(Ok(())) => {}
        Ok(Err(e)) => warn!(%holon, error = %e, "cannot close the zenoh session"),
        Err(_) => warn!(%holon, "the zenoh session did not close within {CLOSE_WITHIN:?}"),
    }
}

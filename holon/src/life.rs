//! The life cycle every holon process shares, written once: resources, products, staff
//! holons and order-nodes each say who they are ([`Life`]) and call these steps in order.
//!
//! | step | what happens | here |
//! |---|---|---|
//! | open | the zenoh session, as the process's TLS identity | [`Life::open`] |
//! | take over | with `--take-over`, the running process of the name hands over first ([`crate::takeover`]) | [`Life::open`] |
//! | claim | a twin (the name alive elsewhere in the cell) is refused before anything is answered | [`Life::claim`] |
//! | serve | the holon's own work: its components, its queryables | the holon |
//! | announce | the liveliness token, and the listener for successors | [`Life::announce`] |
//! | stand in | handing over: the holon stops its work and closes its journal; then the token and the claim go, the successor is released, and the process stands in until the successor serves | [`Life::let_go`] |
//! | close | the session, bounded | [`close`] |
//!
//! A fenced resource on standby (`holon-node --standby`) claims its controller, not the
//! name, before it announces itself; it uses [`Life::open`] and [`Life::announce`] the same.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::presence::{Claim, ClaimError, Holder};
use crate::session::{SessionError, ZenohSettings};
use crate::takeover::{self, Listener, NoSuccessor, Offer, StandInEnd, TakenOver, TakeoverError};

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
    pub session: zenoh::Session,
    /// `Some` when the process was started with `--take-over`: the predecessor's
    /// answer, or `Nobody` when no process held the name.
    pub taken_over: Option<TakenOver>,
}

/// What the holon shows the cell while it serves: its token, and the listener that
/// hears a successor ask to take over.
pub struct Announced {
    pub token: zenoh::liveliness::LivelinessToken,
    pub successors: Listener,
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

    /// Whether a successor's data directory is this process's: it would open the same
    /// journal (a hand-over to one that would not is refused).
    pub fn opens_my_journal(&self, request: &takeover::Request) -> bool {
        let canonical = |dir: Option<&std::path::Path>| {
            dir.map(|d| std::fs::canonicalize(d).unwrap_or_else(|_| d.to_path_buf()))
        };
        canonical(self.data_dir.as_deref()) == canonical(request.data_dir.as_deref())
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

    /// [`Life::open`], then [`Life::claim`]: a holon that has nothing to set up
    /// between the two. The session is closed if the claim is refused.
    pub async fn join(
        &self,
        zenoh: &ZenohSettings,
        tls_identity: &str,
        shutdown: &CancellationToken,
    ) -> Result<Option<(Opened, Claim)>, LifeError> {
        let Some(opened) = self.open(zenoh, tls_identity, shutdown).await? else {
            return Ok(None);
        };
        match self.claim(&opened.session).await {
            Ok(claim) => Ok(Some((opened, claim))),
            Err(e) => {
                close(&self.holder, opened.session).await;
                Err(e)
            }
        }
    }

    /// Declares the token (the holon serves: others may book it, ask it, watch it) and
    /// listens for successors.
    pub async fn announce(&self, session: &zenoh::Session) -> Result<Announced, LifeError> {
        let described = |e: zenoh::Error| LifeError::Zenoh(crate::zenoh_error::describe(&e));
        let token = session
            .liveliness()
            .declare_token(&self.presence_key)
            .await
            .map_err(described)?;
        let successors = takeover::listen(session, &self.presence_key)
            .await
            .map_err(described)?;
        info!(holon = %self.holder, key = %self.presence_key, "holon ready");
        Ok(Announced { token, successors })
    }

    /// The end of a hand-over, once the holon has stopped its work and closed its
    /// journal (its stand-in answers meanwhile): withdraws the token and the claim,
    /// releases the successor, and stands in until the successor serves, for at most
    /// [`takeover::STAND_IN_LIMIT`], or until `shutdown`. `started` is when the hand-
    /// over began, for the logs. An error when no successor served: the supervisor
    /// starts this process again, on its journal.
    pub async fn let_go(
        &self,
        session: &zenoh::Session,
        token: zenoh::liveliness::LivelinessToken,
        claim: Claim,
        offer: Offer,
        started: Instant,
        shutdown: &CancellationToken,
    ) -> Result<(), LifeError> {
        let holon = &self.holder;
        if let Err(e) = token.undeclare().await {
            warn!(%holon, error = %e, "cannot withdraw the liveliness token; it goes with the session");
        }
        drop(claim);
        let successor = offer.request.successor.clone();
        offer.release(self.version).await;
        info!(%holon, %successor, released_in_ms = started.elapsed().as_millis() as u64, "handed over: work stopped, journal closed, token withdrawn; standing in until the successor serves");
        let end = takeover::stand_by(session, &self.presence_key, shutdown).await;
        let gap_ms = started.elapsed().as_millis() as u64;
        match end {
            StandInEnd::Served => {
                info!(%holon, gap_ms, "the successor serves; this process ends");
                Ok(())
            }
            StandInEnd::Shutdown => {
                warn!(%holon, gap_ms, "told to stop while standing in for the successor");
                Ok(())
            }
            StandInEnd::NoSuccessor => {
                warn!(%holon, gap_ms, "the successor did not serve within the stand-in limit; this process ends with an error, so that its supervisor starts it again (on its journal, where it left off)");
                Err(NoSuccessor {
                    successor: successor.to_string(),
                }
                .into())
            }
        }
    }
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

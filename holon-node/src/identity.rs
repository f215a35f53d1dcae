//! Who a holon without hardware or journal (a product, a staff holon) is in the cell:
//! the `cell`, `name`, `kind` and `[zenoh]` of its config with the command line applied
//! and checked, and its session opened as that identity with its name claimed.

use holon::ZenohSettings;
use schemas::{CellKeys, HolonId, HolonKind};
use tracing::warn;

use crate::config::{ConfigError, Overrides};
use crate::node::{NodeError, STARTUP_TIMEOUT};

/// A plain holon's identity, from its config file.
#[derive(Debug, Clone)]
pub struct Identity {
    pub keys: CellKeys,
    /// `<kind>/<name>`.
    pub holon: HolonId,
    pub zenoh: ZenohSettings,
    /// Start as the successor of the running process (`--take-over`), waiting this
    /// long at most for it to hand over.
    pub take_over: Option<std::time::Duration>,
}

pub use holon::config_file::Header;

impl Identity {
    /// Checks `header` (of the file at `path`, whose `kind` field says `written_kind`)
    /// for a holon of `kind`, with the command line's `overrides` applied. Such a holon
    /// keeps no state: a data directory, if given, is not used.
    pub fn from_header(
        header: Header,
        written_kind: &str,
        kind: HolonKind,
        path: &str,
        overrides: &Overrides,
    ) -> Result<Identity, ConfigError> {
        let invalid = holon::config_file::invalid(path);
        if written_kind != kind.to_string() {
            return Err(invalid(format!("kind: {written_kind:?} is not {kind}")));
        }
        let header = header
            .check(
                path,
                &overrides.common,
                &mut None,
                holon::role::Role::of_holon(kind),
            )
            .map_err(&invalid)?;
        let holon = HolonId::new(kind, &header.name).map_err(|e| invalid(format!("name: {e}")))?;
        Ok(Identity {
            keys: header.keys,
            holon,
            zenoh: header.zenoh,
            take_over: overrides.common.take_over,
        })
    }

    /// Who the holon is, for the life cycle every holon shares.
    pub fn life(&self) -> holon::life::Life {
        holon::life::Life {
            presence_key: self.keys.alive(&self.holon),
            holder: self.holon.to_string(),
            version: crate::VERSION,
            take_over: self.take_over,
            data_dir: None,
            startup_timeout: STARTUP_TIMEOUT,
        }
    }

    /// Opens the holon's session (as `<kind>.<name>` for TLS) and claims its name: a
    /// twin (the name alive elsewhere in the cell) is refused before this process
    /// answers anything. Keep the claim for as long as the holon serves. With
    /// `--take-over`, the running process hands the name over first.
    /// `None` when `shutdown` came while it was taking over.
    pub async fn join(
        &self,
        shutdown: &tokio_util::sync::CancellationToken,
    ) -> Result<Option<(zenoh::Session, holon::presence::Claim)>, NodeError> {
        let holon = &self.holon;
        let tls_identity =
            holon::role::identity(holon::role::Role::of_holon(holon.kind()), holon.name());
        let joined = self
            .life()
            .join(&self.zenoh, &tls_identity, shutdown)
            .await?;
        Ok(joined.map(|(opened, claim)| (opened.session, claim)))
    }
}

/// A plain holon's hand-over to its successor (it has nothing to finish): answers on
/// `stand_in` keys with `unavailable` and a retry hint, then drops `replaced` (its own
/// queryables on those keys: until then both answer, and a requester takes the answer
/// that is not `unavailable`, so no request in the switch goes unanswered), withdraws
/// the token and the claim, releases the name, and stands in until the successor serves
/// (or `shutdown`). An error when no successor served: the supervisor starts this holon
/// again.
#[allow(clippy::too_many_arguments)]
pub async fn hand_over<Replaced: Send>(
    identity: &Identity,
    session: &zenoh::Session,
    offer: holon::takeover::Offer,
    token: zenoh::liveliness::LivelinessToken,
    claim: holon::presence::Claim,
    stand_in: &[(String, bool)],
    replaced: Replaced,
    shutdown: &tokio_util::sync::CancellationToken,
) -> Result<(), NodeError> {
    let holon = &identity.holon;
    let started = std::time::Instant::now();
    let refusal = schemas::ErrorReply::unavailable(
        format!("{holon} is being handed over to its successor (an upgrade); ask again shortly"),
        HANDOVER_RETRY,
    )
    .to_json();
    let answer: holon::takeover::Answer = {
        let holon = holon.clone();
        std::sync::Arc::new(move |query: &zenoh::query::Query| {
            use zenoh::Wait;
            if let Err(e) = query.reply_err(refusal.clone()).wait() {
                warn!(%holon, error = %e, "cannot answer a request while handed over");
            }
        })
    };
    let stand_in = match holon::takeover::stand_in(session, stand_in, answer).await {
        Ok(stand_in) => Some(stand_in),
        Err(e) => {
            warn!(%holon, error = %e, "cannot stand in for the successor: requests in the gap go unanswered");
            None
        }
    };
    drop(replaced);
    let ended = identity
        .life()
        .let_go(session, token, claim, offer, started, shutdown)
        .await;
    drop(stand_in);
    Ok(ended?)
}

/// When a request refused during a hand-over is to be asked again.
const HANDOVER_RETRY: std::time::Duration = std::time::Duration::from_millis(100);

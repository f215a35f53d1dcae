//! Who a holon without hardware or journal (a product, a staff holon) is in the cell:
//! the `cell`, `name`, `kind` and `[zenoh]` of its config with the command line applied
//! and checked, and its session opened as that identity with its name claimed.

use std::path::Path;

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

/// The fields every holon file has, as read.
pub struct Header {
    pub cell: String,
    pub name: String,
    pub kind: String,
    pub zenoh: ZenohSettings,
}

impl Identity {
    /// Checks `header` (of the file at `path`) for a holon of `kind`, with the command
    /// line's `overrides` applied. Such a holon keeps no state: a data directory, if
    /// given, is not used.
    pub fn from_header(
        mut header: Header,
        kind: HolonKind,
        path: &str,
        overrides: &Overrides,
    ) -> Result<Identity, ConfigError> {
        let invalid = |message: String| ConfigError::Invalid {
            path: path.to_string(),
            message,
        };
        let mut no_data_dir = None;
        if let Some(base) = Path::new(path).parent() {
            header.zenoh.resolve_paths(base);
        }
        overrides.common.apply(
            &mut header.cell,
            &mut header.name,
            &mut header.zenoh,
            &mut no_data_dir,
        );
        if header.kind != kind.to_string() {
            return Err(invalid(format!("kind: {:?} is not {kind}", header.kind)));
        }
        let keys = CellKeys::new(&header.cell).map_err(|e| invalid(format!("cell: {e}")))?;
        let holon = HolonId::new(kind, &header.name).map_err(|e| invalid(format!("name: {e}")))?;
        header
            .zenoh
            .validate(&holon::tls::identity(&kind.to_string(), holon.name()))
            .map_err(|e| invalid(format!("zenoh: {e}")))?;
        Ok(Identity {
            keys,
            holon,
            zenoh: header.zenoh,
            take_over: overrides.common.take_over,
        })
    }

    /// Opens the holon's session (as `<kind>.<name>` for TLS) and claims its name: a
    /// twin (the name alive elsewhere in the cell) is refused before this process
    /// answers anything. Keep the claim for as long as the holon serves.
    pub async fn join(&self) -> Result<(zenoh::Session, holon::presence::Claim), NodeError> {
        let holon = &self.holon;
        let tls_identity = holon::tls::identity(&holon.kind().to_string(), holon.name());
        let session = self.zenoh.open(&tls_identity, STARTUP_TIMEOUT).await?;
        match holon::presence::claim(
            &session,
            &self.keys.alive(holon),
            &holon.to_string(),
            STARTUP_TIMEOUT,
        )
        .await
        {
            Ok(claim) => Ok((session, claim)),
            Err(e) => {
                if let Err(close) = session.close().await {
                    warn!(%holon, error = %close, "cannot close the zenoh session");
                }
                Err(e.into())
            }
        }
    }
}

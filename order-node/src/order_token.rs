//! The order's liveliness token: a resource keeps a booking only while its requester's
//! token lives.

use schemas::HolonId;
use tracing::warn;

use crate::context::{OrderContext, OrderError};

/// The order's liveliness token (`alive/order/<name>`), declared the first time the
/// order books and held until it ends: a resource keeps a booking only while its
/// requester's token lives. An order still looking for a resource holds none, so
/// thousands of waiting orders cost the cell no declaration.
pub struct OrderToken {
    session: zenoh::Session,
    key: String,
    holon: HolonId,
    token: Option<zenoh::liveliness::LivelinessToken>,
}

impl OrderToken {
    pub fn new(ctx: &OrderContext, holon: &HolonId) -> OrderToken {
        OrderToken {
            session: ctx.session.clone(),
            key: ctx.keys.alive(holon),
            holon: holon.clone(),
            token: None,
        }
    }

    /// Declares the token unless it is already declared.
    pub async fn declare(&mut self) -> Result<(), OrderError> {
        if self.token.is_none() {
            let declared = self
                .session
                .liveliness()
                .declare_token(&self.key)
                .await
                .map_err(|e| OrderError::Other(format!("cannot declare {}: {e}", self.key)))?;
            self.token = Some(declared);
        }
        Ok(())
    }

    /// Withdraws the token: the order wants no booking any more.
    pub async fn undeclare(&mut self) {
        if let Some(token) = self.token.take() {
            if let Err(e) = token.undeclare().await {
                warn!(holon = %self.holon, error = %e, "cannot withdraw the order's token; it goes with the session");
            }
        }
    }
}

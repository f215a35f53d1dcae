//! A proposal round with the staff's advice asked together, as both an order's step
//! (its booking) and its part's station round ask it: the offers ranked, the advised
//! resource first if it proposed.

use schemas::layout::LocationId;
use schemas::{HolonId, Service};
use tracing::info;

use super::OrderTask;
use crate::ranking::InFlight;
use crate::requests;

/// What a round found.
pub(super) struct Round {
    /// The resources that proposed, best first (the advised one first, if it did).
    pub ranked: Vec<HolonId>,
    /// The staff's advice, if one was asked and usable.
    pub advised: Option<HolonId>,
    /// The booking in flight the ranking counted, if any.
    pub in_flight: Option<InFlight>,
}

impl OrderTask<'_> {
    /// Asks the resources for proposals to `ask` and, with `advise`, a staff holon for
    /// its advice on the order's route ahead (from `at`, where the part is), together:
    /// the advice costs no time unless the staff is slower than the round (then at
    /// most `orders.advice_timeout_ms`), and without a staff nothing at all. Takes its
    /// turn among the node's rounds.
    pub(super) async fn round(&self, ask: &Service, advise: bool, at: Option<LocationId>) -> Round {
        let ctx = self.ctx.clone();
        let conversation_id = ask.conversation_id.as_str();
        let (route, urgency, avoid) = {
            let p = self.progress.get();
            (p.route_ahead(), (p.priority, p.due), p.avoid.clone())
        };
        let _turn = ctx.rounds.acquire().await.expect("never closed");
        let (advised, offers) = tokio::join!(
            async {
                if !advise {
                    return requests::Advised::NoStaff;
                }
                requests::advice(
                    &ctx,
                    &self.holon,
                    conversation_id,
                    route,
                    urgency,
                    &avoid,
                    at,
                )
                .await
            },
            requests::offers(&ctx, ask, &avoid)
        );
        let advised = match advised {
            requests::Advised::Resource(resource) => Some(resource),
            requests::Advised::NoStaff => None,
            requests::Advised::Unusable(why) => {
                info!(holon = %self.holon, %conversation_id, why = %why, "no usable advice: contract net alone");
                None
            }
        };
        let (ranked, in_flight) = requests::rank(&ctx, ask, offers, advised.as_ref());
        Round {
            ranked,
            advised,
            in_flight,
        }
    }
}

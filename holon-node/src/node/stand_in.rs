//! What answers for a resource while it is handed over to its successor.

use schemas::Service;
use tracing::warn;

/// The stand-in's answer to a Service request while the resource is handed over:
/// refused `unavailable`, with a retry hint.
pub(super) fn stand_in_answer(holon: schemas::HolonId) -> holon::takeover::Answer {
    std::sync::Arc::new(move |query: &zenoh::query::Query| {
        use zenoh::Wait;
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let sent = match Service::from_json(&payload) {
            Ok(request) => {
                let mut refusal = request.refused(&holon, schemas::Reason::Unavailable);
                crate::machine::agenda::handing_over_hint(&mut refusal.info);
                query
                    .reply(query.key_expr().clone(), refusal.to_json())
                    .wait()
            }
            Err(e) => query
                .reply_err(schemas::ErrorReply::for_schema_error(&e).to_json())
                .wait(),
        };
        if let Err(e) = sent {
            warn!(%holon, error = %e, "cannot answer a request while handed over; the requester asks again after its timeout");
        }
    })
}

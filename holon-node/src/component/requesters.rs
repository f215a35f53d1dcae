//! Booking lifetime: a booking lasts while its requester is in the cell.
//!
//! Every holon that books (an order; products and staff may too, resources never: the
//! agenda refuses them) holds a liveliness token at `holarchy/<cell>/alive/<kind>/<name>`
//! while it wants its bookings. The requesters component watches the tokens of those
//! kinds, not the other resources' (in a cell of N resources, watching every token
//! would cost each new resource N samples, N² in all); when the requester of a booking has been absent longer
//! than `agenda.requester_grace_ms` (its order ended, was faked, or its order-node is gone
//! for good), the agenda manager releases its bookings, so they no longer block the
//! resource or lengthen its offers. The grace covers an order-node restart and a short
//! network cut; the snapshot shows since when a booked requester is absent.
//!
//! [`Absences`] is the pure part (what is known of presence, and which requesters have
//! outstayed the grace); [`run`] is the component that feeds it liveliness samples and
//! a tick, and sends the agenda manager a `RequesterGone` per expired requester.

use std::collections::HashSet;
use std::sync::Arc;
use std::time::Duration;

use futures_util::future::select_all;
use holon::ChildError;
use schemas::{CellKeys, HolonId, HolonKind};
use tokio::sync::mpsc;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::absences::{Absences, Moment};
use crate::agenda::AgendaEvent;
use crate::component::agenda_manager::AgendaMessage;
use crate::views::Views;

/// The kinds of holon that may book a resource: every kind but resources.
fn requester_kinds() -> impl Iterator<Item = HolonKind> {
    HolonKind::ALL
        .into_iter()
        .filter(|kind| *kind != HolonKind::Resource)
}

/// A liveliness subscriber of one requester kind.
type Watch = zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>;

/// The next token change of any requester kind.
async fn next_change(watches: &[Watch]) -> Result<zenoh::sample::Sample, zenoh::Error> {
    select_all(watches.iter().map(|w| w.recv_async())).await.0
}

/// How often booked requesters are checked against the grace.
const CHECK_EVERY: Duration = Duration::from_secs(1);

/// What the requesters component is linked to.
pub struct Links {
    pub holon: HolonId,
    pub session: zenoh::Session,
    pub keys: CellKeys,
    /// How long a requester may be absent before its bookings are released.
    pub grace: Duration,
    /// The agenda manager's mailbox.
    pub agenda: mpsc::Sender<AgendaMessage>,
    /// Where it reads the agenda and publishes the absences it owns.
    pub views: Arc<Views>,
}

/// The requesters of the bookings on the agenda, as the agenda manager last published it.
fn booked_requesters(views: &Views) -> HashSet<HolonId> {
    views
        .agenda
        .borrow()
        .snapshot
        .agenda
        .iter()
        .map(|b| b.requester.clone())
        .collect()
}

/// The requesters component: watches every liveliness token of the cell and releases
/// the bookings of requesters absent longer than the grace. It owns the absences, and
/// publishes them when a booked requester leaves or comes back.
pub async fn run(links: Arc<Links>, token: CancellationToken) -> Result<(), ChildError> {
    let Links {
        holon, keys, grace, ..
    } = &*links;
    let absences = &links.views.absences;
    // A restarted component starts a fresh watch: absences count from now (the grace
    // is restarted, never shortened).
    absences.send_replace(Absences::new(Moment::now()));
    let mut watches = Vec::new();
    for kind in requester_kinds() {
        let watch = links
            .session
            .liveliness()
            .declare_subscriber(keys.alive_kind(kind))
            .history(true)
            .await
            .map_err(|e| format!("cannot watch the cell's {kind} tokens: {e}"))?;
        watches.push(watch);
    }
    let mut tick = tokio::time::interval(CHECK_EVERY);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = token.cancelled() => return Ok(()),
            sample = next_change(&watches) => {
                let sample = sample.map_err(|e| format!("liveliness subscriber closed: {e}"))?;
                let Some(other) = keys.holon_from_alive(sample.key_expr().as_str()) else {
                    continue;
                };
                let booked = booked_requesters(&links.views).contains(&other);
                let kind = sample.kind();
                // Published only when a booked requester's presence changed: the
                // snapshot shows nobody else's.
                let mut news = false;
                absences.send_if_modified(|absences| {
                    news = match kind {
                        zenoh::sample::SampleKind::Put => absences.appeared(other.clone()),
                        zenoh::sample::SampleKind::Delete => absences.vanished(other.clone(), Moment::now()),
                    };
                    news && booked
                });
                if news && booked {
                    match kind {
                        zenoh::sample::SampleKind::Put => info!(%holon, requester = %other, "requester of a booking is back"),
                        zenoh::sample::SampleKind::Delete => warn!(%holon, requester = %other, grace = ?grace, "requester of a booking left the cell; its bookings end unless it is back within the grace"),
                    }
                }
            }
            _ = tick.tick() => {
                let booked = booked_requesters(&links.views);
                let mut expired = Vec::new();
                absences.send_if_modified(|absences| {
                    absences.forget_except(&booked);
                    expired = absences.expired(&booked, Instant::now(), *grace);
                    false
                });
                for requester in expired {
                    warn!(%holon, %requester, grace = ?grace, "requester absent longer than the grace: its bookings are released");
                    links
                        .agenda
                        .send(AgendaEvent::RequesterGone { requester }.into())
                        .await
                        .map_err(|_| "agenda mailbox closed")?;
                }
            }
        }
    }
}

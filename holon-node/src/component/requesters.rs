//! Booking lifetime: a booking lasts while its requester is in the cell.
//!
//! A product or a staff holon that books holds its liveliness token at
//! `holarchy/<cell>/alive/<kind>/<name>`; an order holds none (a key per order would
//! stay in zenoh's routing tables for good, [`schemas::held`]): its order-node answers
//! for it. Every [`CHECK_EVERY`] the component asks every order-node which of the
//! orders with a booking or a result here it holds (`host/order-node/*/held`); an
//! order is present while a node holds it, or while it has a token (an order of an
//! order-node of an earlier release). It watches the tokens of the kinds that book, not
//! the other resources' (in a cell of N resources, watching every token would cost
//! each new resource N samples, N² in all). When the requester of a booking has been
//! absent longer than `agenda.requester_grace_ms` (its order ended, was faked, or its
//! order-node is gone for good), the agenda manager releases its bookings, so they no
//! longer block the resource or lengthen its offers. The grace covers an order-node
//! restart, a question not answered in time and a short network cut; the snapshot shows
//! since when a booked requester is absent.
//!
//! [`Absences`] is the pure part (what is known of presence, and which requesters have
//! outstayed the grace); [`run`] is the component that feeds it liveliness samples, the
//! nodes' answers and a tick, and sends the agenda manager a `RequesterGone` per expired
//! requester.

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

use crate::component::agenda_manager::AgendaMessage;
use crate::machine::absences::{Absences, Moment};
use crate::machine::agenda::AgendaEvent;
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

/// How often booked requesters are checked against the grace, and the order-nodes
/// asked which orders they hold.
pub const CHECK_EVERY: Duration = Duration::from_secs(1);

/// How long the order-nodes' answers are waited for (within a check).
const HELD_WITHIN: Duration = Duration::from_millis(800);

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

/// The orders whose presence matters here: those with a booking, or a result still to
/// be acknowledged (a withdrawing resource need not wait for a requester that left).
fn orders_to_ask(views: &Views) -> Vec<HolonId> {
    let view = views.agenda.borrow();
    let mut orders: Vec<HolonId> = view
        .snapshot
        .agenda
        .iter()
        .map(|b| &b.requester)
        .chain(view.deliverable.iter().map(|r| &r.requester))
        .filter(|r| r.kind() == HolonKind::Order)
        .cloned()
        .collect();
    orders.sort();
    orders.dedup();
    orders
}

/// Asks every order-node which of `orders` it holds: those held by some node. A node
/// that does not answer within [`HELD_WITHIN`] holds nothing this time (the grace
/// covers it); a question no node hears is answered by none.
async fn held_orders(links: &Links, orders: &[HolonId]) -> HashSet<HolonId> {
    let mut held = HashSet::new();
    for chunk in orders.chunks(schemas::MAX_HELD_ASKED) {
        let question = schemas::HeldRequest {
            orders: chunk.iter().map(|o| o.name().to_string()).collect(),
        };
        let payload = serde_json::to_vec(&question).expect("serializes");
        let replies = links
            .session
            .get(links.keys.node_held_all())
            .payload(payload)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(HELD_WITHIN)
            .await;
        let replies = match replies {
            Ok(replies) => replies,
            Err(e) => {
                warn!(holon = %links.holon, error = %e, "cannot ask the order-nodes which orders they hold; their orders count as absent until the next check");
                return held;
            }
        };
        let deadline = Instant::now() + HELD_WITHIN + Duration::from_millis(200);
        while let Ok(Ok(reply)) = tokio::time::timeout_at(deadline, replies.recv_async()).await {
            let answer = match reply.result() {
                Ok(sample) => {
                    serde_json::from_slice::<schemas::HeldReply>(&sample.payload().to_bytes())
                }
                Err(err) => {
                    warn!(holon = %links.holon, answer = %err.payload().try_to_string().unwrap_or_default(), "an order-node refused the held question");
                    continue;
                }
            };
            match answer {
                Ok(answer) => held.extend(
                    answer
                        .held
                        .iter()
                        .filter_map(|name| HolonId::order(name).ok()),
                ),
                Err(e) => {
                    warn!(holon = %links.holon, error = %e, "an order-node answered the held question with what is not a held reply")
                }
            }
        }
    }
    held
}

/// Records that `other` is present or not, and says so when it is news about a booked
/// requester.
fn see(links: &Links, other: &HolonId, present: bool, booked: bool) {
    let mut news = false;
    // Published only when a booked requester's presence changed: the snapshot shows
    // nobody else's.
    links.views.absences.send_if_modified(|absences| {
        news = if present {
            absences.appeared(other.clone())
        } else {
            absences.vanished(other.clone(), Moment::now())
        };
        news && booked
    });
    if news && booked {
        let (holon, grace) = (&links.holon, &links.grace);
        if present {
            info!(%holon, requester = %other, "requester of a booking is back");
        } else {
            warn!(%holon, requester = %other, grace = ?grace, "requester of a booking left the cell; its bookings end unless it is back within the grace");
        }
    }
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
    // Requesters whose token is there, and orders a node said it holds.
    let mut with_token: HashSet<HolonId> = HashSet::new();
    let mut held: HashSet<HolonId> = HashSet::new();
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
                match sample.kind() {
                    zenoh::sample::SampleKind::Put => with_token.insert(other.clone()),
                    zenoh::sample::SampleKind::Delete => with_token.remove(&other),
                };
                let present = with_token.contains(&other) || held.contains(&other);
                let booked = booked_requesters(&links.views).contains(&other);
                see(&links, &other, present, booked);
            }
            _ = tick.tick() => {
                let orders = orders_to_ask(&links.views);
                held = if orders.is_empty() {
                    HashSet::new()
                } else {
                    held_orders(&links, &orders).await
                };
                let booked = booked_requesters(&links.views);
                for order in &orders {
                    let present = with_token.contains(order) || held.contains(order);
                    see(&links, order, present, booked.contains(order));
                }
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

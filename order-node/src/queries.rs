//! The order-node's endpoints: `orders/submit`, the listing of its orders
//! (`host/order-node/<node>/orders`, a page at a time), which orders it holds
//! (`host/order-node/<node>/held`, answered in its callback from the open inboxes:
//! the node's loop may be busy, a resource's question must not wait for it), and its
//! orders' `state`, `cancel` and `inbox` (for results of orders that are not running).
//! The other callbacks queue every query for the node's loop, which answers it here.

use std::time::Duration;

use schemas::{ErrorReply, HolonId, SubmitReply, WorkOrder};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{debug, error, info, warn};
use zenoh::query::Query;

use crate::host::{Host, Tasks};

/// How many queries wait for the node's loop before new ones are refused `unavailable`.
pub const QUERY_QUEUE: usize = 1024;

/// How long a work order waits for its product holon to be seen before it is refused
/// `unknown_product`.
const PRODUCT_GRACE: Duration = Duration::from_secs(2);

/// A query to the node, by the queryable it came to.
pub enum NodeQuery {
    Cancel(Query),
    PartWord(Query),
    Submit(Query),
    State(Query),
    Inbox(Query),
    Listing(Query),
}

/// Queues a query for the node's loop from a queryable's callback (which must not
/// block): refused `unavailable` when [`QUERY_QUEUE`] are already waiting.
fn enqueue(queue: &mpsc::Sender<NodeQuery>, query: NodeQuery) {
    use zenoh::Wait;
    match queue.try_send(query) {
        Ok(()) => {}
        Err(mpsc::error::TrySendError::Full(
            NodeQuery::Cancel(query)
            | NodeQuery::PartWord(query)
            | NodeQuery::Submit(query)
            | NodeQuery::State(query)
            | NodeQuery::Inbox(query)
            | NodeQuery::Listing(query),
        )) => {
            warn!(key = %query.key_expr(), "{QUERY_QUEUE} queries are waiting for the order-node: this one is refused unavailable");
            let busy = schemas::ErrorReply::new(
                schemas::ErrorCode::Unavailable,
                format!(
                    "{QUERY_QUEUE} requests are waiting for this order-node; ask again shortly"
                ),
            );
            if let Err(e) = query.reply_err(busy.to_json()).wait() {
                warn!(error = %e, "cannot refuse a query; the asker times out");
            }
        }
        Err(mpsc::error::TrySendError::Closed(_)) => {
            debug!("a query arrived while the order-node stops: left unanswered, the asker times out or delivers again")
        }
    }
}

/// The node's queryables; dropping them undeclares them.
pub struct Endpoints {
    _submit: zenoh::query::Queryable<()>,
    _states: zenoh::query::Queryable<()>,
    _inboxes: zenoh::query::Queryable<()>,
    _cancels: zenoh::query::Queryable<()>,
    _part_words: zenoh::query::Queryable<()>,
    _listing: zenoh::query::Queryable<()>,
    _held: zenoh::query::Queryable<()>,
}

impl Endpoints {
    /// Declares `orders/submit`, and the node's orders' `state`, `inbox`, `cancel` and
    /// `part`;
    /// every query goes to `queue` (results for running orders straight to them).
    pub async fn declare(
        session: &zenoh::Session,
        host: &Host,
        queue: mpsc::Sender<NodeQuery>,
    ) -> Result<Endpoints, zenoh::Error> {
        let keys = &host.config.keys;
        let name = &host.config.name;
        let to_queue = |wrap: fn(Query) -> NodeQuery| {
            let queue = queue.clone();
            move |query| enqueue(&queue, wrap(query))
        };
        let _submit = session
            .declare_queryable(keys.orders_submit())
            .complete(true)
            .callback(to_queue(NodeQuery::Submit))
            .await?;
        let _states = session
            .declare_queryable(keys.node_orders(name, "state"))
            .callback(to_queue(NodeQuery::State))
            .await?;
        // Results reach running orders straight from this callback; those for orders
        // that are not running (duplicates, late reports of abandoned attempts) are
        // answered by the node's loop.
        let inboxes = host.context.inboxes.clone();
        let inbox_queue = queue.clone();
        let _inboxes = session
            .declare_queryable(keys.node_orders(name, "inbox"))
            .callback(move |query| {
                if let Some(query) = inboxes.route(query) {
                    enqueue(&inbox_queue, NodeQuery::Inbox(query));
                }
            })
            .await?;
        let _cancels = session
            .declare_queryable(keys.node_orders(name, "cancel"))
            .callback(to_queue(NodeQuery::Cancel))
            .await?;
        let _part_words = session
            .declare_queryable(keys.node_orders(name, "part"))
            .callback(to_queue(NodeQuery::PartWord))
            .await?;
        let _listing = session
            .declare_queryable(keys.node_listing(name))
            .callback(to_queue(NodeQuery::Listing))
            .await?;
        let (inboxes, node, reply_key) = (
            host.context.inboxes.clone(),
            name.clone(),
            keys.node_held(name),
        );
        let _held = session
            .declare_queryable(keys.node_held(name))
            .callback(move |query| held(&inboxes, &node, &reply_key, query))
            .await?;
        Ok(Endpoints {
            _submit,
            _states,
            _inboxes,
            _cancels,
            _part_words,
            _listing,
            _held,
        })
    }
}

/// Answers a resource's question of which orders the node holds, from the open inboxes
/// (in the queryable's callback: it does not block); a malformed question is refused
/// `malformed`.
fn held(inboxes: &crate::inbox::Inboxes, node: &str, reply_key: &str, query: Query) {
    use zenoh::Wait;
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let refuse = |query: &Query, why: String| {
        warn!(%node, "held question refused: {why}");
        if let Err(e) = query
            .reply_err(ErrorReply::new(schemas::ErrorCode::Malformed, why).to_json())
            .wait()
        {
            warn!(%node, error = %e, "cannot refuse a held question; the resource times out");
        }
    };
    let asked = match serde_json::from_slice::<schemas::HeldRequest>(&payload) {
        Ok(asked) if asked.orders.len() <= schemas::MAX_HELD_ASKED => asked,
        Ok(asked) => {
            let why = format!(
                "{} orders asked at once, at most {} (ask in several)",
                asked.orders.len(),
                schemas::MAX_HELD_ASKED
            );
            return refuse(&query, why);
        }
        Err(e) => return refuse(&query, format!("not a held question: {e}")),
    };
    let reply = schemas::HeldReply {
        node: node.to_string(),
        held: inboxes.held(&asked.orders),
    };
    let payload = serde_json::to_vec(&reply).expect("serializes");
    if let Err(e) = query.reply(reply_key, payload).wait() {
        warn!(%node, error = %e, "cannot answer a held question; the resource counts this node's orders absent until it asks again");
    }
}

/// Answers one query to the node.
pub async fn answer(
    host: &mut Host,
    query: NodeQuery,
    tasks: &mut Tasks,
    cancel_all: &CancellationToken,
) {
    match query {
        NodeQuery::Submit(query) => submit(host, query, tasks, cancel_all).await,
        NodeQuery::Inbox(query) => acknowledge_finished(host, query).await,
        NodeQuery::Cancel(query) => cancel(host, query).await,
        NodeQuery::PartWord(query) => part_word(host, query).await,
        NodeQuery::Listing(query) => listing(host, query).await,
        NodeQuery::State(query) => {
            for (key, payload) in host.snapshots_matching(query.key_expr()) {
                if let Err(e) = query.reply(&key, payload).await {
                    warn!(node = %host.config.name, %key, error = %e, "cannot answer a state read; the reader gets fewer orders");
                }
            }
        }
    }
}

/// Answers a request for a page of the node's orders ([`Host::page`]); a malformed
/// request is refused `malformed`.
async fn listing(host: &Host, query: Query) {
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let request = match schemas::OrderListRequest::from_json(&payload) {
        Ok(request) => request,
        Err(why) => {
            warn!(node = %host.config.name, "listing request refused: {why}");
            let refusal = ErrorReply::new(schemas::ErrorCode::Malformed, why);
            if let Err(e) = query.reply_err(refusal.to_json()).await {
                warn!(node = %host.config.name, error = %e, "cannot refuse a listing request; the reader times out");
            }
            return;
        }
    };
    let page = host.page(&request);
    let payload = serde_json::to_vec(&page).expect("serializes");
    debug!(node = %host.config.name, orders = page.orders.len(), bytes = payload.len(), "listing page answered");
    if let Err(e) = query
        .reply(host.config.keys.node_listing(&host.config.name), payload)
        .await
    {
        warn!(node = %host.config.name, error = %e, "cannot answer a listing request; the reader says its listing is incomplete");
    }
}

/// Why a work order for `product` cannot be planned now: no product holon of that name
/// is alive (the product tokens, asked for once). `None` when it is there.
async fn product_missing(host: &Host, product: &str) -> Option<String> {
    let keys = &host.config.keys;
    let alive = match holon::presence::tokens(
        &host.context.session,
        &keys.alive_kind(schemas::HolonKind::Product),
        Duration::from_secs(2),
    )
    .await
    {
        Ok(alive) => alive,
        // Presence unknown: accept, the orders wait for their plan as before.
        Err(e) => {
            warn!(node = %host.config.name, error = %e, "cannot ask which products are alive");
            return None;
        }
    };
    let names: Vec<String> = alive
        .iter()
        .filter_map(|k| keys.holon_from_alive(k))
        .map(|h| h.name().to_string())
        .collect();
    if names.iter().any(|n| n == product) {
        return None;
    }
    // A node that has just joined may not know every token yet (a peer learns the
    // others' declarations as its links come up): a product that shows up within the
    // grace is there.
    if let Ok(holon) = HolonId::new(schemas::HolonKind::Product, product) {
        if let Ok(true) =
            holon::presence::wait_token(&host.context.session, &keys.alive(&holon), PRODUCT_GRACE)
                .await
        {
            return None;
        }
    }
    Some(format!(
        "no product holon {product:?} is alive in cell {} (alive: {}); start it, or submit with queue (cell submit --queue) to let the orders wait for its plan",
        keys.cell(),
        if names.is_empty() { "none".to_string() } else { names.join(", ") }
    ))
}

/// Refuses a work order: nothing was created.
async fn refuse_work(host: &Host, query: &Query, refusal: ErrorReply) {
    if let Err(e) = query.reply_err(refusal.to_json()).await {
        warn!(node = %host.config.name, code = %refusal.code, error = %e, "cannot refuse the work order; the submitter times out (nothing was created)");
    }
}

async fn submit(host: &mut Host, query: Query, tasks: &mut Tasks, cancel: &CancellationToken) {
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let work: WorkOrder = match serde_json::from_slice::<WorkOrder>(&payload) {
        Ok(work) => match work.validate() {
            Ok(()) => work,
            Err(e) => {
                return refuse_work(
                    host,
                    &query,
                    ErrorReply::new(schemas::ErrorCode::Invalid, e.to_string()),
                )
                .await
            }
        },
        Err(e) => {
            warn!(node = %host.config.name, error = %e, "malformed work order");
            return refuse_work(
                host,
                &query,
                ErrorReply::new(schemas::ErrorCode::Malformed, e.to_string()),
            )
            .await;
        }
    };
    // A named work order the node made already is answered with its orders, whatever
    // has changed since (its product gone, the quotas reached): asking again is safe.
    if let Some(id) = &work.submit_id {
        if let Some(made) = host.submits.get(id) {
            if made.is_repeated_by(&work) {
                let orders = made.orders(&host.config.name);
                info!(node = %host.config.name, submit_id = %id, product = %work.product, count = work.count, by = requested_by(&query).as_deref().unwrap_or("(not said)"), "work order asked again: answered with the orders made under its name, none made");
                return reply_orders(host, &query, orders).await;
            }
            let why = format!(
                "submit_id {id:?} was given to a work order of {} {} (orders from {}); a name is not reused for other work",
                made.count,
                made.product,
                made.orders(&host.config.name)[0]
            );
            warn!(node = %host.config.name, submit_id = %id, "work order refused: {why}");
            let refusal = ErrorReply::new(schemas::ErrorCode::Invalid, why);
            return refuse_work(host, &query, refusal).await;
        }
    }
    if !work.queue {
        if let Some(why) = product_missing(host, &work.product).await {
            warn!(node = %host.config.name, product = %work.product, "work order refused: {why}");
            if let Err(e) = query
                .reply_err(ErrorReply::new(schemas::ErrorCode::UnknownProduct, why).to_json())
                .await
            {
                warn!(node = %host.config.name, error = %e, "cannot refuse the work order");
            }
            return;
        }
    }
    let limits = &host.config.orders;
    let unfinished = host.unfinished();
    let refusal = if work.count > limits.max_orders_per_submit {
        Some(format!(
            "count {} is over this node's limit of {} orders per work order (orders.max_orders_per_submit)",
            work.count, limits.max_orders_per_submit
        ))
    } else if unfinished + work.count as usize > limits.max_unfinished_orders {
        Some(format!(
            "{unfinished} orders are unfinished; {} more would pass this node's limit of {} (orders.max_unfinished_orders)",
            work.count, limits.max_unfinished_orders
        ))
    } else {
        None
    };
    if let Some(why) = refusal {
        warn!(node = %host.config.name, product = %work.product, count = work.count, "work order refused: {why}");
        if let Err(e) = query
            .reply_err(ErrorReply::new(schemas::ErrorCode::Quota, why).to_json())
            .await
        {
            warn!(node = %host.config.name, error = %e, "cannot refuse the work order");
        }
        return;
    }
    let by = requested_by(&query);
    let orders = match host.create(&work, tasks, cancel) {
        Ok(orders) => orders,
        Err(e) => {
            error!(node = %host.config.name, error = %e, "cannot record the work order");
            let refusal = ErrorReply::new(
                schemas::ErrorCode::Unavailable,
                format!("cannot record the orders: {e}"),
            );
            return refuse_work(host, &query, refusal).await;
        }
    };
    info!(node = %host.config.name, product = %work.product, orders = ?orders, submit_id = work.submit_id.as_deref().unwrap_or("(none)"), by = by.as_deref().unwrap_or("(not said)"), "work order accepted");
    reply_orders(host, &query, orders).await;
}

/// Answers a work order with its orders' names.
async fn reply_orders(host: &Host, query: &Query, orders: Vec<String>) {
    let reply = serde_json::to_vec(&SubmitReply { orders }).expect("serializes");
    if let Err(e) = query.reply(query.key_expr().clone(), reply).await {
        warn!(node = %host.config.name, error = %e, "cannot answer the work order; the submitter times out (the orders are made: asked again under its submit_id, it gets them)");
    }
}

/// Who asks, as the query's attachment says ([`schemas::requested_by`]).
fn requested_by(query: &Query) -> Option<String> {
    query
        .attachment()
        .and_then(|a| schemas::requested_by(&a.to_bytes()))
}

/// An operator's cancel of one order (`order/<name>/cancel`).
async fn cancel(host: &Host, query: Query) {
    let key = query.key_expr().as_str().to_string();
    let name = key
        .strip_suffix("/cancel")
        .and_then(|k| k.rsplit('/').next())
        .unwrap_or_default();
    let by = requested_by(&query);
    info!(node = %host.config.name, order = %name, by = by.as_deref().unwrap_or("(not said)"), "cancel asked");
    let answer = match host.cancel(name).await {
        Ok(reply) => {
            let payload = serde_json::to_vec(&reply).expect("serializes");
            query.reply(host.config.keys.cancel(name), payload).await
        }
        Err((code, why)) => {
            warn!(node = %host.config.name, order = %name, %code, "cancel not taken: {why}");
            query.reply_err(ErrorReply::new(code, why).to_json()).await
        }
    };
    if let Err(e) = answer {
        warn!(node = %host.config.name, order = %name, error = %e, "cannot answer a cancel");
    }
}

/// An operator's word on where an order's lost part is (`order/<name>/part`): a
/// malformed one is refused `malformed`, and nothing changes.
async fn part_word(host: &Host, query: Query) {
    let key = query.key_expr().as_str().to_string();
    let name = key
        .strip_suffix("/part")
        .and_then(|k| k.rsplit('/').next())
        .unwrap_or_default()
        .to_string();
    let by = requested_by(&query).unwrap_or_else(|| "(not said)".to_string());
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let answer = match serde_json::from_slice::<schemas::PartWord>(&payload) {
        Err(e) => Err((
            schemas::ErrorCode::Malformed,
            format!("not a word on a part (`{{\"location\": \"HOLON.NAME\"}}`): {e}"),
        )),
        Ok(word) => {
            info!(node = %host.config.name, order = %name, %by, location = %word.location, "an operator says where a lost part is");
            host.part_word(&name, word.location, by).await
        }
    };
    let answered = match answer {
        Ok(reply) => {
            let payload = serde_json::to_vec(&reply).expect("serializes");
            query.reply(host.config.keys.part(&name), payload).await
        }
        Err((code, why)) => {
            warn!(node = %host.config.name, order = %name, %code, "word on a part not taken: {why}");
            query.reply_err(ErrorReply::new(code, why).to_json()).await
        }
    };
    if let Err(e) = answered {
        warn!(node = %host.config.name, order = %name, error = %e, "cannot answer a word on a part; the operator asks again");
    }
}

/// Acknowledges a result sent to a finished order of this node (it was recorded, or
/// belongs to an attempt the order abandoned); anything else is left to the order. A
/// transporter's `departed` for an order that is not running is acknowledged and
/// ignored, whatever the order: it is never a result, and never sent again (the place
/// it would have released is released at the move's `done`).
async fn acknowledge_finished(host: &Host, query: Query) {
    let key = query.key_expr().as_str().to_string();
    let Some(name) = crate::inbox::order_name(&key).map(str::to_string) else {
        return;
    };
    if let Some(departed) = query
        .payload()
        .and_then(|p| schemas::Service::from_json(&p.to_bytes()).ok())
        .filter(|m| m.message_type == schemas::MessageType::Departed)
    {
        info!(order = %name, conversation_id = %departed.conversation_id, message_type = %departed.message_type, "a departure for an order that is not running acknowledged and ignored");
        let mut ack = departed;
        ack.result = Some(true);
        if let Err(e) = query.reply(query.key_expr().clone(), ack.to_json()).await {
            warn!(order = %name, error = %e, "cannot acknowledge a departure (not sent again: nothing is lost)");
        }
        return;
    }
    if host.forgotten(&name) {
        // Finished longer ago than the retention: its outcome was settled then, and
        // this is a late copy (a resource that was away for long). Acknowledged, so the
        // resource stops sending it.
        info!(order = %name, "result for an order finished long ago (no longer in the journal) acknowledged");
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        match schemas::Service::from_json(&payload) {
            Ok(mut ack) => {
                ack.result = Some(true);
                if let Err(e) = query.reply(query.key_expr().clone(), ack.to_json()).await {
                    warn!(order = %name, error = %e, "cannot acknowledge a result of a forgotten order; the resource delivers it again");
                }
            }
            Err(err) => {
                let refusal = ErrorReply::for_schema_error(&err);
                if let Err(e) = query.reply_err(refusal.to_json()).await {
                    warn!(order = %name, error = %e, "cannot refuse an undecodable message");
                }
            }
        }
        return;
    }
    let progress = match host.progress(&name) {
        Ok(progress) => progress,
        Err(e) => {
            // Unanswered: the resource delivers the result again.
            warn!(order = %name, error = %e, "cannot read a finished order from the journal; its result is left for a later delivery");
            return;
        }
    };
    let Some(progress) = progress else {
        warn!(order = %name, "result for an order this node does not host refused");
        if let Err(e) = query
            .reply_err(
                ErrorReply::new(
                    schemas::ErrorCode::UnknownOrder,
                    format!("{name} is not an order of {}", host.config.name),
                )
                .to_json(),
            )
            .await
        {
            warn!(order = %name, error = %e, "cannot refuse a result");
        }
        return;
    };
    if !progress.status.is_final() {
        // Hosted, but its task is not running now (restarting after a journal error):
        // unanswered, so the resource delivers the result again.
        debug!(order = %name, "result for an order that is not running left for a later delivery");
        return;
    }
    let payload = query
        .payload()
        .map(|p| p.to_bytes().into_owned())
        .unwrap_or_default();
    let message = match schemas::Service::from_json(&payload) {
        Ok(message) => message,
        Err(err) => {
            warn!(order = %name, bytes = payload.len(), error = %err, "undecodable message for a finished order refused");
            if let Err(e) = query
                .reply_err(ErrorReply::for_schema_error(&err).to_json())
                .await
            {
                warn!(order = %name, error = %e, "cannot refuse an undecodable message");
            }
            return;
        }
    };
    {
        if !progress.knows(message.provider.as_ref()) {
            warn!(order = %name, conversation_id = %message.conversation_id, "result for a finished order from a resource it never booked refused");
            if let Err(e) = query
                .reply_err(
                    ErrorReply::new(
                        schemas::ErrorCode::NotBooked,
                        "this order never booked that resource",
                    )
                    .to_json(),
                )
                .await
            {
                warn!(order = %name, error = %e, "cannot refuse a result");
            }
            return;
        }
        info!(order = %name, conversation_id = %message.conversation_id, message_type = %message.message_type, "result for a finished order acknowledged");
        let mut ack = message;
        ack.result = Some(true);
        if let Err(e) = query.reply(query.key_expr().clone(), ack.to_json()).await {
            warn!(order = %name, error = %e, "cannot acknowledge a result of a finished order; the resource delivers it again");
        }
    }
}

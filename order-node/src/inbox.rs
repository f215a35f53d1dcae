//! The orders' inboxes: one queryable for all the orders of a node.
//!
//! A resource delivers `done` / `failed` with a `get` on `holarchy/<cell>/order/<name>/inbox`.
//! The node declares one queryable, `order/<node>-$*/inbox`, and [`Inboxes::route`] hands
//! each result to the task of the running order it names; results for orders that are
//! not running (finished, or waiting to be restarted) go to the node, which acknowledges
//! those of finished orders. An order waiting for a resource therefore costs the cell no
//! declaration of its own (thousands of them used to mean thousands of queryables on
//! every router and peer).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use schemas::{HolonId, MessageType, Service};
use tokio::sync::mpsc;
use tracing::{info, warn};
use zenoh::query::Query;

/// A result in an order's inbox, with the query to acknowledge once it is recorded.
pub struct Delivery {
    pub message: Service,
    pub query: Query,
}

impl Delivery {
    /// Acknowledges the result: the resource stops delivering it.
    pub async fn acknowledge(self) {
        let mut ack = self.message.clone();
        ack.result = Some(true);
        if let Err(e) = self
            .query
            .reply(self.query.key_expr().clone(), ack.to_json())
            .await
        {
            warn!(conversation_id = %self.message.conversation_id, error = %e, "cannot acknowledge a result: the resource delivers it again");
        }
    }

    /// Refuses the result with an error reply (the resource logs it and retries).
    pub async fn refuse(self, code: &str, message: String) {
        if let Err(e) = self
            .query
            .reply_err(schemas::ErrorReply::new(code, message).to_json())
            .await
        {
            warn!(conversation_id = %self.message.conversation_id, error = %e, "cannot refuse a result");
        }
    }
}

/// The inboxes of the running orders, by order name.
#[derive(Default)]
pub struct Inboxes {
    open: Mutex<HashMap<String, mpsc::UnboundedSender<Delivery>>>,
}

/// An open inbox: results for its order arrive here until it is dropped.
pub struct Inbox {
    name: String,
    inboxes: Arc<Inboxes>,
    pub deliveries: mpsc::UnboundedReceiver<Delivery>,
}

impl Drop for Inbox {
    fn drop(&mut self) {
        self.inboxes
            .open
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&self.name);
    }
}

impl Inboxes {
    /// Opens the inbox of `order` (replacing one left by an earlier task of it).
    pub fn open(self: &Arc<Self>, order: &HolonId) -> Inbox {
        let (sender, deliveries) = mpsc::unbounded_channel();
        self.open
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(order.name().to_string(), sender);
        Inbox {
            name: order.name().to_string(),
            inboxes: self.clone(),
            deliveries,
        }
    }

    /// Hands a query on `order/<name>/inbox` to the running order it names; an
    /// undecodable or misaddressed message is refused here. Returns the query when no
    /// running order has that name (the node decides).
    pub fn route(&self, query: Query) -> Option<Query> {
        use zenoh::Wait;
        let name = order_name(query.key_expr().as_str())?.to_string();
        let sender = self
            .open
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .get(&name)
            .cloned();
        let Some(sender) = sender else {
            return Some(query);
        };
        let payload = query
            .payload()
            .map(|p| p.to_bytes().into_owned())
            .unwrap_or_default();
        let refusal = match Service::from_json(&payload) {
            Ok(message)
                if HolonId::order(&name).ok().as_ref() == Some(&message.requester)
                    && matches!(
                        message.message_type,
                        MessageType::Done | MessageType::Failed
                    ) =>
            {
                info!(holon = %message.requester, conversation_id = %message.conversation_id, message_type = %message.message_type, provider = %message.provider.as_ref().map(|p| p.to_string()).unwrap_or_default(), reason = message.reason.as_deref().unwrap_or(""), "received");
                if let Err(returned) = sender.send(Delivery { message, query }) {
                    // The order's task ended between the lookup and the send: the node
                    // answers as for an order that is not running.
                    return Some(returned.0.query);
                }
                return None;
            }
            Ok(other) => schemas::ErrorReply::new(
                "wrong_key",
                format!(
                    "{} for {} is not for this inbox",
                    other.message_type, other.requester
                ),
            ),
            Err(err) => {
                warn!(order = %name, bytes = payload.len(), error = %err, "undecodable message in the inbox refused");
                schemas::ErrorReply::new("malformed", err.to_string())
            }
        };
        if let Err(e) = query.reply_err(refusal.to_json()).wait() {
            warn!(order = %name, error = %e, "cannot refuse a message in the inbox");
        }
        None
    }
}

/// The order named by an inbox key (`.../order/<name>/inbox`).
pub fn order_name(key: &str) -> Option<&str> {
    key.strip_suffix("/inbox")?.rsplit('/').next()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_the_order_of_an_inbox_key() {
        assert_eq!(
            order_name("holarchy/demo/order/orders1-7/inbox"),
            Some("orders1-7")
        );
        assert_eq!(order_name("holarchy/demo/order/orders1-7/state"), None);
    }
}

//! Which orders an order-node holds (`host/order-node/<node>/held`): a resource asks it
//! of the orders whose bookings (or results) it keeps, to learn whether their requester
//! is still in the cell.
//!
//! An order declares no zenoh token of its own: a key per order would stay in zenoh's
//! routing tables for the life of every link it crossed (a key-expression mapping per
//! key, about 1 KB per order in the order-node, the router and each resource,
//! docs/reliability.md). Its node answers for it instead: an order is held from its
//! start until it ends (done, scrapped, failed, cancelled). A resource asks every node
//! at once (`host/order-node/*/held`); an order no node holds is absent.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// The most orders one question names (a resource with more asks in several).
pub const MAX_HELD_ASKED: usize = 1024;

/// A resource's question: which of these orders does the node hold?
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HeldRequest {
    /// The orders' names (`orders1-12`), at most [`MAX_HELD_ASKED`].
    pub orders: Vec<String>,
}

/// A node's answer: those of the orders asked that it holds (runs and has not ended).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HeldReply {
    /// The node that answers.
    pub node: String,
    /// The orders asked that it holds.
    pub held: Vec<String>,
}

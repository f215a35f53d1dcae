//! order-node: the process that hosts order holons (work orders), one supervised task
//! each. [`progress`] is the pure part of an order (what comes next after each step),
//! [`order`] the conversations, [`inbox`] where results reach them, [`node`] the host.

pub mod config;
pub mod inbox;
pub mod node;
pub mod order;
pub mod progress;

//! holon-node: the process of one resource holon.
//!
//! Four components after the seed's Figure 3, each a task under one supervisor:
//! communication ([`communication`]), agenda manager ([`agenda`]), execution
//! ([`execution`]) and interfacing (`robot_bridge::client`). [`node::run`] wires them.

pub mod agenda;
pub mod catalog;
pub mod communication;
pub mod config;
pub mod execution;
pub mod node;
pub mod product;
pub mod requesters;

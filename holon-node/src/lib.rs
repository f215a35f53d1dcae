//! holon-node: the process of one resource holon (or of one product or staff holon).
//!
//! The resource holon is five components, each a task under one supervisor
//! ([`component`]): interfacing, execution, agenda manager, requesters and
//! communication, after the seed's Figure 3. The state machines they own are pure:
//! [`agenda`] (Figure 4), [`execution`] (Figure 5) and [`delivery`] (results until
//! acknowledged). [`node::run`] wires them.

/// This build's release, published in every holon's state (`version`).
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

pub mod absences;
pub mod agenda;
pub mod catalog;
pub mod component;
pub mod config;
pub mod delivery;
pub mod execution;
pub mod fault_injection;
pub mod fence;
pub mod handover;
pub mod holon_config;
pub mod identity;
pub mod node;
pub mod packml;
pub mod product;
pub mod staff;
pub mod views;

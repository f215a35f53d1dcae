//! holon-node: the process of one resource holon (or of one product or staff holon).
//!
//! The resource holon is the seed's five components (Figure 3): interfacing, execution,
//! agenda manager, requesters and communication. They run as four tasks under one
//! supervisor ([`component`]): the interfacing component is a module the execution's
//! task runs; a transporter runs a fifth task, its layout follower. [`node::run`] wires
//! them.
//!
//! Machines and tasks are told apart by folder: a pure state machine lives in
//! [`machine`] (the agenda, Figure 4; the execution, Figure 5; the delivery of results;
//! the PackML unit; absences; the controller's claim), the task that owns it in
//! [`component`], named for its component. Where the two would share a name, the
//! machine's type says `Machine`: the agenda manager task owns an
//! [`machine::agenda::AgendaMachine`], the execution task an
//! [`machine::execution::ExecutionMachine`].
//!
//! The product holon ([`product`]) and the staff holon ([`staff`]) use none of the
//! resource's types: they share with it the life cycle's driver (`holon::life`), the
//! config's header and the command line's overrides ([`identity`]), and stop with a
//! [`HolonError`].

/// This build's release, published in every holon's state (`version`).
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

pub mod catalog;
pub mod component;
pub mod config;
pub mod fault_injection;
pub mod handover;
pub mod holon_config;
mod holon_error;
pub mod identity;
pub mod machine;
pub mod node;
pub mod product;
pub mod staff;
pub mod views;

pub use holon_error::HolonError;

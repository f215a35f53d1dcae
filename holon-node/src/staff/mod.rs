//! The staff holon (PROSA's S): an advisor that plans ahead.
//!
//! It keeps a model of the cell from what the holons publish ([`model`]), forecasts an
//! order's whole remaining route from it and the other orders' intentions
//! ([`planner`]; the part's moves timed from the cell's layout, [`travel`]), and answers `staff/<name>/advice` ([`node`]). It never books, starts
//! or cancels on an order's behalf: orders take its advice when it fits what the
//! resources proposed, and the cell runs the same without it.

pub mod config;
pub mod model;
pub mod node;
pub mod planner;
pub mod travel;

//! The resource holon's five components, each a task under one supervisor (the seed's
//! Figure 3, plus the booking lifetime):
//!
//! | component | owns | receives |
//! |---|---|---|
//! | [`interfacing`] | the controller connection | commands |
//! | [`execution`] | the execution state machine | jobs, controller events |
//! | [`agenda_manager`] | the agenda and its journal, the undelivered results and their delivery ([`delivery`]) | every agenda event, requests with their queries, its attempts' ends |
//! | [`requesters`] | who of the cell is absent | liveliness samples, a tick |
//! | [`communication`] | the queryables, the published snapshot | queries, view changes |
//!
//! Each owns its state alone and hands it to its successor when it crashes
//! ([`crate::handover`]); the others see what it publishes ([`crate::views`]). The
//! agenda manager waits on no other component, and every other component waits only on
//! it (or, the interfacing component, on the execution): no cycle of waits.

pub mod agenda_manager;
pub mod communication;
pub mod delivery;
pub mod execution;
pub mod interfacing;
pub mod outcome;
pub mod question;
pub mod requesters;

//! The resource holon's components (the seed's Figure 3, plus the booking lifetime):
//! four tasks (five for a transporter) under one supervisor, and the interfacing component as a module the
//! execution's task runs:
//!
//! | component | owns | receives |
//! |---|---|---|
//! | [`execution`] (task), with [`interfacing`] (module) | the execution state machine; the controller connection | jobs; the controller's messages (on the socket) |
//! | [`agenda_manager`] | the agenda and its journal, the undelivered results and their delivery ([`delivery`]) | every agenda event, requests with their queries, its attempts' ends |
//! | [`requesters`] | who of the cell is absent | liveliness samples, a tick |
//! | [`communication`] | the queryables, the published snapshot | queries, view changes |
//! | [`layout`] (transporters only) | the cell's layout as last asked | a tick |
//!
//! Each owns its state alone and hands it to its successor when it crashes
//! ([`crate::handover`]); the others see what it publishes ([`crate::views`]). The
//! agenda manager waits on no other component, and every other component waits only on
//! it: no cycle of waits. The execution and the interfacing module share a task, so a
//! command and its reply cross no queue.

pub mod agenda_manager;
pub mod communication;
pub mod delivery;
pub mod execution;
pub mod interfacing;
pub mod layout;
pub mod outcome;
pub mod question;
pub mod requesters;

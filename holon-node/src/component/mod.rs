//! The resource holon's components, the tasks that own the pure machines
//! ([`crate::machine`]): the seed's five (Figure 3: interfacing, execution, agenda
//! manager, requesters, communication) run as four tasks under one supervisor, the
//! interfacing component a module the execution's task runs; a transporter runs a
//! fifth task, its layout follower. A file here is named for its component; what only
//! one component uses lives in that component's folder.
//!
//! | component | owns | receives |
//! |---|---|---|
//! | [`execution`] (task), with [`interfacing`] (module) | the execution machine; the controller connection | jobs; the controller's messages (on the socket) |
//! | [`agenda_manager`] | the agenda machine and its journal, the undelivered results and their delivery machine, with the attempts it sends out ([`agenda_manager::courier`]) | every agenda event, requests with their queries, its attempts' ends |
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
pub mod execution;
pub mod interfacing;
pub mod layout;
pub mod question;
pub mod requesters;

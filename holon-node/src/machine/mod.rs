//! The resource holon's pure state machines: each takes an event (with the time it
//! happened) and returns what to do, and does no I/O, reads no clock and waits on
//! nothing. Each is owned by one task of [`crate::component`], which feeds it its events
//! and carries out its actions:
//!
//! | machine | what it decides | owned by |
//! |---|---|---|
//! | [`agenda::AgendaMachine`] | the seed's Figure 4: bookings, the job, results to deliver | the agenda manager ([`crate::component::agenda_manager`]) |
//! | [`execution::ExecutionMachine`] | the seed's Figure 5: a job's steps, one command each | the execution component ([`crate::component::execution`]) |
//! | [`delivery::DeliveryMachine`] | when each result is sent again until acknowledged | the agenda manager |
//! | [`packml::PackmlUnit`] | the PackML state, mode, counters and stop reason | the agenda manager (through the agenda) |
//! | [`absences::Absences`] | who of the cell is absent, and since when | the requesters component ([`crate::component::requesters`]) |
//! | [`fence::Claim`] | a fenced resource's claim on its controller | the holon's standby round ([`crate::node`]) |
//!
//! Where a machine and the component that owns it would share a name, the machine's
//! type says `Machine`.

pub mod absences;
pub mod agenda;
pub mod delivery;
pub mod execution;
pub mod fence;
pub mod packml;

//! order-node: the process that hosts order holons (work orders), one supervised task
//! each.
//!
//! - [`progress`]: an order's progress through its plan, and what comes next after each
//!   step's outcome (pure);
//! - [`attempt`]: one attempt of one step, proposal to result (a pure state machine);
//! - [`order`]: an order's task, which performs the attempts' actions;
//! - [`requests`]: the order's requests over zenoh; [`ranking`]: how a round's offers
//!   are ranked;
//! - [`presence`]: which resources are alive and whose turn it is on each;
//!   [`station_line`]: parts in the cell take turns to look for a station place;
//! - [`inbox`]: where results (and moves' departures) reach the running orders, and
//!   which orders the node holds (a resource keeps an order's bookings while its node
//!   holds it);
//! - [`context`]: what the orders of a node share; [`journal`]: their store (SQLite,
//!   or etcd for a node with a standby, [`standby`], which says where it stands,
//!   [`fence_report`]);
//! - [`host`]: the orders a node hosts and their tasks; [`listing`]: a page of them;
//!   [`queries`]: its endpoints; [`submits`]: the work orders it made by their
//!   submitter's name, so that asking again is safe;
//!   [`node`]: the process, and [`error`]: why it stops with an error.

pub mod advice_pause;
pub mod attempt;
pub mod cancel;
pub mod config;
pub mod context;
pub mod error;
pub mod fence_report;
pub mod home_line;
pub mod host;
pub mod inbox;
pub mod journal;
pub mod listing;
pub mod node;
pub mod order;
pub mod part;
pub mod part_word;
pub mod phase;
pub mod presence;
pub mod progress;
pub mod queries;
pub mod ranking;
pub mod recovery;
pub mod requests;
pub mod standby;
pub mod station_line;
pub mod submits;

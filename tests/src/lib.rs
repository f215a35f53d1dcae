//! The harness of holarchy's multi-process tests: it starts the real binaries
//! (`robot-sim`, `holon-node`) on loopback with unique ports, talks zenoh to them with
//! multicast scouting off and explicit endpoints, waits on presence rather than sleeps,
//! bounds every wait, and kills its children when a test ends.

mod cell;
mod cell_holons;
pub mod chaos;
mod dashboard;
mod environment;
mod etcd;
mod flow_cell;
pub mod lab;
pub mod opcua;
mod paths;
mod plant;
mod process;
mod resource;
pub mod secure_cell;
mod sim;
pub mod web;
pub mod webdriver;

pub use cell::*;
pub use dashboard::*;
pub use environment::*;
pub use etcd::*;
pub use flow_cell::*;
pub use paths::*;
pub use plant::*;
pub use process::*;
pub use resource::*;
pub use sim::*;

use std::time::Duration;

/// The longest any single wait in a test may take.
pub const WAIT: Duration = Duration::from_secs(20);

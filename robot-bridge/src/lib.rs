//! robot-bridge: the Interfacing component of a resource holon.
//!
//! - [`codec`]: the TCP/XML codec of holarchy's own controller protocol;
//! - [`dialect`]: controller protocols described in files (framing, messages,
//!   correlation, outcomes, status), spoken by the client and the simulator;
//! - [`client`]: the controller client, one persistent connection with reconnection,
//!   per-command timeouts and `ROBOT_STATUS` tracking;
//! - [`sim`]: `robot-sim`, a controller simulator that speaks the same protocol;
//! - [`plant`]: `plant-sim`, the cell's plant simulated once for all its controllers;
//! - [`fence_wire`]: what both ends of the fence for standby holons share;
//! - [`shown`]: how a controller's message is shown in logs and errors.

pub mod client;
pub mod codec;
pub mod dialect;
pub mod fence_wire;
pub mod plant;
pub mod shown;
pub mod sim;

//! robot-bridge: the Interfacing component of a resource holon.
//!
//! - [`codec`]: the TCP/XML codec of the robot controller protocol;
//! - [`client`]: the controller client, one persistent connection with reconnection,
//!   per-command timeouts and `ROBOT_STATUS` tracking;
//! - [`sim`]: `robot-sim`, a controller simulator that speaks the same protocol.

pub mod client;
pub mod codec;
pub mod sim;

//! `cell`: the operator's command. `cell demo` runs a demo cell on this machine;
//! `cell status` lists the live holons of a running cell; `cell dashboard` shows it live
//! in a browser.
//!
//! Where each part lives:
//! - the command line: `src/main.rs` and `src/cli/` (one file per command, with its
//!   flags), calling this library;
//! - asking a running cell as a client (status, orders, submit, PackML, layout):
//!   [`client`];
//! - the process supervisor of a cell host (`cell up`, its manifest, `cell upgrade`):
//!   [`up`]; a zenoh router of its own: [`router`];
//! - the live web page: [`dashboard`];
//! - the OPC UA server: [`opcua`];
//! - users, roles, logins, the audit trail and certificates: [`security`];
//! - the demo cell: [`demo`].

pub mod client;
pub mod dashboard;
pub mod demo;
pub mod opcua;
pub mod router;
pub mod security;
pub mod up;

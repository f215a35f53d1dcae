//! The handlers of `cell`'s commands: one file per command (or a few close ones), with
//! the flags of a command that has many, calling the library. The subcommands are listed
//! in `commands.rs` and dispatched by `run` in `main.rs`.

pub mod dashboard;
pub mod demo;
pub mod opcua;
pub mod orders;
pub mod packml;
pub mod router;
pub mod status;
pub mod up;

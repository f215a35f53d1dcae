//! `cell`: the operator's command. `cell demo` runs a demo cell on this machine;
//! `cell status` lists the live holons of a running cell; `cell dashboard` shows it live
//! in a browser.

pub mod access;
pub mod ask;
pub mod audit;
pub mod certs;
pub mod dashboard;
pub mod demo;
pub mod layout;
pub mod listing;
pub mod logins;
pub mod manifest;
pub mod opcua;
pub mod orders;
pub mod packml;
pub mod part_word;
pub mod private_file;
pub mod router;
pub mod states;
pub mod status;
pub mod submit;
pub mod up;
pub mod upgrade;
pub mod users;

//! Who may do what in a cell: the roles of identities and users ([`access`]), the
//! cell's users and their passwords ([`users`]), failed logins slowed and locked out
//! ([`logins`]), the audit trail ([`audit`]), and the certificates `cell certs` issues
//! ([`certs`]), written readable by their owner only ([`private_file`]).

pub mod access;
pub mod audit;
pub mod certs;
pub mod logins;
pub mod private_file;
pub mod users;

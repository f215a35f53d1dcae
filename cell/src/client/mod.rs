//! Asking a running cell as a client: its holons and fences ([`status`]), its orders
//! ([`listing`], [`orders`]), a work order submitted ([`submit`]), a resource's PackML
//! state and commands ([`packml`]), where a lost part is ([`part_word`]), a conveyor's
//! carrier out of service or back ([`carrier_word`]), the layout the resources state ([`layout`]), and
//! the states the holons publish, heard ([`states`]); [`ask`] is the query they share.

pub mod ask;
pub mod carrier_word;
pub mod layout;
pub mod listing;
pub mod orders;
pub mod packml;
pub mod part_word;
pub mod states;
pub mod status;
pub mod submit;

//! An operator's word on a conveyor's carriers (`cell carrier RESOURCE CARRIER
//! --out|--back`): a pallet or shuttle taken out of service, or put back.
//!
//! A part rides its carrier from the cell's entry to its exit, so a conveyor with fewer
//! carriers in service than its buffers have homes would let in a part no carrier can
//! take: it waits at the entry holding the station place it reserved, while the parts
//! on every carrier wait for that place (docs/material-flow.md, "Carriers out of
//! service"). The conveyor's holon therefore grants a home only while fewer are held
//! than carriers are in service, and an operator who takes one out tells it, as the
//! plant is told.

use serde::{Deserialize, Serialize};

use crate::HolonId;

/// The word: the carrier and whether it is in service now. The query on
/// `resource/<name>/carriers` carries it; who says it travels in the query's
/// attachment ([`crate::requested_by`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CarrierWord {
    /// The carrier as the conveyor numbers its pallets, `p1` to `p<pallets>` (the plant
    /// names it `<conveyor>/p3`; that form is taken too).
    pub carrier: String,
    /// `false`: taken out of service; `true`: back in service.
    pub in_service: bool,
}

/// The conveyor's answer: its carriers as they stand after the word.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CarrierReply {
    /// The conveyor.
    pub resource: HolonId,
    /// Its carriers (the layout's `pallets`).
    pub carriers: u32,
    /// Those out of service, by name.
    pub out_of_service: Vec<String>,
    /// What the word changed, as an operator reads it.
    pub detail: String,
}

/// The carrier's short name (`p3`) if `name` is one of `pallets` carriers of
/// `conveyor` (`p3` or `conveyor1/p3`).
pub fn carrier_name(conveyor: &str, pallets: u32, name: &str) -> Option<String> {
    let short = name
        .strip_prefix(conveyor)
        .and_then(|rest| rest.strip_prefix('/'))
        .unwrap_or(name);
    let number: u32 = short.strip_prefix('p')?.parse().ok()?;
    (1..=pallets)
        .contains(&number)
        .then(|| format!("p{number}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_carrier_is_named_as_the_plant_numbers_them() {
        assert_eq!(carrier_name("conveyor1", 3, "p3").as_deref(), Some("p3"));
        assert_eq!(
            carrier_name("conveyor1", 3, "conveyor1/p1").as_deref(),
            Some("p1")
        );
        assert_eq!(carrier_name("conveyor1", 3, "p4"), None);
        assert_eq!(carrier_name("conveyor1", 3, "p0"), None);
        assert_eq!(carrier_name("conveyor1", 3, "monorail/p1"), None);
        assert_eq!(carrier_name("conveyor1", 3, "shuttle"), None);
        assert_eq!(carrier_name("conveyor1", 3, "p01").as_deref(), Some("p1"));
    }
}

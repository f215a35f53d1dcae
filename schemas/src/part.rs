//! Where an order's part is (docs/material-flow.md, "Parts and carriers"): at exactly one
//! place at every moment, written to the order's journal before anything acts on it.

use std::fmt;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::layout::LocationId;
use crate::HolonId;

/// Where a part is, as its order knows it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(tag = "state", rename_all = "snake_case", deny_unknown_fields)]
pub enum PartPlace {
    /// Not in the cell yet: raw material, to enter at an entry.
    Outside,
    /// At a location of the cell.
    At { location: LocationId },
    /// On a transporter, from a location (its last sure place) to another: its move
    /// may have begun.
    InTransit {
        transporter: HolonId,
        from: LocationId,
        to: LocationId,
    },
    /// Its move ended without its transporter saying where the part is (the
    /// transporter vanished mid-move, or the move failed on the way): in transit on
    /// `transporter`, last seen at `from`. The order waits until the transporter, once
    /// back, says what became of the move, or an operator says where the part is.
    Lost {
        transporter: HolonId,
        from: LocationId,
        to: LocationId,
        /// What ended the move (the transporter's words, or that it vanished).
        why: String,
    },
    /// Left the cell at an exit.
    Shipped { exit: LocationId },
}

impl PartPlace {
    /// The location the part is at, if it is at one.
    pub fn location(&self) -> Option<&LocationId> {
        match self {
            PartPlace::At { location } => Some(location),
            _ => None,
        }
    }
}

/// As an operator reads it: `at robot1.port`, `in transit on resource/conveyor1 from
/// conveyor1.load to robot1.port`, `in transit on resource/conveyor1, last seen at
/// conveyor1.load (the resource vanished)`, `shipped at conveyor1.load`, `outside`.
impl fmt::Display for PartPlace {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            PartPlace::Outside => f.write_str("outside the cell"),
            PartPlace::At { location } => write!(f, "at {location}"),
            PartPlace::InTransit {
                transporter,
                from,
                to,
            } => write!(f, "in transit on {transporter} from {from} to {to}"),
            PartPlace::Lost {
                transporter,
                from,
                why,
                ..
            } => write!(
                f,
                "in transit on {transporter}, last seen at {from} ({why})"
            ),
            PartPlace::Shipped { exit } => write!(f, "shipped at {exit}"),
        }
    }
}

/// An operator's word on where a lost part is (`cell part ORDER --at LOCATION`), as the
/// query on `order/<name>/part` carries it; who says it travels in the query's
/// attachment ([`crate::requested_by`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PartWord {
    /// Where the part is: the lost move's origin (it never left) or its destination
    /// (it arrived). Any other location is refused: the part's places are reserved
    /// there and nowhere else.
    pub location: LocationId,
}

/// The order's answer to an operator's word on its part.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct PartWordReply {
    pub order: String,
    /// Where the part is now, as the order recorded it.
    pub part: PartPlace,
    /// What happens next, as an operator reads it.
    pub detail: String,
}

/// An operator's word on a lost part, as the order's journal keeps it (its audit
/// trail, shown by `cell orders --detail`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct PartFound {
    /// The lost move's conversation (`<order>/m<n>/<attempt>`).
    pub conversation_id: String,
    /// The transporter the part was lost on.
    pub transporter: HolonId,
    /// Where the operator said the part is.
    pub location: LocationId,
    /// Who said it (the asking identity, as `cell` or the dashboard names it).
    pub by: String,
    /// When the order recorded it (Unix ms).
    pub at: u64,
}

impl fmt::Display for PartFound {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "found at {} by {} (lost on {}, move {})",
            self.location, self.by, self.transporter, self.conversation_id
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_place_reads_as_an_operator_says_it_and_travels_tagged() {
        let from = LocationId::new("conveyor1", "load").unwrap();
        let to = LocationId::new("robot1", "port").unwrap();
        let lost = PartPlace::Lost {
            transporter: HolonId::resource("conveyor1").unwrap(),
            from: from.clone(),
            to: to.clone(),
            why: "the resource vanished".into(),
        };
        assert_eq!(
            lost.to_string(),
            "in transit on resource/conveyor1, last seen at conveyor1.load (the resource vanished)"
        );
        let at = PartPlace::At { location: to };
        let json = serde_json::to_value(&at).unwrap();
        assert_eq!(
            json,
            serde_json::json!({"state": "at", "location": "robot1.port"})
        );
        assert_eq!(serde_json::from_value::<PartPlace>(json).unwrap(), at);
    }
}

//! A conveyor's carriers in service (docs/material-flow.md, "Carriers out of service"):
//! an operator who takes a pallet or shuttle out tells the conveyor's holon
//! (`resource/<name>/carriers`, `cell carrier`), which grants a home at its buffers only
//! while fewer homes are held than carriers are in service.
//!
//! A part rides its carrier from the entry to the exit. With more homes than carriers, a
//! part let in would wait at the entry for a carrier, holding the place it reserved for
//! its first station, while the parts on every carrier wait for that place: the cell
//! stops. The plant does not see it (no pallet waits on another: the waits are the
//! control's reservations), so the rule is the home's grant.
//!
//! | word | condition, in order | outcome |
//! |---|---|---|
//! | `carrier` out or back | the resource is not a conveyor | refused `invalid` |
//! | | the carrier is not one of its pallets (`p1` ... `p<pallets>`) | refused `invalid`, naming them |
//! | out | already out | answered, nothing changes |
//! | | otherwise | out; journalled; homes granted while fewer than those in service are held |
//! | back | not out | answered, nothing changes |
//! | | otherwise | back; journalled; the state published (a waiting part looks again) |
//!
//! Homes already held stay held: a carrier taken out with a part aboard still carries
//! it to the exit (the plant retires it once the part has left), and no new part enters
//! until fewer homes are held than carriers are in service.

use std::collections::BTreeSet;

use schemas::{carrier_name, CarrierReply, CarrierWord, ErrorCode};

use super::{AgendaAction, AgendaMachine};

/// A conveyor's carriers and those out of service.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Carriers {
    /// Its pallets (the layout's `pallets`); 0 for a resource that is not a conveyor.
    pallets: u32,
    /// Those an operator took out of service, by name (`p3`); journalled.
    pub(super) out: BTreeSet<String>,
}

impl Carriers {
    /// `pallets` carriers, those named in `out` out of service.
    pub fn new(pallets: u32, out: BTreeSet<String>) -> Carriers {
        Carriers { pallets, out }
    }

    /// How many are in service.
    pub fn in_service(&self) -> u32 {
        self.pallets.saturating_sub(self.out.len() as u32)
    }

    /// Whether one more home may be granted with `homes` held: a carrier in service is
    /// left for it. Always, for a resource that is not a conveyor.
    pub fn room_for_home(&self, homes: usize) -> bool {
        self.pallets == 0 || homes < self.in_service() as usize
    }

    /// Those out of service, by name.
    pub fn out(&self) -> &BTreeSet<String> {
        &self.out
    }
}

impl AgendaMachine {
    /// An operator's word on a carrier: the rows of the table above.
    pub(super) fn carrier_word(&mut self, word: &CarrierWord, by: &str) -> Vec<AgendaAction> {
        let conveyor = self.holon.name().to_string();
        let pallets = self.carriers.pallets;
        if pallets == 0 {
            return vec![AgendaAction::CarrierAnswer(Err((
                ErrorCode::Invalid,
                format!("{conveyor} is not a conveyor: it has no carriers"),
            )))];
        }
        let Some(carrier) = carrier_name(&conveyor, pallets, &word.carrier) else {
            return vec![AgendaAction::CarrierAnswer(Err((
                ErrorCode::Invalid,
                format!(
                    "{:?} is not one of {conveyor}'s carriers (p1 to p{pallets})",
                    word.carrier
                ),
            )))];
        };
        let changed = if word.in_service {
            self.carriers.out.remove(&carrier)
        } else {
            self.carriers.out.insert(carrier.clone())
        };
        let homes = self.places.homes_held();
        let in_service = self.carriers.in_service();
        let now = match (word.in_service, changed) {
            (false, true) => "taken out of service",
            (false, false) => "was out of service already",
            (true, true) => "back in service",
            (true, false) => "was in service already",
        };
        let detail = format!(
            "{carrier} {now}: {in_service} of {pallets} carriers in service, {homes} homes held; \
             a part enters while fewer than {in_service} are held"
        );
        if changed {
            tracing::info!(holon = %self.holon, %carrier, in_service = word.in_service, %by, carriers_in_service = in_service, homes_held = homes, "an operator's word on a carrier");
        }
        let reply = CarrierReply {
            resource: self.holon.clone(),
            carriers: pallets,
            out_of_service: self.carriers.out.iter().cloned().collect(),
            detail,
        };
        let mut actions = vec![AgendaAction::CarrierAnswer(Ok(reply))];
        if changed {
            actions.push(AgendaAction::StateChanged);
        }
        actions
    }
}

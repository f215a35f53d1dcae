//! The model's alarms about parts: `part_lost` while an order's part is lost, and
//! `part_waits` when one stays where it is beyond the bound ([`super::part_waits`]).

use schemas::OrderSnapshot;

use super::{AlarmKind, Model};

impl Model {
    /// Time passes: a part in the cell that has stayed where it is beyond the bound
    /// raises `part_waits`.
    pub(super) fn tick(&mut self, at: u64) -> bool {
        let mut changed = false;
        for (order, message) in self.part_waits.overdue(at) {
            changed |= self.raise(AlarmKind::PartWaits, &order, message, at);
        }
        changed
    }

    /// The `part_lost` alarm of an order: raised while its part is lost, cleared once
    /// its transporter (or an operator) has said where it is.
    pub(super) fn part_alarm(&mut self, snapshot: &OrderSnapshot, at: u64) {
        match &snapshot.part {
            Some(lost @ schemas::PartPlace::Lost { .. }) => {
                let message = format!(
                    "{}'s part is {lost}: it waits until its transporter, once back, or an operator says where it is",
                    snapshot.holon
                );
                self.raise(AlarmKind::PartLost, &snapshot.holon, message, at);
            }
            _ => {
                self.clear(AlarmKind::PartLost, &snapshot.holon, at);
            }
        }
    }
}

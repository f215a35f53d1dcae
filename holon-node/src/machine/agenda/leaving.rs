//! Leaving: a shutdown hands every booking back, a hand-over keeps them for the
//! successor, a deposed holder drops them, and a requester that left has its bookings
//! released.

use schemas::{HolonId, Reason};
use serde_json::Map;

use super::{AgendaAction, AgendaMachine, Job, Outcome};

impl AgendaMachine {
    pub(super) fn hand_over(&mut self, handing_over: bool) -> Vec<AgendaAction> {
        if self.withdrawing || self.handing_over == handing_over {
            return vec![];
        }
        self.handing_over = handing_over;
        vec![AgendaAction::StateChanged]
    }

    pub(super) fn withdraw(&mut self) -> Vec<AgendaAction> {
        if self.withdrawing {
            return vec![];
        }
        self.withdrawing = true;
        self.handing_over = false;
        let mut actions = self.hand_back("the resource is shutting down; book elsewhere");
        actions.push(AgendaAction::StateChanged);
        actions
    }

    pub(super) fn deposed(&mut self) -> Vec<AgendaAction> {
        let dropped = std::mem::take(&mut self.bookings).len();
        if self.withdrawing && dropped == 0 {
            return vec![];
        }
        self.withdrawing = true;
        self.handing_over = false;
        vec![AgendaAction::StateChanged]
    }

    /// Every booking handed back: a `failed` `withdrawn` with `detail` to its
    /// `reply_to`, so its order books elsewhere at once.
    pub(super) fn hand_back(&mut self, detail: &str) -> Vec<AgendaAction> {
        let mut actions = Vec::new();
        for booking in std::mem::take(&mut self.bookings) {
            let Some(reply_to) = booking.reply_to else {
                // Nowhere to tell: the requester finds out when its start is refused.
                continue;
            };
            let message = self.result_message(
                Job {
                    requester: booking.requester,
                    conversation_id: booking.conversation_id,
                    service_type: booking.service_type,
                    reply_to,
                    info: Map::new(),
                    parameters: None,
                    operator: None,
                },
                Outcome::Failed {
                    reason: Reason::Withdrawn,
                    detail: detail.into(),
                },
            );
            self.undelivered.push(message.clone());
            actions.push(AgendaAction::Deliver(message));
        }
        actions
    }

    pub(super) fn release(&mut self, requester: &HolonId) -> Vec<AgendaAction> {
        let before = self.bookings.len();
        self.bookings.retain(|b| &b.requester != requester);
        if self.bookings.len() == before {
            vec![]
        } else {
            vec![AgendaAction::StateChanged]
        }
    }
}

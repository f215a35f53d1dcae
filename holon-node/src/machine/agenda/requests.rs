//! The requests other holons send the agenda: the rows of the table for `proposal_req`,
//! `booking_req`, `booking_cancel` and `start`, checked in the table's order, and their
//! refusals.

use schemas::{HolonId, HolonKind, MessageType, Reason, ResourceState, Service};
use serde_json::Value;

use super::{handing_over_hint, packml_hint, AgendaAction, AgendaMachine, Booking};

/// Where one conversation (a requester and a `conversation_id`) stands on the agenda.
#[derive(Debug, Clone, Copy)]
struct Conversation {
    /// Its booking's index, if it is booked.
    booked: Option<usize>,
    /// Its job is running.
    running: bool,
    /// Its job finished and the result is not acknowledged yet.
    finished: bool,
}

/// How a request's epoch ([`schemas::info_key::EPOCH`]) stands against the highest its
/// booking was asked at.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Epoch {
    /// Not lower (or neither says one): the request goes on; the booking keeps this
    /// epoch from now on (`Some`) if it is higher than the one it had.
    Current(Option<u64>),
    /// Lower than the booking's: from a deposed holder of the order-node.
    Stale { asked: u64, booked: u64 },
}

impl AgendaMachine {
    /// How `request`'s epoch stands against that of the booking at `index`; an error
    /// saying why when its epoch is not a whole number.
    fn epoch(&self, request: &Service, index: usize) -> Result<Epoch, String> {
        let asked = request.epoch()?;
        let booked = self.bookings[index].requester_epoch;
        Ok(match (asked, booked) {
            (Some(asked), Some(booked)) if asked < booked => Epoch::Stale { asked, booked },
            (Some(asked), booked) if booked.is_none_or(|booked| asked > booked) => {
                Epoch::Current(Some(asked))
            }
            _ => Epoch::Current(None),
        })
    }

    /// Checks `request`'s epoch against the booking at `index` and keeps a higher one;
    /// the refusal to answer with when it is stale or malformed, and otherwise whether
    /// the booking changed (to be journalled).
    fn check_epoch(&mut self, request: &Service, index: usize) -> Result<bool, Vec<AgendaAction>> {
        match self.epoch(request, index) {
            Err(detail) => Err(self.refuse(request, Reason::InvalidInfo, Some(detail))),
            Ok(Epoch::Stale { asked, booked }) => Err(self.refuse_stale(request, asked, booked)),
            Ok(Epoch::Current(Some(higher))) => {
                self.bookings[index].requester_epoch = Some(higher);
                Ok(true)
            }
            Ok(Epoch::Current(None)) => Ok(false),
        }
    }

    fn refuse_stale(&self, request: &Service, asked: u64, booked: u64) -> Vec<AgendaAction> {
        let detail = format!(
            "asked at epoch {asked} of its order-node, booked at epoch {booked}: a newer holder has the order"
        );
        self.refuse(request, Reason::StaleEpoch, Some(detail))
    }

    /// Where the request's conversation stands on this agenda.
    fn conversation(&self, request: &Service) -> Conversation {
        let same = |requester: &HolonId, conversation_id: &str| {
            requester == &request.requester && conversation_id == request.conversation_id
        };
        Conversation {
            booked: self
                .bookings
                .iter()
                .position(|b| same(&b.requester, &b.conversation_id)),
            running: self
                .running
                .iter()
                .any(|job| same(&job.requester, &job.conversation_id)),
            finished: self
                .undelivered
                .iter()
                .any(|r| same(&r.requester, &r.conversation_id)),
        }
    }

    /// A request from another holon: the rows of the table (in the documentation of
    /// [`crate::machine::agenda`]), in their order.
    pub(super) fn request(&mut self, request: Service, now: u64) -> Vec<AgendaAction> {
        match request.message_type {
            MessageType::BookingReq if request.service_type == schemas::PLACE_SERVICE => {
                self.hold_place(&request, now)
            }
            MessageType::ProposalReq => self.proposal(&request),
            MessageType::BookingReq => self.book(request),
            MessageType::BookingCancel => self.cancel(&request),
            MessageType::Start => self.start(request),
            // Not agenda requests: the communication component answers `status` itself
            // (a read of the state) and rejects the others.
            MessageType::Proposal
            | MessageType::Done
            | MessageType::Failed
            | MessageType::Departed
            | MessageType::Status => self.refuse(&request, Reason::UnknownService, None),
        }
    }

    pub(super) fn refuse(
        &self,
        request: &Service,
        why: Reason,
        detail: Option<String>,
    ) -> Vec<AgendaAction> {
        let unavailable = why == Reason::Unavailable;
        let mut reply = request.refused(&self.holon, why);
        if let Some(detail) = detail {
            reply.info.insert("detail".into(), Value::String(detail));
        }
        if unavailable && self.handing_over {
            handing_over_hint(&mut reply.info);
        } else if unavailable && !self.packml.takes_orders() {
            packml_hint(&self.packml, &mut reply.info);
        }
        vec![AgendaAction::Reply(reply)]
    }

    fn proposal(&self, request: &Service) -> Vec<AgendaAction> {
        let unreachable = self.unreachable(&request.info);
        let refusal = if !self.catalog.offers(&request.service_type) {
            Some(Reason::UnknownService)
        } else if unreachable.is_some() {
            Some(Reason::InvalidInfo)
        } else if !self.takes_work() {
            Some(Reason::Unavailable)
        } else if self.bookings.len() >= self.capacity {
            Some(Reason::AgendaFull)
        } else {
            None
        };
        let mut reply = request.accepted(&self.holon);
        reply.message_type = MessageType::Proposal;
        if let Some(why) = &refusal {
            reply.result = Some(false);
            reply.reason = Some(why.clone());
        }
        let priority = match request.priority() {
            Ok(priority) => priority,
            Err(detail) => return self.refuse(request, Reason::InvalidInfo, Some(detail)),
        };
        reply.info = self.proposal_info(request, priority);
        if let Some(why) = unreachable {
            reply.info.insert("detail".into(), Value::String(why));
        }
        if refusal == Some(Reason::Unavailable) && self.handing_over {
            handing_over_hint(&mut reply.info);
        } else if refusal == Some(Reason::Unavailable) && !self.packml.takes_orders() {
            packml_hint(&self.packml, &mut reply.info);
        }
        vec![AgendaAction::Reply(reply)]
    }

    fn book(&mut self, request: Service) -> Vec<AgendaAction> {
        let conversation = self.conversation(&request);
        let taking_work = self.takes_work();
        let full = self.bookings.len() >= self.capacity;
        match (conversation, taking_work, full) {
            _ if !self.catalog.offers(&request.service_type) => {
                self.refuse(&request, Reason::UnknownService, None)
            }
            _ if self.unreachable(&request.info).is_some() => {
                let why = self.unreachable(&request.info);
                self.refuse(&request, Reason::InvalidInfo, why)
            }
            _ if request.requester.kind() == HolonKind::Resource => {
                self.refuse(&request, Reason::NotARequester, None)
            }
            (
                Conversation {
                    booked: Some(position),
                    ..
                },
                _,
                _,
            ) => match self.check_epoch(&request, position) {
                Err(refusal) => refusal,
                Ok(raised) => {
                    let mut actions =
                        vec![AgendaAction::Reply(self.booked_reply(&request, position))];
                    if raised {
                        actions.push(AgendaAction::StateChanged);
                    }
                    actions
                }
            },
            // Asked again (a lost reply, a restarted order) after the job began on
            // its turn: it has begun.
            (Conversation { running: true, .. } | Conversation { finished: true, .. }, ..)
                if request.start_on_turn() =>
            {
                vec![AgendaAction::Reply(self.started_reply(&request))]
            }
            (Conversation { running: true, .. }, _, _) => self.refuse(&request, Reason::Busy, None),
            (_, false, _) => self.refuse(&request, Reason::Unavailable, None),
            (_, true, true) => self.refuse(&request, Reason::AgendaFull, None),
            (_, true, false) => self.append(request),
        }
    }

    /// Appends the booking of `request`; one that asks to start on its turn is checked
    /// as a start would be, and begins at once when it is the next job of a free
    /// resource.
    fn append(&mut self, request: Service) -> Vec<AgendaAction> {
        let (priority, due, requester_epoch) =
            match (request.priority(), request.due(), request.epoch()) {
                (Ok(priority), Ok(due), Ok(epoch)) => (priority, due, epoch),
                (Err(detail), _, _) | (_, Err(detail), _) | (_, _, Err(detail)) => {
                    return self.refuse(&request, Reason::InvalidInfo, Some(detail))
                }
            };
        let start_on_turn = request.start_on_turn();
        // Read once, here: the start and each step take them from the booking.
        let parameters = self
            .catalog
            .parameters(&request.service_type, &request.info);
        if start_on_turn {
            if let Err(detail) = parameters {
                return self.refuse(&request, Reason::InvalidInfo, Some(detail));
            }
            if request.reply_to.is_none() {
                let detail = "a booking that starts on its turn needs reply_to".to_string();
                return self.refuse(&request, Reason::InvalidInfo, Some(detail));
            }
        }
        let at = self.insertion_point(priority);
        for passed in &mut self.bookings[at..] {
            passed.overtaken += 1;
        }
        self.bookings.insert(
            at,
            Booking {
                requester: request.requester.clone(),
                conversation_id: request.conversation_id.clone(),
                service_type: request.service_type.clone(),
                reply_to: request.reply_to.clone(),
                info: request.info.clone(),
                parameters: parameters.ok().map(std::sync::Arc::new),
                start_on_turn,
                priority,
                due,
                overtaken: 0,
                requester_epoch,
            },
        );
        match self.start_on_turn() {
            Some(job) => vec![
                AgendaAction::Reply(self.started_reply(&request)),
                AgendaAction::Execute(job),
                AgendaAction::StateChanged,
            ],
            None => {
                let reply = self.booked_reply(&request, at);
                vec![AgendaAction::Reply(reply), AgendaAction::StateChanged]
            }
        }
    }

    fn cancel(&mut self, request: &Service) -> Vec<AgendaAction> {
        match self.conversation(request).booked {
            Some(index) => {
                if let Err(refusal) = self.check_epoch(request, index) {
                    return refusal;
                }
                self.bookings.remove(index);
                vec![
                    AgendaAction::Reply(request.accepted(&self.holon)),
                    AgendaAction::StateChanged,
                ]
            }
            None => match self.release_place(request) {
                Some(released) => released,
                None => self.refuse(request, Reason::NotBooked, None),
            },
        }
    }

    fn start(&mut self, request: Service) -> Vec<AgendaAction> {
        let conversation = self.conversation(&request);
        let booking = conversation
            .booked
            .map(|index| (index, self.bookings[index].service_type.clone()));
        let out_of_work = self.leaving() || !self.packml.takes_orders();
        match (conversation, booking, self.state(), out_of_work) {
            _ if !self.catalog.offers(&request.service_type) => {
                self.refuse(&request, Reason::UnknownService, None)
            }
            // A repeated start of the running job, or of one that finished and whose
            // result is on its way: it has begun.
            (Conversation { running: true, .. } | Conversation { finished: true, .. }, ..) => {
                vec![AgendaAction::Reply(request.accepted(&self.holon))]
            }
            (_, None, _, _) => self.refuse(&request, Reason::NotBooked, None),
            (_, Some(_), _, true) => self.refuse(&request, Reason::Unavailable, None),
            (_, Some((_, booked_type)), _, _) if booked_type != request.service_type => {
                let detail = format!("the booking is for {booked_type}");
                self.refuse(&request, Reason::NotBooked, Some(detail))
            }
            (_, Some((index, _)), state, _) => match self.epoch(&request, index) {
                Err(detail) => self.refuse(&request, Reason::InvalidInfo, Some(detail)),
                Ok(Epoch::Stale { asked, booked }) => self.refuse_stale(&request, asked, booked),
                // (A higher epoch needs no keeping: the booking becomes the job.)
                Ok(Epoch::Current(_)) => match state {
                    ResourceState::Busy => self.refuse(&request, Reason::Busy, None),
                    ResourceState::Init => self.refuse(&request, Reason::Unavailable, None),
                    ResourceState::Free => self.begin(index, request),
                },
            },
        }
    }

    /// Makes the booking at `index` the running job, if what the steps need is there.
    fn begin(&mut self, index: usize, request: Service) -> Vec<AgendaAction> {
        let booking = &self.bookings[index];
        // The booking's info was read when it was booked; a start's own is read now.
        let started_with = if !request.has_service_data() {
            match &booking.parameters {
                Some(_) => None,
                None => {
                    let why = self
                        .catalog
                        .parameters(&request.service_type, &booking.info);
                    let detail = why.err().unwrap_or_default();
                    return self.refuse(&request, Reason::InvalidInfo, Some(detail));
                }
            }
        } else {
            match self
                .catalog
                .parameters(&request.service_type, &request.info)
            {
                Ok(parameters) => Some((request.info.clone(), parameters)),
                Err(detail) => return self.refuse(&request, Reason::InvalidInfo, Some(detail)),
            }
        };
        let Some(reply_to) = request
            .reply_to
            .clone()
            .or_else(|| booking.reply_to.clone())
        else {
            let detail = "neither the start nor the booking has reply_to".to_string();
            return self.refuse(&request, Reason::InvalidInfo, Some(detail));
        };
        let job = self.run_booking(index, reply_to, started_with);
        vec![
            AgendaAction::Reply(request.accepted(&self.holon)),
            AgendaAction::Execute(job),
            AgendaAction::StateChanged,
        ]
    }
}

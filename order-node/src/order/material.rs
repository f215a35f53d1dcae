//! An order's part on its way through the cell (docs/material-flow.md, "Orders arrange
//! their moves"): before a step, the part is brought to a station that works it; after
//! the last step (or when the order ends otherwise) it leaves by an exit.
//!
//! Before each step the order asks the stations for proposals and, best first:
//! - works the step where the part is, if that station proposed;
//! - else reserves a place at a proposing station's port and books the move there
//!   (both or neither: a move that cannot be booked releases the place);
//! - else, when no station has a place for it and the part is at a station's port,
//!   waits there while no other part of the node waits for a service of the station
//!   it holds, for a bounded time (`orders.wait_at_port`, [`port_wait`]); then takes
//!   it back to its home (the buffer place it
//!   holds from its entry until it leaves): so a part waits for a place for long only
//!   where it blocks no station, and finite ports cannot deadlock the cell;
//! - else waits for a place to free up, or a station to appear, in line with the other
//!   parts of the node's orders that wait for a station of the step's service: they
//!   look in turn, oldest first ([`crate::station_line`]), and a part at a port that
//!   finds older parts waiting goes home rather than take the place they wait for.
//!
//! A part enters the cell only once a home is reserved for it: no more parts are in the
//! cell than its buffers hold; a part leaves a freed home to a waiting part of a higher
//! priority ([`crate::home_line`]). Every change of the part ([`crate::part`]) is journalled
//! before it is acted on; a move is booked and followed as a step is ([`crate::attempt`],
//! its own phase).

use std::time::Duration;

use schemas::layout::{CellLayout, LocationId, LocationRole};
use schemas::{info_key, HolonId, MessageType, PartPlace, PlanStep, Reason};
use serde_json::{Map, Value};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::{debug, info, warn};

use super::{Leg, OrderTask};
use crate::context::{jittered, OrderError, IDLE_POLL};
use crate::inbox::ResultReport;
use crate::part::{Move, MoveEnd, MoveGoal, PartProgress, TRANSPORT_SERVICE};
use crate::progress::{Phase, StepOutcome};
use crate::requests;

mod home;
mod lost;
mod port_wait;
use port_wait::PortWait;

/// How long an order waits before asking again for a station place, a home or a
/// transporter that none had (a place freed or a resource appearing wakes it sooner).
const PLACE_RETRY: Duration = Duration::from_millis(500);

/// Where arranging the part for a step ended.
pub(super) enum Arranged {
    /// The part is at a port of this station, which proposed for the step.
    At(HolonId),
    /// No station could take the step within the order's no-resource timeout.
    NoStation,
    /// An operator cancelled the order meanwhile (recorded: the part leaves next).
    Cancelled,
}

impl OrderTask<'_> {
    /// The order's part (a plan that moves parts has one).
    fn part(&self) -> PartProgress {
        self.progress.get().part.clone().unwrap_or_default()
    }

    /// Brings the part to a station that works `step`.
    pub(super) async fn arrange(
        &mut self,
        step: &PlanStep,
        conversation_id: &str,
        operator_cancel: &CancellationToken,
    ) -> Result<Arranged, OrderError> {
        let give_up = Instant::now() + self.ctx.settings.no_resource_timeout;
        // The pause before looking again grows while nothing changes (a freed place or a
        // resource appearing wakes the order sooner), spaced with the other idle orders:
        // a thousand parts waiting outside the cell cost next to nothing.
        let mut backoff = holon::Backoff::new(PLACE_RETRY, IDLE_POLL);
        let priority = self.progress.get().priority;
        let mut ticket = self
            .ctx
            .line
            .ticket(&self.holon, &step.service_type, priority);
        // The part's place among those waiting outside for a home, while it waits.
        let mut home_wait = None;
        // The port the part waits at for its next station, and until when at most.
        let mut port_wait: Option<PortWait> = None;
        // A part that joins a line may want the station whose port this part holds.
        let mut joins = self.ctx.line.joins();
        loop {
            if self.end_move_under_way().await? {
                continue;
            }
            let part = self.part();
            if operator_cancel.is_cancelled() {
                self.ctx.commit(self.progress, |p| p.cancel()).await?;
                return Ok(Arranged::Cancelled);
            }
            let Some(layout) = self.ctx.layout().await else {
                self.pause(PLACE_RETRY).await;
                continue;
            };
            // A part without a home waits outside for one first: no station can take
            // it before it may enter, and its station rounds would only delay those of
            // the parts in the cell (a freed place wakes a waiting order). It leaves a
            // freed home to a part of a higher priority (crate::home_line).
            if part.home.is_none() && !self.enter(&layout, &mut home_wait, &mut backoff).await? {
                continue;
            }
            // In the cell, the parts waiting for a station of this service take turns
            // (crate::station_line): a part that looked before waits for its turn (at
            // its home, or at its port up to its bound); one just worked at a port, or
            // looking for the first time, looks at once only if no part ahead waits.
            let at_port = part
                .place
                .location()
                .filter(|l| is_port(&layout, l))
                .cloned();
            if port_wait
                .as_ref()
                .is_some_and(|wait| Some(&wait.at) != at_port.as_ref())
            {
                port_wait = None;
            }
            let waited = ticket.in_line() && (at_port.is_none() || port_wait.is_some());
            if waited {
                let next_check = port_wait.as_ref().map(PortWait::next_check);
                let recheck = async {
                    match next_check {
                        Some(wake) => {
                            tokio::select! {
                                _ = tokio::time::sleep_until(wake) => {}
                                Ok(()) = joins.changed() => {}
                            }
                        }
                        None => std::future::pending().await,
                    }
                };
                tokio::select! {
                    _ = ticket.turn() => {}
                    _ = recheck => {
                        // No turn yet: the part waits on at its port, or goes home.
                        let wait = port_wait.as_mut().expect("waiting at a port");
                        if !self.keeps_waiting_at_port(wait, &step.service_type).await {
                            port_wait = None;
                            self.go_home(at_port.expect("waiting at a port"), &part).await?;
                        }
                        continue;
                    }
                    _ = operator_cancel.cancelled() => continue,
                }
            }
            let ranked = self.station_round(step, conversation_id, &layout).await;
            if let Some(here) = &at_port {
                let station = HolonId::resource(here.holon()).ok();
                if let Some(station) = station.filter(|s| ranked.contains(s)) {
                    // It proposed just now: the step's booking asks it without a round.
                    self.proposed_at = Some(station.clone());
                    return Ok(Arranged::At(station));
                }
            }
            let placed = if waited || ticket.turn_now().await {
                let placed = self.place_at_station(&layout, &ranked).await?;
                ticket.tried(placed);
                placed
            } else {
                false
            };
            if placed {
                continue;
            } else if let Some(here) = at_port {
                match port_wait.as_mut() {
                    None => {
                        if let Some(wait) = self.port_wait(&layout, &here, &part).await {
                            port_wait = Some(wait);
                            continue;
                        }
                    }
                    Some(wait) => {
                        if self.keeps_waiting_at_port(wait, &step.service_type).await {
                            continue;
                        }
                    }
                }
                port_wait = None;
                self.go_home(here, &part).await?;
                continue;
            }
            if Instant::now() >= give_up && ranked.is_empty() {
                return Ok(Arranged::NoStation);
            }
        }
    }

    /// The part leaves the cell by an exit, and the order's end that waited for it is
    /// recorded. A part that never entered leaves at once (its home released).
    pub(super) async fn leave(&mut self) -> Result<(), OrderError> {
        loop {
            if self.end_move_under_way().await? {
                continue;
            }
            let part = self.part();
            let Some(here) = part.place.location().cloned() else {
                // Outside, or shipped: its places go, and the order ends.
                let held: Vec<_> = part.held.into_iter().collect();
                self.ctx
                    .commit(self.progress, |p| {
                        if let Some(part) = &mut p.part {
                            part.held.clear();
                            part.home = None;
                        }
                        p.part_left();
                    })
                    .await?;
                self.release(held).await;
                return Ok(());
            };
            let Some(layout) = self.ctx.layout().await else {
                self.pause(PLACE_RETRY).await;
                continue;
            };
            let exit = layout
                .locations()
                .map(|(_, l)| l)
                .filter(|l| matches!(l.role, LocationRole::Exit | LocationRole::EntryExit))
                .find(|l| !layout.routes(&here, &l.id).is_empty())
                .map(|l| l.id.clone());
            let Some(exit) = exit else {
                warn!(holon = %self.holon, at = %here, "no exit can be reached from where the part is: it waits for the layout to change");
                self.pause(PLACE_RETRY * 4).await;
                continue;
            };
            self.begin_move(here, exit, MoveGoal::Exit).await?;
        }
    }

    /// Records the part's move from `from` to `to` as begun: its attempt books it next.
    pub(super) async fn begin_move(
        &mut self,
        from: LocationId,
        to: LocationId,
        goal: MoveGoal,
    ) -> Result<(), OrderError> {
        self.ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    part.begin_move(&p.holon, from, to, goal);
                }
            })
            .await
    }

    /// Runs the move under way to its end, if there is one (or, with the part lost,
    /// waits until its transporter says where it is): whether there was one.
    async fn end_move_under_way(&mut self) -> Result<bool, OrderError> {
        let part = self.part();
        let Some(moving) = part.moving else {
            return Ok(false);
        };
        match part.place {
            PartPlace::Lost { .. } => self.find_lost(&moving).await?,
            _ => self.run_move(moving).await?,
        }
        Ok(true)
    }

    /// A proposal round for `step` among the stations, with the staff's advice asked
    /// together: those that proposed, best first (the advised one first, if it
    /// proposed; it is then counted as advised once its step is booked).
    async fn station_round(
        &mut self,
        step: &PlanStep,
        conversation_id: &str,
        layout: &CellLayout,
    ) -> Vec<HolonId> {
        let ask = self.request(MessageType::ProposalReq, step, conversation_id);
        // Where the part is, so that the staff counts its travel (outside: from the
        // cell's entry, where it will enter).
        let at = match self.part().place {
            PartPlace::Outside => entry_of(layout),
            place => place.location().cloned(),
        };
        let super::round::Round {
            ranked, advised, ..
        } = self.round(&ask, true, at).await;
        self.advised = advised.filter(|a| ranked.first() == Some(a));
        ranked
    }

    /// Reserves a place at a port of the best proposing station the part can get to,
    /// and begins the move there. False when none had a place.
    async fn place_at_station(
        &mut self,
        layout: &CellLayout,
        ranked: &[HolonId],
    ) -> Result<bool, OrderError> {
        let part = self.part();
        let from = match &part.place {
            PartPlace::At { location } => location.clone(),
            PartPlace::Outside => match entry_of(layout) {
                Some(entry) => entry,
                None => return Ok(false),
            },
            _ => return Ok(false),
        };
        for station in ranked {
            let ports = layout.parts.get(station.name()).map(|p| {
                p.locations
                    .iter()
                    .filter(|l| matches!(l.role, LocationRole::Port | LocationRole::Input))
                    .map(|l| l.id.clone())
                    .collect::<Vec<_>>()
            });
            for port in ports.unwrap_or_default() {
                if port == from || layout.routes(&from, &port).is_empty() {
                    continue;
                }
                if self.reserve(&port).await? {
                    info!(holon = %self.holon, %station, %port, %from, "a place at the station is reserved: the part moves there");
                    self.begin_move(from.clone(), port, MoveGoal::Station)
                        .await?;
                    return Ok(true);
                }
            }
        }
        Ok(false)
    }

    /// Reserves a place for the part at `location` (at the resource that states it):
    /// journalled as held before it is asked, so that a restart releases it if unused.
    async fn reserve(&mut self, location: &LocationId) -> Result<bool, OrderError> {
        Ok(self.reserve_or_why(location).await?.is_ok())
    }

    /// [`Self::reserve`], saying why a place was not reserved: its resource's reason
    /// (none when it did not answer) and its words.
    pub(super) async fn reserve_or_why(
        &mut self,
        location: &LocationId,
    ) -> Result<Result<(), (Option<Reason>, String)>, OrderError> {
        let mut conversation = String::new();
        let holon = &self.holon;
        self.ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    conversation = part.place_conversation(holon, location);
                    part.held.insert(location.clone(), conversation.clone());
                }
            })
            .await?;
        let request = self.place_request(MessageType::BookingReq, location, &conversation);
        let key = self.ctx.keys.service(location.holon());
        let answer = requests::ask(&self.ctx, &key, &request).await;
        if answer.as_ref().is_some_and(|a| a.result == Some(true)) {
            return Ok(Ok(()));
        }
        let why = answer.as_ref().and_then(|a| a.reason.clone());
        if why != Some(Reason::NoPlace) {
            info!(holon = %self.holon, %location, reason = why.as_ref().map_or("no answer", |r| r.as_str()), "a place could not be reserved");
        }
        let told = match &answer {
            None => format!("{} did not answer", location.holon()),
            Some(refusal) => {
                let reason = why.as_ref().map_or("refused", |r| r.as_str());
                match refusal.info.get("detail").and_then(|d| d.as_str()) {
                    Some(detail) => format!("{reason}: {detail}"),
                    None => reason.to_string(),
                }
            }
        };
        self.ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    part.held.remove(location);
                }
            })
            .await?;
        if answer.is_none() {
            // It may have been reserved with the answer lost: released when it answers.
            self.release(vec![(location.clone(), conversation)]).await;
        }
        Ok(Err((why, told)))
    }

    /// Releases places (each location with its reservation's conversation); one whose
    /// resource does not answer is released when it is back.
    async fn release(&self, places: Vec<(LocationId, String)>) {
        for (location, conversation) in places {
            let cancel = self.place_request(MessageType::BookingCancel, &location, &conversation);
            let owner = match HolonId::resource(location.holon()) {
                Ok(owner) => owner,
                Err(e) => {
                    warn!(holon = %self.holon, %location, error = %e, "a place at a location of no resource: nothing to release");
                    continue;
                }
            };
            let key = self.ctx.keys.service(owner.name());
            match requests::ask(&self.ctx, &key, &cancel).await {
                Some(answer) if answer.result == Some(true) => {
                    info!(holon = %self.holon, %location, "place released")
                }
                Some(answer) if answer.reason == Some(Reason::NotBooked) => {}
                _ => {
                    info!(holon = %self.holon, %location, "the place's resource did not answer: released when it is back");
                    tokio::spawn(requests::cancel_when_back(
                        self.ctx.session.clone(),
                        self.ctx.presence.clone(),
                        owner,
                        key,
                        cancel,
                    ));
                }
            }
        }
    }

    /// A request about a place for this order's part.
    fn place_request(
        &self,
        kind: MessageType,
        location: &LocationId,
        conversation: &str,
    ) -> schemas::Service {
        let mut info = Map::new();
        info.insert(info_key::PART.into(), Value::from(self.holon.name()));
        info.insert(info_key::LOCATION.into(), Value::from(location.as_str()));
        let step = service_step(schemas::PLACE_SERVICE, info);
        requests::request(&self.ctx, &self.holon, kind, &step, conversation)
    }

    /// Runs the move under way to its end: booked on a transporter by contract net and
    /// followed as a step is (its transporter's `departed` releasing the place at its
    /// origin on the way: [`Self::move_departed`]); its end recorded for the part, the
    /// places it left released.
    async fn run_move(&mut self, moving: Move) -> Result<(), OrderError> {
        if let Some(place) = self.part().released_at_departure() {
            // Resumed (a restarted order-node): the departure was journalled, its
            // `booking_cancel` may not have been sent before the crash. Sent again (a
            // released place is answered `not_booked`): released, never held for good.
            info!(holon = %self.holon, conversation_id = %moving.conversation_id, location = %place.0, "resumed a move that had departed: its origin's place is released again");
            self.release(vec![place]).await;
        }
        let step = transport_step(&self.holon, &moving);
        self.leg = Leg::Move;
        let attempt = self
            .attempt(&step, &moving.conversation_id, moving.phase.clone())
            .await;
        self.leg = Leg::Work;
        if let Some(early) = self.early_departure.take() {
            // A departure whose move's start was never recorded after all: nothing of it
            // to apply (the move's end releases the origin's place, if at all).
            info!(holon = %self.holon, conversation_id = %early.message.conversation_id, message_type = %early.message.message_type, "a departure left unapplied at the move's end: acknowledged");
            early.acknowledge().await;
        }
        let (outcome, report) = attempt?;
        let last_phase = self.part().moving.map(|m| m.phase).unwrap_or_default();
        let transporter = last_phase.resource().cloned();
        let may_have_begun = match &last_phase {
            Phase::Started(_) => true,
            Phase::Booked(_) => self.ctx.settings.start_on_turn,
            Phase::Proposing | Phase::Booking(_) => false,
        };
        let end = match move_end(&outcome, may_have_begun) {
            // Its transporter said the part had left its origin: a refusal now does not
            // put it back there (its place may be another part's already).
            MoveEnd::Unattempted if self.part().has_left() => MoveEnd::Unknown {
                why: format!(
                    "its transporter said the part had left {}, then ended the move: {outcome}",
                    moving.from
                ),
            },
            end => end,
        };
        info!(holon = %self.holon, conversation_id = %moving.conversation_id, from = %moving.from, to = %moving.to, outcome = %outcome, "move ended");
        let mut released = Vec::new();
        self.ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    released = part.end_move(end, transporter);
                }
            })
            .await?;
        if let Some(report) = report {
            report.acknowledge().await;
        }
        self.publish().await;
        self.release(released).await;
        if matches!(outcome, StepOutcome::NoResource | StepOutcome::Lost { .. }) {
            self.pause(PLACE_RETRY).await;
        }
        Ok(())
    }

    /// The move's transporter (`transporter`, the one its attempt booked) says the move
    /// has left its origin (docs/material-flow.md, "Departure"): the part's change is
    /// journalled first, the report acknowledged, then the place at the origin released
    /// as at the move's end ([`Self::release`]). A departure that releases nothing (a
    /// second one, from the part's home, before the move's start is recorded) is only
    /// acknowledged. The move goes on: its `done` or `failed` ends it.
    pub(super) async fn move_departed(
        &mut self,
        transporter: &HolonId,
        report: ResultReport,
    ) -> Result<(), OrderError> {
        let conversation_id = report.message.conversation_id.clone();
        let message_type = report.message.message_type;
        // Nothing to record unless it releases a place or marks the move left.
        let mut probe = self.part();
        let had_left = probe.has_left();
        let releases = probe.departed(&conversation_id, transporter).is_some();
        if !releases && (had_left || !probe.has_left()) {
            debug!(holon = %self.holon, %conversation_id, %message_type, %transporter, "the move departed: no place held at its origin to release (its home, a location held by none, released already, or its start not recorded yet)");
            report.acknowledge().await;
            return Ok(());
        }
        let mut released = None;
        self.ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    released = part.departed(&conversation_id, transporter);
                }
            })
            .await?;
        // Recorded: the transporter's report may be acknowledged.
        report.acknowledge().await;
        match &released {
            Some((location, _)) => {
                info!(holon = %self.holon, %conversation_id, %message_type, %transporter, %location, "the move departed: the place at its origin is released")
            }
            None => {
                debug!(holon = %self.holon, %conversation_id, %message_type, %transporter, "the move departed: no place held at its origin (its home)")
            }
        }
        self.publish().await;
        self.release(released.into_iter().collect()).await;
        Ok(())
    }

    /// Waits `pause` (jittered), or until a resource appears or a place frees up.
    async fn pause(&mut self, pause: Duration) {
        tokio::select! {
            _ = tokio::time::sleep(jittered(pause)) => {}
            _ = self.ctx.presence.appeared_or_room(&mut self.appearances) => {}
        }
    }
}

/// The step a move is booked as: `transport` of the part from where it is to where it
/// goes.
fn transport_step(order: &HolonId, moving: &Move) -> PlanStep {
    let mut info = Map::new();
    info.insert(info_key::PART.into(), Value::from(order.name()));
    info.insert(info_key::FROM.into(), Value::from(moving.from.as_str()));
    info.insert(info_key::TO.into(), Value::from(moving.to.as_str()));
    service_step(TRANSPORT_SERVICE, info)
}

/// A request's step that is the order's own, not its plan's (a move, a place): the
/// service and its info, nothing to reject.
fn service_step(service_type: &str, info: Map<String, Value>) -> PlanStep {
    PlanStep {
        service_type: service_type.into(),
        info,
        reject_results: vec![],
        on_reject: None,
    }
}

/// What a move's outcome means for the part. A failure the transporter's controller
/// answered at once (it refused the move: `controller_error`, a refused start, info it
/// could not use) moved nothing, nor did one the controller never began (`not_begun`:
/// its fenced controller says it never had the move), nor one the transporter never
/// sent to its controller (`unavailable`: its controller was not ready when the move's
/// turn came; `busy`: another job still ran; `withdrawn`: it shut down before the
/// move's turn); any other (a fault or an abort on the way, a lost connection, no
/// result in time, the transporter gone while it may have run) may have moved it: the
/// part is lost until the transporter says.
fn move_end(outcome: &StepOutcome, may_have_begun: bool) -> MoveEnd {
    match outcome {
        StepOutcome::Done { .. } => MoveEnd::Done,
        StepOutcome::NoResource | StepOutcome::Cancelled => MoveEnd::Unattempted,
        StepOutcome::Lost { why, .. } if may_have_begun => MoveEnd::Unknown { why: why.clone() },
        StepOutcome::Lost { .. } => MoveEnd::Unattempted,
        StepOutcome::Failed { reason, detail, .. } => {
            let said = Reason::from_word(reason);
            let refused = outcome.never_reached_controller()
                || said == Reason::ControllerError
                || said == Reason::InvalidInfo
                || reason.starts_with("start refused");
            if refused {
                MoveEnd::Unattempted
            } else {
                let said = detail.as_ref().map_or(String::new(), |d| format!(": {d}"));
                MoveEnd::Unknown {
                    why: format!("{reason}{said}"),
                }
            }
        }
    }
}

/// Whether `location` is a station's port (where a step is worked).
fn is_port(layout: &CellLayout, location: &LocationId) -> bool {
    layout
        .location(location)
        .is_some_and(|l| matches!(l.role, LocationRole::Port | LocationRole::Input))
}

/// Where raw material enters the cell: the first entry of the layout.
fn entry_of(layout: &CellLayout) -> Option<LocationId> {
    layout
        .locations()
        .map(|(_, l)| l)
        .find(|l| matches!(l.role, LocationRole::Entry | LocationRole::EntryExit))
        .map(|l| l.id.clone())
}

#[cfg(test)]
mod tests;

//! A part lost with its move's transporter (docs/material-flow.md, section 2): the
//! order asks the transporter, whenever it is there, what became of the move, until it
//! says done (the part arrived) or never reached (the part is where it was), or an
//! operator says where the part is. A move its transporter said had left its origin is
//! never put back there on the transporter's word ("Departure").

use std::time::Duration;

use schemas::layout::LocationId;
use schemas::{unix_ms, ErrorCode, HolonId, PartWordReply, Reason};
use tracing::{info, warn};

use super::super::OrderTask;
use super::{move_end, transport_step};
use crate::context::{jittered, OrderError};
use crate::inbox::Judged;
use crate::part::{Move, MoveEnd};
use crate::part_word::WordAsk;
use crate::requests;

/// How often an order whose part is lost asks its transporter what became of the move.
const LOST_ASK_EVERY: Duration = Duration::from_secs(2);

impl OrderTask<'_> {
    /// The part is lost with its move's transporter: asks it, whenever it is there,
    /// what became of the move, until it says done (the part arrived) or never reached
    /// (the part is where it was), or an operator says where the part is. A result the
    /// transporter sends again meanwhile is read as its answer would be (and
    /// acknowledged), so that it does not wait in the order's inbox.
    pub(super) async fn find_lost(&mut self, moving: &Move) -> Result<(), OrderError> {
        let Some(transporter) = moving.phase.resource().cloned() else {
            self.ctx
                .commit(self.progress, |p| {
                    if let Some(part) = &mut p.part {
                        part.found(false);
                    }
                })
                .await?;
            return Ok(());
        };
        // A part whose move left its origin is not put back there on the transporter's
        // word ("never reached" contradicts its `departed`): only an operator's.
        let left = self.part().has_left();
        let mut contradiction_logged = false;
        loop {
            match self.ask_transporter(&transporter, moving).await {
                Some(false) if left && !contradiction_logged => {
                    warn!(holon = %self.holon, %transporter, conversation_id = %moving.conversation_id, from = %moving.from, "the transporter says the lost move never reached its controller, but it said the part had left its origin: the part stays lost until an operator says where it is");
                    contradiction_logged = true;
                }
                Some(false) if left => {}
                Some(arrived) => {
                    info!(holon = %self.holon, %transporter, conversation_id = %moving.conversation_id, arrived, "the transporter said where the lost part is");
                    return self.lost_part_found(arrived).await;
                }
                None => {}
            }
            tokio::select! {
                _ = tokio::time::sleep(jittered(LOST_ASK_EVERY)) => {}
                _ = self.ctx.presence.appeared_or_room(&mut self.appearances) => {}
                Some(word) = self.part_words.recv() => {
                    if self.take_word(word, moving).await? {
                        return Ok(());
                    }
                }
                Some(report) = self.inbox.reports.recv() => {
                    let worked_with = self.progress.get().worked_with.clone();
                    let judged = crate::inbox::judge(report, &transporter, &worked_with, &moving.conversation_id).await;
                    let (outcome, report) = match judged {
                        Some(Judged::Ended(outcome, report)) => (outcome, report),
                        Some(Judged::Departed(report)) => {
                            // Its result said where it was not: a departure says no
                            // more of where it is now. The origin's place is released
                            // once the part is found at the destination.
                            info!(holon = %self.holon, %transporter, conversation_id = %moving.conversation_id, message_type = %report.message.message_type, "a departure of the lost part's move: acknowledged and ignored");
                            report.acknowledge().await;
                            continue;
                        }
                        None => continue,
                    };
                    let arrived = match move_end(&outcome, true) {
                        MoveEnd::Done => Some(true),
                        MoveEnd::Unattempted if left => None,
                        MoveEnd::Unattempted => Some(false),
                        MoveEnd::Unknown { .. } => None,
                    };
                    if let Some(arrived) = arrived {
                        info!(holon = %self.holon, %transporter, conversation_id = %moving.conversation_id, arrived, %outcome, "the transporter's result says where the lost part is");
                        self.lost_part_found(arrived).await?;
                    }
                    // Recorded (or still unknown, as the part's place says): the
                    // transporter need not send it again.
                    report.acknowledge().await;
                    if arrived.is_some() {
                        return Ok(());
                    }
                }
            }
        }
    }

    /// The lost part is found: at its move's destination (`arrived`) or its origin.
    async fn lost_part_found(&mut self, arrived: bool) -> Result<(), OrderError> {
        let mut released = Vec::new();
        self.ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    released = part.found(arrived);
                }
            })
            .await?;
        self.publish().await;
        self.release(released).await;
        Ok(())
    }

    /// Asks the lost move's transporter, if it is there, what became of the move:
    /// whether the part arrived, once it knows.
    async fn ask_transporter(&self, transporter: &HolonId, moving: &Move) -> Option<bool> {
        if !self.ctx.presence.is_alive(transporter) {
            return None;
        }
        let step = transport_step(&self.holon, moving);
        let answer = requests::ask_outcome(
            &self.ctx,
            &self.holon,
            transporter,
            &step,
            &moving.conversation_id,
        )
        .await;
        match answer.map(|a| a.outcome) {
            Some(schemas::Outcome::Done) => Some(true),
            Some(schemas::Outcome::NeverReached) => Some(false),
            _ => None,
        }
    }

    /// An operator's word on where the lost part is: recorded with who said it, then
    /// answered. Whether the part is found (a word about another move, or one whose
    /// asker has left, changes nothing).
    async fn take_word(&mut self, word: WordAsk, moving: &Move) -> Result<bool, OrderError> {
        let name = self.holon.name().to_string();
        if word.conversation_id != moving.conversation_id || word.reply.is_closed() {
            let why = format!("{name}: the word was about another move of its part; ask again");
            if word.reply.send(Err((ErrorCode::Invalid, why))).is_err() {
                info!(holon = %self.holon, "a stale word on the part was dropped: its asker has left");
            }
            return Ok(false);
        }
        if let Err(refused) = crate::part_word::check(&name, &self.progress.get(), &word.location) {
            if word.reply.send(Err(refused)).is_err() {
                info!(holon = %self.holon, "a refused word on the part was not answered: its asker has left");
            }
            return Ok(false);
        }
        let refused = match self.hold_origin_again(&word.location, moving).await {
            Ok(Ok(())) => None,
            Ok(Err(refused)) => Some(refused),
            Err(e) => {
                let why = format!("{name}: cannot record the word: {e}");
                if word.reply.send(Err((ErrorCode::Internal, why))).is_err() {
                    info!(holon = %self.holon, "the word's asker left before it heard the word was not recorded");
                }
                return Err(e);
            }
        };
        if let Some(refused) = refused {
            if word.reply.send(Err(refused)).is_err() {
                info!(holon = %self.holon, "a refused word on the part was not answered: its asker has left");
            }
            return Ok(false);
        }
        let mut released = Vec::new();
        let recorded = self
            .ctx
            .commit(self.progress, |p| {
                if let Some(part) = &mut p.part {
                    released = part.found_by_operator(&word.location, &word.by, unix_ms());
                }
            })
            .await;
        if let Err(e) = recorded {
            let why = format!("{name}: cannot record the word: {e}");
            if word.reply.send(Err((ErrorCode::Internal, why))).is_err() {
                info!(holon = %self.holon, "the word's asker left before it heard the word was not recorded");
            }
            return Err(e);
        }
        let part = self.part().place;
        info!(holon = %self.holon, by = %word.by, location = %word.location, conversation_id = %moving.conversation_id, "an operator said where the lost part is, recorded");
        let reply = PartWordReply {
            order: name,
            detail: format!("recorded: its part is {part}; the order goes on from there"),
            part,
        };
        if word.reply.send(Ok(reply)).is_err() {
            warn!(holon = %self.holon, "the word's asker left before the answer; the order's state shows it was recorded");
        }
        self.publish().await;
        self.release(released).await;
        Ok(true)
    }

    /// Before an operator's word that the lost part is at `location` is recorded: when
    /// that is the origin of a move that had departed (its place there released then,
    /// [`crate::part::PartProgress::needs_origin_again`]), the place is reserved again,
    /// or the word is refused (nothing changes): another part's place, `invalid` (the
    /// order as it stands; asked again once the place is free, it is taken); its
    /// resource not answering, `unavailable` (ask again). Two parts are never taken to
    /// be at a port of one place (docs/material-flow.md, "Departure").
    async fn hold_origin_again(
        &mut self,
        location: &LocationId,
        moving: &Move,
    ) -> Result<Result<(), (ErrorCode, String)>, OrderError> {
        if !self.part().needs_origin_again(location) {
            return Ok(Ok(()));
        }
        let (reason, why) = match self.reserve_or_why(location).await? {
            Ok(()) => {
                info!(holon = %self.holon, %location, conversation_id = %moving.conversation_id, "the lost part's origin, released at its departure, is reserved again for an operator's word");
                return Ok(Ok(()));
            }
            Err(refusal) => refusal,
        };
        info!(holon = %self.holon, %location, conversation_id = %moving.conversation_id, %why, "an operator's word that the lost part is back at its origin refused: its place there is not to be had");
        // Its resource's silence, or its controller not ready: not now, ask again.
        // Any other refusal (another part's place) stands as the cell is.
        let code = match reason {
            None | Some(Reason::Unavailable) => ErrorCode::Unavailable,
            Some(_) => ErrorCode::Invalid,
        };
        let refused = format!(
            "{name}: its move had left {from}, whose place was released then and cannot be \
             reserved again ({why}); put the part at {to}, where its place is held, and say \
             so, or ask again once {from} is free; nothing changed",
            name = self.holon.name(),
            from = moving.from,
            to = moving.to,
        );
        Ok(Err((code, refused)))
    }
}

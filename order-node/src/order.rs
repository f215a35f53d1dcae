//! One order holon's task: gets its product made by negotiating with the live resources.
//!
//! For each step of the plan it runs one attempt after another until the step is done
//! or the order ends: an attempt is the pure machine of [`crate::attempt`] (proposal
//! round, booking, start, waiting for the result), and this task performs its actions
//! and feeds their answers back. What an outcome means for the order (next step, retry
//! elsewhere, rework, failure) is decided by [`crate::progress`].
//!
//! Every change of the order's progress is written to the journal before the order acts
//! on it, and a result is acknowledged only after its outcome is written: a restarted
//! order-node resumes each order where it stood (see [`Phase`]).

use std::sync::Arc;
use std::time::Duration;

use schemas::{HolonId, MessageType, PlanStep, Reason, Service};
use tokio::sync::{broadcast, mpsc, watch};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use tracing::info;

use crate::attempt::{Attempt, AttemptAction, AttemptEvent, AttemptTiming};
use crate::cancel::CancelAsk;
use crate::context::{jittered, IdleOrder, OrderContext, OrderError, Progress, IDLE_POLL};
use crate::inbox::{Inbox, ResultReport};
use crate::part_word::WordAsk;
use crate::progress::{Phase, StepOutcome};
use crate::ranking::InFlight;
use crate::requests;

mod material;
mod round;
mod watching;

use watching::Watched;

/// Which attempt the order's task runs: its step's, or a move of its part.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Leg {
    /// The current step's attempt (its phase is the progress's `phase`).
    Work,
    /// A move of the part (its phase is the part's `moving.phase`).
    Move,
}

/// What operators ask of one run of an order's task.
pub struct Mailboxes {
    /// Cancels: this task records each and answers ([`crate::cancel`]).
    pub cancel_asks: mpsc::Receiver<CancelAsk>,
    /// Words on where the order's lost part is: taken while the order waits for it
    /// ([`crate::part_word`]).
    pub part_words: mpsc::Receiver<WordAsk>,
}

/// Runs one order until it is done, scrapped, failed or cancelled by an operator, or
/// its node stops (`cancel`). An operator's cancel arrives in its mailbox: this task
/// records it and answers ([`crate::cancel`]), then `operator_cancel` stops the attempt.
pub async fn run(
    ctx: Arc<OrderContext>,
    progress: Progress,
    cancel: CancellationToken,
    operator_cancel: CancellationToken,
    mailboxes: Mailboxes,
) -> Result<(), OrderError> {
    let Mailboxes {
        cancel_asks,
        part_words,
    } = mailboxes;
    let holon = progress.get().holon.clone();
    let mut order = OrderTask {
        inbox: ctx.inboxes.open(&holon),
        changes: ctx.presence.changes(),
        appearances: ctx.presence.appearances(),
        in_flight: None,
        advised: None,
        leg: Leg::Work,
        work_at: None,
        proposed_at: None,
        part_words,
        early_departure: None,
        ctx,
        progress: &progress,
        holon: holon.clone(),
    };
    order.publish().await;
    let own_ctx = order.ctx.clone();
    // Both borrow the progress, in turn: this task is its only writer.
    let cancels = async {
        crate::cancel::answer_cancels(&own_ctx, &progress, cancel_asks, &operator_cancel).await;
        // The node dropped the mailbox (it replaced this run's): nothing more to answer.
        std::future::pending::<()>().await
    };
    tokio::select! {
        worked = order.work(&operator_cancel) => worked?,
        () = cancels => {}
        _ = cancel.cancelled() => {
            info!(%holon, "order stopped with its node; it resumes from the journal");
            return Ok(());
        }
    }
    let p = order.progress.get().snapshot();
    info!(%holon, status = %p.status, reason = p.reason.as_ref().map_or("", |r| r.as_str()), reworks = p.reworks, rebooks = p.rebooks, "order finished");
    // Results still arriving for this order (duplicates, late reports of abandoned
    // attempts) are acknowledged by the node from now on, and the node no longer holds
    // it (its inbox closes): the resources release what it still has booked.
    drop(order);
    Ok(())
}

/// What one running order's task holds.
struct OrderTask<'a> {
    /// What the orders of the node share.
    ctx: Arc<OrderContext>,
    /// The order's progress, written by this task alone (the node sees it through its
    /// view).
    progress: &'a Progress,
    /// The order.
    holon: HolonId,
    /// Results for this order; while it is open the node holds the order
    /// (`host/order-node/<node>/held`): its bookings last.
    inbox: Inbox,
    /// Resources appearing (true) and vanishing (false).
    changes: broadcast::Receiver<(HolonId, bool)>,
    /// Appearances since the last proposal round began: one that happens during the
    /// round wakes the wait after it.
    appearances: watch::Receiver<u64>,
    /// The booking the last round's ranking counted in flight, until it is answered.
    in_flight: Option<InFlight>,
    /// The resource the last round booked first on a staff holon's advice: counted
    /// in the order's `advised` when its booking is recorded.
    advised: Option<HolonId>,
    /// The attempt under way: the step's, or a move's.
    leg: Leg,
    /// For a plan that moves parts: the station whose port holds the part, the only
    /// one the step is booked on.
    work_at: Option<HolonId>,
    /// The station that proposed for the step in the round that found the part at its
    /// port, just before the step's attempt: its first booking asks that station
    /// without another round (taken by the first [`OrderTask::ask_proposals`]).
    proposed_at: Option<HolonId>,
    /// Operators' words on where the part is, taken while it is lost.
    part_words: mpsc::Receiver<WordAsk>,
    /// A move's `departed` that came while its start on its turn was not seen yet: it
    /// says the move began (the attempt records it started), and is applied once it is
    /// ([`OrderTask::await_outcome`]); acknowledged at the move's end at the latest.
    early_departure: Option<ResultReport>,
}

impl OrderTask<'_> {
    async fn publish(&self) {
        self.ctx.publish(self.progress).await;
    }

    /// The order's life: its plan, then its steps until none is left.
    async fn work(&mut self, operator_cancel: &CancellationToken) -> Result<(), OrderError> {
        // An order that waits for its plan (a queued work order whose product holon is
        // not up yet) ends at an operator's cancel: without a plan it holds no booking.
        let planned = self.progress.get().plan.is_some();
        tokio::select! {
            biased;
            _ = operator_cancel.cancelled(), if !planned => {
                info!(holon = %self.holon, "cancelled while waiting for its plan");
                self.ctx.commit(self.progress, |p| p.cancel()).await?;
                self.publish().await;
                return Ok(());
            }
            planned = self.plan() => planned?,
        }
        loop {
            let (mut step, conversation_id) = {
                let p = self.progress.get();
                match p.current_step() {
                    Some(step) => (step.clone(), p.conversation_id()),
                    None => break,
                }
            };
            if self.progress.get().part.is_some() {
                // The step names its part: the station's controller works on that part,
                // one of those at its ports (a port may hold several).
                step.info
                    .entry(schemas::info_key::PART)
                    .or_insert_with(|| self.holon.name().into());
            }
            self.work_at = None;
            self.proposed_at = None;
            if self.progress.get().part.is_some() {
                match self
                    .arrange(&step, &conversation_id, operator_cancel)
                    .await?
                {
                    material::Arranged::At(station) => self.work_at = Some(station),
                    material::Arranged::Cancelled => continue,
                    material::Arranged::NoStation => {
                        self.ctx
                            .commit(self.progress, |p| p.record(StepOutcome::NoResource))
                            .await?;
                        self.publish().await;
                        continue;
                    }
                }
            }
            if !self.step(&step, &conversation_id, operator_cancel).await? {
                break;
            }
        }
        // A part still in the cell leaves it by an exit before the order's end is
        // recorded.
        let leaving = self
            .progress
            .get()
            .part
            .as_ref()
            .is_some_and(|p| p.leaving.is_some());
        if leaving {
            self.leave().await?;
            self.publish().await;
        }
        Ok(())
    }

    /// Fetches the plan from the product holon unless the order has it already.
    async fn plan(&mut self) -> Result<(), OrderError> {
        if self.progress.get().plan.is_some() {
            return Ok(());
        }
        let product = self.progress.get().product.clone();
        let plan = requests::fetch_plan(&self.ctx, &product).await;
        self.ctx
            .commit(self.progress, |p| match plan {
                Some(plan) => p.set_plan(plan),
                None => p.fail(format!("no plan for product {product:?}")),
            })
            .await?;
        self.publish().await;
        Ok(())
    }

    /// One attempt of the current step, its outcome recorded: false when the order
    /// ended (cancelled).
    async fn step(
        &mut self,
        step: &PlanStep,
        conversation_id: &str,
        operator_cancel: &CancellationToken,
    ) -> Result<bool, OrderError> {
        let progress = self.progress;
        let holon = self.holon.clone();
        // An operator's cancel (also one recorded before a restart) stops the attempt
        // unless its step runs: a running step is let finish and its result recorded.
        let mut finishing = false;
        let (outcome, report) = {
            let phase = progress.get().phase.clone();
            if phase != Phase::Proposing {
                // Resumed past its round (a restart): the station's word is not fresh.
                self.proposed_at = None;
            }
            let attempt = self.attempt(step, conversation_id, phase);
            tokio::pin!(attempt);
            loop {
                tokio::select! {
                    biased;
                    _ = operator_cancel.cancelled(), if !finishing => {
                        if matches!(progress.get().phase, Phase::Started(_)) {
                            info!(%holon, %conversation_id, "cancel requested: the running step finishes first");
                            finishing = true;
                        } else {
                            break (StepOutcome::Cancelled, None);
                        }
                    }
                    ended = &mut attempt => break ended?,
                }
            }
        };
        if outcome == StepOutcome::Cancelled {
            self.cancel(step, conversation_id).await?;
            self.publish().await;
            return Ok(false);
        }
        info!(%holon, %conversation_id, outcome = %outcome, "step attempt ended");
        self.ctx
            .commit(self.progress, |p| {
                p.record(outcome);
                if finishing {
                    p.cancel();
                }
            })
            .await?;
        // Recorded: now the result may be acknowledged.
        if let Some(report) = report {
            report.acknowledge().await;
        }
        self.publish().await;
        Ok(true)
    }

    /// Runs one attempt of `step` from wherever its phase stands: the machine's actions
    /// performed in order, the answer of the last fed back, until it ends. Returns how
    /// it ended and the result to acknowledge once the outcome is recorded.
    async fn attempt(
        &mut self,
        step: &PlanStep,
        conversation_id: &str,
        phase: Phase,
    ) -> Result<(StepOutcome, Option<Box<ResultReport>>), OrderError> {
        let settings = &self.ctx.settings;
        let timing = AttemptTiming {
            retry_interval: settings.retry_interval,
            retry_max: settings.retry_max,
            idle_poll: IDLE_POLL,
            no_resource_timeout: settings.no_resource_timeout,
            step_timeout: settings.step_timeout,
        };
        let mut attempt =
            Attempt::new(phase, timing, Instant::now()).starting_on_turn(settings.start_on_turn);
        let mut event = AttemptEvent::Resumed;
        // The result that ended a watch, kept for the end of the attempt.
        let mut report = None;
        loop {
            let actions = attempt.handle(event.clone(), Instant::now());
            if actions.is_empty() {
                return Err(OrderError::Other(format!(
                    "the attempt has no transition for {event:?} in {:?}",
                    attempt.phase()
                )));
            }
            let mut next = None;
            for action in actions {
                if let AttemptAction::End(outcome) = action {
                    return Ok((outcome, report));
                }
                next = self
                    .perform(action, step, conversation_id, &mut report)
                    .await?;
            }
            event = next.ok_or_else(|| {
                OrderError::Other("an attempt's transition ended without awaiting anything".into())
            })?;
        }
    }

    /// Performs one action of the attempt: the event it answers, if it awaits one.
    async fn perform(
        &mut self,
        action: AttemptAction,
        step: &PlanStep,
        conversation_id: &str,
        report: &mut Option<Box<ResultReport>>,
    ) -> Result<Option<AttemptEvent>, OrderError> {
        Ok(match action {
            AttemptAction::Record(phase) => {
                self.record(phase).await?;
                None
            }
            AttemptAction::Publish => {
                self.publish().await;
                None
            }
            AttemptAction::AskProposals => Some(self.ask_proposals(step, conversation_id).await),
            AttemptAction::AskBooking(candidate) => {
                Some(self.ask_booking(candidate, step, conversation_id).await)
            }
            AttemptAction::AskStart(provider) => {
                Some(self.ask_start(provider, step, conversation_id).await?)
            }
            AttemptAction::CancelBooking(provider) => {
                self.cancel_booking(provider, step, conversation_id).await;
                None
            }
            AttemptAction::CancelWhenBack(provider) => {
                let ctx = &self.ctx;
                tokio::spawn(requests::cancel_when_back(
                    ctx.session.clone(),
                    ctx.presence.clone(),
                    provider.clone(),
                    ctx.keys.service(provider.name()),
                    self.request(MessageType::BookingCancel, step, conversation_id),
                ));
                None
            }
            AttemptAction::AskOutcome(provider) => {
                let answer =
                    requests::ask_outcome(&self.ctx, &self.holon, &provider, step, conversation_id)
                        .await;
                Some(AttemptEvent::Outcome(answer))
            }
            AttemptAction::Wait { pause, idle, until } => {
                self.wait_for_resource(pause, idle, until).await;
                Some(AttemptEvent::Woken)
            }
            AttemptAction::Watch {
                provider,
                pause,
                started,
                may_run,
            } => {
                let pause = if started { pause } else { jittered(pause) };
                match self
                    .await_outcome(&provider, conversation_id, pause, started, may_run)
                    .await?
                {
                    Watched::Elapsed => Some(AttemptEvent::Watched(None)),
                    Watched::Began => Some(AttemptEvent::Began),
                    Watched::CameBack => Some(AttemptEvent::CameBack),
                    Watched::Ended(outcome, delivered) => {
                        *report = delivered;
                        Some(AttemptEvent::Watched(Some(outcome)))
                    }
                }
            }
            AttemptAction::End(_) => unreachable!("the attempt loop ends on End"),
        })
    }

    /// A request of the step: it carries the order's priority and due time, by which
    /// the resource queues its booking (and a proposal says where it would go).
    fn request(&self, kind: MessageType, step: &PlanStep, conversation_id: &str) -> Service {
        let (priority, due) = {
            let progress = self.progress.get();
            (progress.priority, progress.due)
        };
        requests::request(&self.ctx, &self.holon, kind, step, conversation_id)
            .with_urgency(priority, due)
    }

    /// Records the attempt's new phase.
    async fn record(&mut self, phase: Phase) -> Result<(), OrderError> {
        if self.leg == Leg::Move {
            // A move's phase is the part's; its transporter is one the order worked with.
            return self
                .ctx
                .commit(self.progress, |p| {
                    if let Some(resource) = phase.resource() {
                        p.worked_with.insert(resource.clone());
                    }
                    if let Some(part) = &mut p.part {
                        part.move_phase(phase);
                    }
                })
                .await;
        }
        // A booking made on advice counts once, when it is recorded.
        let on_advice = matches!(&phase, Phase::Booked(p) | Phase::Started(p) if self.advised.as_ref() == Some(p));
        if !matches!(&phase, Phase::Booking(p) if self.advised.as_ref() == Some(p)) {
            // Used up, or the booking moved on to another resource.
            self.advised = None;
        }
        // A fenced provider is remembered with its booking (see
        // `OrderProgress::fenced`).
        let fenced = phase
            .resource()
            .filter(|resource| self.ctx.presence.fenced(resource))
            .cloned();
        self.ctx
            .commit(self.progress, |p| {
                if on_advice {
                    p.advised += 1;
                }
                if let Some(resource) = fenced {
                    p.fenced.insert(resource);
                }
                p.set_phase(phase)
            })
            .await
    }

    /// A proposal round, with the staff's advice asked together: the offers ranked.
    async fn ask_proposals(&mut self, step: &PlanStep, conversation_id: &str) -> AttemptEvent {
        self.appearances = self.ctx.presence.appearances();
        // The station that found the part at its port a moment ago proposed then: its
        // step's first booking asks it without another round (docs/material-flow.md,
        // "A move's conversations"); a refusal leads to a round.
        let proposed = match self.leg {
            Leg::Work => self
                .proposed_at
                .take()
                .filter(|s| self.work_at.as_ref() == Some(s)),
            Leg::Move => None,
        };
        if let Some(station) = proposed {
            self.in_flight = None;
            return AttemptEvent::Proposals(vec![station]);
        }
        let ask = self.request(MessageType::ProposalReq, step, conversation_id);
        // A move is not the staff's to advise; a step of a part at a station is
        // worked there.
        let work = self.leg == Leg::Work && self.work_at.is_none();
        let round::Round {
            mut ranked,
            advised,
            in_flight,
        } = self.round(&ask, work, None).await;
        if let (Leg::Work, Some(station)) = (self.leg, &self.work_at) {
            ranked.retain(|r| r == station);
        }
        self.in_flight = in_flight;
        if !work {
            // A move, or a step at the station where the part is: the advice (if any)
            // was the station round's.
            return AttemptEvent::Proposals(ranked);
        }
        self.advised = match advised {
            Some(resource) if ranked.first() == Some(&resource) => Some(resource),
            Some(resource) => {
                info!(holon = %self.holon, %conversation_id, %resource, "advice ignored: the advised resource did not propose");
                None
            }
            None => None,
        };
        AttemptEvent::Proposals(ranked)
    }

    /// Asks `candidate` for a booking: its answer.
    async fn ask_booking(
        &mut self,
        candidate: HolonId,
        step: &PlanStep,
        conversation_id: &str,
    ) -> AttemptEvent {
        let ctx = &self.ctx;
        let asked = std::time::Instant::now();
        let request = self.request(MessageType::BookingReq, step, conversation_id);
        let answer = requests::ask(ctx, &ctx.keys.service(candidate.name()), &request).await;
        if self
            .in_flight
            .as_ref()
            .is_some_and(|counted| counted.resource == candidate)
        {
            self.in_flight = None;
        }
        match &answer {
            Some(a) if a.result == Some(true) => {
                info!(holon = %self.holon, %conversation_id, resource = %candidate, service_type = %step.service_type, started = a.started(), took_us = asked.elapsed().as_micros() as u64, "booked")
            }
            Some(a) => {
                info!(holon = %self.holon, %conversation_id, resource = %candidate, reason = a.reason.as_ref().map_or("", |r| r.as_str()), "booking refused")
            }
            None => {}
        }
        AttemptEvent::BookingAnswer(requests::answer(answer))
    }

    /// Asks `provider` to start the booked step: its answer.
    async fn ask_start(
        &mut self,
        provider: HolonId,
        step: &PlanStep,
        conversation_id: &str,
    ) -> Result<AttemptEvent, OrderError> {
        let ctx = &self.ctx;
        // On etcd a start is journalled at this node's epoch before it is sent: a
        // deposed holder's write is refused, and it sends nothing.
        if let Some(epoch) = ctx.epoch() {
            ctx.commit(self.progress, |p| p.start_epoch = Some(epoch))
                .await?;
        }
        let request = self.request(MessageType::Start, step, conversation_id);
        let answer = requests::ask(ctx, &ctx.keys.service(provider.name()), &request).await;
        if answer.as_ref().is_some_and(|a| a.result == Some(true)) {
            info!(holon = %self.holon, %conversation_id, resource = %provider, "started");
        }
        Ok(AttemptEvent::StartAnswer(requests::answer(answer)))
    }

    /// Cancels the booking on `provider`; when that is not taken, it is sent again
    /// once the resource answers.
    async fn cancel_booking(&self, provider: HolonId, step: &PlanStep, conversation_id: &str) {
        let ctx = &self.ctx;
        let cancel = self.request(MessageType::BookingCancel, step, conversation_id);
        let key = ctx.keys.service(provider.name());
        let answer = requests::ask(ctx, &key, &cancel).await;
        let handed_over =
            answer.as_ref().and_then(|a| a.reason.as_ref()) == Some(&Reason::Unavailable);
        if answer.is_none() || handed_over {
            // Not answered, or by a stand-in while the resource is handed over (it keeps
            // its bookings): sent again until the resource answers, so that its
            // successor does not run the abandoned booking.
            info!(holon = %self.holon, %conversation_id, resource = %provider, handed_over, "the cancel of a booking was not taken; sent again when the resource answers");
            tokio::spawn(requests::cancel_when_back(
                ctx.session.clone(),
                ctx.presence.clone(),
                provider,
                key,
                cancel,
            ));
        }
    }

    /// Waits `pause` (jittered; an idle order also spaced with the other idle orders),
    /// at most until `until`, or until a resource appears or becomes ready or a place
    /// on an agenda frees up for this order.
    async fn wait_for_resource(&mut self, pause: Duration, idle: bool, until: Instant) {
        // Counted among the idle orders while it waits: thousands of orders waiting for
        // a missing resource then cost next to nothing.
        let idle = idle.then(|| IdleOrder::count(&self.ctx.idle));
        let pause = match &idle {
            Some(idle) => pause.max(idle.spacing()),
            None => pause,
        };
        let pause = jittered(pause).min(until.saturating_duration_since(Instant::now()));
        tokio::select! {
            _ = tokio::time::sleep(pause) => {}
            _ = self.ctx.presence.appeared_or_room(&mut self.appearances) => {}
        }
    }

    /// Ends the order as cancelled: a booking it holds (or may hold) is cancelled first.
    async fn cancel(&mut self, step: &PlanStep, conversation_id: &str) -> Result<(), OrderError> {
        let ctx = &self.ctx;
        let holon = &self.holon;
        let phase = self.progress.get().phase.clone();
        if let Phase::Booking(resource) | Phase::Booked(resource) = &phase {
            let cancel = requests::request(
                ctx,
                holon,
                MessageType::BookingCancel,
                step,
                conversation_id,
            );
            match requests::ask(ctx, &ctx.keys.service(resource.name()), &cancel).await {
                Some(answer) if answer.result == Some(true) => {
                    info!(%holon, %conversation_id, %resource, "booking cancelled with the order")
                }
                _ => {
                    // Not reachable now: cancel it when it is back (from its journal).
                    tokio::spawn(requests::cancel_when_back(
                        ctx.session.clone(),
                        ctx.presence.clone(),
                        resource.clone(),
                        ctx.keys.service(resource.name()),
                        cancel,
                    ));
                }
            }
        }
        ctx.commit(self.progress, |p| p.cancel()).await?;
        info!(%holon, "order cancelled by an operator");
        Ok(())
    }
}

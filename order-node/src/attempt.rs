//! One attempt of one step, as a pure state machine: `(attempt, event) -> actions`.
//!
//! The order's task performs the actions in order (journal writes, requests, waits)
//! and feeds back the event the last of them produced; [`crate::order`] is that loop.
//! The machine does no I/O and holds no clock: the caller passes `now`.
//!
//! | phase | event | actions | next phase |
//! |---|---|---|---|
//! | proposing | resumed, woken | ask proposals | proposing |
//! | proposing | proposals: some | record booking(first), ask it | booking(first) |
//! | proposing | proposals: none, before give-up | wait for a resource (idle) | proposing |
//! | proposing | proposals: none, past give-up | end: no resource | — |
//! | booking(c) | resumed | ask c again (booking is idempotent) | booking(c) |
//! | booking(c) | accepted and started (on its turn) | record started(c), publish, watch (step timeout) | started(c) |
//! | booking(c) | accepted, asked to start on its turn | record booked(c), publish, watch for the turn (backoff) | booked(c) |
//! | booking(c) | accepted | record booked(c), publish, ask start | booked(c) |
//! | booking(c) | no answer, asked to start on its turn (it may have begun) | record booked(c), ask start | booked(c) |
//! | booking(c) | refused or no answer, candidates left | record booking(next), ask it | booking(next) |
//! | booking(c) | refused or no answer, resumed (no round) | record proposing, ask proposals | proposing |
//! | booking(c) | refused or no answer, round over, before give-up | record proposing, wait (backoff) | proposing |
//! | booking(c) | refused or no answer, round over, past give-up | record proposing, end: no resource | — |
//! | booked(p) | resumed | ask start | booked(p) |
//! | booked(p) | start accepted | record started(p), publish, watch (step timeout) | started(p) |
//! | booked(p) | `busy`, no answer, `unavailable` before give-up | watch for the turn (backoff) | booked(p) |
//! | booked(p) | `not_booked` | ask p the outcome | booked(p), asking |
//! | booked(p) | other refusal | cancel the booking, end: failed | — |
//! | booked(p) | watched: pause over or turn | ask start | booked(p) |
//! | booked(p) | began (p published that the step runs) | record started(p), publish, watch (step timeout) | started(p) |
//! | booked(p) | watched: lost | cancel the booking when p is back, end: lost | — |
//! | booked(p) | watched: another outcome | end with it | — |
//! | started(p) | resumed (a restart, or a takeover of the node) | ask p the outcome (the step timeout starts) | started(p), asking |
//! | started(p) | watched: `failed` `interrupted` (p's journal knew only that it ran) | ask p the outcome | started(p), asking |
//! | started(p) | watched: another outcome | end with it | — |
//! | started(p) | watched: pause over (the step timeout, or a poll of a running step) | ask p the outcome | started(p), asking |
//! | started(p) | came back (p vanished and returned, or a holder of a higher epoch serves it) | ask p the outcome | started(p), asking |
//! | asking | outcome `done` | end: done with its results (as if delivered) | — |
//! | asking | outcome `failed` | end: failed with its reason | — |
//! | asking | outcome `running` | (booked: record started(p), publish) watch for a poll pause | started(p) |
//! | asking | outcome `never_reached` | end: lost (rebook: nothing ran) | — |
//! | asking (timed out or came back), step timeout over | `unknown` or no answer | end: failed, no result within the step timeout | — |
//! | asking (a poll, or came back), step timeout not over | `unknown` or no answer | watch what is left of the step timeout | started(p) |
//! | asking after `not_booked` | `unknown` or no answer | end: lost | — |
//! | asking after `interrupted` | `unknown` or no answer | end: failed `interrupted`, as reported | — |
//!
//! Any other (phase, event) pair is a bug in the loop and changes nothing (no actions,
//! logged by the caller). The backoff doubles with each refused round and each wait for
//! the turn, and starts over once booked.
//!
//! A booking asked to start on its turn (the node's `orders.start_on_turn`) begins
//! without the order's `start`: the order learns it from the resource's state
//! publication (its job runs) and sends no `start`, unless a pause passes without
//! news (a publication missed) or the resource says it is this order's turn (a
//! resource restarted on its journal waits for its requesters' `start`); a `start` is
//! answered true if the job began. While booked, a vanished resource gets the same
//! grace as one running the step (it may be).
//!
//! Before it gives up on a step that may have run, the attempt asks the resource what
//! became of its conversation (`resource/<name>/outcome`, [`schemas::OutcomeRequest`]):
//! a resource whose holder died after its controller ran the step, and whose standby
//! took over, learns it from the controller (`STEP_STATUS`), so the step ends done
//! instead of being booked again under a new conversation, whose new step ids the
//! controller would run again (docs/reliability.md, "Standby resources").

use std::collections::VecDeque;
use std::time::Duration;

use holon::Backoff;
use schemas::{HolonId, Outcome, OutcomeReply, OutcomeSource, Reason};
use tokio::time::Instant;

use crate::progress::{Phase, StepOutcome};

/// How a resource answered a booking or a start.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Answer {
    Accepted,
    /// Accepted, and the job has begun: a booking that asked to start on its turn.
    Started,
    /// Refused, with its reason.
    Refused(Option<Reason>),
    /// No answer within the request timeout, or an error reply.
    Silent,
}

/// What the attempt reacts to.
#[derive(Debug, Clone, PartialEq)]
pub enum AttemptEvent {
    /// The attempt begins, or resumes after a restart, from its recorded phase.
    Resumed,
    /// A proposal round ended: these resources proposed, best first.
    Proposals(Vec<HolonId>),
    /// The answer to the booking request of the current phase.
    BookingAnswer(Answer),
    /// The answer to the start request.
    StartAnswer(Answer),
    /// A wait for a resource ended (its pause, an appearance, a freed place).
    Woken,
    /// A watch ended: `None` when its pause is over (or the resource said it is this
    /// order's turn), else how the attempt ended.
    Watched(Option<StepOutcome>),
    /// Booked: the resource published that the step runs (it began on its turn).
    Began,
    /// Started: the provider came back while the step ran (its token vanished and
    /// returned, or a holder of a higher epoch serves it): its result may never come.
    CameBack,
    /// The resource's answer to [`AttemptAction::AskOutcome`] (`None`: no answer).
    Outcome(Option<OutcomeReply>),
}

/// Why the attempt asks its resource the outcome of its conversation.
#[derive(Debug, Clone, PartialEq)]
enum Asking {
    /// The step timeout (or a poll of a step still running) passed without a result.
    TimedOut,
    /// The provider came back while the step ran.
    CameBack,
    /// The resource said `not_booked` to a start: the job may have begun unseen.
    NotBooked,
    /// The resource reported the step `interrupted` (this outcome): its journal
    /// knew only that it was running when the holder stopped, the controller may know
    /// that it completed.
    Interrupted(StepOutcome),
}

/// What the order's task must do, in order.
#[derive(Debug, Clone, PartialEq)]
pub enum AttemptAction {
    /// Write this phase to the journal before going on.
    Record(Phase),
    /// Publish the order's state.
    Publish,
    /// Ask for proposals (avoiding the resources that failed this step); answers
    /// [`AttemptEvent::Proposals`].
    AskProposals,
    /// Ask this resource for a booking; answers [`AttemptEvent::BookingAnswer`].
    AskBooking(HolonId),
    /// Ask this resource to start; answers [`AttemptEvent::StartAnswer`].
    AskStart(HolonId),
    /// Cancel the booking on this resource (once, whatever it answers).
    CancelBooking(HolonId),
    /// Cancel the booking on this resource whenever it is seen back.
    CancelWhenBack(HolonId),
    /// Ask this resource what became of the conversation; answers
    /// [`AttemptEvent::Outcome`].
    AskOutcome(HolonId),
    /// Wait `pause` (jittered; `idle`: spaced with the other idle orders), at most
    /// until `until`, or until a resource appears or a place frees up; answers
    /// [`AttemptEvent::Woken`].
    Wait {
        pause: Duration,
        idle: bool,
        until: Instant,
    },
    /// Watch the inbox and `provider`'s presence for `pause` (jittered unless
    /// `started`); before `started` the resource's turn also ends the watch. Answers
    /// [`AttemptEvent::Watched`].
    Watch {
        provider: HolonId,
        pause: Duration,
        started: bool,
        /// The step may be running (started, or booked to start on its turn): a
        /// provider that vanishes gets the grace to come back and report.
        may_run: bool,
    },
    /// The attempt is over.
    End(StepOutcome),
}

/// The timing an attempt works with (from the order-node's settings).
#[derive(Debug, Clone, Copy)]
pub struct AttemptTiming {
    /// The first retry pause; it doubles up to `retry_max`.
    pub retry_interval: Duration,
    pub retry_max: Duration,
    /// How long an order that nobody could take waits before asking again, at most.
    pub idle_poll: Duration,
    /// How long the attempt may look for a resource (and accept `unavailable`).
    pub no_resource_timeout: Duration,
    /// How long a started step may take.
    pub step_timeout: Duration,
}

/// One attempt's state.
#[derive(Debug, Clone)]
pub struct Attempt {
    /// Where the attempt stands, as last recorded.
    phase: Phase,
    /// The candidates of the current round not asked yet, best first; `None` when the
    /// booking being asked for was not chosen in a round here (resumed).
    round: Option<VecDeque<HolonId>>,
    /// The pause before the next retry.
    backoff: Backoff,
    /// When the attempt stops looking for a resource.
    give_up: Instant,
    timing: AttemptTiming,
    /// Bookings ask the resource to start on their turn.
    start_on_turn: bool,
    /// Set while the attempt asks its resource the outcome of its conversation: why.
    asking: Option<Asking>,
    /// Started: when its step timeout ends (set when the step is watched from its
    /// beginning, or from a resume).
    deadline: Option<Instant>,
}

impl Attempt {
    /// An attempt from its recorded phase, begun (or resumed) at `now`.
    pub fn new(phase: Phase, timing: AttemptTiming, now: Instant) -> Attempt {
        Attempt {
            phase,
            round: None,
            backoff: Backoff::new(timing.retry_interval, timing.retry_max),
            give_up: now + timing.no_resource_timeout,
            timing,
            start_on_turn: false,
            asking: None,
            deadline: None,
        }
    }

    /// The same attempt, its bookings asking to start on their turn.
    pub fn starting_on_turn(mut self, start_on_turn: bool) -> Attempt {
        self.start_on_turn = start_on_turn;
        self
    }

    pub fn phase(&self) -> &Phase {
        &self.phase
    }

    /// The machine: one event in, the actions out.
    pub fn handle(&mut self, event: AttemptEvent, now: Instant) -> Vec<AttemptAction> {
        use AttemptEvent as E;
        match (self.phase.clone(), event) {
            (Phase::Proposing, E::Resumed | E::Woken) => vec![AttemptAction::AskProposals],
            (Phase::Proposing, E::Proposals(candidates)) => self.proposals(candidates, now),
            (Phase::Booking(candidate), E::Resumed) => vec![AttemptAction::AskBooking(candidate)],
            (Phase::Booking(candidate), E::BookingAnswer(Answer::Started)) => {
                self.backoff.reset();
                self.round = None;
                self.started(candidate, now)
            }
            // Silence after asking to start on its turn: the job may run there; only
            // the resource can say (a start is answered true if it began, `not_booked`
            // if the booking never arrived).
            (Phase::Booking(candidate), E::BookingAnswer(Answer::Silent)) if self.start_on_turn => {
                self.round = None;
                let mut actions = self.record(Phase::Booked(candidate.clone()));
                actions.push(AttemptAction::AskStart(candidate));
                actions
            }
            (Phase::Booking(candidate), E::BookingAnswer(Answer::Accepted)) => {
                self.backoff.reset();
                self.round = None;
                let mut actions = self.record(Phase::Booked(candidate.clone()));
                actions.push(AttemptAction::Publish);
                if self.start_on_turn {
                    // It starts by itself on its turn, and says so in its state.
                    actions.extend(self.watch_for_turn(candidate));
                } else {
                    actions.push(AttemptAction::AskStart(candidate));
                }
                actions
            }
            (Phase::Booking(_), E::BookingAnswer(_)) => self.next_candidate(now),
            (Phase::Booked(provider), E::Resumed) => vec![AttemptAction::AskStart(provider)],
            (Phase::Booked(provider), E::StartAnswer(answer)) => {
                self.start_answer(provider, answer, now)
            }
            (Phase::Booked(provider), E::Watched(None)) => vec![AttemptAction::AskStart(provider)],
            (Phase::Booked(provider), E::Began) => {
                self.backoff.reset();
                self.started(provider, now)
            }
            (Phase::Booked(provider), E::Watched(Some(outcome))) => {
                let mut actions = Vec::new();
                if matches!(outcome, StepOutcome::Lost { .. }) {
                    // The resource vanished with the booking: if it comes back with it
                    // (from its journal), take the booking back off its agenda.
                    actions.push(AttemptAction::CancelWhenBack(provider));
                }
                actions.push(AttemptAction::End(outcome));
                actions
            }
            (Phase::Started(provider), E::Resumed) => {
                // What happened while no process watched (a restart, a takeover of the
                // node) only the resource can say: asked at once.
                self.deadline = Some(now + self.timing.step_timeout);
                self.asking = Some(Asking::CameBack);
                vec![AttemptAction::AskOutcome(provider)]
            }
            (Phase::Started(provider), E::Watched(Some(outcome))) if interrupted(&outcome) => {
                self.asking = Some(Asking::Interrupted(outcome));
                vec![AttemptAction::AskOutcome(provider)]
            }
            (Phase::Started(_), E::Watched(Some(outcome))) => vec![AttemptAction::End(outcome)],
            (Phase::Started(provider), E::Watched(None)) => {
                self.asking = Some(Asking::TimedOut);
                vec![AttemptAction::AskOutcome(provider)]
            }
            (Phase::Started(provider), E::CameBack) => {
                self.asking = Some(Asking::CameBack);
                vec![AttemptAction::AskOutcome(provider)]
            }
            (Phase::Booked(provider) | Phase::Started(provider), E::Outcome(answer)) => {
                match self.asking.take() {
                    Some(asking) => self.told(provider, asking, answer, now),
                    None => vec![],
                }
            }
            (_, _) => vec![],
        }
    }

    /// Records `phase` (and takes it as the current one).
    fn record(&mut self, phase: Phase) -> Vec<AttemptAction> {
        self.phase = phase.clone();
        vec![AttemptAction::Record(phase)]
    }

    fn proposals(&mut self, candidates: Vec<HolonId>, now: Instant) -> Vec<AttemptAction> {
        let mut round: VecDeque<HolonId> = candidates.into();
        let Some(first) = round.pop_front() else {
            if now >= self.give_up {
                return vec![AttemptAction::End(StepOutcome::NoResource)];
            }
            // Nobody could take it: a resource that appears, becomes ready or frees a
            // place wakes this order, so the fallback poll can be rare.
            return vec![AttemptAction::Wait {
                pause: self.timing.idle_poll.max(self.timing.retry_max),
                idle: true,
                until: self.give_up,
            }];
        };
        self.round = Some(round);
        let mut actions = self.record(Phase::Booking(first.clone()));
        actions.push(AttemptAction::AskBooking(first));
        actions
    }

    /// The booking asked for was refused (or not answered): the next candidate of the
    /// round, a new round, or a pause.
    fn next_candidate(&mut self, now: Instant) -> Vec<AttemptAction> {
        match self.round.as_mut().map(VecDeque::pop_front) {
            Some(Some(next)) => {
                let mut actions = self.record(Phase::Booking(next.clone()));
                actions.push(AttemptAction::AskBooking(next));
                actions
            }
            // Resumed with a booking that did not hold: look again at once.
            None => {
                let mut actions = self.record(Phase::Proposing);
                actions.push(AttemptAction::AskProposals);
                actions
            }
            Some(None) => {
                self.round = None;
                let mut actions = self.record(Phase::Proposing);
                if now >= self.give_up {
                    actions.push(AttemptAction::End(StepOutcome::NoResource));
                } else {
                    actions.push(AttemptAction::Wait {
                        pause: self.backoff.next_pause(),
                        idle: false,
                        until: self.give_up,
                    });
                }
                actions
            }
        }
    }

    fn start_answer(
        &mut self,
        provider: HolonId,
        answer: Answer,
        now: Instant,
    ) -> Vec<AttemptAction> {
        let refusal = match answer {
            Answer::Accepted | Answer::Started => return self.started(provider, now),
            Answer::Silent => None,
            // A refusal without a reason is a refusal all the same.
            Answer::Refused(why) => Some(why.unwrap_or_else(|| Reason::Other("refused".into()))),
        };
        match refusal {
            None | Some(Reason::Busy) => self.watch_for_turn(provider),
            Some(Reason::Unavailable) if now < self.give_up => self.watch_for_turn(provider),
            // Gone from the agenda: never booked there, or begun unseen (on its turn,
            // or a start whose answer was lost) by a holder that has since died.
            Some(Reason::NotBooked) => {
                self.asking = Some(Asking::NotBooked);
                vec![AttemptAction::AskOutcome(provider)]
            }
            Some(other) => vec![
                AttemptAction::CancelBooking(provider.clone()),
                AttemptAction::End(StepOutcome::Failed {
                    provider,
                    reason: format!("start refused: {other}"),
                    detail: None,
                }),
            ],
        }
    }

    /// What the resource said of the conversation, asked for `asking`.
    fn told(
        &mut self,
        provider: HolonId,
        asking: Asking,
        answer: Option<OutcomeReply>,
        now: Instant,
    ) -> Vec<AttemptAction> {
        let end = |outcome| vec![AttemptAction::End(outcome)];
        // What is left of the step timeout.
        let left = self
            .deadline
            .map_or(Duration::ZERO, |d| d.saturating_duration_since(now));
        let Some(answer) = answer.filter(|a| a.outcome != Outcome::Unknown) else {
            // Nobody could tell: as without asking. The step timeout stands (a poll
            // of a running step, or a provider back early, waits out what is left).
            return match asking {
                Asking::TimedOut | Asking::CameBack if left.is_zero() => end(StepOutcome::Failed {
                    provider,
                    reason: format!("no result within {:?}", self.timing.step_timeout),
                    detail: None,
                }),
                Asking::TimedOut | Asking::CameBack => vec![AttemptAction::Watch {
                    provider,
                    pause: left,
                    started: true,
                    may_run: true,
                }],
                Asking::NotBooked => end(StepOutcome::Lost {
                    provider,
                    why: "the booking was lost".into(),
                }),
                Asking::Interrupted(reported) => end(reported),
            };
        };
        match answer.outcome {
            Outcome::Done => end(StepOutcome::Done {
                provider,
                results: answer.results,
            }),
            Outcome::Failed => end(StepOutcome::Failed {
                provider,
                reason: answer
                    .reason
                    .as_ref()
                    .map_or_else(|| "failed".to_string(), Reason::to_string),
                detail: answer.detail.filter(|d| !d.is_empty()),
            }),
            Outcome::NeverReached => end(StepOutcome::Lost {
                provider,
                why: "the step never reached the controller".into(),
            }),
            Outcome::Running | Outcome::Unknown => {
                // A resource that runs it itself (its journal knows it) reports its
                // result: watched for what is left of the step timeout, or a poll
                // pause. One whose controller runs it for a dead holder reports
                // nothing: asked again after a poll pause.
                let mut actions = Vec::new();
                let mut left = left;
                if matches!(self.phase, Phase::Booked(_)) {
                    actions.extend(self.record(Phase::Started(provider.clone())));
                    actions.push(AttemptAction::Publish);
                    self.deadline = Some(now + self.timing.step_timeout);
                    left = self.timing.step_timeout;
                }
                let pause = match answer.source {
                    OutcomeSource::Journal => left.max(self.poll()),
                    OutcomeSource::Controller | OutcomeSource::Nowhere => self.poll(),
                };
                actions.push(AttemptAction::Watch {
                    provider,
                    pause,
                    started: true,
                    may_run: true,
                });
                actions
            }
        }
    }

    /// How long a step the resource says runs is watched before it is asked again.
    fn poll(&self) -> Duration {
        self.timing.retry_max.min(self.timing.step_timeout)
    }

    /// The step has begun on `provider`: recorded, published, its result awaited.
    fn started(&mut self, provider: HolonId, now: Instant) -> Vec<AttemptAction> {
        let mut actions = self.record(Phase::Started(provider.clone()));
        actions.push(AttemptAction::Publish);
        actions.push(self.watch_started(provider, now));
        actions
    }

    /// Booked, not started: wait (the backoff) for the resource to say it is this
    /// order's turn (or to start it on its turn and report), then ask again.
    fn watch_for_turn(&mut self, provider: HolonId) -> Vec<AttemptAction> {
        vec![AttemptAction::Watch {
            provider,
            pause: self.backoff.next_pause(),
            started: false,
            may_run: self.start_on_turn,
        }]
    }

    /// Watches a step that began (or resumed) at `now` for its step timeout.
    fn watch_started(&mut self, provider: HolonId, now: Instant) -> AttemptAction {
        self.deadline = Some(now + self.timing.step_timeout);
        AttemptAction::Watch {
            provider,
            pause: self.timing.step_timeout,
            started: true,
            may_run: true,
        }
    }
}

/// Whether `outcome` is a result `failed` `interrupted`: the resource's journal says the
/// step was running when its holder stopped, not how it ended.
fn interrupted(outcome: &StepOutcome) -> bool {
    matches!(outcome, StepOutcome::Failed { reason, .. } if reason == Reason::Interrupted.as_str())
}

#[cfg(test)]
mod tests;

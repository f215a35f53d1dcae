//! An order's progress through its product's plan: the pure part of an order holon.
//! It decides what comes next after each step's outcome; the task around it talks.

use std::collections::BTreeSet;

use schemas::{
    unix_ms, AttemptEnd, AttemptRecord, HolonId, OnReject, OrderSnapshot, OrderStatus, Plan,
    Reason, MAX_ATTEMPT_HISTORY,
};
use serde_json::{Map, Value};

use crate::part::PartProgress;

pub use crate::phase::Phase;

/// How a step attempt ended.
#[derive(Debug, Clone, PartialEq)]
pub enum StepOutcome {
    /// The resource reported `done` with these controller results.
    Done {
        provider: HolonId,
        results: Map<String, Value>,
    },
    /// The resource reported `failed`: it may have moved the part, and counts as a
    /// failure, unless its reason says the job never reached the controller
    /// (`withdrawn`, `unavailable`, `busy`, `not_begun`:
    /// [`schemas::Reason::never_reached_controller`]), which is booked again as a lost
    /// booking is.
    /// `detail`: what the resource said of it beyond the reason (a `failed` message's
    /// `info.detail`, an outcome's `detail`): the controller's own words, where it had
    /// any (`pick failed: overtravel axis 3`).
    Failed {
        provider: HolonId,
        reason: String,
        detail: Option<String>,
    },
    /// The booking ended without the step being attempted to completion: the resource
    /// vanished, or lost the booking. Book elsewhere; does not count as a failure.
    Lost { provider: HolonId, why: String },
    /// No resource could be booked within the allowed time.
    NoResource,
    /// An operator cancelled the order before the step started.
    Cancelled,
}

impl StepOutcome {
    /// Whether the resource said the step failed before its job reached the controller
    /// ([`schemas::Reason::never_reached_controller`]): nothing of it ran.
    pub fn never_reached_controller(&self) -> bool {
        matches!(self, StepOutcome::Failed { reason, .. } if Reason::from_word(reason).never_reached_controller())
    }
}

/// As an operator reads it in a log: `done by resource/robot1 (pick=picking_done ...)`,
/// `failed on resource/robot2: controller_error`, `lost resource/robot1: vanished`, ...
impl std::fmt::Display for StepOutcome {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StepOutcome::Done { provider, results } => {
                write!(f, "done by {provider}")?;
                let shown: Vec<String> = results
                    .iter()
                    .map(|(action, result)| match result.as_str() {
                        Some(text) => format!("{action}={text}"),
                        None => format!("{action}={result}"),
                    })
                    .collect();
                if !shown.is_empty() {
                    write!(f, " ({})", shown.join(" "))?;
                }
                Ok(())
            }
            StepOutcome::Failed {
                provider,
                reason,
                detail: None,
            } => write!(f, "failed on {provider}: {reason}"),
            StepOutcome::Failed {
                provider,
                reason,
                detail: Some(detail),
            } => write!(f, "failed on {provider}: {reason} ({detail})"),
            StepOutcome::Lost { provider, why } => write!(f, "lost {provider}: {why}"),
            StepOutcome::NoResource => f.write_str("no resource could be booked"),
            StepOutcome::Cancelled => f.write_str("cancelled by an operator"),
        }
    }
}

#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct OrderProgress {
    pub holon: HolonId,
    pub product: String,
    pub plan: Option<Plan>,
    /// Index of the current step (0-based).
    pub step: usize,
    /// Attempt of the current step, from 1; a new conversation each attempt. A step
    /// worked on again after a rework continues from its last attempt, so every
    /// execution has its own conversation id.
    pub attempt: u32,
    /// The last attempt of each step left behind (by index), for reworks.
    #[serde(default)]
    pub last_attempts: std::collections::BTreeMap<usize, u32>,
    /// Failed attempts of the current step.
    pub failures: u32,
    /// Resources that failed the current step (avoided when others propose).
    pub avoid: BTreeSet<HolonId>,
    pub reworks: u32,
    pub rebooks: u32,
    /// Failed attempts over all steps.
    #[serde(default)]
    pub failed_attempts: u32,
    pub status: OrderStatus,
    pub reason: Option<String>,
    pub completed: Vec<(String, HolonId)>,
    /// Where the current attempt stands.
    pub phase: Phase,
    /// Failed attempts of one step before the order fails.
    pub max_attempts: u32,
    /// An operator asked to cancel the order (recorded before the request is
    /// acknowledged; a restarted node carries it out).
    #[serde(default)]
    pub cancel_requested: bool,
    /// Every resource an attempt of this order was booked on: the only ones whose
    /// results of earlier conversations (duplicates, late reports) are acknowledged.
    #[serde(default)]
    pub worked_with: BTreeSet<HolonId>,
    /// Every ended attempt, oldest first (the last `MAX_ATTEMPT_HISTORY`).
    #[serde(default)]
    pub history: Vec<AttemptRecord>,
    /// When the order's end was recorded (Unix ms): it leaves the journal
    /// `journal.keep_finished_ms` later.
    #[serde(default)]
    pub finished_at: Option<u64>,
    /// The work order's priority: every booking of this order carries it.
    #[serde(default)]
    pub priority: i32,
    /// When the work order is due (Unix ms), if it said.
    #[serde(default)]
    pub due: Option<u64>,
    /// Steps booked on a staff holon's advice.
    #[serde(default)]
    pub advised: u32,
    /// On etcd: the epoch of the order-node at which the step's last `start` was
    /// journalled, before it was sent with that epoch ([`schemas::info_key::EPOCH`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub start_epoch: Option<u64>,
    /// The resources this order booked that were heard of as fenced when it booked
    /// them (their state carried an epoch): journalled with the booking, so that a
    /// node resuming the order knows, before its own presence has heard them, that a
    /// holder of one that vanished may still run the step (it waits rather than book
    /// the step elsewhere).
    #[serde(default, skip_serializing_if = "BTreeSet::is_empty")]
    pub fenced: BTreeSet<HolonId>,
    /// The order's part, once its plan moves parts ([`crate::part`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub part: Option<PartProgress>,
    /// The recovery under way of a part that its step rejected (the plan's
    /// `on_reject` `recover`): worked before the order goes on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub recovering: Option<Recovering>,
}

/// A rejected part's recovery: one step that is not in the plan, then the plan again.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Recovering {
    /// The recovery step: its service, with the rejected step's `info`.
    pub step: schemas::PlanStep,
    /// The plan's step the order goes on from once the part is recovered (0-based).
    pub then_step: usize,
}

impl OrderProgress {
    pub fn new(holon: HolonId, product: &str, max_attempts: u32) -> Self {
        OrderProgress {
            holon,
            product: product.to_string(),
            plan: None,
            step: 0,
            attempt: 1,
            last_attempts: Default::default(),
            failures: 0,
            avoid: BTreeSet::new(),
            reworks: 0,
            rebooks: 0,
            failed_attempts: 0,
            status: OrderStatus::Running,
            reason: None,
            completed: Vec::new(),
            phase: Phase::Proposing,
            max_attempts: max_attempts.max(1),
            cancel_requested: false,
            worked_with: BTreeSet::new(),
            history: Vec::new(),
            finished_at: None,
            priority: 0,
            due: None,
            advised: 0,
            start_epoch: None,
            fenced: BTreeSet::new(),
            part: None,
            recovering: None,
        }
    }

    /// Takes the plan: an order whose plan moves parts gets its part, outside the cell.
    pub fn set_plan(&mut self, plan: Plan) {
        if plan.moves_parts && self.part.is_none() {
            self.part = Some(PartProgress::default());
        }
        self.plan = Some(plan);
    }

    /// Ends the order with `status`: at once, unless its part is in the cell, in which
    /// case the end is recorded once the part has left by an exit.
    fn end(&mut self, status: OrderStatus, reason: Option<String>) {
        self.phase = Phase::Proposing;
        match &mut self.part {
            Some(part) if part.in_cell() => {
                if part.leaving.is_none() {
                    part.leaving = Some((status, reason));
                }
            }
            _ => {
                self.status = status;
                self.reason = reason;
            }
        }
    }

    /// The part has left the cell (or never entered it): the end that waited for it is
    /// recorded.
    pub fn part_left(&mut self) {
        if let Some((status, reason)) = self.part.as_mut().and_then(|p| p.leaving.take()) {
            self.status = status;
            self.reason = reason;
        }
    }

    /// The steps still ahead of the order (the current one first), as a staff holon
    /// is asked to plan them: each one's service type and program.
    pub fn route_ahead(&self) -> Vec<schemas::RouteStep> {
        let Some(plan) = &self.plan else {
            return Vec::new();
        };
        let ahead: Vec<&schemas::PlanStep> = match &self.recovering {
            Some(recovering) => std::iter::once(&recovering.step)
                .chain(plan.steps.iter().skip(recovering.then_step))
                .collect(),
            None => plan.steps.iter().skip(self.step).collect(),
        };
        ahead
            .into_iter()
            .map(|step| schemas::RouteStep {
                service_type: step.service_type.clone(),
                program: step
                    .info
                    .get("program")
                    .and_then(|p| p.as_str())
                    .map(str::to_string),
            })
            .collect()
    }

    /// The same new order, as urgent as its work order says.
    pub fn with_urgency(mut self, priority: i32, due: Option<u64>) -> Self {
        self.priority = priority;
        self.due = due;
        self
    }

    /// Moves the current attempt to `phase`, remembering the resource it names.
    pub fn set_phase(&mut self, phase: Phase) {
        if let Some(resource) = phase.resource() {
            self.worked_with.insert(resource.clone());
        }
        self.phase = phase;
    }

    /// Whether a result of an earlier conversation from `provider` is one to
    /// acknowledge (a duplicate or a late report from a resource this order booked).
    pub fn knows(&self, provider: Option<&HolonId>) -> bool {
        provider.is_some_and(|p| self.worked_with.contains(p))
    }

    /// Ends a running order as cancelled by an operator.
    pub fn cancel(&mut self) {
        if self.status == OrderStatus::Running {
            self.end(
                OrderStatus::Cancelled,
                Some("cancelled by an operator".into()),
            );
        }
    }

    /// The conversation of the current step's attempt: `<order>/<step>/<attempt>`.
    pub fn conversation_id(&self) -> String {
        format!("{}/{}/{}", self.holon.name(), self.step + 1, self.attempt)
    }

    /// The step to work on, if the order is still running and has its plan.
    pub fn current_step(&self) -> Option<&schemas::PlanStep> {
        if self.status != OrderStatus::Running
            || self.part.as_ref().is_some_and(|p| p.leaving.is_some())
        {
            return None;
        }
        if let Some(recovering) = &self.recovering {
            return Some(&recovering.step);
        }
        self.plan.as_ref()?.steps.get(self.step)
    }

    /// The service the part was last worked for, if it was.
    pub fn last_worked_for(&self) -> Option<&str> {
        self.completed.last().map(|(service, _)| service.as_str())
    }

    pub fn fail(&mut self, reason: String) {
        self.end(OrderStatus::Failed, Some(reason));
    }

    fn next_attempt(&mut self) {
        self.attempt += 1;
        self.phase = Phase::Proposing;
    }

    fn next_step(&mut self, step: usize) {
        self.last_attempts.insert(self.step, self.attempt);
        self.step = step;
        self.attempt = self.last_attempts.get(&step).map_or(1, |a| a + 1);
        self.failures = 0;
        self.avoid.clear();
        self.phase = Phase::Proposing;
    }

    /// The rejected part is recovered by `step` before the order goes on from
    /// `then_step`: the recovery counts as the next attempt of the rejected step (its
    /// own conversation), and the step after it continues that count.
    fn recover(&mut self, step: schemas::PlanStep, then_step: usize) {
        self.recovering = Some(Recovering { step, then_step });
        self.attempt += 1;
        self.failures = 0;
        self.avoid.clear();
        self.phase = Phase::Proposing;
    }

    /// Applies a step's outcome and moves on.
    pub fn record(&mut self, outcome: StepOutcome) {
        let Some(current) = self.current_step().cloned() else {
            return;
        };
        self.remember(&current, &outcome);
        match outcome {
            StepOutcome::Done { provider, results } => {
                self.completed
                    .push((current.service_type.clone(), provider.clone()));
                let rejected = results.values().any(|v| {
                    v.as_str()
                        .is_some_and(|r| current.reject_results.iter().any(|x| x == r))
                });
                if rejected {
                    match &current.on_reject {
                        Some(OnReject::Rework {
                            from_step,
                            max_reworks,
                        }) if self.reworks < *max_reworks => {
                            self.reworks += 1;
                            self.next_step(from_step - 1);
                        }
                        Some(OnReject::Rework { max_reworks, .. }) => {
                            let reason = format!(
                                "rejected at step {} ({}) after {max_reworks} reworks",
                                self.step + 1,
                                current.service_type
                            );
                            self.end(OrderStatus::Scrapped, Some(reason));
                        }
                        Some(OnReject::Scrap { reason }) => {
                            self.end(OrderStatus::Scrapped, Some(reason.clone()));
                        }
                        Some(OnReject::Recover {
                            service_type,
                            then_step,
                            max_recoveries,
                        }) if self.reworks < *max_recoveries => {
                            self.reworks += 1;
                            let step = schemas::PlanStep {
                                service_type: service_type.clone(),
                                info: current.info.clone(),
                                reject_results: vec![],
                                on_reject: None,
                            };
                            self.recover(step, then_step - 1);
                        }
                        Some(OnReject::Recover { max_recoveries, .. }) => {
                            let reason = format!(
                                "rejected at step {} ({}) after {max_recoveries} recoveries",
                                self.step + 1,
                                current.service_type
                            );
                            self.end(OrderStatus::Scrapped, Some(reason));
                        }
                        None => self.advance(),
                    }
                } else {
                    self.advance();
                }
            }
            StepOutcome::Failed { ref provider, .. } if outcome.never_reached_controller() => {
                // Nothing of it ran (its turn came while the controller reconnected,
                // the resource was stopped or handed it back): booked again, as a lost
                // booking is, not counted against the step; others preferred.
                self.rebooks += 1;
                self.avoid.insert(provider.clone());
                self.next_attempt();
            }
            StepOutcome::Failed {
                provider,
                reason,
                detail,
            } => {
                self.failures += 1;
                self.failed_attempts += 1;
                self.avoid.insert(provider.clone());
                if self.failures >= self.max_attempts {
                    let said = detail
                        .as_ref()
                        .map_or_else(String::new, |d| format!(" ({d})"));
                    self.fail(format!(
                        "step {} ({}) failed {} times; last on {provider}: {reason}{said}",
                        self.step + 1,
                        current.service_type,
                        self.failures
                    ));
                } else {
                    self.next_attempt();
                }
            }
            StepOutcome::Lost { .. } => {
                self.rebooks += 1;
                self.next_attempt();
            }
            StepOutcome::Cancelled => self.cancel(),
            StepOutcome::NoResource => {
                self.fail(format!(
                    "step {} ({}): no resource could be booked",
                    self.step + 1,
                    current.service_type
                ));
            }
        }
    }

    /// Adds the attempt's end to the history.
    fn remember(&mut self, current: &schemas::PlanStep, outcome: &StepOutcome) {
        let (end, resource) = match outcome {
            StepOutcome::Done { provider, results } => {
                let rejected = results.values().any(|v| {
                    v.as_str()
                        .is_some_and(|r| current.reject_results.iter().any(|x| x == r))
                });
                let end = if rejected {
                    AttemptEnd::Rejected
                } else {
                    AttemptEnd::Done
                };
                (end, Some(provider.clone()))
            }
            // Booked again, not counted (see `record`): an attempt lost, as the
            // operator reads the trail, in the resource's words.
            StepOutcome::Failed { provider, .. } if outcome.never_reached_controller() => {
                (AttemptEnd::Lost, Some(provider.clone()))
            }
            StepOutcome::Failed { provider, .. } => (AttemptEnd::Failed, Some(provider.clone())),
            StepOutcome::Lost { provider, .. } => (AttemptEnd::Lost, Some(provider.clone())),
            StepOutcome::NoResource => (AttemptEnd::NoResource, None),
            StepOutcome::Cancelled => (AttemptEnd::Cancelled, self.phase.resource().cloned()),
        };
        if self.history.len() >= MAX_ATTEMPT_HISTORY {
            self.history.remove(0);
        }
        self.history.push(AttemptRecord {
            conversation_id: self.conversation_id(),
            step: self.step + 1,
            service_type: current.service_type.clone(),
            resource,
            end,
            detail: outcome.to_string(),
            at: unix_ms(),
        });
    }

    fn advance(&mut self) {
        if let Some(recovering) = self.recovering.take() {
            self.next_step(recovering.then_step);
            return;
        }
        let steps = self.plan.as_ref().map_or(0, |p| p.steps.len());
        if self.step + 1 >= steps {
            self.end(OrderStatus::Done, None);
        } else {
            self.next_step(self.step + 1);
        }
    }

    pub fn snapshot(&self) -> OrderSnapshot {
        OrderSnapshot {
            holon: self.holon.clone(),
            product: self.product.clone(),
            status: self.status,
            reason: self.reason.clone(),
            step: if self.plan.is_some() {
                self.step + 1
            } else {
                0
            },
            steps: self.plan.as_ref().map_or(0, |p| p.steps.len()),
            service_type: self.current_step().map(|s| s.service_type.clone()),
            resource: self.phase.resource().cloned(),
            attempt: self.attempt,
            completed: self.completed.clone(),
            reworks: self.reworks,
            rebooks: self.rebooks,
            failed_attempts: self.failed_attempts,
            attempts: self.history.clone(),
            priority: self.priority,
            due: self.due,
            advised: self.advised,
            version: Some(env!("CARGO_PKG_VERSION").to_string()),
            part: self.part.as_ref().map(|p| p.place.clone()),
            part_found: self
                .part
                .as_ref()
                .map_or_else(Vec::new, |p| p.found.clone()),
            at: unix_ms(),
        }
    }
}

#[cfg(test)]
mod tests;

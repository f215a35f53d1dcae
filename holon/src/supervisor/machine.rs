//! The supervision machine: what a supervisor does when one of its children ends, after
//! Erlang/OTP's supervisor, as a pure machine (`handle(event, now) -> actions`, no I/O,
//! one owner). Its executors carry the actions out for their kind of child: the tasks of
//! [`crate::Supervisor`], the order tasks of an order-node, the processes of `cell up`.
//!
//! Children are known by a key `K` (an index for static children, a name for dynamic
//! ones) and kept in the order they were added. Each child has a restart type
//! ([`RestartType`]); the supervisor has a [`Strategy`], an [`Intensity`] counted over
//! the whole supervisor or per child ([`Scope`]), and optionally a [`Backoff`] that every
//! child gets a copy of (without one, a restart is at once).
//!
//! | state of `child` | event | actions | next state |
//! |---|---|---|---|
//! | unknown or any | `Added { child, restart }` | `Start(child)` | running |
//! | running | `Exited`, restart type says not restarted (permanent: never; transient: `normally`; temporary: always) | `Done(child)` | done (forgotten under `simple_one_for_one`) |
//! | running | `Exited`, to restart, past the intensity, scope whole | `GiveUp { child, error }`, `Stop(every other running child, last first)` | the supervisor gave up: every later event is ignored |
//! | running | `Exited`, to restart, past the intensity, scope per child | `GiveUp { child, error }` | forgotten (only this child ends) |
//! | running | `Exited`, to restart, within the intensity | `Stop(the group's other running children, last first)` (none under one_for_one and simple_one_for_one), then for each child of the group that is not done, in order: `Start(it)`, or `RestartAfter(it, pause)` with a backoff | running, or waiting |
//! | waiting | `RestartDue { child }` | `Start(child)` | running |
//! | running, waiting | `StartFailed { child }`, with a backoff | `RestartAfter(child, pause)` (not counted against the intensity) | waiting |
//! | running, waiting | `StartFailed { child, why }`, without a backoff | as `Exited { normally: false, why }` | as there |
//! | any | `Replaced { child, started_at }` (a successor took over) | none; its backoff starts over | running |
//! | any | `Removed { child }` (the executor stopped it for good) | none | forgotten |
//! | done, waiting, unknown | `Exited` (stale: already handled by a group restart) | none | unchanged |
//! | running, done, unknown | `RestartDue` (stale: started meanwhile) | none | unchanged |
//!
//! The group of a restart is the child itself under `one_for_one` and
//! `simple_one_for_one`, every child under `one_for_all`, and the child and those added
//! after it under `rest_for_one`. Every restart decision counts once against the
//! intensity, however many children it restarts. The pause of a group restart is the
//! failed child's next pause. A child's backoff starts over when it fails after running
//! for at least the intensity's period (it earned it), and when a successor replaced it.

use std::collections::HashMap;
use std::fmt::{Debug, Display};
use std::hash::Hash;
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::time::Instant;

use crate::backoff::Backoff;
use crate::restart::{Intensity, RestartType, RestartWindow};

/// Which children a failure restarts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Strategy {
    /// Only the child that failed.
    #[default]
    OneForOne,
    /// Every child: the others are stopped (in reverse order) and all restarted in order.
    OneForAll,
    /// The failed child and every child started after it.
    RestForOne,
    /// Dynamic children of one kind, added and ended at any time: only the child that
    /// failed (as `one_for_one`), and a child that ends for good is forgotten.
    SimpleOneForOne,
}

/// What the restart intensity is counted over.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Scope {
    /// One window for the whole supervisor: past it, the supervisor gives up.
    #[default]
    Whole,
    /// One window per child: past it, only that child is given up on.
    PerChild,
}

/// What happened to a child, told to the machine by its executor.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Event<K> {
    /// A child was added (and is to start).
    Added {
        /// The child.
        child: K,
        /// When it is restarted.
        restart: RestartType,
    },
    /// A running child ended.
    Exited {
        /// The child.
        child: K,
        /// It ended normally (returned `Ok`, exited with status 0).
        normally: bool,
        /// Why, for logs and the error of giving up.
        why: String,
    },
    /// The pause before a child's restart is over.
    RestartDue {
        /// The child.
        child: K,
    },
    /// A child could not be started.
    StartFailed {
        /// The child.
        child: K,
        /// Why.
        why: String,
    },
    /// A successor took over from the child (an upgrade): it runs on as that successor.
    Replaced {
        /// The child.
        child: K,
        /// When the successor started.
        started_at: Instant,
    },
    /// The executor stopped the child for good (shutdown, abort): it is forgotten.
    Removed {
        /// The child.
        child: K,
    },
}

/// What the executor is to do.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Action<K> {
    /// Start the child (again) now.
    Start(K),
    /// Stop these running children, in this order (the last started first).
    Stop(Vec<K>),
    /// Start the child again after this pause (then tell [`Event::RestartDue`]).
    RestartAfter(K, Duration),
    /// The child ended and is not restarted (its restart type says so).
    Done(K),
    /// The intensity is exceeded: under [`Scope::Whole`] the supervisor ends with the
    /// error (the `Stop` that follows stops the rest), under [`Scope::PerChild`] only
    /// this child does.
    GiveUp {
        /// The child whose failure was one too many.
        child: K,
        /// What to report.
        error: GaveUp,
    },
}

/// The restart intensity was exceeded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("more than {max_restarts} restarts within {period:?} (last failure: {child}: {failure})")]
pub struct GaveUp {
    /// The intensity's restarts.
    pub max_restarts: u32,
    /// The intensity's period.
    pub period: Duration,
    /// The child whose failure was one too many, as the executor names it.
    pub child: String,
    /// Why it failed.
    pub failure: String,
}

/// Where a child is in its life.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Life {
    /// Started and not known to have ended.
    Running,
    /// Ended; to start again when its pause is over.
    Waiting,
    /// Ended and not restarted.
    Done,
}

/// What the machine knows of one child.
#[derive(Debug, Clone)]
struct Child {
    /// The order it was added in (the order of starts; stops are the reverse).
    position: u64,
    /// When it is restarted.
    restart: RestartType,
    /// Where it is in its life.
    life: Life,
    /// When it was last started.
    started_at: Instant,
    /// Its restarts, under [`Scope::PerChild`].
    window: Option<RestartWindow>,
    /// Its pauses before restarts, when the supervisor has a backoff.
    backoff: Option<Backoff>,
}

/// The supervision machine (see the module's table).
#[derive(Debug, Clone)]
pub struct Machine<K> {
    /// Which children a failure restarts.
    strategy: Strategy,
    /// At most so many restarts within a period.
    intensity: Intensity,
    /// Whether the intensity counts the whole supervisor's restarts or each child's.
    scope: Scope,
    /// The restarts of the whole supervisor, under [`Scope::Whole`].
    window: RestartWindow,
    /// The backoff each child starts with, if restarts pause.
    backoff: Option<Backoff>,
    /// The children, by key.
    children: HashMap<K, Child>,
    /// The position of the next child added.
    next_position: u64,
    /// The supervisor gave up (scope whole): nothing more is decided.
    gave_up: bool,
}

impl<K> Machine<K>
where
    K: Clone + Eq + Hash + Debug + Display,
{
    /// A machine without children, its intensity counted over the whole supervisor and
    /// restarts at once.
    pub fn new(strategy: Strategy, intensity: Intensity) -> Machine<K> {
        Machine {
            strategy,
            intensity,
            scope: Scope::Whole,
            window: RestartWindow::new(intensity),
            backoff: None,
            children: HashMap::new(),
            next_position: 0,
            gave_up: false,
        }
    }

    /// Counts the intensity over the whole supervisor or per child.
    pub fn scope(mut self, scope: Scope) -> Machine<K> {
        self.scope = scope;
        self
    }

    /// Restarts pause after a copy of `backoff`, one per child.
    pub fn backoff(mut self, backoff: Backoff) -> Machine<K> {
        self.backoff = Some(backoff);
        self
    }

    /// The intensity held against.
    pub fn intensity(&self) -> Intensity {
        self.intensity
    }

    /// The children it knows of (running, waiting or done).
    pub fn len(&self) -> usize {
        self.children.len()
    }

    /// Whether it knows of no child.
    pub fn is_empty(&self) -> bool {
        self.children.is_empty()
    }

    /// Decides what to do about `event`, which happened at `now`.
    pub fn handle(&mut self, event: Event<K>, now: Instant) -> Vec<Action<K>> {
        if self.gave_up {
            return Vec::new();
        }
        match event {
            Event::Added { child, restart } => {
                let position = self.next_position;
                self.next_position += 1;
                let window =
                    (self.scope == Scope::PerChild).then(|| RestartWindow::new(self.intensity));
                self.children.insert(
                    child.clone(),
                    Child {
                        position,
                        restart,
                        life: Life::Running,
                        started_at: now,
                        window,
                        backoff: self.backoff.clone(),
                    },
                );
                vec![Action::Start(child)]
            }
            Event::Exited {
                child,
                normally,
                why,
            } => self.exited(child, normally, why, now),
            Event::RestartDue { child } => match self.children.get_mut(&child) {
                Some(c) if c.life == Life::Waiting => {
                    c.life = Life::Running;
                    c.started_at = now;
                    vec![Action::Start(child)]
                }
                _ => Vec::new(),
            },
            Event::StartFailed { child, why } => {
                let Some(c) = self.children.get_mut(&child) else {
                    return Vec::new();
                };
                match c.backoff.as_mut() {
                    Some(backoff) => {
                        c.life = Life::Waiting;
                        vec![Action::RestartAfter(child, backoff.next_pause())]
                    }
                    None => {
                        c.life = Life::Running;
                        self.exited(child, false, why, now)
                    }
                }
            }
            Event::Replaced { child, started_at } => {
                if let Some(c) = self.children.get_mut(&child) {
                    c.life = Life::Running;
                    c.started_at = started_at;
                    if let Some(backoff) = c.backoff.as_mut() {
                        backoff.reset();
                    }
                }
                Vec::new()
            }
            Event::Removed { child } => {
                self.children.remove(&child);
                Vec::new()
            }
        }
    }

    fn exited(&mut self, child: K, normally: bool, why: String, now: Instant) -> Vec<Action<K>> {
        let period = self.intensity.period;
        let Some(c) = self.children.get_mut(&child) else {
            return Vec::new();
        };
        if c.life != Life::Running {
            return Vec::new();
        }
        if !c.restart.restarts(normally) {
            match self.strategy {
                Strategy::SimpleOneForOne => {
                    self.children.remove(&child);
                }
                _ => c.life = Life::Done,
            }
            return vec![Action::Done(child)];
        }
        if now.saturating_duration_since(c.started_at) >= period {
            if let Some(backoff) = c.backoff.as_mut() {
                backoff.reset();
            }
        }
        let allowed = match (self.scope, c.window.as_mut()) {
            (Scope::PerChild, Some(window)) => window.allow(now),
            _ => self.window.allow(now),
        };
        if !allowed {
            let error = GaveUp {
                max_restarts: self.intensity.max_restarts,
                period,
                child: child.to_string(),
                failure: why,
            };
            return match self.scope {
                Scope::PerChild => {
                    self.children.remove(&child);
                    vec![Action::GiveUp { child, error }]
                }
                Scope::Whole => {
                    self.gave_up = true;
                    c.life = Life::Done;
                    let running = self.in_order(|_, c| c.life == Life::Running);
                    let mut actions = vec![Action::GiveUp { child, error }];
                    if !running.is_empty() {
                        actions.push(Action::Stop(running.into_iter().rev().collect()));
                    }
                    actions
                }
            };
        }
        let pause = c.backoff.as_mut().map(Backoff::next_pause);
        let from = c.position;
        let group = match self.strategy {
            Strategy::OneForOne | Strategy::SimpleOneForOne => vec![child.clone()],
            Strategy::OneForAll => self.in_order(|_, _| true),
            Strategy::RestForOne => self.in_order(|_, c| c.position >= from),
        };
        let mut actions = Vec::new();
        let stop: Vec<K> = group
            .iter()
            .rev()
            .filter(|k| **k != child && self.children[*k].life == Life::Running)
            .cloned()
            .collect();
        if !stop.is_empty() {
            actions.push(Action::Stop(stop));
        }
        for key in group {
            let c = self.children.get_mut(&key).expect("a member of the group");
            if c.life == Life::Done {
                continue;
            }
            match pause {
                Some(pause) => {
                    c.life = Life::Waiting;
                    actions.push(Action::RestartAfter(key, pause));
                }
                None => {
                    c.life = Life::Running;
                    c.started_at = now;
                    actions.push(Action::Start(key));
                }
            }
        }
        actions
    }

    /// The keys of the children that pass `keep`, in the order they were added.
    fn in_order(&self, keep: impl Fn(&K, &Child) -> bool) -> Vec<K> {
        let mut keys: Vec<(u64, &K)> = self
            .children
            .iter()
            .filter(|(k, c)| keep(k, c))
            .map(|(k, c)| (c.position, k))
            .collect();
        keys.sort_unstable_by_key(|(position, _)| *position);
        keys.into_iter().map(|(_, k)| k.clone()).collect()
    }
}

#[cfg(test)]
mod tests;

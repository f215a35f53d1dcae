//! The controller's fence for standby holons (`robot-sim --fenced`): which session holds
//! the claim and with which epoch, its lease, and each step id's stored outcome. Pure
//! state: the sessions call it with the time and their session number, and act on what
//! it answers (`docs/controller-protocol.md`, "Fencing (standby)").

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::time::{Duration, Instant};

/// How many step ids are remembered (outcomes and execution counts), oldest forgotten.
pub const STEPS_KEPT: usize = 10_000;

/// The session holding the claim.
#[derive(Debug, Clone)]
struct Holder {
    /// The session (connection) number.
    session: u64,
    /// Its epoch.
    epoch: u64,
    /// The holon name it claimed with.
    name: String,
    /// When it last showed life.
    last_seen: Instant,
}

/// A step id's state on the controller.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum StepRecord {
    /// Begun, not ended.
    Running,
    /// Ended with this success result.
    Done(String),
    /// Ended failed, with this message.
    Failed(String),
}

/// What a claim gets.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ClaimAnswer {
    Granted {
        epoch: u64,
    },
    /// Another live session holds it, with this epoch.
    Held {
        epoch: u64,
        holder: String,
    },
}

/// Whether a command may run.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum CommandCheck {
    /// The holder's current epoch: run it (or replay its step's stored outcome).
    Current,
    /// Refused: the epoch is not the holder's, or the session holds no claim; the
    /// controller's epoch.
    Stale { epoch: u64 },
}

/// What a fence keeps across a restart of its controller (the plant simulator's
/// memory): the last epoch granted and the latest steps' states, oldest first.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FenceMemory {
    /// The last epoch granted.
    pub epoch: u64,
    /// The latest step ids and their states, oldest first.
    pub steps: Vec<(String, StepRecord)>,
}

/// The fence's state, shared by the controller's sessions.
#[derive(Debug)]
pub struct FenceBook {
    /// How long a holder may stay silent.
    pub lease: Duration,
    /// The last epoch granted (0: none yet).
    epoch: u64,
    holder: Option<Holder>,
    steps: HashMap<String, StepRecord>,
    /// Executions per step id.
    executions: HashMap<String, u64>,
    /// Step ids, oldest first, to forget beyond [`STEPS_KEPT`].
    order: VecDeque<String>,
    /// Commands refused for a stale epoch.
    pub stale_refused: u64,
}

impl FenceBook {
    /// A fence whose epochs go on from `epoch` (the last granted before a restart).
    pub fn new(lease: Duration, epoch: u64) -> FenceBook {
        FenceBook {
            lease,
            epoch,
            holder: None,
            steps: HashMap::new(),
            executions: HashMap::new(),
            order: VecDeque::new(),
            stale_refused: 0,
        }
    }

    /// A fence as `memory` left it: its epochs go on from the last granted, its steps'
    /// states are known again (nobody holds the claim).
    pub fn resume(lease: Duration, memory: FenceMemory) -> FenceBook {
        let mut book = FenceBook::new(lease, memory.epoch);
        for (step, record) in memory.steps {
            if book.begin_step(&step) {
                book.steps.insert(step, record);
            }
        }
        book
    }

    /// What the fence keeps across a restart: its epoch and its latest `last` steps.
    pub fn memory(&self, last: usize) -> FenceMemory {
        let skip = self.order.len().saturating_sub(last);
        FenceMemory {
            epoch: self.epoch,
            steps: self
                .order
                .iter()
                .skip(skip)
                .filter_map(|step| Some((step.clone(), self.steps.get(step)?.clone())))
                .collect(),
        }
    }

    /// The step ids recorded as running.
    pub fn running(&self) -> Vec<String> {
        self.order
            .iter()
            .filter(|step| self.steps.get(*step) == Some(&StepRecord::Running))
            .cloned()
            .collect()
    }

    /// The last epoch granted.
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    fn live_holder(&self, now: Instant) -> Option<&Holder> {
        self.holder
            .as_ref()
            .filter(|h| now.saturating_duration_since(h.last_seen) < self.lease)
    }

    /// `session` asks for the claim as `name`.
    pub fn claim(&mut self, session: u64, name: &str, now: Instant) -> ClaimAnswer {
        if let Some(holder) = self.live_holder(now) {
            if holder.session == session {
                // Its own claim again (a lost answer): the same epoch.
                let epoch = holder.epoch;
                self.holder.as_mut().expect("live").last_seen = now;
                return ClaimAnswer::Granted { epoch };
            }
            return ClaimAnswer::Held {
                epoch: holder.epoch,
                holder: holder.name.clone(),
            };
        }
        self.epoch += 1;
        self.holder = Some(Holder {
            session,
            epoch: self.epoch,
            name: name.to_string(),
            last_seen: now,
        });
        ClaimAnswer::Granted { epoch: self.epoch }
    }

    /// Life from `session` (a heartbeat or any message): its lease starts again if it
    /// holds the claim. Whether it holds it.
    pub fn seen(&mut self, session: u64, now: Instant) -> bool {
        let live = self.live_holder(now).is_some_and(|h| h.session == session);
        if live {
            self.holder.as_mut().expect("live").last_seen = now;
        }
        live
    }

    /// A heartbeat with `epoch`: true if `session` holds the claim with it.
    pub fn heartbeat(&mut self, session: u64, epoch: Option<u64>, now: Instant) -> bool {
        let current = self.holder.as_ref().map(|h| h.epoch);
        self.seen(session, now) && epoch == current
    }

    /// When `session`'s lease ends, if it holds the claim.
    pub fn lease_end(&self, session: u64) -> Option<Instant> {
        self.holder
            .as_ref()
            .filter(|h| h.session == session)
            .map(|h| h.last_seen + self.lease)
    }

    /// `session` is gone (its socket closed) or silent past its lease: it loses the
    /// claim. True if it held it.
    pub fn release(&mut self, session: u64) -> bool {
        if self.holder.as_ref().is_some_and(|h| h.session == session) {
            self.holder = None;
            return true;
        }
        false
    }

    /// Whether a command from `session` with `epoch` may run; a refusal is counted.
    pub fn check_command(
        &mut self,
        session: u64,
        epoch: Option<u64>,
        now: Instant,
    ) -> CommandCheck {
        let holds = self.seen(session, now);
        let current = self.holder.as_ref().map(|h| h.epoch);
        if holds && epoch.is_some() && epoch == current {
            return CommandCheck::Current;
        }
        self.stale_refused += 1;
        CommandCheck::Stale { epoch: self.epoch }
    }

    /// The stored state of step `step`.
    pub fn step(&self, step: &str) -> Option<&StepRecord> {
        self.steps.get(step)
    }

    /// Step `step` begins: false (and nothing changes) if it is known already.
    pub fn begin_step(&mut self, step: &str) -> bool {
        if self.steps.contains_key(step) {
            return false;
        }
        self.steps.insert(step.to_string(), StepRecord::Running);
        self.order.push_back(step.to_string());
        while self.order.len() > STEPS_KEPT {
            if let Some(old) = self.order.pop_front() {
                self.steps.remove(&old);
                self.executions.remove(&old);
            }
        }
        true
    }

    /// Step `step` ended; a `Done` counts as an execution.
    pub fn settle(&mut self, step: &str, record: StepRecord) {
        if let Some(stored) = self.steps.get_mut(step) {
            if matches!(record, StepRecord::Done(_)) {
                *self.executions.entry(step.to_string()).or_default() += 1;
            }
            *stored = record;
        }
    }

    /// Step `step` did not begin after all (a fault before the action): forgotten.
    pub fn forget(&mut self, step: &str) {
        if self.steps.get(step) == Some(&StepRecord::Running) {
            self.steps.remove(step);
            self.order.retain(|s| s != step);
        }
    }

    /// Executions per step id (the last [`STEPS_KEPT`]).
    pub fn by_step(&self) -> BTreeMap<String, u64> {
        self.executions
            .iter()
            .map(|(k, v)| (k.clone(), *v))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LEASE: Duration = Duration::from_millis(1000);

    #[test]
    fn a_resumed_fence_keeps_its_epoch_and_its_latest_steps() {
        let mut book = FenceBook::new(LEASE, 0);
        let now = Instant::now();
        assert_eq!(
            book.claim(1, "robot1", now),
            ClaimAnswer::Granted { epoch: 1 }
        );
        for step in ["a#0", "b#0", "c#0"] {
            assert!(book.begin_step(step));
        }
        book.settle("a#0", StepRecord::Done("arrived".into()));
        book.settle("b#0", StepRecord::Failed("aborted".into()));
        let memory = book.memory(2);
        assert_eq!(
            memory.steps,
            vec![
                ("b#0".to_string(), StepRecord::Failed("aborted".into())),
                ("c#0".to_string(), StepRecord::Running)
            ]
        );
        let json = serde_json::to_string(&memory).unwrap();
        let mut resumed = FenceBook::resume(LEASE, serde_json::from_str(&json).unwrap());
        assert_eq!(resumed.epoch(), 1);
        assert_eq!(resumed.running(), vec!["c#0".to_string()]);
        assert_eq!(resumed.step("a#0"), None, "beyond the kept ones");
        assert!(
            !resumed.begin_step("b#0"),
            "a known step does not run again"
        );
        // Nobody holds the claim: the next gets a new epoch.
        assert_eq!(
            resumed.claim(7, "robot1", now),
            ClaimAnswer::Granted { epoch: 2 }
        );
    }

    #[test]
    fn one_live_holder_and_increasing_epochs() {
        let t0 = Instant::now();
        let mut book = FenceBook::new(LEASE, 4);
        assert_eq!(book.claim(1, "r1", t0), ClaimAnswer::Granted { epoch: 5 });
        assert_eq!(
            book.claim(2, "r1", t0),
            ClaimAnswer::Held {
                epoch: 5,
                holder: "r1".into()
            }
        );
        assert_eq!(book.claim(1, "r1", t0), ClaimAnswer::Granted { epoch: 5 });
        // Silent past its lease: the next claim is granted with epoch + 1.
        let later = t0 + LEASE;
        assert_eq!(
            book.claim(2, "r1", later),
            ClaimAnswer::Granted { epoch: 6 }
        );
        assert_eq!(
            book.check_command(1, Some(5), later),
            CommandCheck::Stale { epoch: 6 }
        );
        assert_eq!(book.check_command(2, Some(6), later), CommandCheck::Current);
        assert_eq!(
            book.check_command(2, None, later),
            CommandCheck::Stale { epoch: 6 }
        );
        assert_eq!(book.stale_refused, 2);
        assert!(book.release(2));
        assert_eq!(
            book.claim(1, "r1", later),
            ClaimAnswer::Granted { epoch: 7 }
        );
    }

    #[test]
    fn a_step_runs_at_most_once_and_is_forgotten_past_the_bound() {
        let mut book = FenceBook::new(LEASE, 0);
        assert!(book.begin_step("o/1#0"));
        assert!(!book.begin_step("o/1#0"));
        book.settle("o/1#0", StepRecord::Done("picking_done".into()));
        assert_eq!(
            book.step("o/1#0"),
            Some(&StepRecord::Done("picking_done".into()))
        );
        assert_eq!(book.by_step().get("o/1#0"), Some(&1));
        assert!(book.begin_step("o/2#0"));
        book.forget("o/2#0");
        assert_eq!(book.step("o/2#0"), None);
        for i in 0..STEPS_KEPT {
            book.begin_step(&format!("s{i}"));
        }
        assert_eq!(book.step("o/1#0"), None);
        assert!(book.by_step().len() <= STEPS_KEPT);
    }

    use proptest::prelude::*;

    /// One thing that happens to the fence.
    #[derive(Debug, Clone)]
    enum Op {
        Claim(u64),
        Heartbeat(u64, u64),
        Command(u64, u64),
        Release(u64),
        Wait(u64),
    }

    fn op() -> impl Strategy<Value = Op> {
        prop_oneof![
            (0..3u64).prop_map(Op::Claim),
            (0..3u64, 0..6u64).prop_map(|(s, e)| Op::Heartbeat(s, e)),
            (0..3u64, 0..6u64).prop_map(|(s, e)| Op::Command(s, e)),
            (0..3u64).prop_map(Op::Release),
            (0..1500u64).prop_map(Op::Wait),
        ]
    }

    proptest! {
        /// Whatever happens: a new grant is always a new, higher epoch; a command runs
        /// only from the live holder with its epoch; and at most one session holds the
        /// claim while its lease runs.
        #[test]
        fn one_holder_and_increasing_epochs_whatever_happens(ops in proptest::collection::vec(op(), 1..60)) {
            let mut now = Instant::now();
            let mut book = FenceBook::new(LEASE, 0);
            let mut granted: Vec<(u64, u64)> = Vec::new();
            for op in ops {
                match op {
                    Op::Claim(s) => {
                        if let ClaimAnswer::Granted { epoch } = book.claim(s, "r", now) {
                            match granted.last() {
                                Some(&(session, last)) if session == s && last == epoch => {}
                                Some(&(_, last)) => prop_assert!(epoch > last),
                                None => prop_assert_eq!(epoch, 1),
                            }
                            granted.push((s, epoch));
                        }
                    }
                    Op::Heartbeat(s, e) => { book.heartbeat(s, Some(e), now); }
                    Op::Command(s, e) => {
                        if book.check_command(s, Some(e), now) == CommandCheck::Current {
                            let &(holder, epoch) = granted.last().expect("a grant");
                            prop_assert_eq!((holder, epoch), (s, e));
                        }
                    }
                    Op::Release(s) => { book.release(s); }
                    Op::Wait(ms) => now += Duration::from_millis(ms),
                }
                prop_assert_eq!(book.epoch(), granted.last().map_or(0, |g| g.1));
            }
        }
    }
}

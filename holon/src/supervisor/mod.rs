//! A small supervisor after Erlang/OTP's: child specs started in order and stopped in
//! reverse, the restart strategies `one_for_one`, `one_for_all` and `rest_for_one`, and a
//! restart intensity (at most `max_restarts` restarts within `period`; past it the
//! supervisor stops every child and returns an error, so the process exits non-zero and
//! its launcher or service manager restarts it).
//!
//! Each child has a restart type ([`RestartType`], permanent unless told otherwise): a
//! permanent child that returns while the supervisor runs counts as failed and is
//! restarted; a transient one that returns `Ok` is done and stays stopped. Restarts count
//! against the intensity ([`crate::restart`], the one restart policy of the project).
//!
//! What to do when a child ends is decided by the one supervision [`machine`] (the same
//! machine decides for the order-node's order tasks and `cell up`'s processes); this
//! module is its executor for tasks: it starts a child's future, cancels and aborts it,
//! and waits. Each child gets its own [`CancellationToken`] and must return soon after it
//! is cancelled; one that does not return within its `shutdown_timeout` is aborted.

pub mod machine;

use std::collections::VecDeque;
use std::fmt;
use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use tokio::task::{AbortHandle, Id, JoinSet};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

use tracing::{error, info, warn};

pub use crate::restart::{Intensity, RestartType};
pub use machine::{Action, Event, GaveUp, Machine, Scope, Strategy};

/// How long an aborted child is waited for (an abort takes effect at its next await).
const ABORTED_WITHIN: Duration = Duration::from_secs(1);

/// What a child returns when it fails.
pub type ChildError = Box<dyn std::error::Error + Send + Sync>;

/// A running child: the future its start function returned.
pub type ChildFuture = Pin<Box<dyn Future<Output = Result<(), ChildError>> + Send>>;

type StartFn = Arc<dyn Fn(CancellationToken) -> ChildFuture + Send + Sync>;

/// How one child is started (again).
#[derive(Clone)]
pub struct ChildSpec {
    /// The component's name in logs and errors.
    name: String,
    /// Starts it (again).
    start: StartFn,
    /// How long it has to return once cancelled before it is aborted.
    shutdown_timeout: Duration,
    /// When it is restarted.
    restart: RestartType,
}

impl ChildSpec {
    /// `start` is called with the child's cancellation token every time the child (re)starts.
    pub fn new<F, Fut>(name: impl Into<String>, start: F) -> ChildSpec
    where
        F: Fn(CancellationToken) -> Fut + Send + Sync + 'static,
        Fut: Future<Output = Result<(), ChildError>> + Send + 'static,
    {
        ChildSpec {
            name: name.into(),
            start: Arc::new(move |token| Box::pin(start(token))),
            shutdown_timeout: Duration::from_secs(5),
            restart: RestartType::Permanent,
        }
    }

    /// When the child is restarted (permanent by default).
    pub fn restart(mut self, restart: RestartType) -> ChildSpec {
        self.restart = restart;
        self
    }

    /// How long it has to return once cancelled before it is aborted (5 s by default).
    pub fn shutdown_timeout(mut self, timeout: Duration) -> ChildSpec {
        self.shutdown_timeout = timeout;
        self
    }

    /// The component's name in logs and errors.
    pub fn name(&self) -> &str {
        &self.name
    }
}

impl fmt::Debug for ChildSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ChildSpec")
            .field("name", &self.name)
            .finish()
    }
}

/// Why a supervisor ended other than by its shutdown.
#[derive(Debug, thiserror::Error)]
pub enum SupervisorError {
    /// Its children failed more often than its intensity allows.
    #[error("restart intensity exceeded: more than {max_restarts} restarts within {period:?} (last failure: {last_child}: {last_failure})")]
    IntensityExceeded {
        /// The intensity's restarts.
        max_restarts: u32,
        /// The intensity's period.
        period: Duration,
        /// The child whose failure was one too many.
        last_child: String,
        /// Why it failed.
        last_failure: String,
    },
}

/// The message a panic carried (`panic!("...")`), for logs.
pub fn panic_message(payload: Box<dyn std::any::Any + Send>) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into())
}

/// A child's running task.
struct Running {
    /// Cancelled to ask it to return.
    token: CancellationToken,
    /// Aborts it when it does not.
    abort: AbortHandle,
}

/// The supervisor of one holon's components.
pub struct Supervisor {
    /// Its name in logs.
    name: String,
    /// Which children a failure restarts (`simple_one_for_one` is `one_for_one` here:
    /// the children are static).
    strategy: Strategy,
    /// At most so many restarts within a period, of all children together.
    intensity: Intensity,
    /// The children, in the order they start.
    children: Vec<ChildSpec>,
}

impl Supervisor {
    /// A supervisor without children yet.
    pub fn new(name: impl Into<String>, strategy: Strategy, intensity: Intensity) -> Supervisor {
        Supervisor {
            name: name.into(),
            strategy,
            intensity,
            children: Vec::new(),
        }
    }

    /// Adds a child; children start in the order they are added.
    pub fn child(mut self, spec: ChildSpec) -> Supervisor {
        self.children.push(spec);
        self
    }

    /// Starts the children in order and supervises them until `shutdown` is cancelled
    /// (then stops them in reverse order and returns `Ok`) or the restart intensity is
    /// exceeded (then stops them likewise and returns the error).
    pub async fn run(self, shutdown: CancellationToken) -> Result<(), SupervisorError> {
        let mut machine = Machine::new(self.strategy, self.intensity);
        let mut state = State {
            supervisor: &self,
            set: JoinSet::new(),
            running: (0..self.children.len()).map(|_| None).collect(),
            exited: VecDeque::new(),
        };
        for (index, spec) in self.children.iter().enumerate() {
            let added = Event::Added {
                child: index,
                restart: spec.restart,
            };
            for action in machine.handle(added, Instant::now()) {
                if let Action::Start(index) = action {
                    state.start(index);
                }
            }
        }
        loop {
            let (index, exit) = match state.exited.pop_front() {
                Some(exit) => exit,
                None => tokio::select! {
                    _ = shutdown.cancelled() => {
                        state.stop_all().await;
                        info!(supervisor = %self.name, "all components stopped");
                        return Ok(());
                    }
                    joined = state.set.join_next_with_id() => match joined {
                        Some(joined) => match state.record_exit(joined) {
                            Some(exit) => exit,
                            None => continue,
                        },
                        None => {
                            // No children at all: wait for shutdown.
                            shutdown.cancelled().await;
                            return Ok(());
                        }
                    },
                },
            };
            let spec = &self.children[index];
            let exited = Event::Exited {
                child: index,
                normally: exit.normally,
                why: exit.why.clone(),
            };
            let actions = machine.handle(exited, Instant::now());
            if !matches!(actions.first(), Some(Action::Done(_)) | None) {
                error!(supervisor = %self.name, component = %spec.name, failure = %exit.why, "component failed");
            }
            let mut gave_up = None;
            for action in actions {
                match action {
                    Action::Done(_) => {
                        info!(supervisor = %self.name, component = %spec.name, restart = %spec.restart, how = %exit.why, "component ended; not restarted");
                    }
                    Action::GiveUp { error, .. } => {
                        error!(supervisor = %self.name, component = %spec.name, max_restarts = error.max_restarts, period = ?error.period, "restart intensity exceeded; stopping");
                        gave_up = Some(SupervisorError::IntensityExceeded {
                            max_restarts: error.max_restarts,
                            period: error.period,
                            last_child: spec.name.clone(),
                            last_failure: error.failure,
                        });
                    }
                    Action::Stop(children) => {
                        state.stop(&children).await;
                        // Exits collected while stopping of children the machine has
                        // decided on already (they are restarted below) are moot.
                        state.exited.retain(|(i, _)| !children.contains(i));
                    }
                    Action::Start(i) | Action::RestartAfter(i, _) => {
                        // No backoff here: `RestartAfter` is not decided, and would be
                        // a start as well.
                        warn!(supervisor = %self.name, component = %self.children[i].name, strategy = ?self.strategy, "restarting component");
                        state.start(i);
                    }
                }
            }
            if let Some(error) = gave_up {
                // Anything that ended while the others were stopped ends with them.
                state.stop_all().await;
                return Err(error);
            }
        }
    }
}

/// The running children of a supervisor, and the exits it has yet to decide on.
struct State<'a> {
    /// The children's specs.
    supervisor: &'a Supervisor,
    /// The children's tasks.
    set: JoinSet<Result<(), ChildError>>,
    /// Each child's task while it runs, by index.
    running: Vec<Option<Running>>,
    /// Children that exited and still await the machine's decision.
    exited: VecDeque<(usize, Exit)>,
}

/// How a child ended.
struct Exit {
    /// It returned `Ok` (rather than an error, a panic or an abort).
    normally: bool,
    /// For the log.
    why: String,
}

impl State<'_> {
    fn start(&mut self, index: usize) {
        let spec = &self.supervisor.children[index];
        let token = CancellationToken::new();
        let abort = self.set.spawn((spec.start)(token.clone()));
        info!(supervisor = %self.supervisor.name, component = %spec.name, "component started");
        self.running[index] = Some(Running { token, abort });
    }

    fn index_of(&self, id: Id) -> Option<usize> {
        self.running
            .iter()
            .position(|r| r.as_ref().is_some_and(|r| r.abort.id() == id))
    }

    /// Marks the child of a joined task as exited; returns its index and why it ended.
    fn record_exit(
        &mut self,
        joined: Result<(Id, Result<(), ChildError>), tokio::task::JoinError>,
    ) -> Option<(usize, Exit)> {
        let (id, normally, why) = match joined {
            Ok((id, Ok(()))) => (id, true, "returned while the holon runs".to_string()),
            Ok((id, Err(e))) => (id, false, e.to_string()),
            Err(e) if e.is_panic() => {
                let id = e.id();
                let why = format!("panicked: {}", panic_message(e.into_panic()));
                (id, false, why)
            }
            Err(e) => (e.id(), false, "aborted".to_string()),
        };
        let index = self.index_of(id)?;
        self.running[index] = None;
        Some((index, Exit { normally, why }))
    }

    /// Stops every running child, last first.
    async fn stop_all(&mut self) {
        let all: Vec<usize> = (0..self.running.len()).rev().collect();
        self.stop(&all).await;
    }

    /// Stops these children, in this order, each within its timeout (those not running
    /// are passed over).
    async fn stop(&mut self, children: &[usize]) {
        for &index in children {
            let Some(running) = self.running[index].take() else {
                continue;
            };
            let spec = &self.supervisor.children[index];
            running.token.cancel();
            let id = running.abort.id();
            let mut deadline = Instant::now() + spec.shutdown_timeout;
            let mut aborted = false;
            loop {
                match tokio::time::timeout_at(deadline, self.set.join_next_with_id()).await {
                    Ok(Some(joined)) => {
                        let joined_id = match &joined {
                            Ok((joined_id, _)) => *joined_id,
                            Err(e) => e.id(),
                        };
                        if joined_id == id {
                            if !aborted {
                                info!(supervisor = %self.supervisor.name, component = %spec.name, "component stopped");
                            }
                            break;
                        }
                        // Another child ended meanwhile: its exit is handled afterwards.
                        if let Some(exit) = self.record_exit(joined) {
                            self.exited.push_back(exit);
                        }
                    }
                    Ok(None) => break,
                    Err(_) if !aborted => {
                        warn!(supervisor = %self.supervisor.name, component = %spec.name, timeout = ?spec.shutdown_timeout, "component did not stop in time; aborted");
                        running.abort.abort();
                        // Waited for, so that what it holds (a journal, a socket) is
                        // let go of when the supervisor returns.
                        aborted = true;
                        deadline = Instant::now() + ABORTED_WITHIN;
                    }
                    Err(_) => {
                        error!(supervisor = %self.supervisor.name, component = %spec.name, within = ?ABORTED_WITHIN, "an aborted component has not ended (blocked outside an await?); it ends with the process");
                        break;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;
    use tokio::sync::mpsc;

    /// A child that logs "start name" / "stop name" and fails when told to.
    fn child(
        name: &'static str,
        log: Arc<Mutex<Vec<String>>>,
        fail: Arc<tokio::sync::Mutex<mpsc::UnboundedReceiver<()>>>,
    ) -> ChildSpec {
        ChildSpec::new(name, move |token: CancellationToken| {
            let log = log.clone();
            let fail = fail.clone();
            async move {
                log.lock().unwrap().push(format!("start {name}"));
                let mut fail = fail.lock().await;
                tokio::select! {
                    _ = token.cancelled() => {
                        log.lock().unwrap().push(format!("stop {name}"));
                        Ok(())
                    }
                    _ = fail.recv() => Err(format!("{name} told to fail").into()),
                }
            }
        })
    }

    struct Harness {
        log: Arc<Mutex<Vec<String>>>,
        fail: Vec<mpsc::UnboundedSender<()>>,
        shutdown: CancellationToken,
        task: tokio::task::JoinHandle<Result<(), SupervisorError>>,
    }

    fn start(strategy: Strategy, intensity: Intensity) -> Harness {
        let log = Arc::new(Mutex::new(Vec::new()));
        let mut supervisor = Supervisor::new("test", strategy, intensity);
        let mut fail = Vec::new();
        for name in ["a", "b", "c"] {
            let (tx, rx) = mpsc::unbounded_channel();
            fail.push(tx);
            supervisor = supervisor.child(child(
                name,
                log.clone(),
                Arc::new(tokio::sync::Mutex::new(rx)),
            ));
        }
        let shutdown = CancellationToken::new();
        let task = tokio::spawn(supervisor.run(shutdown.clone()));
        Harness {
            log,
            fail,
            shutdown,
            task,
        }
    }

    impl Harness {
        async fn settle(&self, entries: usize) -> Vec<String> {
            for _ in 0..200 {
                if self.log.lock().unwrap().len() >= entries {
                    break;
                }
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
            self.log.lock().unwrap().drain(..).collect()
        }
    }

    fn strings(items: &[&str]) -> Vec<String> {
        items.iter().map(|s| s.to_string()).collect()
    }

    #[tokio::test]
    async fn starts_in_order_and_stops_in_reverse() {
        let mut h = start(Strategy::OneForOne, Intensity::default());
        assert_eq!(
            h.settle(3).await,
            strings(&["start a", "start b", "start c"])
        );
        h.shutdown.cancel();
        (&mut h.task).await.unwrap().unwrap();
        assert_eq!(h.settle(3).await, strings(&["stop c", "stop b", "stop a"]));
    }

    #[tokio::test]
    async fn one_for_one_restarts_only_the_failed_child() {
        let h = start(Strategy::OneForOne, Intensity::default());
        h.settle(3).await;
        h.fail[1].send(()).unwrap();
        assert_eq!(h.settle(1).await, strings(&["start b"]));
    }

    #[tokio::test]
    async fn one_for_all_restarts_every_child() {
        let h = start(Strategy::OneForAll, Intensity::default());
        h.settle(3).await;
        h.fail[1].send(()).unwrap();
        assert_eq!(
            h.settle(5).await,
            strings(&["stop c", "stop a", "start a", "start b", "start c"])
        );
    }

    #[tokio::test]
    async fn rest_for_one_restarts_the_failed_child_and_those_after_it() {
        let h = start(Strategy::RestForOne, Intensity::default());
        h.settle(3).await;
        h.fail[1].send(()).unwrap();
        assert_eq!(
            h.settle(3).await,
            strings(&["stop c", "start b", "start c"])
        );
        h.fail[0].send(()).unwrap();
        assert_eq!(
            h.settle(5).await,
            strings(&["stop c", "stop b", "start a", "start b", "start c"])
        );
    }

    #[tokio::test]
    async fn exceeding_the_intensity_stops_everything_with_an_error() {
        let intensity = Intensity {
            max_restarts: 2,
            period: Duration::from_secs(60),
        };
        let h = start(Strategy::OneForOne, intensity);
        h.settle(3).await;
        for _ in 0..2 {
            h.fail[2].send(()).unwrap();
            assert_eq!(h.settle(1).await, strings(&["start c"]));
        }
        h.fail[2].send(()).unwrap();
        let result = tokio::time::timeout(Duration::from_secs(5), h.task)
            .await
            .unwrap()
            .unwrap();
        assert!(matches!(
            result,
            Err(SupervisorError::IntensityExceeded {
                max_restarts: 2,
                ..
            })
        ));
        assert_eq!(
            h.log.lock().unwrap().clone(),
            strings(&["stop b", "stop a"])
        );
    }

    #[tokio::test]
    async fn restarts_outside_the_period_are_forgotten() {
        let intensity = Intensity {
            max_restarts: 1,
            period: Duration::from_millis(100),
        };
        let h = start(Strategy::OneForOne, intensity);
        h.settle(3).await;
        for _ in 0..3 {
            h.fail[0].send(()).unwrap();
            assert_eq!(h.settle(1).await, strings(&["start a"]));
            tokio::time::sleep(Duration::from_millis(150)).await;
        }
        assert!(!h.task.is_finished());
    }

    #[tokio::test]
    async fn a_panicking_child_is_restarted() {
        let count = Arc::new(Mutex::new(0));
        let spec = ChildSpec::new("panicky", {
            let count = count.clone();
            move |token: CancellationToken| {
                let count = count.clone();
                async move {
                    let n = {
                        let mut c = count.lock().unwrap();
                        *c += 1;
                        *c
                    };
                    if n == 1 {
                        panic!("first run panics");
                    }
                    token.cancelled().await;
                    Ok(())
                }
            }
        });
        let shutdown = CancellationToken::new();
        let task = tokio::spawn(
            Supervisor::new("t", Strategy::OneForOne, Intensity::default())
                .child(spec)
                .run(shutdown.clone()),
        );
        for _ in 0..100 {
            if *count.lock().unwrap() == 2 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        assert_eq!(*count.lock().unwrap(), 2);
        shutdown.cancel();
        task.await.unwrap().unwrap();
    }

    #[tokio::test]
    async fn a_child_that_ignores_cancellation_is_aborted() {
        let spec = ChildSpec::new("stubborn", |_token: CancellationToken| async {
            std::future::pending::<()>().await;
            Ok(())
        })
        .shutdown_timeout(Duration::from_millis(50));
        let shutdown = CancellationToken::new();
        let task = tokio::spawn(
            Supervisor::new("t", Strategy::OneForOne, Intensity::default())
                .child(spec)
                .run(shutdown.clone()),
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
        shutdown.cancel();
        tokio::time::timeout(Duration::from_secs(2), task)
            .await
            .unwrap()
            .unwrap()
            .unwrap();
    }

    /// A child whose n-th run (1-based) fails for n in `failing`, ends normally
    /// otherwise; counts its runs.
    fn counted(name: &'static str, runs: Arc<Mutex<u32>>, failing: &'static [u32]) -> ChildSpec {
        ChildSpec::new(name, move |_token: CancellationToken| {
            let runs = runs.clone();
            async move {
                let n = {
                    let mut r = runs.lock().unwrap();
                    *r += 1;
                    *r
                };
                if failing.contains(&n) {
                    Err(format!("run {n} fails").into())
                } else {
                    Ok(())
                }
            }
        })
    }

    #[tokio::test]
    async fn a_transient_child_is_restarted_after_a_failure_not_after_it_is_done() {
        let runs = Arc::new(Mutex::new(0));
        let spec = counted("transient", runs.clone(), &[1]).restart(RestartType::Transient);
        let shutdown = CancellationToken::new();
        let task = tokio::spawn(
            Supervisor::new("t", Strategy::OneForOne, Intensity::default())
                .child(spec)
                .run(shutdown.clone()),
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
        assert_eq!(
            *runs.lock().unwrap(),
            2,
            "failed once, restarted, then done"
        );
        assert!(
            !task.is_finished(),
            "a done child does not stop its supervisor"
        );
        shutdown.cancel();
        task.await.unwrap().unwrap();
    }

    #[tokio::test]
    async fn a_temporary_child_is_never_restarted_and_a_permanent_one_always() {
        let temporary = Arc::new(Mutex::new(0));
        let permanent = Arc::new(Mutex::new(0));
        let shutdown = CancellationToken::new();
        let task = tokio::spawn(
            Supervisor::new(
                "t",
                Strategy::OneForOne,
                Intensity {
                    max_restarts: 3,
                    period: Duration::from_secs(10),
                },
            )
            .child(counted("temporary", temporary.clone(), &[1]).restart(RestartType::Temporary))
            .child(counted("permanent", permanent.clone(), &[]))
            .run(shutdown.clone()),
        );
        // The permanent child ends normally every run: restarted until the intensity
        // (3 restarts) is exceeded on its fourth end.
        let result = tokio::time::timeout(Duration::from_secs(2), task)
            .await
            .unwrap()
            .unwrap();
        assert!(
            matches!(result, Err(SupervisorError::IntensityExceeded { .. })),
            "{result:?}"
        );
        assert_eq!(*temporary.lock().unwrap(), 1);
        assert_eq!(*permanent.lock().unwrap(), 4);
    }
}

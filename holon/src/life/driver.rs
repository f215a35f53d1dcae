//! The one driver of a holon process's life ([`run`]), after OTP's behaviours: the
//! driver owns the order (open, claim, start, announce, serve, answer successors, hand
//! over or stop, close), a holon supplies what is its own ([`Behaviour`] and its
//! [`Work`]), and who may serve is one of three [`Leadership`] strategies: the name's
//! liveliness claim ([`LivelinessClaim`], here), a resource's controller fence
//! (`holon-node/src/node/standby.rs`) and an order-node's etcd leader key
//! (`order-node/src/standby.rs`). Every move follows [`super::machine::TRANSITIONS`].

use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::machine::{Event, Machine};
use super::{close, Life, LifeError};
use crate::presence::Claim;
use crate::session::ZenohSettings;
use crate::takeover::{self, Answer, Listener, NoSuccessor, Offer, Request, StandInEnd, TakenOver};

/// When a request refused during a hand-over is to be asked again (the
/// `retry_after_ms` of every stand-in's `unavailable`).
pub const HANDOVER_RETRY: Duration = Duration::from_millis(100);

/// Who a process is and how it opens its session.
pub struct Process<'a> {
    /// Its name, presence key, release, `--take-over` and data directory.
    pub life: Life,
    /// Its session's settings.
    pub zenoh: &'a ZenohSettings,
    /// The TLS identity it opens the session as (`<role>.<name>`).
    pub tls_identity: String,
}

/// What a holon's work starts with.
pub struct Start<G> {
    /// The open session.
    pub session: zenoh::Session,
    /// True when a predecessor released the name to this process just now (its
    /// journal's bookings are a hand-over, not a restart's).
    pub handed_over: bool,
    /// What the leadership gave (a fence's controller handle, an etcd journal).
    pub grant: G,
}

/// What the holon's work produced next.
pub enum Next<E, Err> {
    /// One of its own events, for [`Work::handle`].
    Event(E),
    /// Its work ended on its own (a supervisor gave up, a mailbox closed).
    Ended(Result<(), Err>),
}

/// How the holon leaves serving; its [`Work`] is told so.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Leaving {
    /// Shutdown (SIGTERM): work handed back, then stopped.
    Stopping,
    /// A successor takes over: the work finished what it must and stops.
    HandingOver,
    /// The leadership was lost: why.
    Deposed(String),
    /// The work ended on its own.
    WorkEnded,
}

/// How a leadership's hold on a started holon went.
pub enum Held<E> {
    /// It holds: the holon is announced.
    Held,
    /// Told to stop before it held.
    Stopped,
    /// The work ended on its own before it held.
    Ended(Result<(), E>),
}

/// What answers for the holon between its hand-over and its successor's start.
#[derive(Clone)]
pub struct StandInSpec {
    /// The keys, each with whether its queryable is `complete`.
    pub keys: Vec<(String, bool)>,
    /// The answer to every query there.
    pub answer: Answer,
}

/// A holon's own part of its life: what it starts. (Async functions in these traits:
/// the driver runs on the process's own `block_on`, so its futures need not be `Send`.)
#[allow(async_fn_in_trait)]
pub trait Behaviour {
    /// What the leadership gives the holon to start with.
    type Grant;
    /// The holon's work once started.
    type Work: Work<Error = Self::Error>;
    /// Why the holon's process fails.
    type Error: From<LifeError> + std::fmt::Display;

    /// Right after the session opened, before the leadership: what must run from the
    /// start whoever serves (an order-node follows the resources' presence).
    async fn opened(&mut self, _session: &zenoh::Session) -> Result<(), Self::Error> {
        Ok(())
    }

    /// Starts the work: its components, queryables, journal.
    async fn start(&mut self, start: Start<Self::Grant>) -> Result<Self::Work, Self::Error>;
}

/// A started holon's work, driven by [`run`] until it leaves.
#[allow(async_fn_in_trait)]
pub trait Work {
    /// One of its own events.
    type Event;
    /// Why it fails.
    type Error: std::fmt::Display;

    /// Waits until the work can be announced (its components serve).
    async fn ready(&mut self) -> Result<(), Self::Error> {
        Ok(())
    }

    /// Announced: what it begins only once the cell sees its token (an order-node
    /// resumes its orders).
    async fn serving(&mut self) {}

    /// Its next event. Cancel-safe: a successor or a shutdown may come first.
    async fn next(&mut self) -> Next<Self::Event, Self::Error>;

    /// Handles one event.
    async fn handle(&mut self, event: Self::Event);

    /// Why it cannot hand over to `request` now; `None` when it can.
    fn refusal(&self, _request: &Request) -> Option<String> {
        None
    }

    /// Finishes what it must before a hand-over, within `wait`; an error says why it
    /// could not (it has undone the preparation and serves on).
    async fn prepare(&mut self, _wait: Duration) -> Result<(), String> {
        Ok(())
    }

    /// What it does while its token is still declared, before it leaves `how`.
    async fn leave(&mut self, _how: &Leaving) {}

    /// Its stand-in while it is handed over.
    fn stand_in(&self) -> StandInSpec;

    /// Stops its work; its journal closes when it is dropped.
    async fn stop(self, how: &Leaving) -> Result<(), Self::Error>;
}

/// Who may serve the name: how it is won, held, lost and given up.
#[allow(async_fn_in_trait)]
pub trait Leadership<B: Behaviour> {
    /// Before the work starts: the claim or the campaign. `None` when told to stop.
    async fn win(
        &mut self,
        life: &Life,
        session: &zenoh::Session,
        shutdown: &CancellationToken,
    ) -> Result<Option<B::Grant>, B::Error>;

    /// Once the work runs, before it is announced.
    async fn hold(
        &mut self,
        _work: &mut B::Work,
        _shutdown: &CancellationToken,
    ) -> Result<Held<B::Error>, B::Error> {
        Ok(Held::Held)
    }

    /// Whether the holon listens for successors while it serves.
    fn takes_successors(&self) -> bool {
        true
    }

    /// Why no successor may take over under this leadership; `None` when one may.
    fn refusal(&self) -> Option<String> {
        None
    }

    /// The holon is announced (a report, a log line).
    async fn serving(&mut self, _life: &Life) {}

    /// Waits until the leadership is lost; why. Cancel-safe.
    async fn lost(&mut self) -> String {
        std::future::pending().await
    }

    /// The hand-over: the name is let go of, after the token.
    fn let_go(&mut self) {}

    /// After a stop: give the leadership up.
    async fn resign(&mut self) {}

    /// Deposed, token withdrawn: `Ok` to claim again once the work stopped, else the
    /// error the process ends with.
    async fn deposed(&mut self, _why: &str) -> Result<(), B::Error> {
        Ok(())
    }
}

/// The default leadership: the name's liveliness claim (a twin is refused before
/// anything is answered), kept while the holon serves.
#[derive(Default)]
pub struct LivelinessClaim {
    /// The claim, while held.
    claim: Option<Claim>,
}

impl<B: Behaviour> Leadership<B> for LivelinessClaim
where
    B::Grant: Default,
{
    async fn win(
        &mut self,
        life: &Life,
        session: &zenoh::Session,
        _shutdown: &CancellationToken,
    ) -> Result<Option<B::Grant>, B::Error> {
        self.claim = Some(life.claim(session).await?);
        Ok(Some(B::Grant::default()))
    }

    fn let_go(&mut self) {
        self.claim = None;
    }
}

/// Why the serving loop ended.
enum Ending<E> {
    /// Shutdown.
    Stopping,
    /// A successor takes over: its offer.
    HandingOver(Box<Offer>),
    /// The leadership was lost: why.
    Deposed(String),
    /// The work ended on its own.
    WorkEnded(Result<(), E>),
}

/// Runs a holon process's whole life: opens its session as its identity (taking over
/// from a predecessor with `--take-over`), wins its `leadership`, starts its work,
/// declares its token and serves until `shutdown`, a successor, a deposition or its
/// work's own end; then hands over, stops or steps down (and, if its leadership says
/// so, claims again), and closes the session within its budget.
pub async fn run<B, L>(
    process: Process<'_>,
    mut behaviour: B,
    mut leadership: L,
    shutdown: CancellationToken,
) -> Result<(), B::Error>
where
    B: Behaviour,
    L: Leadership<B>,
{
    let life = &process.life;
    let mut machine = Machine::new(&life.holder);
    let opened = match life
        .open(process.zenoh, &process.tls_identity, &shutdown)
        .await
    {
        Ok(Some(opened)) => opened,
        Ok(None) => {
            machine.on(Event::Shutdown);
            return Ok(());
        }
        Err(e) => {
            machine.on(Event::Failed);
            return Err(e.into());
        }
    };
    machine.on(Event::Opened);
    let handed_over = matches!(opened.taken_over, Some(TakenOver::From(_)));
    let session = opened.session;
    let driver = Driver {
        life,
        session: &session,
        shutdown: &shutdown,
        machine,
    };
    let ended = driver
        .live(&mut behaviour, &mut leadership, handed_over)
        .await;
    close(&life.holder, session).await;
    ended
}

/// The driver of one process's life, on its open session.
struct Driver<'a> {
    /// Who it is.
    life: &'a Life,
    /// Its session.
    session: &'a zenoh::Session,
    /// SIGTERM / Ctrl-C.
    shutdown: &'a CancellationToken,
    /// Where it is in its life.
    machine: Machine,
}

impl Driver<'_> {
    /// From the open session to the end: rounds of win, start, serve, leave.
    async fn live<B: Behaviour, L: Leadership<B>>(
        mut self,
        behaviour: &mut B,
        leadership: &mut L,
        mut handed_over: bool,
    ) -> Result<(), B::Error> {
        if let Err(e) = behaviour.opened(self.session).await {
            self.machine.on(Event::Failed);
            return Err(e);
        }
        loop {
            let grant = match leadership.win(self.life, self.session, self.shutdown).await {
                Ok(Some(grant)) => grant,
                Ok(None) => {
                    self.machine.on(Event::Shutdown);
                    return Ok(());
                }
                Err(e) => {
                    self.machine.on(Event::Failed);
                    return Err(e);
                }
            };
            self.machine.on(Event::Won);
            let start = Start {
                session: self.session.clone(),
                // Only the first round inherits a predecessor's hand-over.
                handed_over: std::mem::take(&mut handed_over),
                grant,
            };
            let work = match behaviour.start(start).await {
                Ok(work) => work,
                Err(e) => {
                    self.machine.on(Event::Failed);
                    return Err(e);
                }
            };
            self.machine.on(Event::Started);
            match self.round(work, leadership).await {
                Some(ended) => return ended,
                None => continue,
            }
        }
    }

    /// One round with the work started: hold, announce, serve, leave. `None` when the
    /// holon was deposed and its leadership claims again.
    async fn round<B: Behaviour, L: Leadership<B>>(
        &mut self,
        mut work: B::Work,
        leadership: &mut L,
    ) -> Option<Result<(), B::Error>> {
        let held = match leadership.hold(&mut work, self.shutdown).await {
            Ok(Held::Held) => work.ready().await.map(|()| Held::Held),
            other => other,
        };
        let announced = match held {
            Ok(Held::Held) => self
                .life
                .announce(self.session, leadership.takes_successors())
                .await
                .map_err(B::Error::from),
            Ok(Held::Stopped) => {
                self.machine.on(Event::Shutdown);
                return Some(self.stop(work, &Leaving::Stopping, Ok(())).await);
            }
            Ok(Held::Ended(result)) => {
                self.machine.on(Event::WorkEnded);
                return Some(self.stop(work, &Leaving::WorkEnded, result).await);
            }
            Err(e) => Err(e),
        };
        let super::Announced { token, successors } = match announced {
            Ok(announced) => announced,
            Err(e) => {
                self.machine.on(Event::Failed);
                return Some(self.stop(work, &Leaving::WorkEnded, Err(e)).await);
            }
        };
        self.machine.on(Event::Held);
        leadership.serving(self.life).await;
        work.serving().await;
        let mut successors = successors;
        let ending = self.serve(&mut work, leadership, successors.as_mut()).await;
        if let Some(successors) = successors {
            successors.close(self.life.version, refusal(&ending)).await;
        }
        self.leave(work, leadership, token, ending).await
    }

    /// Serves until shutdown, a successor the holon can hand over to, a deposition or
    /// the work's own end.
    async fn serve<B: Behaviour, L: Leadership<B>>(
        &mut self,
        work: &mut B::Work,
        leadership: &mut L,
        mut successors: Option<&mut Listener>,
    ) -> Ending<B::Error> {
        let holon = &self.life.holder;
        loop {
            tokio::select! {
                _ = self.shutdown.cancelled() => return Ending::Stopping,
                why = leadership.lost() => return Ending::Deposed(why),
                offer = next_offer(&mut successors) => {
                    info!(%holon, successor = %offer.request.successor, version = %offer.request.version, "a successor asks to take over");
                    self.machine.on(Event::SuccessorAsks);
                    if let Some(ending) = self.hand_over(work, leadership, offer).await {
                        return ending;
                    }
                }
                next = work.next() => match next {
                    Next::Event(event) => work.handle(event).await,
                    Next::Ended(result) => return Ending::WorkEnded(result),
                },
            }
        }
    }

    /// A successor asks: refused (the holon serves on, `None`), or prepared for.
    async fn hand_over<B: Behaviour, L: Leadership<B>>(
        &mut self,
        work: &mut B::Work,
        leadership: &L,
        offer: Offer,
    ) -> Option<Ending<B::Error>> {
        let holon = &self.life.holder;
        let refused = leadership
            .refusal()
            .or_else(|| work.refusal(&offer.request));
        if let Some(detail) = refused {
            warn!(%holon, %detail, "hand-over refused");
            offer.refuse(self.life.version, detail).await;
            self.machine.on(Event::Refused);
            return None;
        }
        // The successor's wait runs from its request; stopping the work afterwards has
        // its own allowance (takeover::RELEASE_ALLOWANCE).
        let prepared = tokio::select! {
            prepared = work.prepare(offer.remaining()) => prepared,
            _ = self.shutdown.cancelled() => Err("the holon is shutting down".into()),
        };
        match prepared {
            Ok(()) => Some(Ending::HandingOver(Box::new(offer))),
            Err(detail) => {
                warn!(%holon, %detail, "hand-over abandoned; serving on");
                offer.refuse(self.life.version, detail).await;
                if self.shutdown.is_cancelled() {
                    return Some(Ending::Stopping);
                }
                self.machine.on(Event::Refused);
                None
            }
        }
    }

    /// Leaves serving as `ending` says; `None` when deposed and claiming again.
    async fn leave<B: Behaviour, L: Leadership<B>>(
        &mut self,
        mut work: B::Work,
        leadership: &mut L,
        token: zenoh::liveliness::LivelinessToken,
        ending: Ending<B::Error>,
    ) -> Option<Result<(), B::Error>> {
        match ending {
            Ending::Stopping => {
                self.machine.on(Event::Shutdown);
                work.leave(&Leaving::Stopping).await;
                self.withdraw(token).await;
                let stopped = self.stop(work, &Leaving::Stopping, Ok(())).await;
                leadership.resign().await;
                Some(stopped)
            }
            Ending::WorkEnded(result) => {
                self.machine.on(Event::WorkEnded);
                self.withdraw(token).await;
                if result.is_ok() {
                    leadership.resign().await;
                }
                Some(self.stop(work, &Leaving::WorkEnded, result).await)
            }
            Ending::HandingOver(offer) => {
                self.machine.on(Event::Prepared);
                Some(self.let_go(work, leadership, token, *offer).await)
            }
            Ending::Deposed(why) => {
                self.machine.on(Event::Deposed);
                let how = Leaving::Deposed(why.clone());
                work.leave(&how).await;
                self.withdraw(token).await;
                let stopped = work.stop(&how).await;
                let next = leadership.deposed(&why).await;
                match (next, stopped) {
                    (Ok(()), Ok(())) => {
                        self.machine.on(Event::Again);
                        None
                    }
                    (Err(e), _) | (Ok(()), Err(e)) => {
                        self.machine.on(Event::Ended);
                        Some(Err(e))
                    }
                }
            }
        }
    }

    /// The hand-over, once the work finished what it must: the stand-in declared, the
    /// work stopped (its journal closed), the token and the name let go of, the
    /// successor released; then it stands in until the successor serves, for at most
    /// [`takeover::STAND_IN_LIMIT`], or until shutdown. An error when no successor
    /// served: the supervisor starts this process again, on its journal.
    async fn let_go<B: Behaviour, L: Leadership<B>>(
        &mut self,
        mut work: B::Work,
        leadership: &mut L,
        token: zenoh::liveliness::LivelinessToken,
        offer: Offer,
    ) -> Result<(), B::Error> {
        let holon = &self.life.holder;
        let started = Instant::now();
        work.leave(&Leaving::HandingOver).await;
        let spec = work.stand_in();
        let stand_in = match takeover::stand_in(self.session, &spec.keys, spec.answer).await {
            Ok(stand_in) => Some(stand_in),
            Err(e) => {
                warn!(%holon, error = %e, "cannot stand in for the successor: requests in the gap go unanswered");
                None
            }
        };
        if let Err(e) = work.stop(&Leaving::HandingOver).await {
            warn!(%holon, error = %e, "the work did not stop cleanly before the hand-over");
        }
        if let Err(e) = token.undeclare().await {
            warn!(%holon, error = %e, "cannot withdraw the liveliness token; it goes with the session");
        }
        leadership.let_go();
        let successor = offer.request.successor.clone();
        offer.release(self.life.version).await;
        info!(%holon, %successor, released_in_ms = started.elapsed().as_millis() as u64, "handed over: work stopped, journal closed, token withdrawn; standing in until the successor serves");
        let end = takeover::stand_by(self.session, &self.life.presence_key, self.shutdown).await;
        drop(stand_in);
        let gap_ms = started.elapsed().as_millis() as u64;
        match end {
            StandInEnd::Served => {
                self.machine.on(Event::Served);
                info!(%holon, gap_ms, "the successor serves; this process ends");
                Ok(())
            }
            StandInEnd::Shutdown => {
                self.machine.on(Event::Shutdown);
                warn!(%holon, gap_ms, "told to stop while standing in for the successor");
                Ok(())
            }
            StandInEnd::NoSuccessor => {
                self.machine.on(Event::NoSuccessor);
                warn!(%holon, gap_ms, "the successor did not serve within the stand-in limit; this process ends with an error, so that its supervisor starts it again (on its journal, where it left off)");
                Err(LifeError::from(NoSuccessor {
                    successor: successor.to_string(),
                })
                .into())
            }
        }
    }

    /// Withdraws the token: no one books or asks a holon that is going away.
    async fn withdraw(&self, token: zenoh::liveliness::LivelinessToken) {
        if let Err(e) = token.undeclare().await {
            warn!(holon = %self.life.holder, error = %e, "cannot withdraw the liveliness token; it goes with the session");
        }
    }

    /// Stops the work; the process ends with `outcome` (a failed stop is logged when
    /// the outcome is an error already).
    async fn stop<W: Work>(
        &mut self,
        work: W,
        how: &Leaving,
        outcome: Result<(), W::Error>,
    ) -> Result<(), W::Error> {
        let stopped = work.stop(how).await;
        self.machine.on(Event::Left);
        match outcome {
            Ok(()) => stopped,
            Err(e) => {
                if let Err(stop) = stopped {
                    warn!(holon = %self.life.holder, error = %stop, "the work did not stop cleanly after it failed");
                }
                Err(e)
            }
        }
    }
}

/// The next successor's offer, or never without a listener.
async fn next_offer(successors: &mut Option<&mut Listener>) -> Offer {
    match successors {
        Some(listener) => listener.next().await,
        None => std::future::pending().await,
    }
}

/// What a successor that asks once the loop ended is told.
fn refusal<E>(ending: &Ending<E>) -> &'static str {
    match ending {
        Ending::HandingOver(_) => "another successor is taking over already",
        Ending::Deposed(_) => "the holon is deposed",
        Ending::Stopping | Ending::WorkEnded(_) => "the holon is stopping",
    }
}

/// A stand-in's answer for a holon whose requests are plain queries: the error
/// `unavailable` with [`HANDOVER_RETRY`], saying `holder` is being handed over.
pub fn unavailable_answer(holder: &str, message: String) -> Answer {
    let refusal = schemas::ErrorReply::unavailable(message, HANDOVER_RETRY).to_json();
    let holder = holder.to_string();
    std::sync::Arc::new(move |query: &zenoh::query::Query| {
        use zenoh::Wait;
        if let Err(e) = query.reply_err(refusal.clone()).wait() {
            warn!(holon = %holder, error = %e, "cannot answer a request while handed over; the requester asks again after its timeout");
        }
    })
}

//! The line at the stations: the parts of a node's orders that wait in the cell for a
//! place at a station take turns to look for one, per service, oldest first
//! ([`machine`], the rules). A part with the turn runs its proposal round and tries to
//! reserve a place; then the turn passes to the next younger part, so a freed place
//! goes to the part that has waited longest for it, however often younger parts look.
//!
//! One task owns the lines: it takes the orders' requests and the news that a place
//! may have freed (a resource's published places, a resource appearing or becoming
//! ready, and a fallback every [`FALLBACK_SWEEP`]), and tells each order its turn.
//! Fair within a node: parts of another order-node's orders take their own turns.

pub mod machine;

use std::collections::HashMap;
use std::time::Duration;

use schemas::HolonId;
use tokio::sync::{mpsc, oneshot, watch};
use tokio::time::Instant;
use tracing::debug;

use machine::{Action, Event, Lines};

/// How often the parts waiting in line look again when no news came (a resource's
/// publication can be lost, or a place free up without one).
pub const FALLBACK_SWEEP: Duration = Duration::from_secs(2);

/// The orders' handle on the line at the stations.
#[derive(Clone)]
pub struct StationLine {
    /// The task's mailbox. Unbounded so that a ticket dropped with its order's task
    /// leaves the line synchronously; an order has at most one request in it.
    requests: mpsc::UnboundedSender<Request>,
    /// Moves each time a part joins a service's line: a part waiting at a port for
    /// its next station looks again whether a part now waits for the station it holds.
    joined: watch::Receiver<u64>,
}

/// What the task is asked.
enum Request {
    /// An event of the lines; a `Wait` comes with where its answer goes.
    Event(Event, Option<oneshot::Sender<bool>>),
    /// How many parts other than the order's stand in line for the service.
    WaitingFor(String, HolonId, oneshot::Sender<usize>),
}

impl StationLine {
    /// Starts the line's task; it ends when the last handle (and ticket) is dropped.
    /// `freed` and `appeared` move when places free up and resources appear.
    pub fn start(freed: watch::Receiver<u64>, appeared: watch::Receiver<u64>) -> StationLine {
        let (requests, mailbox) = mpsc::unbounded_channel();
        let (joins, joined) = watch::channel(0);
        tokio::spawn(run(mailbox, freed, appeared, joins));
        StationLine { requests, joined }
    }

    /// News of parts joining a line, seen from now: it changes each time a part joins
    /// the line for a station of some service.
    pub fn joins(&self) -> watch::Receiver<u64> {
        let mut joins = self.joined.clone();
        joins.mark_unchanged();
        joins
    }

    /// A ticket for `order`'s part, which looks for a place at a station of `service`
    /// with the order's `priority`: it joins the line when it first asks for a turn,
    /// and leaves when dropped.
    pub fn ticket(&self, order: &HolonId, service: &str, priority: i32) -> Ticket {
        Ticket {
            line: self.clone(),
            order: order.clone(),
            service: service.to_string(),
            priority,
            since: Instant::now(),
            in_line: false,
        }
    }

    /// How many parts of the node's orders other than `order`'s wait in line for a
    /// station of `service` (0 once the line has stopped).
    pub async fn waiting_for(&self, service: &str, order: &HolonId) -> usize {
        let (answer, answered) = oneshot::channel();
        let request = Request::WaitingFor(service.to_string(), order.clone(), answer);
        if self.requests.send(request).is_err() {
            debug!("the station line has stopped");
            return 0;
        }
        answered.await.unwrap_or(0)
    }

    fn send(&self, event: Event, answer: Option<oneshot::Sender<bool>>) {
        if self.requests.send(Request::Event(event, answer)).is_err() {
            // Only when the node's orders are being dropped: no turn to keep.
            debug!("the station line has stopped");
        }
    }
}

/// An order's place in the line at the stations, for one step.
pub struct Ticket {
    /// The line.
    line: StationLine,
    /// The order.
    order: HolonId,
    /// The service of the step its part is to be brought to a station for.
    service: String,
    /// When the part began to look (its place in line, after its priority).
    since: Instant,
    /// Its order's priority: a part of a higher priority has its turn first.
    priority: i32,
    /// Whether it has asked for a turn (it is then in line until placed or dropped).
    in_line: bool,
}

impl Ticket {
    /// Whether the part stands in line (it has asked for a turn before).
    pub fn in_line(&self) -> bool {
        self.in_line
    }

    /// The turn if the part can have it at once (no older part waits for a station of
    /// its service); else false, and it keeps its place in line.
    pub async fn turn_now(&mut self) -> bool {
        self.ask(true).await
    }

    /// Waits for the part's turn (cancel-safe: dropping it keeps the place in line).
    pub async fn turn(&mut self) {
        while !self.ask(false).await {}
    }

    /// The part with the turn has looked: `placed`, it has a place and leaves the line.
    pub fn tried(&mut self, placed: bool) {
        let order = self.order.clone();
        self.line.send(Event::Tried { order, placed }, None);
        if placed {
            self.in_line = false;
            self.since = Instant::now();
        }
    }

    async fn ask(&mut self, now_only: bool) -> bool {
        self.in_line = true;
        let (answer, answered) = oneshot::channel();
        let event = Event::Wait {
            order: self.order.clone(),
            service: self.service.clone(),
            since: self.since,
            priority: self.priority,
            now_only,
        };
        self.line.send(event, Some(answer));
        // No answer only when the line has stopped (the node's orders are being
        // dropped): the part looks as if alone.
        answered.await.unwrap_or(true)
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if self.in_line {
            let order = self.order.clone();
            self.line.send(Event::Left { order }, None);
        }
    }
}

/// The line's task: the one owner of the lines.
async fn run(
    mut mailbox: mpsc::UnboundedReceiver<Request>,
    mut freed: watch::Receiver<u64>,
    mut appeared: watch::Receiver<u64>,
    joins: watch::Sender<u64>,
) {
    let mut lines = Lines::default();
    // Where each waiting order's answer goes.
    let mut answers: HashMap<HolonId, oneshot::Sender<bool>> = HashMap::new();
    let mut fallback = tokio::time::interval(FALLBACK_SWEEP);
    fallback.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        let event = tokio::select! {
            request = mailbox.recv() => match request {
                Some(Request::Event(event, answer)) => {
                    if let (Event::Wait { order, .. }, Some(answer)) = (&event, answer) {
                        answers.insert(order.clone(), answer);
                    }
                    event
                }
                Some(Request::WaitingFor(service, order, answer)) => {
                    if answer.send(lines.waiting_for(&service, &order)).is_err() {
                        debug!(holon = %order, "the count of parts in line was not waited for");
                    }
                    continue;
                }
                None => return,
            },
            Ok(()) = freed.changed() => Event::Room,
            Ok(()) = appeared.changed() => Event::Room,
            _ = fallback.tick(), if lines.any_waiting() => Event::Room,
        };
        let joining = match &event {
            Event::Wait { order, service, .. } => !lines.in_line_for(order, service),
            _ => false,
        };
        let mut actions = lines.handle(event);
        if joining {
            joins.send_modify(|n| *n += 1);
        }
        while let Some(action) = actions.pop() {
            let (order, turn) = match action {
                Action::Turn(order) => (order, true),
                Action::NotNow(order) => (order, false),
            };
            let delivered = answers.remove(&order).is_some_and(|a| a.send(turn).is_ok());
            if turn && !delivered {
                // Its order stopped waiting (cancelled, or its task ended): the turn
                // goes on at once, or it would hold the line until its ticket is dropped.
                debug!(holon = %order, "a turn nobody waited for: passed on");
                actions.extend(lines.handle(Event::Tried {
                    order,
                    placed: false,
                }));
            }
        }
    }
}

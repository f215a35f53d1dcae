//! Results on their way: each `done` / `failed` is sent to its `reply_to` again and
//! again, with a doubling pause, until the requester acknowledges it.
//!
//! [`Deliveries`] is owned by the communication component, which feeds it new results,
//! wakes it when an attempt is due, and hands it each attempt's end. An acknowledged
//! result is reported to the agenda manager, which removes it from the undelivered.

use std::collections::BTreeMap;
use std::time::Duration;

use holon::Backoff;
use schemas::{HolonId, Service};
use tokio::task::JoinSet;
use tokio::time::Instant;
use tracing::{debug, info, warn};
use zenoh::query::ConsolidationMode;

use crate::config::DeliverySettings;

/// How one attempt ended: acknowledged, not answered, or refused (and why).
type AttemptEnd = (String, Result<bool, String>);

/// A result waiting for its acknowledgement.
struct Delivery {
    /// The `done` / `failed` message.
    message: Service,
    /// When the next attempt may go out.
    next_attempt: Instant,
    /// The pauses between attempts.
    backoff: Backoff,
    /// Attempts made so far.
    attempts: u32,
    /// Whether an attempt is out and not yet ended.
    in_flight: bool,
}

/// Every result not yet acknowledged, by `conversation_id`, and the attempts in flight.
pub struct Deliveries {
    holon: HolonId,
    session: zenoh::Session,
    settings: DeliverySettings,
    pending: BTreeMap<String, Delivery>,
    attempts: JoinSet<AttemptEnd>,
    /// Attempts after a result's first, since the process started (a requester away or
    /// slow to acknowledge); published in the state for the dashboard's metrics.
    retries: u64,
}

impl Deliveries {
    pub fn new(holon: HolonId, session: zenoh::Session, settings: DeliverySettings) -> Deliveries {
        Deliveries {
            holon,
            session,
            settings,
            pending: BTreeMap::new(),
            attempts: JoinSet::new(),
            retries: 0,
        }
    }

    /// Takes in every result the agenda says is not acknowledged (a starting component:
    /// a result whose `Deliver` or acknowledgement was lost to a crash goes out again),
    /// and sends what is due.
    pub fn resync(&mut self, undelivered: &[Service]) {
        for message in undelivered {
            self.schedule(message.clone());
        }
        self.send_due();
    }

    /// Adds a result (a repeat of one already pending changes nothing) and sends what is
    /// due: the first attempt goes out at once.
    pub fn add(&mut self, message: Service) {
        self.schedule(message);
        self.send_due();
    }

    fn schedule(&mut self, message: Service) {
        let backoff = Backoff::new(self.settings.retry_initial, self.settings.retry_max);
        self.pending
            .entry(message.conversation_id.clone())
            .or_insert(Delivery {
                message,
                next_attempt: Instant::now(),
                backoff,
                attempts: 0,
                in_flight: false,
            });
    }

    /// Attempts after a result's first, since the process started.
    pub fn retries(&self) -> u64 {
        self.retries
    }

    /// When the next attempt is due, if any is waiting.
    pub fn next_due(&self) -> Option<Instant> {
        self.pending
            .values()
            .filter(|d| !d.in_flight)
            .map(|d| d.next_attempt)
            .min()
    }

    /// Starts an attempt for every result whose time has come.
    pub fn send_due(&mut self) {
        let now = Instant::now();
        let holon = &self.holon;
        for (conversation_id, delivery) in self.pending.iter_mut() {
            if delivery.in_flight || delivery.next_attempt > now {
                continue;
            }
            delivery.in_flight = true;
            delivery.attempts += 1;
            if delivery.attempts > 1 {
                self.retries += 1;
            }
            if repeat_worth_logging(delivery.attempts) {
                info!(%holon, %conversation_id, message_type = %delivery.message.message_type, reply_to = delivery.message.reply_to.as_deref().unwrap_or(""), attempt = delivery.attempts, "sending result");
            } else {
                debug!(%holon, %conversation_id, attempt = delivery.attempts, "sending result again");
            }
            let session = self.session.clone();
            let message = delivery.message.clone();
            let conversation_id = conversation_id.clone();
            let timeout = self.settings.attempt_timeout;
            self.attempts.spawn(async move {
                let acked = attempt(&session, &message, timeout).await;
                (conversation_id, acked)
            });
        }
    }

    /// The next attempt to end (pending forever while none is in flight).
    pub async fn attempt_ended(&mut self) -> Option<AttemptEnd> {
        if self.attempts.is_empty() {
            return std::future::pending().await;
        }
        match self.attempts.join_next().await? {
            Ok(end) => Some(end),
            Err(e) => {
                warn!(holon = %self.holon, error = %e, "a delivery attempt did not end normally; its result is sent again when due");
                None
            }
        }
    }

    /// Takes in how an attempt ended: the `conversation_id` of an acknowledged result
    /// (now removed), or `None` when it is to be sent again after its pause.
    pub fn ended(&mut self, (conversation_id, acked): AttemptEnd) -> Option<String> {
        let holon = &self.holon;
        let delivery = self.pending.get_mut(&conversation_id)?;
        delivery.in_flight = false;
        match acked {
            Ok(true) => {
                info!(%holon, %conversation_id, message_type = %delivery.message.message_type, attempts = delivery.attempts, "result acknowledged");
                self.pending.remove(&conversation_id);
                Some(conversation_id)
            }
            Ok(false) | Err(_) => {
                let pause = delivery.backoff.next_pause();
                delivery.next_attempt = Instant::now() + pause;
                match acked {
                    Err(why) if repeat_worth_logging(delivery.attempts) => {
                        warn!(%holon, %conversation_id, attempt = delivery.attempts, reason = %why, retry_in = ?pause, "result refused; it is sent again until acknowledged");
                    }
                    _ => {
                        debug!(%holon, %conversation_id, retry_in = ?pause, "result not acknowledged yet");
                    }
                }
                None
            }
        }
    }

    /// Stops the attempts in flight; their results are due again at once for the
    /// component's successor (they stay undelivered on the agenda).
    pub async fn shutdown(&mut self) {
        self.attempts.shutdown().await;
        for delivery in self.pending.values_mut() {
            delivery.in_flight = false;
        }
    }
}

/// Whether the `attempt`th try of the same delivery is logged above debug: the first,
/// then every tenth (a requester that stays away does not fill the log).
fn repeat_worth_logging(attempt: u32) -> bool {
    attempt == 1 || attempt.is_multiple_of(10)
}

/// One delivery attempt: true when the requester acknowledged.
async fn attempt(
    session: &zenoh::Session,
    message: &Service,
    timeout: Duration,
) -> Result<bool, String> {
    let key = message.reply_to.as_deref().ok_or("no reply_to")?;
    let mut replies = session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .with(holon::query::replies())
        .await
        .map_err(|e| e.to_string())?;
    while let Some(reply) = replies.recv().await {
        match reply.result() {
            Ok(sample) if sample.key_expr().as_str() != key => {
                warn!(conversation_id = %message.conversation_id, reply_to = key, from = %sample.key_expr(), "an acknowledgement from another key than reply_to is ignored");
            }
            Ok(sample) => match Service::from_json(&sample.payload().to_bytes()) {
                Ok(ack)
                    if ack.conversation_id == message.conversation_id
                        && ack.message_type == message.message_type
                        && ack.result == Some(true) =>
                {
                    return Ok(true)
                }
                Ok(other) => {
                    debug!(conversation_id = %message.conversation_id, ?other, "reply is not an acknowledgement")
                }
                Err(e) => {
                    debug!(conversation_id = %message.conversation_id, error = %e, "undecodable reply to a result")
                }
            },
            Err(err) => {
                let text = err
                    .payload()
                    .try_to_string()
                    .map(|s| s.into_owned())
                    .unwrap_or_default();
                // The requester refused it (malformed, not booked, ...): the caller logs why.
                return Err(format!("refused by the requester: {text}"));
            }
        }
    }
    Ok(false)
}

#[cfg(test)]
mod tests {
    //! The delivery of results against a requester's inbox on a real zenoh session (one
    //! peer, on loopback, that both sends and answers).

    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use schemas::{MessageType, Service};

    use super::*;

    const INBOX: &str = "holarchy/test/inbox/o-1";

    fn settings() -> DeliverySettings {
        DeliverySettings {
            retry_initial: Duration::from_millis(20),
            retry_max: Duration::from_millis(80),
            attempt_timeout: Duration::from_millis(500),
        }
    }

    async fn session() -> zenoh::Session {
        let mut config = zenoh::Config::default();
        for (key, value) in [
            ("mode", "\"peer\""),
            ("scouting/multicast/enabled", "false"),
            ("listen/endpoints", "[\"tcp/127.0.0.1:0\"]"),
        ] {
            config.insert_json5(key, value).unwrap();
        }
        zenoh::open(config).await.unwrap()
    }

    fn done(conversation: &str) -> Service {
        Service::request(
            MessageType::Done,
            "pick_n_place",
            conversation,
            HolonId::order("o-1").unwrap(),
        )
        .with_reply_to(INBOX)
    }

    /// An inbox that refuses the first `refuse` results it gets, then acknowledges (or,
    /// with `wrong`, answers with another conversation); counts what it got.
    async fn inbox(
        session: &zenoh::Session,
        refuse: usize,
        wrong: bool,
    ) -> (Arc<AtomicUsize>, zenoh::query::Queryable<()>) {
        let got = Arc::new(AtomicUsize::new(0));
        let counter = got.clone();
        let queryable = session
            .declare_queryable(INBOX)
            .callback(move |query| {
                let n = counter.fetch_add(1, Ordering::SeqCst);
                let Some(payload) = query.payload() else {
                    return;
                };
                let mut ack = Service::from_json(&payload.to_bytes()).unwrap();
                tokio::spawn(async move {
                    let sent = if n < refuse {
                        query
                            .reply_err(
                                schemas::ErrorReply::new(schemas::ErrorCode::NotBooked, "not yet")
                                    .to_json(),
                            )
                            .await
                    } else {
                        if wrong {
                            ack.conversation_id.push_str("-other");
                        }
                        ack.result = Some(true);
                        query.reply(query.key_expr().clone(), ack.to_json()).await
                    };
                    sent.unwrap();
                });
            })
            .await
            .unwrap();
        (got, queryable)
    }

    /// Runs the deliveries' loop (as the communication component does) until `until`
    /// conversations are acknowledged or `deadline` passes; returns them in order.
    async fn run(deliveries: &mut Deliveries, until: usize, deadline: Duration) -> Vec<String> {
        let mut acked = Vec::new();
        let end = Instant::now() + deadline;
        while acked.len() < until && Instant::now() < end {
            let due = deliveries.next_due().unwrap_or(end).min(end);
            tokio::select! {
                ended = deliveries.attempt_ended() => {
                    if let Some(conversation) = ended.and_then(|e| deliveries.ended(e)) {
                        acked.push(conversation);
                    }
                }
                _ = tokio::time::sleep_until(due) => deliveries.send_due(),
            }
        }
        acked
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_result_is_sent_until_acknowledged() {
        let session = session().await;
        let (got, _inbox) = inbox(&session, 3, false).await;
        let holon = HolonId::resource("robot1").unwrap();
        let mut deliveries = Deliveries::new(holon, session.clone(), settings());
        deliveries.add(done("c1"));
        // A repeat of a pending result changes nothing.
        deliveries.add(done("c1"));
        let acked = run(&mut deliveries, 1, Duration::from_secs(10)).await;
        assert_eq!(acked, vec!["c1".to_string()]);
        assert_eq!(
            got.load(Ordering::SeqCst),
            4,
            "three refusals, then the ack"
        );
        assert_eq!(deliveries.retries(), 3);
        assert_eq!(deliveries.next_due(), None, "nothing left to send");
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_acknowledgement_of_another_conversation_does_not_count() {
        let session = session().await;
        let (got, _inbox) = inbox(&session, 0, true).await;
        let holon = HolonId::resource("robot1").unwrap();
        let mut deliveries = Deliveries::new(holon, session.clone(), settings());
        deliveries.add(done("c1"));
        let acked = run(&mut deliveries, 1, Duration::from_millis(600)).await;
        assert!(acked.is_empty(), "{acked:?}");
        assert!(got.load(Ordering::SeqCst) >= 2, "it was sent again");
        assert!(deliveries.retries() >= 1, "it was counted as a retry");
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_requester_away_is_tried_again_until_it_is_back() {
        let session = session().await;
        let holon = HolonId::resource("robot1").unwrap();
        let mut deliveries = Deliveries::new(holon, session.clone(), settings());
        // Nobody answers on the inbox: each attempt ends unanswered at once.
        deliveries.add(done("c1"));
        let acked = run(&mut deliveries, 1, Duration::from_millis(1000)).await;
        assert!(acked.is_empty());
        let tried = deliveries.retries();
        assert!(tried >= 2, "tried again {tried} times in a second");
        assert_eq!(deliveries.pending["c1"].attempts as u64, tried + 1);
        // The requester comes back: the next attempt is acknowledged.
        let (_, _inbox) = inbox(&session, 0, false).await;
        let acked = run(&mut deliveries, 1, Duration::from_secs(5)).await;
        assert_eq!(acked, vec!["c1".to_string()]);
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn after_a_shutdown_the_undelivered_are_due_again_for_the_successor() {
        let session = session().await;
        let holon = HolonId::resource("robot1").unwrap();
        let mut deliveries = Deliveries::new(holon.clone(), session.clone(), settings());
        deliveries.add(done("c1"));
        deliveries.shutdown().await;
        assert!(deliveries
            .next_due()
            .is_some_and(|due| due <= Instant::now()));
        // A successor takes the undelivered from the agenda and delivers them.
        let (_, _inbox) = inbox(&session, 0, false).await;
        let mut successor = Deliveries::new(holon, session.clone(), settings());
        successor.resync(&[done("c1"), done("c2")]);
        let mut acked = run(&mut successor, 2, Duration::from_secs(5)).await;
        acked.sort();
        assert_eq!(acked, vec!["c1".to_string(), "c2".to_string()]);
        session.close().await.unwrap();
    }
}

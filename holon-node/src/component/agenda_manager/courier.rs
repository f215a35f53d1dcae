//! The attempts to deliver results, carried out for the agenda manager.
//!
//! The agenda manager owns the undelivered results and the machine that schedules their
//! delivery ([`crate::machine::delivery`]); a [`Courier`] holds the attempts it has sent out, each
//! a future owned by the agenda manager's task and polled by its loop (no task, no
//! channel: an attempt never waits on the agenda manager, and the agenda manager never
//! waits on an attempt).

use std::future::Future;
use std::pin::Pin;
use std::time::Duration;

use futures_util::stream::{FuturesUnordered, StreamExt};
use schemas::Service;
use tracing::{debug, warn};
use zenoh::query::ConsolidationMode;

use crate::machine::delivery::AttemptOutcome;

/// An attempt out: it ends with the result's conversation and how it went.
type Attempt = Pin<Box<dyn Future<Output = (String, AttemptOutcome)> + Send>>;

/// The attempts out, sent on one zenoh session.
pub struct Courier {
    /// Where attempts are sent from.
    session: zenoh::Session,
    /// How long an attempt waits for its acknowledgement.
    timeout: Duration,
    /// The attempts not yet ended.
    attempts: FuturesUnordered<Attempt>,
}

impl Courier {
    pub fn new(session: zenoh::Session, timeout: Duration) -> Courier {
        Courier {
            session,
            timeout,
            attempts: FuturesUnordered::new(),
        }
    }

    /// Sends `message` once; its end comes from [`Courier::next_end`].
    pub fn send(&mut self, message: Service) {
        let session = self.session.clone();
        let timeout = self.timeout;
        self.attempts.push(Box::pin(async move {
            let outcome = attempt(&session, &message, timeout).await;
            (message.conversation_id, outcome)
        }));
    }

    /// The next attempt to end (pending for ever while none is out).
    pub async fn next_end(&mut self) -> (String, AttemptOutcome) {
        match self.attempts.next().await {
            Some(end) => end,
            None => std::future::pending().await,
        }
    }
}

/// One delivery attempt to the message's `reply_to` (also a move's one `departed`,
/// [`crate::component::execution`]).
pub(crate) async fn attempt(
    session: &zenoh::Session,
    message: &Service,
    timeout: Duration,
) -> AttemptOutcome {
    let Some(key) = message.reply_to.as_deref() else {
        return AttemptOutcome::Refused("no reply_to".into());
    };
    let replies = session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .with(holon::query::replies())
        .await;
    let mut replies = match replies {
        Ok(replies) => replies,
        Err(e) => return AttemptOutcome::Refused(e.to_string()),
    };
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
                    return AttemptOutcome::Acknowledged
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
                // The requester refused it (malformed, not booked, ...): the owner logs why.
                return AttemptOutcome::Refused(format!("refused by the requester: {text}"));
            }
        }
    }
    AttemptOutcome::Unanswered
}

#[cfg(test)]
mod tests {
    //! The delivery of results against a requester's inbox on a real zenoh session (one
    //! peer, on loopback, that both sends and answers): the machine and the courier run
    //! together as the agenda manager runs them.

    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;

    use schemas::{HolonId, MessageType, Service};
    use tokio::time::Instant;

    use super::*;
    use crate::config::DeliverySettings;
    use crate::machine::delivery::{DeliveryAction, DeliveryEvent, DeliveryMachine};

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

    /// The machine and its courier.
    struct Owner {
        deliveries: DeliveryMachine,
        courier: Courier,
    }

    impl Owner {
        fn new(session: &zenoh::Session) -> Owner {
            let mut owner = Owner {
                deliveries: DeliveryMachine::new(settings(), 0),
                courier: Courier::new(session.clone(), settings().attempt_timeout),
            };
            owner.handle(DeliveryEvent::Serving);
            owner
        }

        /// One event; the acknowledged conversations.
        fn handle(&mut self, event: DeliveryEvent) -> Vec<String> {
            let mut acked = Vec::new();
            for action in self.deliveries.handle(event, Instant::now()) {
                match action {
                    DeliveryAction::Attempt { message, .. } => self.courier.send(message),
                    DeliveryAction::Acknowledged {
                        conversation_id, ..
                    } => acked.push(conversation_id),
                    DeliveryAction::Retry { .. } => {}
                }
            }
            acked
        }

        /// Runs until `until` conversations are acknowledged or `deadline` passes;
        /// returns them in order.
        async fn run(&mut self, until: usize, deadline: Duration) -> Vec<String> {
            let mut acked = Vec::new();
            let end = Instant::now() + deadline;
            while acked.len() < until && Instant::now() < end {
                let due = self.deliveries.next_due().unwrap_or(end).min(end);
                let event = tokio::select! {
                    (conversation_id, outcome) = self.courier.next_end() => DeliveryEvent::AttemptEnded { conversation_id, outcome },
                    _ = tokio::time::sleep_until(due) => DeliveryEvent::Tick,
                };
                acked.extend(self.handle(event));
            }
            acked
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_result_is_sent_until_acknowledged() {
        let session = session().await;
        let (got, _inbox) = inbox(&session, 3, false).await;
        let mut owner = Owner::new(&session);
        owner.handle(DeliveryEvent::Result(done("c1")));
        let acked = owner.run(1, Duration::from_secs(10)).await;
        assert_eq!(acked, vec!["c1".to_string()]);
        assert_eq!(
            got.load(Ordering::SeqCst),
            4,
            "three refusals, then the ack"
        );
        assert_eq!(owner.deliveries.retries(), 3);
        assert_eq!(owner.deliveries.next_due(), None, "nothing left to send");
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_acknowledgement_of_another_conversation_does_not_count() {
        let session = session().await;
        let (got, _inbox) = inbox(&session, 0, true).await;
        let mut owner = Owner::new(&session);
        owner.handle(DeliveryEvent::Result(done("c1")));
        let acked = owner.run(1, Duration::from_millis(600)).await;
        assert!(acked.is_empty(), "{acked:?}");
        assert!(got.load(Ordering::SeqCst) >= 2, "it was sent again");
        assert!(owner.deliveries.retries() >= 1, "it was counted as a retry");
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_requester_away_is_tried_again_until_it_is_back() {
        let session = session().await;
        let mut owner = Owner::new(&session);
        // Nobody answers on the inbox: each attempt ends unanswered at once.
        owner.handle(DeliveryEvent::Result(done("c1")));
        let acked = owner.run(1, Duration::from_millis(1000)).await;
        assert!(acked.is_empty());
        let tried = owner.deliveries.retries();
        assert!(tried >= 2, "tried again {tried} times in a second");
        // The requester comes back: the next attempt is acknowledged.
        let (_, _inbox) = inbox(&session, 0, false).await;
        let acked = owner.run(1, Duration::from_secs(5)).await;
        assert_eq!(acked, vec!["c1".to_string()]);
        session.close().await.unwrap();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_restarted_owner_delivers_what_the_agenda_still_holds() {
        let session = session().await;
        let mut owner = Owner::new(&session);
        owner.handle(DeliveryEvent::Result(done("c1")));
        // The owner dies with its attempt out; its successor starts from the agenda's
        // undelivered results.
        drop(owner);
        let (_, _inbox) = inbox(&session, 0, false).await;
        let mut successor = Owner::new(&session);
        successor.handle(DeliveryEvent::Result(done("c1")));
        successor.handle(DeliveryEvent::Result(done("c2")));
        let mut acked = successor.run(2, Duration::from_secs(5)).await;
        acked.sort();
        assert_eq!(acked, vec!["c1".to_string(), "c2".to_string()]);
        session.close().await.unwrap();
    }
}

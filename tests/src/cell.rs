//! A test cell: a zenoh router and session of its own, and the questions a test asks
//! its holons (states, services, proposals, an order's inbox).

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, bail, Result};
use schemas::{CellKeys, ErrorReply, HolonId, MessageType, Service};
use tokio::sync::mpsc;
use zenoh::query::ConsolidationMode;
use zenoh::sample::SampleKind;

use crate::*;

/// The test's own zenoh session, listening on a unique port that every process joins.
pub struct Cell {
    pub session: zenoh::Session,
    pub keys: CellKeys,
    /// The endpoint processes connect to, e.g. `tcp/127.0.0.1:PORT`.
    pub endpoint: String,
}

impl Cell {
    pub async fn open(cell: &str) -> Result<Cell> {
        // A free port is closed again before zenoh binds it, and another process's
        // outgoing connection may take it in between: then another port, a few times.
        let mut attempts = 0;
        loop {
            let endpoint = format!("tcp/127.0.0.1:{}", free_port());
            let settings = holon::ZenohSettings {
                mode: holon::Mode::Router,
                listen: vec![endpoint.clone()],
                ..holon::ZenohSettings::default()
            };
            match settings.open("router.local", WAIT).await {
                Ok(session) => {
                    return Ok(Cell {
                        session,
                        keys: CellKeys::new(cell)?,
                        endpoint,
                    })
                }
                Err(e) if e.to_string().contains("Address already in use") && attempts < 5 => {
                    attempts += 1;
                }
                Err(e) => bail!("open zenoh: {e}"),
            }
        }
    }

    /// Waits until `holon`'s liveliness token appears.
    pub async fn wait_alive(&self, holon: &HolonId) -> Result<()> {
        let found = holon::presence::wait_alive(&self.session, &self.keys, holon, WAIT)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        if !found {
            bail!("{holon} did not appear within {WAIT:?}");
        }
        Ok(())
    }

    /// Waits until `holon`'s liveliness token is gone.
    pub async fn wait_gone(&self, holon: &HolonId) -> Result<()> {
        self.wait_token_gone(&self.keys.alive(holon)).await
    }

    /// Waits until the liveliness token on `key` is gone (at once if it is not there):
    /// a process killed is not gone from the cell until the router has seen its link
    /// close, and a successor started meanwhile under the same key is not told apart.
    pub async fn wait_token_gone(&self, key: &str) -> Result<()> {
        // Subscribed before asking, so that a Delete after the answer is not missed.
        let subscriber = self
            .session
            .liveliness()
            .declare_subscriber(key)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let there = self
            .session
            .liveliness()
            .get(key)
            .timeout(Duration::from_secs(2))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        if there.recv_async().await.is_err() {
            return Ok(());
        }
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            match tokio::time::timeout_at(deadline, subscriber.recv_async()).await {
                Ok(Ok(sample)) if sample.kind() == SampleKind::Delete => return Ok(()),
                Ok(Ok(_)) => {}
                Ok(Err(e)) => bail!("{e}"),
                Err(_) => bail!("{key} still alive after {WAIT:?}"),
            }
        }
    }

    /// Sends `payload` to `key` and returns the single answer's payload: `Ok` for a
    /// reply, `Err` for an error reply.
    pub async fn ask(
        &self,
        key: &str,
        payload: Vec<u8>,
    ) -> Result<std::result::Result<Vec<u8>, Vec<u8>>> {
        let replies = self
            .session
            .get(key)
            .payload(payload)
            .consolidation(ConsolidationMode::None)
            .timeout(Duration::from_secs(5))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| anyhow!("no reply from {key}"))?;
        Ok(match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(err) => Err(err.payload().to_bytes().into_owned()),
        })
    }

    /// Sends a request to `key` and returns the single answer: a Service, or an error reply.
    pub async fn request(
        &self,
        key: &str,
        payload: Vec<u8>,
    ) -> Result<std::result::Result<Service, ErrorReply>> {
        Ok(match self.ask(key, payload).await? {
            Ok(answer) => Ok(Service::from_json(&answer)?),
            Err(error) => Err(serde_json::from_slice(&error)?),
        })
    }

    /// Sends a Service request to `resource/<name>/service` and expects a Service answer.
    pub async fn service(&self, resource: &str, message: &Service) -> Result<Service> {
        self.request(&self.keys.service(resource), message.to_json())
            .await?
            .map_err(|e| anyhow!("error reply {}: {}", e.code, e.message))
    }

    /// Every proposal for `service_type` (contract net in one `get`).
    pub async fn proposals(&self, message: &Service) -> Result<Vec<Service>> {
        let replies = self
            .session
            .get(self.keys.offers(&message.service_type))
            .payload(message.to_json())
            .consolidation(ConsolidationMode::None)
            .timeout(Duration::from_secs(2))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let mut proposals = Vec::new();
        while let Ok(reply) = replies.recv_async().await {
            if let Ok(sample) = reply.result() {
                proposals.push(Service::from_json(&sample.payload().to_bytes())?);
            }
        }
        Ok(proposals)
    }

    /// Proposal rounds until exactly `n` resources propose (offers appear a moment after
    /// a resource's state turns free: they are declared, then reach the others).
    pub async fn wait_proposals(&self, message: &Service, n: usize) -> Result<Vec<Service>> {
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            let proposals = self.proposals(message).await?;
            if proposals.len() == n {
                return Ok(proposals);
            }
            if tokio::time::Instant::now() > deadline {
                bail!(
                    "{} proposals instead of {n}: {proposals:?}",
                    proposals.len()
                );
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// The resource's state, asked with a `status` request.
    pub async fn status(&self, resource: &str) -> Result<serde_json::Value> {
        let ask = Service::request(
            MessageType::Status,
            "pick_n_place",
            "status",
            test_requester(),
        );
        let answer = self.service(resource, &ask).await?;
        Ok(serde_json::Value::Object(answer.info))
    }

    /// Any holon's state, asked on `<kind>/<name>/state`.
    pub async fn ask_state(&self, holon: &HolonId) -> Result<serde_json::Value> {
        let replies = self
            .session
            .get(self.keys.state(holon))
            .timeout(Duration::from_secs(2))
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| anyhow!("{holon} did not answer"))?;
        let sample = reply.result().map_err(|e| anyhow!("{e:?}"))?;
        Ok(serde_json::from_slice(&sample.payload().to_bytes())?)
    }

    /// Polls the resource's state until `check` holds.
    pub async fn wait_state(
        &self,
        resource: &str,
        what: &str,
        check: impl Fn(&serde_json::Value) -> bool,
    ) -> Result<serde_json::Value> {
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            if let Ok(state) = self.status(resource).await {
                if check(&state) {
                    return Ok(state);
                }
                if tokio::time::Instant::now() > deadline {
                    bail!("{resource} never reached {what}; last state {state}");
                }
            } else if tokio::time::Instant::now() > deadline {
                bail!("{resource} never answered status");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    /// Declares an order's inbox. The first `refuse_first` results are answered with an
    /// error reply (no acknowledgement); every later one is acknowledged.
    pub async fn inbox(&self, order: &str, refuse_first: usize) -> Result<Inbox> {
        let key = self.keys.inbox(order);
        let (tx, rx) = mpsc::unbounded_channel();
        let seen = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let queryable = self
            .session
            .declare_queryable(&key)
            .callback({
                let seen = seen.clone();
                move |query| {
                    use zenoh::Wait;
                    let payload = query
                        .payload()
                        .map(|p| p.to_bytes().into_owned())
                        .unwrap_or_default();
                    let Ok(message) = Service::from_json(&payload) else {
                        let _ = query.reply_err(b"undecodable".to_vec()).wait();
                        return;
                    };
                    let n = seen.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                    if n < refuse_first {
                        let _ = query
                            .reply_err(
                                ErrorReply::new(schemas::ErrorCode::NotYet, "test refuses")
                                    .to_json(),
                            )
                            .wait();
                    } else {
                        let mut ack = message.clone();
                        ack.result = Some(true);
                        let _ = query.reply(query.key_expr().clone(), ack.to_json()).wait();
                    }
                    let _ = tx.send(message);
                }
            })
            .await
            .map_err(|e| anyhow!("{e}"))?;
        Ok(Inbox {
            key,
            received: rx,
            _queryable: queryable,
        })
    }
}

/// An order's inbox as the tests see it: every delivery attempt received.
pub struct Inbox {
    pub key: String,
    pub received: mpsc::UnboundedReceiver<Service>,
    _queryable: zenoh::query::Queryable<()>,
}

impl Inbox {
    /// The next delivery attempt, within `WAIT`.
    pub async fn next(&mut self) -> Result<Service> {
        tokio::time::timeout(WAIT, self.received.recv())
            .await
            .map_err(|_| anyhow!("nothing reached the inbox within {WAIT:?}"))?
            .ok_or_else(|| anyhow!("inbox closed"))
    }

    /// The next result (`done` / `failed`), with the `departed` delivered before it (a
    /// move's word that it left its origin, acknowledged like a result), each within
    /// `WAIT`.
    pub async fn next_result(&mut self) -> Result<(Service, Vec<Service>)> {
        let mut departed = Vec::new();
        loop {
            let message = self.next().await?;
            if message.message_type == MessageType::Departed {
                departed.push(message);
            } else {
                return Ok((message, departed));
            }
        }
    }

    /// Whether anything arrives within `quiet`.
    pub async fn silent_for(&mut self, quiet: Duration) -> bool {
        tokio::time::timeout(quiet, self.received.recv())
            .await
            .is_err()
    }
}

/// The requester the tests act as.
pub fn test_requester() -> HolonId {
    HolonId::order("tester").expect("valid id")
}

/// A `pick_n_place` request from `order/<order>`, with poses and the order's inbox.
pub fn pick_n_place(
    keys: &CellKeys,
    kind: MessageType,
    order: &str,
    conversation: &str,
) -> Service {
    let info = serde_json::json!({
        "pick": {"x": 100.0, "y": 20.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 0.0},
        "place": {"x": 300.0, "y": 40.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 90.0}
    });
    Service::request(
        kind,
        "pick_n_place",
        conversation,
        HolonId::order(order).expect("valid order name"),
    )
    .with_reply_to(keys.inbox(order))
    .with_info(info.as_object().expect("object").clone())
}

/// Writes `DIR/part.toml`: the product `part`, one `pick_n_place` step (the cell is
/// set by the harness's `--cell`).
pub fn one_step_product(dir: &Path) -> Result<PathBuf> {
    let path = dir.join("part.toml");
    fs::write(
        &path,
        r#"
cell = "unset"
name = "part"
kind = "product"

[[steps]]
service_type = "pick_n_place"
info = { pick = { x = 1.0, y = 2.0, z = 3.0 }, place = { x = 4.0, y = 5.0, z = 6.0 } }
"#,
    )?;
    Ok(path)
}

/// Submits `work` on `orders/submit` from `session` and returns the new orders' names.
pub async fn submit_on(
    session: &zenoh::Session,
    keys: &CellKeys,
    work: &schemas::WorkOrder,
) -> Result<Vec<String>> {
    let replies = session
        .get(keys.orders_submit())
        .payload(serde_json::to_vec(work)?)
        .timeout(Duration::from_secs(5))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let reply = replies
        .recv_async()
        .await
        .map_err(|_| anyhow!("no order-node answered"))?;
    let sample = reply
        .result()
        .map_err(|e| anyhow!("work order refused: {:?}", e.payload().try_to_string()))?;
    Ok(serde_json::from_slice::<schemas::SubmitReply>(&sample.payload().to_bytes())?.orders)
}

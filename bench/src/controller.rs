//! The controller's figures: a command's round trip through the controller client and
//! robot-sim, without a holon, in every shipped dialect, beside the client as it was
//! before dialects (holarchy's XML through the codec alone) measured in the same
//! sitting, interleaved round by round so the machine's noise falls on both alike.

use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{bail, Result};
use holarchy_tests::Sim;
use robot_bridge::client::{self, ClientConfig, ControllerEvent, ControllerRequest};
use robot_bridge::dialect::{Dialect, SHIPPED};
use schemas::RobotCommand;
use serde_json::json;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use crate::codec_client;
use crate::run::Table;
use crate::stats::Latency;

/// Commands per round; rounds alternate between the clients.
const ROUND: usize = 100;

/// The controller rows of the floors: `samples` round trips per client on the simulator
/// at `address` (holarchy-xml) and on one robot-sim per other shipped dialect, started in
/// `dir`, against the TCP floor `tcp`.
pub async fn section(
    table: &mut Table,
    dir: &Path,
    address: &str,
    samples: usize,
    tcp: &Latency,
) -> Result<()> {
    // The baseline first in every round, then each dialect.
    let mut clients = vec![Client::start(address, None).await?];
    let mut sims = Vec::new();
    for (name, _) in SHIPPED {
        let dialect = Dialect::shipped(name)?;
        let at = if *name == "holarchy-xml" {
            address.to_string()
        } else {
            let sim = Sim::start(
                dir,
                &format!("sim-{name}"),
                "127.0.0.1:0",
                &["--dialect", name],
            )?;
            let at = sim.address.clone();
            sims.push(sim);
            at
        };
        clients.push(Client::start(&at, Some(dialect)).await?);
    }
    let mut times: Vec<Vec<Duration>> = vec![Vec::with_capacity(samples); clients.len()];
    let started = Instant::now();
    let mut next_id = 1u64;
    while times[0].len() < samples {
        let n = ROUND.min(samples - times[0].len());
        for (client, times) in clients.iter_mut().zip(times.iter_mut()) {
            for _ in 0..n {
                times.push(client.round_trip(next_id).await?);
                next_id += 1;
            }
        }
    }
    let elapsed = started.elapsed();
    let latencies: Vec<Latency> = times
        .into_iter()
        .map(|t| Latency::new(t, elapsed / clients.len() as u32))
        .collect();
    for client in clients {
        client.stop().await;
    }
    let codec = &latencies[0];
    table.add(
        "controller command: codec (before dialects)",
        codec.p50_p99(),
        format!("TCP p50 {:.0} us", tcp.pct(0.5)),
        codec.json(),
    );
    for ((name, _), latency) in SHIPPED.iter().zip(&latencies[1..]) {
        // holarchy-xml keeps the row's old name: the floor of an execution step.
        let row = if *name == "holarchy-xml" {
            "floor: controller command (robot-bridge <-> robot-sim)".to_string()
        } else {
            format!("controller command: dialect {name}")
        };
        let ratio = latency.pct(0.5) / codec.pct(0.5);
        table.add(
            &row,
            latency.p50_p99(),
            format!("{name}: {ratio:.2}x the codec's p50"),
            json!({"dialect": name, "latency": latency.json(), "ratio_to_codec_p50": ratio}),
        );
    }
    Ok(())
}

/// A controller client (today's, in a dialect, or the codec one) and its mailboxes.
struct Client {
    commands: mpsc::Sender<ControllerRequest>,
    events: mpsc::Receiver<ControllerEvent>,
    shutdown: CancellationToken,
    task: tokio::task::JoinHandle<()>,
}

impl Client {
    /// Starts a client of `address` (the codec one without a dialect) and waits until
    /// the controller is ready.
    async fn start(address: &str, dialect: Option<Arc<Dialect>>) -> Result<Client> {
        let (commands, mut command_rx) = mpsc::channel(16);
        let (event_tx, mut events) = mpsc::channel(16);
        let shutdown = CancellationToken::new();
        let mut config = ClientConfig::new(address);
        let task = tokio::spawn({
            let shutdown = shutdown.clone();
            async move {
                match dialect {
                    Some(dialect) => {
                        config.dialect = dialect;
                        client::run(config, &mut command_rx, event_tx, shutdown).await
                    }
                    None => codec_client::run(config, &mut command_rx, event_tx, shutdown).await,
                }
            }
        });
        let ready = tokio::time::timeout(Duration::from_secs(10), async {
            loop {
                match events.recv().await {
                    Some(ControllerEvent::Status(s, _)) if s.is_ready() => return Ok(()),
                    Some(_) => continue,
                    None => bail!("controller client stopped"),
                }
            }
        })
        .await;
        match ready {
            Ok(result) => result?,
            Err(_) => bail!("the controller at {address} was not ready within 10 s"),
        }
        Ok(Client {
            commands,
            events,
            shutdown,
            task,
        })
    }

    /// One `pick` and its reply.
    async fn round_trip(&mut self, id: u64) -> Result<Duration> {
        let t = Instant::now();
        self.commands
            .send(
                RobotCommand {
                    id,
                    action: "pick".into(),
                    pos: Some(schemas::Pose {
                        x: 1.0,
                        y: 2.0,
                        z: 3.0,
                        ..Default::default()
                    }),
                    program: None,
                    info: Default::default(),
                }
                .into(),
            )
            .await?;
        match tokio::time::timeout(Duration::from_secs(10), self.events.recv()).await {
            Ok(Some(ControllerEvent::Reply {
                id: got, result, ..
            })) if got == id && result == "picking_done" => Ok(t.elapsed()),
            Ok(other) => bail!("unexpected {other:?}"),
            Err(_) => bail!("no reply within 10 s"),
        }
    }

    async fn stop(self) {
        self.shutdown.cancel();
        if let Err(e) = self.task.await {
            eprintln!("a controller client ended abnormally: {e}");
        }
    }
}

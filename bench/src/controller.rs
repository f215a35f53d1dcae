//! The controller's figures: a command's round trip through the controller client and
//! robot-sim, without a holon.

use std::time::Instant;

use anyhow::{bail, Result};

use crate::run::Table;
use crate::stats::Latency;

/// The controller's rows of the floors: a command's round trip on the simulator at
/// `address`, `samples` times, against the TCP floor `tcp`.
pub async fn section(
    table: &mut Table,
    address: &str,
    samples: usize,
    tcp: &Latency,
) -> Result<()> {
    let controller = controller_floor(address, samples).await?;
    table.add(
        "floor: controller command (robot-bridge <-> robot-sim)",
        format!(
            "p50 {:.0} us, p99 {:.0} us",
            controller.pct(0.5),
            controller.pct(0.99)
        ),
        format!("TCP p50 {:.0} us", tcp.pct(0.5)),
        controller.json(),
    );
    Ok(())
}

/// One controller command's round trip through the controller client and robot-sim,
/// without a holon: the floor of an execution step.
async fn controller_floor(address: &str, samples: usize) -> Result<Latency> {
    use robot_bridge::client::{self, ClientConfig, ControllerEvent};
    let (commands, mut command_rx) = tokio::sync::mpsc::channel(16);
    let (event_tx, mut events) = tokio::sync::mpsc::channel(16);
    let shutdown = tokio_util::sync::CancellationToken::new();
    let config = ClientConfig::new(address);
    let task = tokio::spawn({
        let shutdown = shutdown.clone();
        async move { client::run(config, &mut command_rx, event_tx, shutdown).await }
    });
    loop {
        match events.recv().await {
            Some(ControllerEvent::Status(s)) if s.is_ready() => break,
            Some(_) => continue,
            None => bail!("controller client stopped"),
        }
    }
    let mut times = Vec::new();
    let started = Instant::now();
    for id in 0..samples as u64 {
        let t = Instant::now();
        commands
            .send(schemas::RobotCommand {
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
            })
            .await?;
        match events.recv().await {
            Some(ControllerEvent::Reply { .. }) => times.push(t.elapsed()),
            other => bail!("unexpected {other:?}"),
        }
    }
    shutdown.cancel();
    let _ = task.await;
    Ok(Latency::new(times, started.elapsed()))
}

//! The plant's control port (`plant-sim --control HOST:PORT`): tests and operators ask
//! where everything is and play the plant's faults, one command a line, one answer a
//! line.
//!
//! | command | answer |
//! |---|---|
//! | `where` | where everything is: the state file's JSON, on one line |
//! | `jam CONVEYOR.STOPPER` | `ok`: the track that ends at that stopper is jammed; a move along it does not end |
//! | `clear CONVEYOR.STOPPER` | `ok`: it is not any more; the moves held up go on |
//! | `silence PALLET` | `ok`: the pallet (`conveyor1/p2`) stops reporting: a move it carries ends in the plant without its controller saying so |
//! | `report PALLET` | `ok`: it reports again |
//!
//! Anything else is answered `error ` and why; nothing changes.

use std::sync::{Arc, Mutex};

use schemas::layout::Dock;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpListener;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use super::controller::OnChange;
use super::model::Plant;

/// The longest command line read.
const MAX_LINE: usize = 256;

/// Carries out one command line on `plant`: the answer, and whether the plant changed.
pub fn command(plant: &mut Plant, line: &str) -> (String, bool) {
    let words: Vec<&str> = line.split_whitespace().collect();
    let done = |result: Result<(), String>| match result {
        Ok(()) => ("ok".to_string(), true),
        Err(why) => (format!("error {why}"), false),
    };
    let dock = |text: &str| Dock::try_from(text.to_string());
    match words.as_slice() {
        ["where"] => (
            serde_json::to_string(&plant.view()).expect("a plant view serializes"),
            false,
        ),
        ["jam", at] => done(dock(at).and_then(|at| plant.jam(at, true))),
        ["clear", at] => done(dock(at).and_then(|at| plant.jam(at, false))),
        ["silence", pallet] => done(plant.silence(pallet, true)),
        ["report", pallet] => done(plant.silence(pallet, false)),
        _ => (
            format!("error {line:?}: not a command (where, jam, clear, silence, report)"),
            false,
        ),
    }
}

/// Serves the control port until `shutdown`.
pub async fn serve(
    listener: TcpListener,
    plant: Arc<Mutex<Plant>>,
    on_change: OnChange,
    shutdown: CancellationToken,
) {
    loop {
        let (stream, peer) = tokio::select! {
            _ = shutdown.cancelled() => return,
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    warn!(error = %e, "the control port cannot accept a connection");
                    continue;
                }
            },
        };
        let (plant, on_change, shutdown) = (plant.clone(), on_change.clone(), shutdown.clone());
        tokio::spawn(async move {
            let (read, mut write) = stream.into_split();
            // A connection reads at most 1 MiB in all: a bounded window, not a stream.
            let mut lines = BufReader::new(read.take(1 << 20)).lines();
            loop {
                let line = tokio::select! {
                    _ = shutdown.cancelled() => return,
                    line = lines.next_line() => match line {
                        Ok(Some(line)) if line.len() <= MAX_LINE => line,
                        Ok(Some(_)) => "(a line too long)".to_string(),
                        _ => return,
                    },
                };
                let answer = {
                    let mut plant = plant.lock().unwrap_or_else(|e| e.into_inner());
                    let (answer, changed) = command(&mut plant, line.trim());
                    if changed {
                        info!(%peer, command = %line.trim(), "the plant changed by its control port");
                        on_change(&plant);
                    }
                    answer
                };
                if let Err(e) = write.write_all(format!("{answer}\n").as_bytes()).await {
                    warn!(%peer, error = %e, "cannot answer on the control port: the connection is gone");
                    return;
                }
            }
        });
    }
}

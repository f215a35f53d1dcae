//! What the plant's tests share: its control port's commands.

use std::path::Path;

use robot_bridge::plant::PlantSim;
use schemas::TimeScale;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio_util::sync::CancellationToken;

/// A plant running in this test, with its control port.
pub struct RunningPlant {
    /// Each controller's resource and address.
    pub addresses: Vec<(String, String)>,
    /// The control port's address.
    pub control: String,
    /// Stops the plant.
    pub shutdown: CancellationToken,
}

impl RunningPlant {
    /// The address of `resource`'s controller.
    pub fn address(&self, resource: &str) -> &str {
        self.addresses
            .iter()
            .find(|(r, _)| r == resource)
            .map(|(_, a)| a.as_str())
            .unwrap_or_else(|| panic!("no controller for {resource}"))
    }
}

/// Binds the plant file at `path` at `scale`, its control port on a free port, and runs
/// it until the returned plant's `shutdown`.
pub async fn start_plant(path: &Path, scale: TimeScale) -> RunningPlant {
    let plant = PlantSim::bind(path, Default::default(), Some("127.0.0.1:0"), scale)
        .await
        .unwrap();
    let addresses = plant
        .addresses()
        .iter()
        .map(|(resource, address)| (resource.to_string(), address.to_string()))
        .collect();
    let control = plant.control_address().unwrap().to_string();
    let shutdown = CancellationToken::new();
    tokio::spawn(plant.run(shutdown.clone()));
    RunningPlant {
        addresses,
        control,
        shutdown,
    }
}

/// One command on the plant's control port, and its answer as JSON.
pub async fn control(address: &str, line: &str) -> serde_json::Value {
    serde_json::from_str(&control_line(address, line).await).unwrap()
}

/// One command on the plant's control port, and its answer.
pub async fn control_line(address: &str, line: &str) -> String {
    let mut stream = tokio::net::TcpStream::connect(address).await.unwrap();
    stream
        .write_all(format!("{line}\n").as_bytes())
        .await
        .unwrap();
    let mut answer = String::new();
    BufReader::new(stream).read_line(&mut answer).await.unwrap();
    answer.trim_end().to_string()
}

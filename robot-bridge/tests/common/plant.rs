//! What the plant's tests share: a conveyor loop's plant file, its control port's
//! commands, and a client's move on it.

use std::path::{Path, PathBuf};

use robot_bridge::client::ControllerRequest;
use robot_bridge::plant::PlantSim;
use schemas::{RobotCommand, TimeScale};
use tokio::io::{AsyncBufReadExt, AsyncWriteExt, BufReader};
use tokio_util::sync::CancellationToken;

/// conveyor1: a loop of 2000 mm at 1000 mm/s, its loading point at 0 mm and a buffer at
/// 1000 mm (a move between them rides about a second), with `pallets` pallets.
pub fn loop_conveyor(pallets: u32) -> String {
    format!(
        r#"
name = "conveyor1"

[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"

[[layout.locations]]
name = "buffer"
role = "buffer"
capacity = 3
dock = "conveyor1.buf"

[layout.conveyor]
length_mm = 2000
speed_mm_s = 1000
pallets = {pallets}
stoppers = [{{ name = "load", at_mm = 0 }}, {{ name = "buf", at_mm = 1000 }}]
"#
    )
}

/// Writes `conveyor` as DIR/conveyor1.toml and a plant file of it alone, its one
/// controller's section ending with `controller_lines` (each ending with a newline);
/// returns the plant file's path.
pub fn one_conveyor_plant(dir: &Path, conveyor: &str, controller_lines: &str) -> PathBuf {
    std::fs::write(dir.join("conveyor1.toml"), conveyor).unwrap();
    let path = dir.join("plant.toml");
    std::fs::write(
        &path,
        format!("layout = [\"conveyor1.toml\"]\n\n[[controller]]\nresource = \"conveyor1\"\nlisten = \"127.0.0.1:0\"\n{controller_lines}"),
    )
    .unwrap();
    path
}

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

/// The client's command `id` moving `part` from the loading point to the buffer.
pub fn move_to_buffer(id: u64, part: &str) -> ControllerRequest {
    let info = [
        ("part", part),
        ("from", "conveyor1.load"),
        ("to", "conveyor1.buffer"),
    ]
    .into_iter()
    .map(|(k, v)| (k.to_string(), serde_json::Value::from(v)))
    .collect();
    ControllerRequest::Command(RobotCommand {
        id,
        action: "move".into(),
        pos: None,
        program: None,
        info,
    })
}

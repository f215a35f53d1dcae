//! The plant simulator as the tests start it: `plant-sim` with a plant file.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::{bin, Process};

/// A running plant-sim and its controllers' addresses.
pub struct PlantProcess {
    pub process: Process,
    /// Each controller's resource and the address it listens on.
    pub controllers: BTreeMap<String, String>,
    /// Where the plant writes where everything is.
    pub state_file: PathBuf,
    /// The plant's control port.
    pub control: String,
}

impl PlantProcess {
    /// Writes `plant` as DIR/plant.toml and starts plant-sim on it, its state file
    /// DIR/plant-state.json; returns once it says it is ready.
    pub fn start(dir: &Path, plant: &str) -> PlantProcess {
        let file = dir.join("plant.toml");
        let state_file = dir.join("plant-state.json");
        std::fs::write(&file, plant).expect("write the plant file");
        let stderr_path = dir.join("plant.stderr");
        let mut child = Command::new(bin("plant-sim"))
            .arg("--plant")
            .arg(&file)
            .arg("--state-file")
            .arg(&state_file)
            .args(["--control", "127.0.0.1:0"])
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&stderr_path).expect("create the plant's stderr"))
            .spawn()
            .expect("start plant-sim");
        let stdout = child.stdout.take().expect("piped");
        let process = Process {
            name: "plant-sim".into(),
            child: Some(child),
            stderr_path,
        };
        let mut controllers = BTreeMap::new();
        let mut control = String::new();
        for line in BufReader::new(stdout).lines() {
            let line = line.expect("plant-sim's stdout");
            if line == "plant ready" {
                return PlantProcess {
                    process,
                    controllers,
                    state_file,
                    control,
                };
            }
            if let Some(address) = line.strip_prefix("control port listening on ") {
                control = address.to_string();
                continue;
            }
            let (resource, address) = line
                .strip_prefix("controller ")
                .and_then(|l| l.split_once(" listening on "))
                .unwrap_or_else(|| panic!("plant-sim said {line:?}"));
            controllers.insert(resource.to_string(), address.to_string());
        }
        panic!("plant-sim ended before it was ready: {}", process.stderr());
    }

    /// One command on the plant's control port, and its answer.
    pub fn command(&self, line: &str) -> String {
        use std::io::Write;
        let mut stream = std::net::TcpStream::connect(&self.control).expect("the control port");
        writeln!(stream, "{line}").expect("a command to the control port");
        let mut answer = String::new();
        BufReader::new(stream)
            .read_line(&mut answer)
            .expect("the control port's answer");
        answer.trim_end().to_string()
    }

    /// Where everything is, as the plant's state file says.
    pub fn state(&self) -> serde_json::Value {
        let bytes = std::fs::read(&self.state_file).expect("the plant's state file");
        serde_json::from_slice(&bytes).expect("the plant's state is JSON")
    }
}

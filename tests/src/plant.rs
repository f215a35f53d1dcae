//! The plant simulator as the tests start it: `plant-sim` with a plant file.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

use crate::{bin, resource_config, Process};

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
    /// DIR/plant-state.json and its trace DIR/plant-trace.jsonl; returns once it says
    /// it is ready.
    pub fn start(dir: &Path, plant: &str) -> PlantProcess {
        std::fs::write(dir.join("plant.toml"), plant).expect("write the plant file");
        PlantProcess::launch(dir, "127.0.0.1:0")
    }

    /// Kills plant-sim with SIGKILL and starts it again on the same state file, each
    /// controller and the control port on the address it had: the plant resumes from
    /// its memory.
    pub fn kill_and_restart(&mut self, dir: &Path) {
        self.kill_and_restart_after(dir, std::time::Duration::ZERO);
    }

    /// As [`PlantProcess::kill_and_restart`], started again once `pause` has passed
    /// (the plant dead meanwhile: its controllers refuse connections).
    pub fn kill_and_restart_after(&mut self, dir: &Path, pause: std::time::Duration) {
        self.process.kill();
        std::thread::sleep(pause);
        let file = dir.join("plant.toml");
        let text = std::fs::read_to_string(&file).expect("the plant file");
        let mut plant: toml::Table = toml::from_str(&text).expect("the plant file is TOML");
        for controller in plant["controller"].as_array_mut().expect("[[controller]]") {
            let table = controller.as_table_mut().expect("a controller table");
            let resource = table["resource"].as_str().expect("resource").to_string();
            table.insert(
                "listen".into(),
                toml::Value::String(self.controllers[&resource].clone()),
            );
        }
        std::fs::write(&file, toml::to_string(&plant).expect("TOML")).expect("the plant file");
        let control = self.control.clone();
        let again = PlantProcess::launch(dir, &control);
        assert_eq!(again.controllers, self.controllers, "the same addresses");
        *self = again;
    }

    /// Starts plant-sim on DIR/plant.toml, its control port at `control`.
    fn launch(dir: &Path, control: &str) -> PlantProcess {
        let file = dir.join("plant.toml");
        let state_file = dir.join("plant-state.json");
        let stderr_path = dir.join("plant.stderr");
        let stderr = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&stderr_path)
            .expect("open the plant's stderr");
        let mut child = Command::new(bin("plant-sim"))
            .arg("--plant")
            .arg(&file)
            .arg("--state-file")
            .arg(&state_file)
            .arg("--trace")
            .arg(dir.join("plant-trace.jsonl"))
            .args(["--control", control])
            .stdout(Stdio::piped())
            .stderr(stderr)
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

    /// Every action the plant's controllers ran to its end, across its lives (its
    /// trace): how many of `action` each resource did.
    pub fn done_in_trace(dir: &Path, action: &str) -> BTreeMap<String, u64> {
        let text = std::fs::read_to_string(dir.join("plant-trace.jsonl")).unwrap_or_default();
        let mut done = BTreeMap::new();
        for line in text.lines() {
            let record: serde_json::Value =
                serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}"));
            if record["done"] == true && record["action"] == action {
                let resource = record["resource"].as_str().unwrap_or("").to_string();
                *done.entry(resource).or_default() += 1;
            }
        }
        done
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

    /// The plant's action counts (its control port's `counts`), per controller.
    pub fn counts(&self) -> serde_json::Value {
        serde_json::from_str(&self.command("counts")).expect("the plant's counts are JSON")
    }

    /// Where everything is, as the plant's state file says.
    pub fn state(&self) -> serde_json::Value {
        let bytes = std::fs::read(&self.state_file).expect("the plant's state file");
        serde_json::from_slice(&bytes).expect("the plant's state is JSON")
    }
}

/// How many of `conveyor`'s pallets are free in the plant's state `truth`.
pub fn free_pallets(truth: &serde_json::Value, conveyor: &str) -> usize {
    truth["free_pallets"][conveyor]
        .as_array()
        .map_or(0, Vec::len)
}

/// One connection to a controller of the plant, speaking holarchy-xml as a holon does
/// (docs/controller-protocol.md): for tests that drive the plant without holons.
pub struct ControllerLink {
    /// The connection.
    stream: std::net::TcpStream,
    /// What the controller sent and the test has not read yet.
    received: String,
    /// The next command's ID.
    next_id: u64,
}

impl ControllerLink {
    /// Connects to the controller at `address`.
    pub fn connect(address: &str) -> ControllerLink {
        let stream = std::net::TcpStream::connect(address).expect("the controller's address");
        stream
            .set_read_timeout(Some(std::time::Duration::from_millis(200)))
            .expect("a read timeout");
        ControllerLink {
            stream,
            received: String::new(),
            next_id: 1,
        }
    }

    /// Sends a move of `part` from `from` to `to`; returns its command ID.
    pub fn send_move(&mut self, part: &str, from: &str, to: &str) -> u64 {
        use std::io::Write;
        let id = self.next_id;
        self.next_id += 1;
        let command = format!(
            "<ROBOT_CMD><ID>{id}</ID><ACTION>move</ACTION><PART>{part}</PART><FROM>{from}</FROM><TO>{to}</TO></ROBOT_CMD>"
        );
        self.stream
            .write_all(command.as_bytes())
            .expect("a command to the controller");
        id
    }

    /// Whether the controller closes the connection within `within` (what it sends
    /// meanwhile is kept).
    pub fn closed(&mut self, within: std::time::Duration) -> bool {
        use std::io::Read;
        let deadline = std::time::Instant::now() + within;
        while std::time::Instant::now() < deadline {
            let mut buffer = [0u8; 4096];
            match self.stream.read(&mut buffer) {
                Ok(0) => return true,
                Ok(n) => self
                    .received
                    .push_str(&String::from_utf8_lossy(&buffer[..n])),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(_) => return true,
            }
        }
        false
    }

    /// Sends `text` as it is (a claim, a fenced command, a `STEP_STATUS`).
    pub fn send_raw(&mut self, text: &str) {
        use std::io::Write;
        self.stream
            .write_all(text.as_bytes())
            .expect("a message to the controller");
    }

    /// The reply to command `id` (the whole `ROBOT_REPLY` document), waiting at most
    /// `within`; None if none came by then.
    pub fn reply(&mut self, id: u64, within: std::time::Duration) -> Option<String> {
        let start = format!("<ROBOT_REPLY><ID>{id}</ID>");
        self.message(&start, "</ROBOT_REPLY>", within)
    }

    /// The first message that begins with `start` and ends with `end` (what came before
    /// it is dropped), waiting at most `within`; None if none came by then.
    pub fn message(
        &mut self,
        start: &str,
        end_tag: &str,
        within: std::time::Duration,
    ) -> Option<String> {
        use std::io::Read;
        let deadline = std::time::Instant::now() + within;
        loop {
            if let Some(at) = self.received.find(start) {
                if let Some(end) = self.received[at..].find(end_tag) {
                    let end = at + end + end_tag.len();
                    let reply = self.received[at..end].to_string();
                    self.received.replace_range(..end, "");
                    return Some(reply);
                }
            }
            if std::time::Instant::now() >= deadline {
                return None;
            }
            let mut buffer = [0u8; 4096];
            match self.stream.read(&mut buffer) {
                Ok(0) => panic!("the controller closed the connection: {}", self.received),
                Ok(n) => self
                    .received
                    .push_str(&String::from_utf8_lossy(&buffer[..n])),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) => {}
                Err(e) => panic!("cannot read from the controller: {e}"),
            }
        }
    }
}

/// A small plant's conveyor (conveyor1: the loading point `load`, entry and exit, and the
/// stopper `s1`; two pallets), its controller's address to be set.
pub const SMALL_CONVEYOR: &str = r#"
cell = "unset"
name = "conveyor1"

[controller]
address = "127.0.0.1:1"
reconnect_interval_ms = 100
reconnect_max_ms = 1000
command_timeout_ms = 5000
connect_timeout_ms = 500

[services.transport]
nominal_duration_ms = 300
steps = [{ action = "move", until = ["arrived"] }]

[[layout.locations]]
name = "load"
role = "entry_exit"
capacity = 2
dock = "conveyor1.load"

[layout.conveyor]
length_mm = 2000
speed_mm_s = 4000
pallets = 2
stoppers = [{ name = "load", at_mm = 0 }, { name = "s1", at_mm = 1000 }]
"#;

/// The plant of conveyor1 and robot1.
pub const SMALL_PLANT: &str = r#"
layout = ["conveyor1.toml", "robot1.toml"]

[[controller]]
resource = "conveyor1"
listen = "127.0.0.1:0"

[[controller]]
resource = "robot1"
listen = "127.0.0.1:0"
delay_ms = 20
"#;

/// robot1's config in `dir` for [`SMALL_PLANT`]: a pick-'n-place robot whose port is on the conveyor's stopper s1.
pub fn small_robot1(dir: &Path) -> PathBuf {
    let path = resource_config(dir, "robot1", 5000).unwrap();
    let text = std::fs::read_to_string(&path).unwrap();
    let layout =
        "\n[[layout.locations]]\nname = \"port\"\nrole = \"port\"\ndock = \"conveyor1.s1\"\n";
    std::fs::write(&path, format!("{text}{layout}")).unwrap();
    path
}

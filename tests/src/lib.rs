//! The harness of holarchy's multi-process tests: it starts the real binaries
//! (`robot-sim`, `holon-node`) on loopback with unique ports, talks zenoh to them with
//! multicast scouting off and explicit endpoints, waits on presence rather than sleeps,
//! bounds every wait, and kills its children when a test ends.

pub mod secure_cell;
pub mod web;
pub mod webdriver;

use std::fs;
use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::{Mutex, OnceLock};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use schemas::{CellKeys, ErrorReply, HolonId, MessageType, Service};
use tokio::sync::mpsc;
use zenoh::query::ConsolidationMode;
use zenoh::sample::SampleKind;

/// The longest any single wait in a test may take.
pub const WAIT: Duration = Duration::from_secs(20);

/// The directory holding the workspace's binaries (`target/debug` next to the tests).
pub fn bin_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("HOLARCHY_BIN_DIR") {
        return PathBuf::from(dir);
    }
    let exe = std::env::current_exe().expect("current exe");
    // A test: target/<profile>/deps/<test>; a binary (bench): target/<profile>/<bin>.
    let dir = exe.parent().expect("the executable has a directory");
    if dir.ends_with("deps") {
        dir.parent().expect("target/<profile>").to_path_buf()
    } else {
        dir.to_path_buf()
    }
}

/// The path of a workspace binary, built on first use if `cargo test` did not build it
/// (the binaries of `HOLARCHY_BIN_DIR` are taken as they are).
pub fn bin(name: &str) -> PathBuf {
    static BUILT: OnceLock<()> = OnceLock::new();
    let path = bin_dir().join(name);
    BUILT.get_or_init(|| {
        if std::env::var_os("HOLARCHY_BIN_DIR").is_some() {
            return;
        }
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut build = Command::new(cargo);
        build.args(["build", "--bins", "--quiet"]);
        // What cargo sets for a test process is not the user's build environment: a
        // build script that watches one of these (ring's watches CARGO_MANIFEST_DIR)
        // would rebuild half the workspace here, and again at the next plain build.
        for (key, _) in std::env::vars_os() {
            let key = key.to_string_lossy().into_owned();
            if [
                "CARGO_MANIFEST_",
                "CARGO_PKG_",
                "CARGO_CRATE_",
                "CARGO_BIN_",
                "CARGO_PRIMARY_PACKAGE",
                "CARGO_TARGET_TMPDIR",
            ]
            .iter()
            .any(|prefix| key.starts_with(prefix))
            {
                build.env_remove(key);
            }
        }
        // The profile of this executable's directory: target/debug, target/release,
        // target/release-small...
        match bin_dir().file_name().and_then(|n| n.to_str()) {
            Some("debug") | None => {}
            Some(profile) => {
                build.args(["--profile", profile]);
            }
        }
        let status = build
            .current_dir(workspace_root())
            .status()
            .expect("cannot run cargo build");
        assert!(status.success(), "cargo build --bins failed");
    });
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// The workspace's root directory.
pub fn workspace_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is in the workspace")
        .to_path_buf()
}

/// The log level of the holons the harness starts: `HOLARCHY_HOLON_LOG`, default `info`
/// (the tests read the logs; the benchmarks also measure with `warn`).
pub fn holon_log_level() -> String {
    std::env::var("HOLARCHY_HOLON_LOG").unwrap_or_else(|_| "info".into())
}

/// A free TCP port on loopback (closed again; used at once by the caller).
pub fn free_port() -> u16 {
    static USED: Mutex<Vec<u16>> = Mutex::new(Vec::new());
    loop {
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|l| l.local_addr())
            .expect("bind an ephemeral port")
            .port();
        let mut used = USED.lock().unwrap();
        if !used.contains(&port) {
            used.push(port);
            return port;
        }
    }
}

/// A child process killed (SIGKILL) when dropped, with its output in files.
pub struct Process {
    pub name: String,
    child: Option<Child>,
    pub stderr_path: PathBuf,
}

impl Process {
    pub fn pid(&self) -> i32 {
        self.child.as_ref().map(|c| c.id() as i32).unwrap_or(0)
    }

    /// Sends a signal (e.g. SIGTERM) to the process.
    pub fn signal(&self, signal: nix::sys::signal::Signal) -> Result<()> {
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(self.pid()), signal)?;
        Ok(())
    }

    /// Kills the process (SIGKILL) and reaps it.
    pub fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    /// Waits for the process to exit by itself, at most `timeout`.
    pub fn wait_exit(&mut self, timeout: Duration) -> Result<std::process::ExitStatus> {
        let deadline = std::time::Instant::now() + timeout;
        let child = self
            .child
            .as_mut()
            .ok_or_else(|| anyhow!("already reaped"))?;
        loop {
            if let Some(status) = child.try_wait()? {
                self.child = None;
                return Ok(status);
            }
            if std::time::Instant::now() > deadline {
                bail!("{} did not exit within {timeout:?}", self.name);
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// What the process wrote to stderr so far.
    pub fn stderr(&self) -> String {
        fs::read_to_string(&self.stderr_path).unwrap_or_default()
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A `robot-sim` process.
pub struct Sim {
    pub process: Process,
    pub address: String,
    pub count_file: PathBuf,
}

impl Sim {
    /// Starts `robot-sim --listen ADDRESS` with extra flags and waits for its ready line.
    pub fn start(dir: &Path, name: &str, address: &str, flags: &[&str]) -> Result<Sim> {
        let count_file = dir.join(format!("{name}.counts.json"));
        let stderr_path = dir.join(format!("{name}.stderr"));
        let mut child = Command::new(bin("robot-sim"))
            .args(["--listen", address, "--count-file"])
            .arg(&count_file)
            .args(flags)
            .stdout(Stdio::piped())
            .stderr(fs::File::create(&stderr_path)?)
            .spawn()
            .context("start robot-sim")?;
        let stdout = child.stdout.take().expect("piped stdout");
        let process = Process {
            name: name.to_string(),
            child: Some(child),
            stderr_path,
        };
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut line = String::new();
            let _ = BufReader::new(stdout).read_line(&mut line);
            let _ = tx.send(line);
        });
        let line = rx
            .recv_timeout(WAIT)
            .map_err(|_| anyhow!("robot-sim printed no ready line"))?;
        let address = line
            .trim()
            .strip_prefix("listening on ")
            .ok_or_else(|| anyhow!("unexpected robot-sim line {line:?}"))?
            .to_string();
        Ok(Sim {
            process,
            address,
            count_file,
        })
    }

    /// The simulator's counts (`{"executed": N, "by_action": {...}, ...}`), once its
    /// count file settled (unchanged for 25 ms): the simulator rewrites the file from a
    /// thread of its own just after each reply goes out, so a reader that saw a reply's
    /// effects may be early.
    pub fn counts(&self) -> serde_json::Value {
        let read = || {
            fs::read_to_string(&self.count_file)
                .ok()
                .and_then(|t| serde_json::from_str(&t).ok())
                .unwrap_or(serde_json::Value::Null)
        };
        // A write may wait for the simulator's writer thread (a loaded machine delays
        // it by milliseconds): the counts are those that stayed the same for 25 ms.
        let mut counts = read();
        for _ in 0..40 {
            std::thread::sleep(Duration::from_millis(25));
            let again = read();
            if again == counts {
                break;
            }
            counts = again;
        }
        counts
    }

    pub fn executed(&self, action: &str) -> u64 {
        self.counts()["by_action"][action].as_u64().unwrap_or(0)
    }

    /// Waits, at most 10 s, until the simulator has executed `action` at least `n`
    /// times, and returns the settled count (more than `n` if it ran more often). The
    /// error, at the deadline, says how often it did. (A test that checks a count was
    /// *not* reached settles for a while and reads [`Sim::executed`] instead.)
    pub async fn wait_executed(&self, action: &str, n: u64) -> Result<u64> {
        const WITHIN: Duration = Duration::from_secs(10);
        let deadline = tokio::time::Instant::now() + WITHIN;
        loop {
            let executed = self.executed(action);
            if executed >= n {
                return Ok(executed);
            }
            if tokio::time::Instant::now() >= deadline {
                bail!(
                    "the simulator {} executed {action} {executed} times, never {n} within {WITHIN:?}",
                    self.process.name
                );
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// Waits, at most 10 s, until the simulator has received `n` commands in all. A
    /// holon's state names a step as soon as its command is handed to the bridge,
    /// which writes it to the socket a moment later: a test that kills something
    /// mid-step waits for this first.
    pub async fn wait_received(&self, n: u64) -> Result<()> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        loop {
            let received = fs::read_to_string(&self.count_file)
                .ok()
                .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
                .and_then(|c| c["received"].as_u64())
                .unwrap_or(0);
            if received >= n {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                bail!("the simulator received {received} commands, never {n}");
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    }
}

/// Writes a resource config for tests: short timeouts, one pick_n_place robot.
pub fn resource_config(dir: &Path, name: &str, command_timeout_ms: u64) -> Result<PathBuf> {
    let path = dir.join(format!("{name}.toml"));
    fs::write(
        &path,
        format!(
            r#"
cell = "unset"
name = "{name}"

[controller]
address = "127.0.0.1:1"
reconnect_interval_ms = 100
command_timeout_ms = {command_timeout_ms}
connect_timeout_ms = 500

[supervisor]
strategy = "one_for_one"
max_restarts = 5
period_ms = 10000

[delivery]
retry_initial_ms = 100
retry_max_ms = 400
attempt_timeout_ms = 500

[services.pick_n_place]
nominal_duration_ms = 1000
steps = [
  {{ action = "pick", until = ["picking_done"], position = "pick" }},
  {{ action = "place", until = ["placing_done"], position = "place" }},
]
"#
        ),
    )?;
    Ok(path)
}

/// Starts `holon-node` with `--config FILE --cell CELL --connect ROUTER --controller ADDR`
/// and extra flags. Wait for it with [`Cell::wait_alive`].
pub fn start_node(
    dir: &Path,
    config: &Path,
    cell: &str,
    connect: &str,
    controller: &str,
    extra: &[&str],
) -> Result<Process> {
    let name = config
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stderr_path = dir.join(format!("{name}.node.stderr"));
    let child = Command::new(bin("holon-node"))
        .arg("--config")
        .arg(config)
        .args([
            "--cell",
            cell,
            "--connect",
            connect,
            "--controller",
            controller,
        ])
        .arg("--log-file")
        .arg(dir.join(format!("{name}.log.json")))
        .args(extra)
        .env("RUST_LOG", holon_log_level())
        .stdout(Stdio::null())
        .stderr(fs::File::create(&stderr_path)?)
        .spawn()
        .context("start holon-node")?;
    Ok(Process {
        name,
        child: Some(child),
        stderr_path,
    })
}

/// The test's own zenoh session, listening on a unique port that every process joins.
pub struct Cell {
    pub session: zenoh::Session,
    pub keys: CellKeys,
    /// The endpoint processes connect to, e.g. `tcp/127.0.0.1:PORT`.
    pub endpoint: String,
}

impl Cell {
    pub async fn open(cell: &str) -> Result<Cell> {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let settings = holon::ZenohSettings {
            mode: holon::Mode::Router,
            listen: vec![endpoint.clone()],
            ..holon::ZenohSettings::default()
        };
        let session = settings
            .open("router.local", WAIT)
            .await
            .map_err(|e| anyhow!("open zenoh: {e}"))?;
        Ok(Cell {
            session,
            keys: CellKeys::new(cell)?,
            endpoint,
        })
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
        let subscriber = self
            .session
            .liveliness()
            .declare_subscriber(self.keys.alive(holon))
            .history(true)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let deadline = tokio::time::Instant::now() + WAIT;
        let mut alive = false;
        // History tells whether it is there now; then wait for its Delete.
        loop {
            match tokio::time::timeout_at(deadline, subscriber.recv_async()).await {
                Ok(Ok(sample)) => match sample.kind() {
                    SampleKind::Put => alive = true,
                    SampleKind::Delete => return Ok(()),
                },
                Ok(Err(e)) => bail!("{e}"),
                Err(_) if !alive => return Ok(()),
                Err(_) => bail!("{holon} still alive after {WAIT:?}"),
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
                            .reply_err(ErrorReply::new("not_yet", "test refuses").to_json())
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

/// Prints the end of every process's log: what a failed run on a CI machine leaves to read.
pub fn print_log_tails(dir: &Path) {
    let Ok(entries) = fs::read_dir(dir) else {
        return;
    };
    let mut logs: Vec<_> = entries
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "log"))
        .collect();
    logs.sort();
    for log in logs {
        let text = fs::read_to_string(&log).unwrap_or_default();
        let lines: Vec<&str> = text.lines().collect();
        let tail = &lines[lines.len().saturating_sub(40)..];
        println!("---- {} (last {} lines)", log.display(), tail.len());
        for line in tail {
            println!("{line}");
        }
    }
}

/// A config shipped in `deploy/cells/demo/`.
pub fn demo_config(file: &str) -> PathBuf {
    workspace_root().join("deploy/cells/demo").join(file)
}

/// Starts `program` (holon-node or order-node) with `--config FILE --cell CELL --name
/// NAME --connect ENDPOINT` (a client of the test's router) and extra flags; its log goes to
/// `DIR/NAME.log.json`.
pub fn start_holon(
    dir: &Path,
    program: &str,
    config: &Path,
    name: &str,
    cell: &Cell,
    extra: &[&str],
) -> Result<Process> {
    let stderr_path = dir.join(format!("{name}.stderr"));
    let child = Command::new(bin(program))
        .arg("--config")
        .arg(config)
        .args(["--cell", cell.keys.cell(), "--name", name])
        .args(["--connect", &cell.endpoint])
        .arg("--log-file")
        .arg(dir.join(format!("{name}.log.json")))
        .args(extra)
        .env("RUST_LOG", holon_log_level())
        .stdout(Stdio::null())
        .stderr(fs::File::create(&stderr_path)?)
        .spawn()
        .with_context(|| format!("start {program}"))?;
    Ok(Process {
        name: name.to_string(),
        child: Some(child),
        stderr_path,
    })
}

impl Cell {
    /// Starts the demo's order-node `orders1` (its log and stderr in `dir`) with extra
    /// flags, and waits until it serves.
    pub async fn start_order_node(&self, dir: &Path, extra: &[&str]) -> Result<Process> {
        let process = start_holon(
            dir,
            "order-node",
            &demo_config("orders1.toml"),
            "orders1",
            self,
            extra,
        )?;
        self.wait_token(&self.keys.host("order-node", "orders1"))
            .await?;
        Ok(process)
    }

    /// Waits until a liveliness token on `key` appears (e.g. an order-node's host token).
    pub async fn wait_token(&self, key: &str) -> Result<()> {
        let found = holon::presence::wait_token(&self.session, key, WAIT)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        if !found {
            bail!("{key} did not appear within {WAIT:?}");
        }
        Ok(())
    }

    /// The state of one order, asked of its order-node (`None`: no node knows it).
    pub async fn order_state(&self, order: &str) -> Option<serde_json::Value> {
        let replies = self
            .session
            .get(format!("holarchy/{}/order/{order}/state", self.keys.cell()))
            .timeout(Duration::from_secs(2))
            .await
            .ok()?;
        let reply = replies.recv_async().await.ok()?;
        serde_json::from_slice(&reply.result().ok()?.payload().to_bytes()).ok()
    }

    /// Waits, at most 30 s, until `check` holds for the order's state as its order-node
    /// answers it (`None`: no node knows the order). The error says what it never did.
    pub async fn wait_order(
        &self,
        order: &str,
        what: &str,
        check: impl Fn(Option<&serde_json::Value>) -> bool,
    ) -> Result<()> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(30);
        loop {
            let state = self.order_state(order).await;
            if check(state.as_ref()) {
                return Ok(());
            }
            if tokio::time::Instant::now() >= deadline {
                bail!("{order} never {what}: {state:?}");
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    }

    /// Starts the product `part` (one `pick_n_place` step, [`one_step_product`]) and the
    /// order-node `orders1` of `orders_config` with its journal in `data`, and waits
    /// until both are in the cell.
    pub async fn start_part_and_orders(
        &self,
        dir: &Path,
        orders_config: &Path,
        data: &Path,
    ) -> Result<(Process, Process)> {
        let product = start_holon(
            dir,
            "holon-node",
            &one_step_product(dir)?,
            "part",
            self,
            &[],
        )?;
        let data = data.to_str().context("a data directory that is UTF-8")?;
        let orders = start_holon(
            dir,
            "order-node",
            orders_config,
            "orders1",
            self,
            &["--data-dir", data],
        )?;
        self.wait_alive(&HolonId::new(schemas::HolonKind::Product, "part")?)
            .await?;
        self.wait_token(&self.keys.host("order-node", "orders1"))
            .await?;
        Ok((product, orders))
    }

    /// Starts the resource holon of `config` (its name is the file's stem) on this
    /// cell, driving the controller at `controller`, and waits until it is alive and
    /// free (its controller ready).
    pub async fn start_free_resource(
        &self,
        dir: &Path,
        config: &Path,
        controller: &str,
        extra: &[&str],
    ) -> Result<Process> {
        let node = start_node(
            dir,
            config,
            self.keys.cell(),
            &self.endpoint,
            controller,
            extra,
        )?;
        let name = config
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        self.wait_alive(&HolonId::resource(&name)?).await?;
        self.wait_state(&name, "free", |s| s["state"] == "free")
            .await?;
        Ok(node)
    }

    /// A resource named `name` with its simulator, both in `dir`: configure it, then
    /// [`ResourceBuilder::start`] it.
    pub fn resource<'a>(&'a self, dir: &Path, name: &str) -> ResourceBuilder<'a> {
        ResourceBuilder {
            cell: self,
            dir: dir.to_path_buf(),
            name: name.to_string(),
            sim_flags: Vec::new(),
            command_timeout_ms: 5000,
            config_extra: String::new(),
            node_flags: Vec::new(),
            dialect: None,
        }
    }

    /// Books and starts one `pick_n_place` job on `resource` for `order` (both must be
    /// accepted), and returns the result `inbox` (the order's) then gets.
    pub async fn job(
        &self,
        resource: &str,
        inbox: &mut Inbox,
        order: &str,
        conversation: &str,
    ) -> Result<Service> {
        for kind in [MessageType::BookingReq, MessageType::Start] {
            let request = pick_n_place(&self.keys, kind, order, conversation);
            let answer = self.service(resource, &request).await?;
            if answer.result != Some(true) {
                bail!("{kind:?} for {conversation} on {resource} refused: {answer:?}");
            }
        }
        inbox.next().await
    }

    /// Sends the PackML `command` (a name, e.g. `hold`) to `resource` over zenoh and
    /// returns its answer; an error if it was refused.
    pub async fn packml(&self, resource: &str, command: &str) -> Result<schemas::PackmlReply> {
        let command: schemas::PackmlCommand = command.parse().map_err(|e: String| anyhow!(e))?;
        let request = schemas::PackmlRequest::command(command, "a test");
        let replies = self
            .session
            .get(self.keys.packml(resource))
            .payload(serde_json::to_vec(&request)?)
            .timeout(WAIT)
            .await
            .map_err(|e| anyhow!("{e}"))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|_| anyhow!("{resource} did not answer the PackML {command}"))?;
        let sample = reply.result().map_err(|e| {
            anyhow!(
                "{resource} rejected the PackML {command}: {}",
                e.payload().try_to_string().unwrap_or_default()
            )
        })?;
        let answer: schemas::PackmlReply = serde_json::from_slice(&sample.payload().to_bytes())?;
        if let Some(why) = &answer.detail {
            bail!("{resource} refused {command}: {why}");
        }
        Ok(answer)
    }

    /// Waits until `resource` is in the PackML state numbered `state`.
    pub async fn wait_packml(&self, resource: &str, state: i32) -> Result<serde_json::Value> {
        self.wait_state(resource, &format!("PackML state {state}"), |s| {
            s["packml"]["state_number"] == state
        })
        .await
    }

    /// Waits until `resource` is free again.
    pub async fn wait_free(&self, resource: &str) -> Result<()> {
        self.wait_state(resource, "free again", |s| s["state"] == "free")
            .await
            .map(|_| ())
    }

    /// Submits a work order on `orders/submit` and returns the new orders' names.
    pub async fn submit(&self, product: &str, count: u32) -> Result<Vec<String>> {
        self.submit_work(schemas::WorkOrder {
            product: product.into(),
            count,
            priority: 0,
            due: None,
            queue: false,
        })
        .await
    }

    /// Submits `work` on `orders/submit` and returns the new orders' names.
    pub async fn submit_work(&self, work: schemas::WorkOrder) -> Result<Vec<String>> {
        submit_on(&self.session, &self.keys, &work).await
    }
}

/// How to start a [`Resource`] (from [`Cell::resource`]): the simulator's flags, the
/// controller's command timeout (5 s unless set), lines appended to the config written
/// by [`resource_config`], and the holon-node's extra flags.
pub struct ResourceBuilder<'a> {
    cell: &'a Cell,
    dir: PathBuf,
    name: String,
    sim_flags: Vec<String>,
    command_timeout_ms: u64,
    config_extra: String,
    node_flags: Vec<String>,
    /// The controller dialect of both the simulator and the holon (None: the default).
    dialect: Option<String>,
}

impl ResourceBuilder<'_> {
    /// Flags of `robot-sim` (e.g. `--delay-ms 100`).
    pub fn sim_flags(mut self, flags: &[&str]) -> Self {
        self.sim_flags = flags.iter().map(|f| f.to_string()).collect();
        self
    }

    pub fn command_timeout_ms(mut self, timeout: u64) -> Self {
        self.command_timeout_ms = timeout;
        self
    }

    /// TOML appended to the resource's config (e.g. an `[agenda]` table).
    pub fn config(mut self, extra: &str) -> Self {
        self.config_extra.push_str(extra);
        self
    }

    /// The controller dialect both the simulator and the holon speak (a shipped name or
    /// a file), set in the config's `[controller]` section and by `--dialect`.
    pub fn dialect(mut self, dialect: &str) -> Self {
        self.dialect = Some(dialect.to_string());
        self
    }

    /// Extra flags of `holon-node` (e.g. `--data-dir DIR`).
    pub fn node_flags(mut self, flags: &[&str]) -> Self {
        self.node_flags = flags.iter().map(|f| f.to_string()).collect();
        self
    }

    /// Starts the simulator (`<name>-sim`), writes the config (`<name>.toml`) and starts
    /// the resource holon on it, and waits until the holon is alive and free.
    pub async fn start(self) -> Result<Resource> {
        let mut sim_flags: Vec<&str> = self.sim_flags.iter().map(String::as_str).collect();
        if let Some(dialect) = &self.dialect {
            sim_flags.extend(["--dialect", dialect.as_str()]);
        }
        let sim = Sim::start(
            &self.dir,
            &format!("{}-sim", self.name),
            "127.0.0.1:0",
            &sim_flags,
        )?;
        let config = resource_config(&self.dir, &self.name, self.command_timeout_ms)?;
        if let Some(dialect) = &self.dialect {
            let text = fs::read_to_string(&config)?.replacen(
                "[controller]\n",
                &format!("[controller]\ndialect = {dialect:?}\n"),
                1,
            );
            fs::write(&config, text)?;
        }
        if !self.config_extra.is_empty() {
            let mut text = fs::read_to_string(&config)?;
            text.push_str(&self.config_extra);
            fs::write(&config, text)?;
        }
        let node_flags: Vec<&str> = self.node_flags.iter().map(String::as_str).collect();
        let node = self
            .cell
            .start_free_resource(&self.dir, &config, &sim.address, &node_flags)
            .await
            .with_context(|| format!("resource {} on its simulator", self.name))?;
        Ok(Resource { sim, node, config })
    }
}

/// A resource with its simulator, ready: the holon is alive and free. Both processes
/// are killed when it is dropped.
pub struct Resource {
    pub node: Process,
    pub sim: Sim,
    /// The resource's config, to start it (or a successor) again.
    pub config: PathBuf,
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

/// Whether this machine can run the network-namespace tests (the multi-host test and the
/// netns scripts): root, and `ip netns` works (a namespace is made and deleted). `Err`
/// says why not, and the test skips, unless `HOLARCHY_REQUIRE_NETNS` is set (CI sets it,
/// as root): then a machine that cannot run them fails the test instead.
pub fn netns_available() -> std::result::Result<(), String> {
    let available = netns_probe();
    if let Err(why) = &available {
        if std::env::var_os("HOLARCHY_REQUIRE_NETNS").is_some() {
            panic!(
                "HOLARCHY_REQUIRE_NETNS is set but network namespaces cannot be used here: {why}"
            );
        }
    }
    available
}

/// Root, and a namespace can be made and deleted.
fn netns_probe() -> std::result::Result<(), String> {
    if !nix::unistd::Uid::effective().is_root() {
        return Err("not root".into());
    }
    // Unique per call: tests of one binary probe at the same time.
    static PROBES: std::sync::atomic::AtomicU32 = std::sync::atomic::AtomicU32::new(0);
    let n = PROBES.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    let probe = format!("hlpr{}x{n}", std::process::id() % 100_000);
    match Command::new("ip").args(["netns", "add", &probe]).status() {
        Ok(s) if s.success() => {
            let _ = Command::new("ip").args(["netns", "del", &probe]).status();
            Ok(())
        }
        Ok(_) => Err("ip netns add is refused".into()),
        Err(e) => Err(format!("no `ip` command (apt-get install iproute2): {e}")),
    }
}

// --- `cell opcua` (tests/tests/opcua.rs) ---

/// Starts `bin(program)` with `args`, its stderr in `dir/<name>.stderr`, stdout dropped.
pub fn start_program(dir: &Path, program: &str, name: &str, args: &[&str]) -> Result<Process> {
    let stderr_path = dir.join(format!("{name}.stderr"));
    let child = Command::new(bin(program))
        .args(args)
        .stdout(Stdio::null())
        .stderr(fs::File::create(&stderr_path)?)
        .spawn()
        .with_context(|| format!("start {program}"))?;
    Ok(Process {
        name: name.to_string(),
        child: Some(child),
        stderr_path,
    })
}

/// Waits, at most [`WAIT`], until something accepts TCP connections on `address`.
pub async fn wait_listening(address: &str) -> Result<()> {
    let deadline = tokio::time::Instant::now() + WAIT;
    while tokio::net::TcpStream::connect(address).await.is_err() {
        if tokio::time::Instant::now() >= deadline {
            bail!("nothing listens on {address} after {WAIT:?}");
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Ok(())
}

/// The Python with asyncua for the OPC UA tests (docs/opcua.md, "Testing"): env
/// `HOLARCHY_OPCUA_PYTHON`, default `target/opcua-venv/bin/python`. `None` when it is
/// missing or has no asyncua (the test then skips), unless `HOLARCHY_REQUIRE_OPCUA=1`:
/// then it panics.
pub fn opcua_python() -> Option<PathBuf> {
    let python = std::env::var_os("HOLARCHY_OPCUA_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace_root().join("target/opcua-venv/bin/python"));
    let works = Command::new(&python)
        .args(["-c", "import asyncua"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    if works {
        return Some(python);
    }
    let why = format!(
        "no Python with asyncua at {} (python3 -m venv target/opcua-venv && target/opcua-venv/bin/pip install asyncua==2.1.0, or set HOLARCHY_OPCUA_PYTHON)",
        python.display()
    );
    if std::env::var("HOLARCHY_REQUIRE_OPCUA").is_ok_and(|v| v == "1") {
        panic!("HOLARCHY_REQUIRE_OPCUA=1 but {why}");
    }
    eprintln!("SKIPPED: {why}");
    None
}

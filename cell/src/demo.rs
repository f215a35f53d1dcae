//! `cell demo`: a demo cell on this machine, with no other install.
//!
//! It starts a controller simulator (`robot-sim`) and a resource holon (`holon-node`
//! with the documented demo config) as real processes, joins them over zenoh, and acts
//! as the requester of `--jobs` pick-'n-place jobs, each through the whole contract:
//! proposal, booking, start, `done` delivered to its inbox and acknowledged. It shows
//! every job as it completes, prints a summary, stops what it started and exits 0 only
//! if every job completed.

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use schemas::{CellKeys, HolonId, MessageType, Service};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::{Child, Command};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use zenoh::query::ConsolidationMode;

/// The demo's resource config: the documented example in deploy/cells/demo/.
const ROBOT_CONFIG: &str = include_str!("../../deploy/cells/demo/robot1.toml");

/// The longest the demo waits for one step of a job.
const STEP_TIMEOUT: Duration = Duration::from_secs(30);

#[derive(Debug, Clone)]
pub struct DemoOptions {
    pub cell: String,
    pub jobs: u32,
    /// Simulated duration of each controller action.
    pub action_delay: Duration,
    /// Where configs and logs go; a temporary directory when not given.
    pub dir: Option<PathBuf>,
}

/// A child process stopped with SIGTERM (then killed) when the demo ends.
struct Managed {
    name: String,
    child: Child,
}

impl Managed {
    async fn stop(mut self) -> Result<std::process::ExitStatus> {
        if let Some(pid) = self.child.id() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(pid as i32),
                nix::sys::signal::Signal::SIGTERM,
            );
        }
        match tokio::time::timeout(Duration::from_secs(10), self.child.wait()).await {
            Ok(status) => Ok(status?),
            Err(_) => {
                self.child.kill().await?;
                bail!("{} did not stop within 10 s; killed", self.name)
            }
        }
    }
}

fn sibling_binary(name: &str) -> Result<PathBuf> {
    let exe = std::env::current_exe().context("cannot find this executable")?;
    let path = exe
        .parent()
        .ok_or_else(|| anyhow!("executable has no directory"))?
        .join(name);
    if !path.exists() {
        bail!(
            "{} not found next to cell; build the workspace (cargo build --bins)",
            path.display()
        );
    }
    Ok(path)
}

fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

async fn start_sim(dir: &Path, delay: Duration) -> Result<(Managed, String)> {
    let mut child = Command::new(sibling_binary("robot-sim")?)
        .args(["--listen", "127.0.0.1:0", "--delay-ms"])
        .arg(delay.as_millis().to_string())
        .arg("--count-file")
        .arg(dir.join("robot1-sim.counts.json"))
        .stdout(Stdio::piped())
        .stderr(std::fs::File::create(dir.join("robot1-sim.log"))?)
        .kill_on_drop(true)
        .spawn()
        .context("cannot start robot-sim")?;
    let stdout = child.stdout.take().expect("piped");
    let mut line = String::new();
    tokio::time::timeout(
        Duration::from_secs(10),
        BufReader::new(stdout).read_line(&mut line),
    )
    .await
    .context("robot-sim did not start within 10 s")??;
    let address = line
        .trim()
        .strip_prefix("listening on ")
        .ok_or_else(|| anyhow!("robot-sim said {line:?}"))?
        .to_string();
    Ok((
        Managed {
            name: "robot-sim".into(),
            child,
        },
        address,
    ))
}

/// Runs the demo; returns whether every job completed.
pub async fn run(options: DemoOptions, shutdown: CancellationToken) -> Result<bool> {
    let keys = CellKeys::new(&options.cell)?;
    let mut temp = None;
    let dir = match &options.dir {
        Some(dir) => {
            std::fs::create_dir_all(dir)?;
            dir.clone()
        }
        None => {
            let made = tempdir()?;
            let path = made.path.clone();
            temp = Some(made);
            path
        }
    };
    let endpoint = format!("tcp/127.0.0.1:{}", free_port()?);
    let settings = holon::ZenohSettings {
        mode: "router".into(),
        listen: vec![endpoint.clone()],
        ..holon::ZenohSettings::default()
    };
    let session = settings
        .open(Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    println!(
        "cell {}: zenoh on {endpoint}; configs and logs in {}",
        options.cell,
        dir.display()
    );

    let (sim, controller) = start_sim(&dir, options.action_delay).await?;
    println!("started robot-sim (controller) on {controller}");
    let config = dir.join("robot1.toml");
    std::fs::write(&config, ROBOT_CONFIG)?;
    let node = Command::new(sibling_binary("holon-node")?)
        .arg("--config")
        .arg(&config)
        .args(["--cell", &options.cell, "--connect", &endpoint])
        .args(["--listen", "tcp/127.0.0.1:0"])
        .args(["--controller", &controller])
        .arg("--log-file")
        .arg(dir.join("robot1.log.json"))
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(dir.join("robot1.log"))?)
        .kill_on_drop(true)
        .spawn()
        .context("cannot start holon-node")?;
    let node = Managed {
        name: "holon-node".into(),
        child: node,
    };
    let robot = HolonId::resource("robot1")?;
    let launched = Instant::now();
    if !holon::presence::wait_alive(&session, &keys, &robot, Duration::from_secs(10))
        .await
        .map_err(|e| anyhow!("{e}"))?
    {
        bail!(
            "robot1 did not come up; see {}",
            dir.join("robot1.log").display()
        );
    }
    println!(
        "resource/robot1 is alive ({} ms after launch)",
        launched.elapsed().as_millis()
    );

    let outcome = tokio::select! {
        outcome = drive(&session, &keys, &options) => outcome,
        _ = shutdown.cancelled() => Err(anyhow!("interrupted")),
    };

    print!("stopping: holon-node");
    let node_status = node.stop().await;
    print!(", robot-sim");
    let sim_status = sim.stop().await;
    println!(" ... done");
    let _ = session.close().await;
    let counts = std::fs::read_to_string(dir.join("robot1-sim.counts.json")).unwrap_or_default();
    let summary = outcome?;
    println!();
    println!("summary");
    println!("  jobs done      {}", summary.done);
    println!("  jobs failed    {}", summary.failed);
    println!("  time taken     {:.2} s", summary.elapsed.as_secs_f64());
    if !summary.cycles.is_empty() {
        let mut cycles = summary.cycles.clone();
        cycles.sort();
        println!(
            "  job cycle      p50 {} ms, max {} ms (book, start, 2 controller steps, done)",
            cycles[cycles.len() / 2].as_millis(),
            cycles[cycles.len() - 1].as_millis()
        );
    }
    println!("  controller     {}", counts.trim());
    if let Ok(status) = node_status {
        println!("  holon-node     exited with {status}");
    }
    if let Ok(status) = sim_status {
        println!("  robot-sim      exited with {status}");
    }
    let success = summary.failed == 0 && summary.done == options.jobs;
    if let (Some(temp), false) = (temp.as_mut(), success) {
        temp.keep = true;
        println!("  logs kept in   {}", dir.display());
    }
    Ok(success)
}

struct Summary {
    done: u32,
    failed: u32,
    elapsed: Duration,
    cycles: Vec<Duration>,
}

/// Acts as the requester of every job: proposal, booking, start, wait for `done`.
async fn drive(
    session: &zenoh::Session,
    keys: &CellKeys,
    options: &DemoOptions,
) -> Result<Summary> {
    let requester = HolonId::order("demo")?;
    let inbox_key = keys.inbox(requester.name());
    let (tx, mut results) = mpsc::unbounded_channel::<Service>();
    let _inbox = session
        .declare_queryable(&inbox_key)
        .callback(move |query| {
            use zenoh::Wait;
            let payload = query
                .payload()
                .map(|p| p.to_bytes().into_owned())
                .unwrap_or_default();
            match Service::from_json(&payload) {
                Ok(message) => {
                    let mut ack = message.clone();
                    ack.result = Some(true);
                    let _ = query.reply(query.key_expr().clone(), ack.to_json()).wait();
                    let _ = tx.send(message);
                }
                Err(e) => {
                    let _ = query
                        .reply_err(schemas::ErrorReply::new("invalid", e.to_string()).to_json())
                        .wait();
                }
            }
        })
        .await
        .map_err(|e| anyhow!("{e}"))?;

    let started = Instant::now();
    let mut summary = Summary {
        done: 0,
        failed: 0,
        elapsed: Duration::ZERO,
        cycles: Vec::new(),
    };
    for job in 1..=options.jobs {
        let conversation = format!("demo/{job}/1");
        let info = serde_json::json!({
            "pick": {"x": 100.0 + job as f64, "y": 20.0, "z": 5.0, "a": 0.0, "b": 0.0, "c": 0.0},
            "place": {"x": 300.0, "y": 40.0 + job as f64, "z": 5.0, "a": 0.0, "b": 0.0, "c": 90.0}
        });
        let request = |kind| {
            Service::request(kind, "pick_n_place", &conversation, requester.clone())
                .with_reply_to(inbox_key.clone())
                .with_info(info.as_object().expect("object").clone())
        };
        let t0 = Instant::now();
        let Some(best) = best_proposal(session, keys, &request(MessageType::ProposalReq)).await?
        else {
            println!(
                "[{job}/{}] no resource proposed pick_n_place within {STEP_TIMEOUT:?}",
                options.jobs
            );
            summary.failed += 1;
            continue;
        };
        let service_key = keys.service(best.name());
        let booked = ask_one(session, &service_key, &request(MessageType::BookingReq)).await?;
        let started_job = if booked.result == Some(true) {
            ask_one(session, &service_key, &request(MessageType::Start)).await?
        } else {
            booked
        };
        if started_job.result != Some(true) {
            println!(
                "[{job}/{}] {best} refused: {}",
                options.jobs,
                started_job.reason.unwrap_or_default()
            );
            summary.failed += 1;
            continue;
        }
        let result = loop {
            let message = tokio::time::timeout(STEP_TIMEOUT, results.recv())
                .await
                .map_err(|_| anyhow!("no result for {conversation} within {STEP_TIMEOUT:?}"))?
                .ok_or_else(|| anyhow!("inbox closed"))?;
            if message.conversation_id == conversation {
                break message;
            }
        };
        let cycle = t0.elapsed();
        if result.message_type == MessageType::Done {
            summary.done += 1;
            summary.cycles.push(cycle);
            println!(
                "[{job}/{}] {conversation}: done by {best} in {} ms ({})",
                options.jobs,
                cycle.as_millis(),
                serde_json::Value::Object(
                    result
                        .info
                        .get("results")
                        .and_then(|r| r.as_object())
                        .cloned()
                        .unwrap_or_default()
                )
            );
        } else {
            summary.failed += 1;
            println!(
                "[{job}/{}] {conversation}: failed on {best}: {}",
                options.jobs,
                result.reason.unwrap_or_default()
            );
        }
    }
    summary.elapsed = started.elapsed();
    Ok(summary)
}

/// Proposal rounds until a resource proposes (one that is still connecting to its
/// controller says `unavailable`): the provider with the shortest expected wait.
async fn best_proposal(
    session: &zenoh::Session,
    keys: &CellKeys,
    request: &Service,
) -> Result<Option<HolonId>> {
    let deadline = Instant::now() + STEP_TIMEOUT;
    loop {
        let proposals = ask_all(session, &keys.offers(&request.service_type), request).await?;
        let best = proposals
            .iter()
            .filter(|p| p.result == Some(true))
            .min_by_key(|p| {
                p.info
                    .get("expected_wait_ms")
                    .and_then(|v| v.as_u64())
                    .unwrap_or(u64::MAX)
            })
            .and_then(|p| p.provider.clone());
        if best.is_some() || Instant::now() > deadline {
            return Ok(best);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn ask_all(session: &zenoh::Session, key: &str, message: &Service) -> Result<Vec<Service>> {
    let replies = session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let mut answers = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            answers.push(Service::from_json(&sample.payload().to_bytes())?);
        }
    }
    Ok(answers)
}

async fn ask_one(session: &zenoh::Session, key: &str, message: &Service) -> Result<Service> {
    let replies = session
        .get(key)
        .payload(message.to_json())
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(5))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let reply = replies
        .recv_async()
        .await
        .map_err(|_| anyhow!("no answer from {key}"))?;
    match reply.result() {
        Ok(sample) => Ok(Service::from_json(&sample.payload().to_bytes())?),
        Err(err) => bail!(
            "{key} answered with an error: {}",
            err.payload().try_to_string().unwrap_or_default()
        ),
    }
}

/// A temporary directory removed when dropped, unless kept for its logs.
struct TempDir {
    path: PathBuf,
    keep: bool,
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if !self.keep {
            let _ = std::fs::remove_dir_all(&self.path);
        }
    }
}

fn tempdir() -> Result<TempDir> {
    let path = std::env::temp_dir().join(format!(
        "holarchy-demo-{}-{}",
        std::process::id(),
        schemas::unix_ms()
    ));
    std::fs::create_dir_all(&path)?;
    Ok(TempDir { path, keep: false })
}

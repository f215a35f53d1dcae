//! `cell up DIR`: launches the processes of a cell from the manifest `DIR/cell.toml` and
//! supervises them like an OTP supervisor (one_for_one): a process that dies is
//! restarted after a backoff that doubles while it keeps dying; more than
//! `restart.max_restarts` restarts within `restart.period_ms` (all processes together)
//! stops everything and exits non-zero. Ctrl-C or SIGTERM stops the processes in
//! reverse order (SIGTERM, then SIGKILL after `restart.stop_timeout_ms`). It runs the
//! cell's zenoh router in its own process when the manifest has a `[router]`.
//!
//! The manifest format is documented in `deploy/cells/demo/cell.toml`.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::process::{ExitStatus, Stdio};
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use serde::Deserialize;
use tokio::process::Command;
use tokio::task::JoinSet;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    pub cell: String,
    /// The router of host `local` (the manifests of one-host cells).
    #[serde(default)]
    pub router: Option<RouterSection>,
    /// Per host: its router (`[hosts.<name>.router]`).
    #[serde(default)]
    pub hosts: std::collections::BTreeMap<String, HostSection>,
    #[serde(default)]
    pub restart: RestartSection,
    /// The cell's identities for mutual TLS (`cell certs`); see docs/security.md.
    #[serde(default)]
    pub pki: PkiSection,
    #[serde(rename = "process")]
    pub processes: Vec<ProcessSection>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RouterSection {
    pub listen: Vec<String>,
    /// Other hosts' routers.
    #[serde(default)]
    pub connect: Vec<String>,
    /// The link lease in ms.
    #[serde(default)]
    pub lease_ms: Option<u64>,
}

impl RouterSection {
    /// The router's zenoh settings; with `tls/` endpoints, mutual TLS and the cell's
    /// access control from the PKI directory `pki` (identity `router.<host>`).
    pub fn settings(&self, pki: &Path) -> holon::ZenohSettings {
        let secure = self
            .listen
            .iter()
            .chain(&self.connect)
            .any(|e| e.starts_with("tls/"));
        holon::ZenohSettings {
            mode: "router".into(),
            listen: self.listen.clone(),
            connect: self.connect.clone(),
            lease_ms: self.lease_ms,
            tls: secure.then(|| holon::tls::TlsSettings {
                pki: Some(pki.to_path_buf()),
                ..holon::tls::TlsSettings::default()
            }),
            ..holon::ZenohSettings::default()
        }
    }
}

#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HostSection {
    #[serde(default)]
    pub router: Option<RouterSection>,
    /// The host's addresses (IPs or DNS names) other processes reach it by; they go
    /// into the certificates of its processes (besides its router's listen addresses).
    #[serde(default)]
    pub addresses: Vec<String>,
}

/// `[pki]`: where `cell certs` writes the identities, and which identities exist
/// besides the processes' (`identity` of each `[[process]]`, `router.<host>` for each
/// router).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PkiSection {
    /// The PKI directory, relative to the manifest's (default "pki").
    #[serde(default = "d_pki_dir")]
    pub dir: PathBuf,
    /// Operators (`operator.<name>`): submit and cancel orders, read everything.
    #[serde(default = "d_default_name")]
    pub operators: Vec<String>,
    /// Observers (`observer.<name>`): read states, plans and presence only.
    #[serde(default = "d_default_name")]
    pub observers: Vec<String>,
    /// Identities provisioned ahead for holons not started yet (hot-add), e.g.
    /// `resource.robot3`: the running processes' access control knows them already.
    #[serde(default)]
    pub spares: Vec<String>,
    /// Validity of each issued certificate, in days (default 365).
    #[serde(default = "d_days")]
    pub days: u32,
}

fn d_pki_dir() -> PathBuf {
    PathBuf::from("pki")
}
fn d_default_name() -> Vec<String> {
    vec!["default".into()]
}
fn d_days() -> u32 {
    365
}

impl Default for PkiSection {
    fn default() -> Self {
        PkiSection {
            dir: d_pki_dir(),
            operators: d_default_name(),
            observers: d_default_name(),
            spares: Vec::new(),
            days: d_days(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RestartSection {
    #[serde(default = "d_max")]
    pub max_restarts: u32,
    #[serde(default = "d_period")]
    pub period_ms: u64,
    #[serde(default = "d_backoff")]
    pub backoff_initial_ms: u64,
    #[serde(default = "d_backoff_max")]
    pub backoff_max_ms: u64,
    #[serde(default = "d_stop")]
    pub stop_timeout_ms: u64,
}

fn d_max() -> u32 {
    10
}
fn d_period() -> u64 {
    60_000
}
fn d_backoff() -> u64 {
    250
}
fn d_backoff_max() -> u64 {
    10_000
}
fn d_stop() -> u64 {
    40_000
}

impl Default for RestartSection {
    fn default() -> Self {
        RestartSection {
            max_restarts: d_max(),
            period_ms: d_period(),
            backoff_initial_ms: d_backoff(),
            backoff_max_ms: d_backoff_max(),
            stop_timeout_ms: d_stop(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProcessSection {
    pub name: String,
    pub program: String,
    #[serde(default)]
    pub args: Vec<String>,
    /// Which host runs it (default `local`): `cell up --host NAME` starts the
    /// processes of host NAME.
    #[serde(default = "d_host")]
    pub host: String,
    /// Its TLS identity, `<role>.<name>` (e.g. `resource.robot1`): `cell certs` issues
    /// its certificate. Controllers' simulators have none.
    #[serde(default)]
    pub identity: Option<String>,
}

fn d_host() -> String {
    "local".into()
}

impl Manifest {
    pub fn load(dir: &Path) -> Result<Manifest> {
        let path = dir.join("cell.toml");
        let text = std::fs::read_to_string(&path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let manifest: Manifest =
            toml::from_str(&text).with_context(|| format!("{}", path.display()))?;
        schemas::validate_name("cell name", &manifest.cell)
            .with_context(|| format!("{}: cell", path.display()))?;
        if manifest.processes.is_empty() {
            bail!("{}: no [[process]]", path.display());
        }
        for host in manifest.hosts.keys() {
            schemas::validate_name("host name", host)
                .with_context(|| format!("{}: hosts", path.display()))?;
        }
        let mut names = std::collections::HashSet::new();
        for p in &manifest.processes {
            schemas::validate_name("process name", &p.name)
                .with_context(|| format!("{}: process", path.display()))?;
            if let Some(identity) = &p.identity {
                crate::access::parse_identity(identity)
                    .with_context(|| format!("{}: process {}", path.display(), p.name))?;
            }
            if !names.insert(&p.name) {
                bail!("{}: process {} appears twice", path.display(), p.name);
            }
            if p.host != "local" && !manifest.hosts.contains_key(&p.host) {
                bail!(
                    "{}: process {} runs on host {:?}, which has no [hosts.{}] section",
                    path.display(),
                    p.name,
                    p.host,
                    p.host
                );
            }
        }
        if manifest.restart.backoff_initial_ms == 0 || manifest.restart.period_ms == 0 {
            bail!("{}: restart periods must be greater than 0", path.display());
        }
        Ok(manifest)
    }
}

/// A program named in a manifest: a binary next to `cell` if there is one, else as given.
fn resolve(program: &str) -> PathBuf {
    if !program.contains('/') {
        if let Some(dir) = std::env::current_exe()
            .ok()
            .and_then(|e| e.parent().map(Path::to_path_buf))
        {
            let sibling = dir.join(program);
            if sibling.exists() {
                return sibling;
            }
        }
    }
    PathBuf::from(program)
}

fn say(started: Instant, text: impl std::fmt::Display) {
    println!("[{:8.2}s] {text}", started.elapsed().as_secs_f64());
}

struct Slot {
    pid: Option<u32>,
    generation: u64,
    backoff: Duration,
    started_at: Instant,
    restart_at: Option<Instant>,
}

/// Which hosts a manifest knows, for an operator who named another.
fn hosts_hint(manifest: &Manifest) -> String {
    let mut hosts: Vec<&str> = Vec::new();
    if manifest.router.is_some() || manifest.processes.iter().any(|p| p.host == "local") {
        hosts.push("local");
    }
    hosts.extend(manifest.hosts.keys().map(String::as_str));
    format!(
        "its hosts are {} (cell up DIR --host NAME)",
        hosts.join(", ")
    )
}

/// Runs the cell until `shutdown`; Ok(false) when the restart intensity was exceeded.
pub async fn run(dir: &Path, host: &str, shutdown: CancellationToken) -> Result<bool> {
    let mut manifest = Manifest::load(dir)?;
    let router = if host == "local" {
        manifest.router.clone()
    } else {
        match manifest.hosts.get(host) {
            Some(section) => section.router.clone(),
            None => bail!(
                "the manifest has no host {host:?}; {}",
                hosts_hint(&manifest)
            ),
        }
    };
    manifest.processes.retain(|p| p.host == host);
    if manifest.processes.is_empty() && router.is_none() {
        bail!(
            "the manifest gives host {host:?} nothing to run; {}",
            hosts_hint(&manifest)
        );
    }
    let clock = Instant::now();
    let logs = dir.join("logs");
    std::fs::create_dir_all(&logs)?;
    let _router = match &router {
        Some(router) => {
            let settings = router.settings(&crate::certs::pki_dir(dir, &manifest));
            let session = settings
                .open(
                    &holon::tls::identity("router", host),
                    Duration::from_secs(10),
                )
                .await
                .map_err(|e| anyhow!("router: {e}"))?;
            say(
                clock,
                format!(
                    "zenoh router of cell {} listening on {}",
                    manifest.cell,
                    router.listen.join(", ")
                ),
            );
            Some(session)
        }
        None => None,
    };
    let restart = &manifest.restart;
    let initial = Duration::from_millis(restart.backoff_initial_ms);
    let mut slots: Vec<Slot> = manifest
        .processes
        .iter()
        .map(|_| Slot {
            pid: None,
            generation: 0,
            backoff: initial,
            started_at: clock,
            restart_at: None,
        })
        .collect();
    let mut waits: JoinSet<(usize, u64, std::io::Result<ExitStatus>)> = JoinSet::new();
    let start = |index: usize, slots: &mut Vec<Slot>, waits: &mut JoinSet<_>| -> Result<()> {
        let spec = &manifest.processes[index];
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(logs.join(format!("{}.log", spec.name)))?;
        let mut child = Command::new(resolve(&spec.program))
            .args(&spec.args)
            .current_dir(dir)
            .stdin(Stdio::null())
            .stdout(log.try_clone()?)
            .stderr(log)
            .kill_on_drop(true)
            .spawn()
            .with_context(|| format!("cannot start {} ({})", spec.name, spec.program))?;
        let slot = &mut slots[index];
        slot.generation += 1;
        slot.pid = child.id();
        slot.started_at = Instant::now();
        slot.restart_at = None;
        let generation = slot.generation;
        say(
            clock,
            format!("started {} (pid {})", spec.name, slot.pid.unwrap_or(0)),
        );
        waits.spawn(async move { (index, generation, child.wait().await) });
        Ok(())
    };
    for index in 0..slots.len() {
        start(index, &mut slots, &mut waits)?;
    }
    let period = Duration::from_millis(restart.period_ms);
    let mut restarts: VecDeque<Instant> = VecDeque::new();
    let mut healthy = true;
    loop {
        let next_restart = slots.iter().filter_map(|s| s.restart_at).min();
        tokio::select! {
            _ = shutdown.cancelled() => break,
            Some(joined) = waits.join_next() => {
                let Ok((index, generation, status)) = joined else { continue };
                let slot = &mut slots[index];
                if slot.generation != generation {
                    continue;
                }
                slot.pid = None;
                let name = &manifest.processes[index].name;
                let status = status.map(|s| s.to_string()).unwrap_or_else(|e| e.to_string());
                // A process that ran for a whole period has earned a fresh backoff.
                if slot.started_at.elapsed() >= period {
                    slot.backoff = initial;
                }
                let now = Instant::now();
                restarts.push_back(now);
                while restarts.front().is_some_and(|t| now.duration_since(*t) > period) {
                    restarts.pop_front();
                }
                if restarts.len() > restart.max_restarts as usize {
                    say(clock, format!("{name} exited ({status}); more than {} restarts within {:?}: giving up", restart.max_restarts, period));
                    healthy = false;
                    break;
                }
                say(clock, format!("{name} exited ({status}); restarting in {} ms", slot.backoff.as_millis()));
                slot.restart_at = Some(now + slot.backoff);
                slot.backoff = (slot.backoff * 2).min(Duration::from_millis(restart.backoff_max_ms));
            }
            _ = async { tokio::time::sleep_until(next_restart.unwrap_or_else(Instant::now)).await }, if next_restart.is_some() => {
                let now = Instant::now();
                for index in 0..slots.len() {
                    if slots[index].restart_at.is_some_and(|t| t <= now) {
                        if let Err(e) = start(index, &mut slots, &mut waits) {
                            say(clock, format!("{e:#}; retrying"));
                            slots[index].restart_at = Some(now + slots[index].backoff);
                        }
                    }
                }
            }
        }
    }
    say(clock, "stopping the cell, in reverse order");
    let stop_timeout = Duration::from_millis(restart.stop_timeout_ms);
    for index in (0..slots.len()).rev() {
        let Some(pid) = slots[index].pid.take() else {
            continue;
        };
        let name = &manifest.processes[index].name;
        let generation = slots[index].generation;
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(pid as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
        let deadline = Instant::now() + stop_timeout;
        loop {
            match tokio::time::timeout_at(deadline, waits.join_next()).await {
                Ok(Some(Ok((i, g, status)))) if i == index && g == generation => {
                    let status = status
                        .map(|s| s.to_string())
                        .unwrap_or_else(|e| e.to_string());
                    say(clock, format!("stopped {name} ({status})"));
                    break;
                }
                Ok(Some(Ok((i, g, status)))) => {
                    // Another process ended meanwhile (e.g. it got the same signal).
                    if slots[i].generation == g && slots[i].pid.take().is_some() {
                        let status = status
                            .map(|s| s.to_string())
                            .unwrap_or_else(|e| e.to_string());
                        say(
                            clock,
                            format!("stopped {} ({status})", manifest.processes[i].name),
                        );
                    }
                }
                Ok(Some(Err(_))) => {}
                Ok(None) => break,
                Err(_) => {
                    let _ = nix::sys::signal::kill(
                        nix::unistd::Pid::from_raw(pid as i32),
                        nix::sys::signal::Signal::SIGKILL,
                    );
                    say(
                        clock,
                        format!("{name} did not stop within {stop_timeout:?}; killed"),
                    );
                    break;
                }
            }
        }
    }
    say(clock, "cell stopped");
    Ok(healthy)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(flavor = "multi_thread")]
    async fn a_host_with_nothing_to_run_names_the_hosts() {
        let dir = Path::new(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../deploy/cells/factory"
        ));
        let err = run(dir, "local", CancellationToken::new())
            .await
            .unwrap_err()
            .to_string();
        assert!(err.contains("its hosts are a, b, c"), "{err}");
    }

    #[test]
    fn the_demo_manifest_loads() {
        let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/cells/demo"));
        let manifest = Manifest::load(dir).unwrap();
        assert_eq!(manifest.cell, "demo");
        let names: Vec<&str> = manifest.processes.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names.first(), Some(&"robot1-sim"));
        assert_eq!(names.last(), Some(&"orders1"));
        assert_eq!(manifest.restart.max_restarts, 10);
    }
}

//! The manifest of a cell, `DIR/cell.toml`: its processes, routers, hosts, restart
//! policy and PKI. `cell up` runs it, `cell certs` issues its identities; the format is
//! documented in `deploy/cells/demo/cell.toml`.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use holon::RestartType;
use serde::Deserialize;

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
    /// The plant runs this many times faster than real time (docs/scheduling.md,
    /// "Scaled time"): `cell up` gives every `plant-sim` and `holon-node` process
    /// `--time-scale` with it. None: real time (or `cell up --time-scale`).
    #[serde(default)]
    pub time_scale: Option<f64>,
}

/// The programs that take `--time-scale`: the plant and the resource holons.
const SCALED_PROGRAMS: [&str; 2] = ["plant-sim", "holon-node"];

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
            mode: holon::Mode::Router,
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
    #[serde(default = "default_pki_dir")]
    pub dir: PathBuf,
    /// Operators (`operator.<name>`): submit and cancel orders, read everything.
    #[serde(default = "default_default_name")]
    pub operators: Vec<String>,
    /// Observers (`observer.<name>`): read states, plans and presence only.
    #[serde(default = "default_default_name")]
    pub observers: Vec<String>,
    /// Identities provisioned ahead for holons not started yet (hot-add), e.g.
    /// `resource.robot3`: the running processes' access control knows them already.
    #[serde(default)]
    pub spares: Vec<String>,
    /// Validity of each issued certificate, in days (default 365).
    #[serde(default = "default_days")]
    pub days: u32,
    /// The hosts that run an etcd member (`local`, or hosts of `[hosts]`): each gets
    /// `etcd.<host>`, a server and client certificate with the host's addresses, for
    /// its client URL (the order-nodes' journal) and its peer links.
    #[serde(default)]
    pub etcd_hosts: Vec<String>,
}

fn default_pki_dir() -> PathBuf {
    PathBuf::from("pki")
}
fn default_default_name() -> Vec<String> {
    vec!["default".into()]
}
fn default_days() -> u32 {
    365
}

impl Default for PkiSection {
    fn default() -> Self {
        PkiSection {
            dir: default_pki_dir(),
            operators: default_default_name(),
            observers: default_default_name(),
            spares: Vec::new(),
            days: default_days(),
            etcd_hosts: Vec::new(),
        }
    }
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RestartSection {
    #[serde(default = "default_max")]
    pub max_restarts: u32,
    #[serde(default = "default_period")]
    pub period_ms: u64,
    #[serde(default = "default_backoff")]
    pub backoff_initial_ms: u64,
    #[serde(default = "default_backoff_max")]
    pub backoff_max_ms: u64,
    #[serde(default = "default_stop")]
    pub stop_timeout_ms: u64,
}

fn default_max() -> u32 {
    10
}
fn default_period() -> u64 {
    60_000
}
fn default_backoff() -> u64 {
    250
}
fn default_backoff_max() -> u64 {
    10_000
}
fn default_stop() -> u64 {
    40_000
}

impl Default for RestartSection {
    fn default() -> Self {
        RestartSection {
            max_restarts: default_max(),
            period_ms: default_period(),
            backoff_initial_ms: default_backoff(),
            backoff_max_ms: default_backoff_max(),
            stop_timeout_ms: default_stop(),
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
    #[serde(default = "default_host")]
    pub host: String,
    /// Its TLS identity, `<role>.<name>` (e.g. `resource.robot1`): `cell certs` issues
    /// its certificate. Controllers' simulators have none.
    #[serde(default)]
    pub identity: Option<String>,
    /// When it is restarted: `permanent` (default: whenever it exits), `transient`
    /// (only when it fails; exit status 0 means its work is done) or `temporary` (never).
    #[serde(default)]
    pub restart: RestartType,
    /// Another host that runs a standby of this process: `cell up --host` there starts
    /// it too. For a resource holon (`holon-node`, identity `resource.<name>`) whose
    /// controller fences (docs/reliability.md, "Standby resources"), or an order-node
    /// (`order-node`, identity `order-node.<name>`) whose config keeps its orders on
    /// etcd (`[journal] etcd`, "Order-node standby on etcd"). Both copies are started
    /// with `--standby`: the one that holds the controller's claim (the etcd leader
    /// key) serves, the other waits and takes over when the holder's lease ends.
    #[serde(default)]
    pub standby_on: Option<String>,
    /// The standby's arguments, where they differ from `args`: its own host's router
    /// (`--connect`) and data directory. Default: `args`.
    #[serde(default)]
    pub standby_args: Option<Vec<String>>,
    /// True on the copy that `standby_on` names, as [`Manifest::for_host`] gives it.
    #[serde(skip)]
    pub standby: bool,
}

/// The flag that makes a resource holon claim its controller before it serves.
pub const STANDBY_FLAG: &str = "--standby";

fn default_host() -> String {
    "local".into()
}

impl ProcessSection {
    /// Whether this process may have a standby on `standby_on`: a resource holon, on
    /// another host.
    fn check_standby(&self, standby_on: &str) -> Result<()> {
        if standby_on == self.host {
            bail!("standby_on: {standby_on:?} is the host it runs on; a standby belongs on another host");
        }
        let identity = self.identity.as_deref().unwrap_or_default();
        let program = Path::new(&self.program)
            .file_name()
            .and_then(|name| name.to_str())
            .unwrap_or_default();
        let resource = identity.starts_with("resource.") && program == "holon-node";
        let order_node = identity.starts_with("order-node.") && program == "order-node";
        if !(resource || order_node) {
            bail!("standby_on: only a resource holon (program holon-node, identity resource.<name>) or an order-node (program order-node, identity order-node.<name>, its config with [journal] etcd) can have a standby");
        }
        Ok(())
    }
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
                crate::security::access::parse_identity(identity)
                    .with_context(|| format!("{}: process {}", path.display(), p.name))?;
            }
            if !names.insert(&p.name) {
                bail!("{}: process {} appears twice", path.display(), p.name);
            }
            for host in std::iter::once(&p.host).chain(&p.standby_on) {
                if host != "local" && !manifest.hosts.contains_key(host) {
                    bail!(
                        "{}: process {} runs on host {host:?}, which has no [hosts.{host}] section",
                        path.display(),
                        p.name,
                    );
                }
            }
            if let Some(standby_on) = &p.standby_on {
                p.check_standby(standby_on)
                    .with_context(|| format!("{}: process {}", path.display(), p.name))?;
            } else if p.standby_args.is_some() {
                bail!(
                    "{}: process {}: standby_args without standby_on",
                    path.display(),
                    p.name
                );
            }
        }
        if manifest.restart.backoff_initial_ms == 0 || manifest.restart.period_ms == 0 {
            bail!("{}: restart periods must be greater than 0", path.display());
        }
        Ok(manifest)
    }

    /// The part of the manifest host `host` runs: its router, if it has one, and the
    /// manifest with only its processes.
    pub fn for_host(mut self, host: &str) -> Result<(Manifest, Option<RouterSection>)> {
        let router = if host == "local" {
            self.router.clone()
        } else {
            match self.hosts.get(host) {
                Some(section) => section.router.clone(),
                None => bail!("the manifest has no host {host:?}; {}", self.hosts_hint()),
            }
        };
        self.processes.retain_mut(|p| {
            if p.standby_on.as_deref() == Some(host) {
                p.host = host.to_string();
                p.standby = true;
                if let Some(args) = p.standby_args.take() {
                    p.args = args;
                }
            }
            p.host == host
        });
        for p in &mut self.processes {
            if p.standby_on.is_some() && !p.args.iter().any(|a| a == STANDBY_FLAG) {
                p.args.push(STANDBY_FLAG.into());
            }
        }
        if let Some(factor) = self.time_scale {
            let scale =
                schemas::TimeScale::new(factor).map_err(|e| anyhow::anyhow!("time_scale: {e}"))?;
            for p in &mut self.processes {
                let program = Path::new(&p.program).file_name().and_then(|n| n.to_str());
                let scaled = program.is_some_and(|name| SCALED_PROGRAMS.contains(&name));
                if scaled && !p.args.iter().any(|a| a == "--time-scale") {
                    p.args
                        .extend(["--time-scale".to_string(), scale.to_string()]);
                }
            }
        }
        if self.processes.is_empty() && router.is_none() {
            bail!(
                "the manifest gives host {host:?} nothing to run; {}",
                self.hosts_hint()
            );
        }
        Ok((self, router))
    }

    /// Which hosts the manifest knows, for an operator who named another.
    fn hosts_hint(&self) -> String {
        let mut hosts: Vec<&str> = Vec::new();
        if self.router.is_some() || self.processes.iter().any(|p| p.host == "local") {
            hosts.push("local");
        }
        hosts.extend(self.hosts.keys().map(String::as_str));
        format!(
            "its hosts are {} (cell up DIR --host NAME)",
            hosts.join(", ")
        )
    }

    /// The restart intensity of `[restart]`, all processes together.
    pub fn intensity(&self) -> holon::Intensity {
        holon::Intensity {
            max_restarts: self.restart.max_restarts,
            period: std::time::Duration::from_millis(self.restart.period_ms),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_demo_manifest_loads() {
        let dir = Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/cells/demo"));
        let manifest = Manifest::load(dir).unwrap();
        assert_eq!(manifest.cell, "demo");
        let names: Vec<&str> = manifest.processes.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names.first(), Some(&"plant"));
        assert_eq!(names.last(), Some(&"opcua"));
        let opcua = manifest.processes.last().unwrap();
        assert_eq!(
            (
                opcua.program.as_str(),
                opcua.args.first().map(String::as_str)
            ),
            ("cell", Some("opcua"))
        );
        assert_eq!(manifest.restart.max_restarts, 10);
        assert!(manifest
            .processes
            .iter()
            .all(|p| p.restart == RestartType::Permanent));
    }

    fn two_hosts(robot: &str) -> String {
        format!(
            r#"
cell = "t"
[router]
listen = ["tcp/127.0.0.1:7447"]
[hosts.b]
addresses = ["10.0.0.2"]
[[process]]
name = "sim"
program = "robot-sim"
[[process]]
{robot}
"#
        )
    }

    fn load(text: &str) -> Result<Manifest> {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("cell.toml"), text).unwrap();
        Manifest::load(dir.path())
    }

    #[test]
    fn a_scaled_cell_gives_its_plant_and_its_holons_the_factor() {
        let text = r#"cell = "fast"
time_scale = 20
[router]
listen = ["tcp/127.0.0.1:7447"]
[[process]]
name = "plant"
program = "target/debug/plant-sim"
args = ["--plant", "plant.toml"]
[[process]]
name = "robot1"
program = "holon-node"
args = ["--config", "robot1.toml"]
[[process]]
name = "orders1"
program = "order-node"
args = ["--config", "orders1.toml"]
[[process]]
name = "slow"
program = "holon-node"
args = ["--config", "slow.toml", "--time-scale", "5"]
"#;
        let (local, _) = load(text).unwrap().for_host("local").unwrap();
        let args = |name: &str| {
            local
                .processes
                .iter()
                .find(|p| p.name == name)
                .unwrap()
                .args
                .join(" ")
        };
        assert_eq!(args("plant"), "--plant plant.toml --time-scale 20");
        assert_eq!(args("robot1"), "--config robot1.toml --time-scale 20");
        assert_eq!(args("orders1"), "--config orders1.toml");
        assert_eq!(args("slow"), "--config slow.toml --time-scale 5");
        let err = load(&text.replace("time_scale = 20", "time_scale = 0.5"))
            .unwrap()
            .for_host("local")
            .unwrap_err()
            .to_string();
        assert!(err.contains("time_scale"), "{err}");
    }

    #[test]
    fn a_resource_with_a_standby_runs_fenced_on_both_hosts() {
        let manifest = load(&two_hosts(
            r#"name = "robot1"
program = "holon-node"
args = ["--config", "robot1.toml"]
identity = "resource.robot1"
standby_on = "b"
standby_args = ["--config", "robot1.toml", "--data-dir", "data-b"]"#,
        ))
        .unwrap();
        let (local, _) = manifest.clone().for_host("local").unwrap();
        let primary = local.processes.iter().find(|p| p.name == "robot1").unwrap();
        assert!(!primary.standby);
        assert_eq!(primary.args.last().map(String::as_str), Some(STANDBY_FLAG));
        let (b, router) = manifest.clone().for_host("b").unwrap();
        assert!(router.is_none());
        let names: Vec<&str> = b.processes.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["robot1"], "only the standby runs on b");
        assert!(b.processes[0].standby);
        assert_eq!(b.processes[0].host, "b");
        assert_eq!(
            b.processes[0].args,
            [
                "--config",
                "robot1.toml",
                "--data-dir",
                "data-b",
                STANDBY_FLAG
            ]
        );
        assert_eq!(
            b.processes[0]
                .args
                .iter()
                .filter(|a| *a == STANDBY_FLAG)
                .count(),
            1
        );
        // Its certificate names both hosts.
        let identities = crate::security::certs::identities(&manifest).unwrap();
        let robot = identities
            .iter()
            .find(|i| i.name == "resource.robot1")
            .unwrap();
        assert!(
            robot.addresses.contains(&"10.0.0.2".to_string()),
            "{:?}",
            robot.addresses
        );
    }

    #[test]
    fn a_standby_is_refused_where_it_cannot_be_kept_apart() {
        let cases = [
            (
                r#"name = "router-ish"
program = "robot-sim"
standby_on = "b""#,
                "only a resource holon",
            ),
            (
                r#"name = "orders1"
program = "holon-node"
identity = "order-node.orders1"
standby_on = "b""#,
                "or an order-node",
            ),
            (
                r#"name = "robot1"
program = "holon-node"
identity = "resource.robot1"
standby_on = "local""#,
                "belongs on another host",
            ),
            (
                r#"name = "robot1"
program = "holon-node"
identity = "resource.robot1"
standby_on = "c""#,
                "no [hosts.c] section",
            ),
        ];
        for (process, expected) in cases {
            let err = format!("{:#}", load(&two_hosts(process)).unwrap_err());
            assert!(err.contains(expected), "{expected}: {err}");
        }
    }
}

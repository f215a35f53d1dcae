//! Hosts on this machine for a test: network namespaces joined by veth links to
//! bridges, one bridge per network (a cell network, a plant segment, ...), so a test can
//! cut one host from one network and keep it on another, freeze a host's processes as a
//! power loss would, and heal. Needs root and iproute2 ([`netns_available`]).
//!
//! Every namespace and process is removed when the [`Lab`] is dropped, even when the
//! test fails (then the tails of the processes' logs are printed).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;

/// One network: its bridge's name and its addresses' first three bytes.
#[derive(Debug, Clone)]
pub struct Network {
    /// A short name (one letter: it goes into interface names of at most 15 bytes).
    pub name: &'static str,
    /// `10.213.78` for 10.213.78.0/24.
    pub subnet: &'static str,
}

/// A process the lab started.
struct Started {
    host: String,
    name: String,
    child: Child,
}

/// Namespaces, links and processes of one test.
pub struct Lab {
    /// Prefix of every namespace and interface name (unique per test process).
    prefix: String,
    /// Host name -> its address's last byte.
    hosts: BTreeMap<String, u8>,
    networks: Vec<Network>,
    started: Vec<Started>,
    /// Where the processes log (`<name>.log`).
    pub logs: PathBuf,
}

impl Lab {
    /// Makes a namespace per host and a bridge per network (in a switch namespace), and
    /// joins every host to every network in `on` (host, its address's last byte, the
    /// networks it is on).
    pub fn new(tag: &str, logs: &Path, networks: &[Network], on: &[(&str, u8, &[&str])]) -> Lab {
        let mut lab = Lab {
            prefix: format!("{tag}{}", std::process::id() % 100_000),
            hosts: BTreeMap::new(),
            networks: networks.to_vec(),
            started: Vec::new(),
            logs: logs.to_path_buf(),
        };
        let sw = lab.ns("s");
        ip(&["netns", "add", &sw]);
        for network in networks {
            let bridge = format!("br{}", network.name);
            in_ns(&sw, &["ip", "link", "add", &bridge, "type", "bridge"]);
            in_ns(&sw, &["ip", "link", "set", &bridge, "up"]);
        }
        for (host, byte, nets) in on {
            let ns = lab.ns(host);
            ip(&["netns", "add", &ns]);
            in_ns(&ns, &["ip", "link", "set", "lo", "up"]);
            lab.hosts.insert(host.to_string(), *byte);
            for net in *nets {
                let network = lab
                    .networks
                    .iter()
                    .find(|n| n.name == *net)
                    .unwrap_or_else(|| panic!("no network {net}"))
                    .clone();
                let (inner, outer) = lab.veth(host, net);
                ip(&[
                    "link", "add", &inner, "type", "veth", "peer", "name", &outer,
                ]);
                ip(&["link", "set", &inner, "netns", &ns]);
                ip(&["link", "set", &outer, "netns", &sw]);
                let bridge = format!("br{}", network.name);
                in_ns(&sw, &["ip", "link", "set", &outer, "master", &bridge]);
                in_ns(&sw, &["ip", "link", "set", &outer, "up"]);
                let cidr = format!("{}.{byte}/24", network.subnet);
                in_ns(&ns, &["ip", "addr", "add", &cidr, "dev", &inner]);
                in_ns(&ns, &["ip", "link", "set", &inner, "up"]);
            }
        }
        lab
    }

    fn ns(&self, host: &str) -> String {
        format!("{}{host}", self.prefix)
    }

    fn veth(&self, host: &str, net: &str) -> (String, String) {
        (
            format!("{}{host}{net}0", self.prefix),
            format!("{}{host}{net}1", self.prefix),
        )
    }

    /// `host`'s address on `network`.
    pub fn address(&self, host: &str, network: &str) -> String {
        let subnet = self
            .networks
            .iter()
            .find(|n| n.name == network)
            .unwrap_or_else(|| panic!("no network {network}"))
            .subnet;
        format!("{subnet}.{}", self.hosts[host])
    }

    /// Starts `program` with `args` inside `host`'s namespace; its stdout and stderr go
    /// to `<logs>/<name>.log`. Returns its PID.
    pub fn spawn(
        &mut self,
        host: &str,
        name: &str,
        program: &Path,
        args: &[&str],
        env: &[(&str, &str)],
    ) -> u32 {
        let log = std::fs::File::create(self.log_path(name)).expect("a log file");
        let child = Command::new("ip")
            .args(["netns", "exec", &self.ns(host)])
            .arg(program)
            .args(args)
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(log.try_clone().expect("a log file"))
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("start {name}: {e}"));
        let pid = child.id();
        self.started.push(Started {
            host: host.to_string(),
            name: name.to_string(),
            child,
        });
        pid
    }

    /// Where the process called `name` logs.
    pub fn log_path(&self, name: &str) -> PathBuf {
        self.logs.join(format!("{name}.log"))
    }

    /// What the process called `name` logged so far.
    pub fn log(&self, name: &str) -> String {
        std::fs::read_to_string(self.log_path(name)).unwrap_or_default()
    }

    /// Runs `program` with `args` in `host`'s namespace and returns its stdout.
    pub fn output(&self, host: &str, program: &Path, args: &[&str]) -> String {
        String::from_utf8_lossy(&self.run(host, program, args).stdout).into_owned()
    }

    /// Runs `program` with `args` on `host` to its end: its exit status and outputs.
    pub fn run(&self, host: &str, program: &Path, args: &[&str]) -> std::process::Output {
        Command::new("ip")
            .args(["netns", "exec", &self.ns(host)])
            .arg(program)
            .args(args)
            .output()
            .expect("run a command in a namespace")
    }

    /// Takes `host`'s link to `network` down (`up` false: no FIN, no RST, packets
    /// vanish) or up again.
    pub fn link(&self, host: &str, network: &str, up: bool) {
        let (inner, _) = self.veth(host, network);
        in_ns(
            &self.ns(host),
            &["ip", "link", "set", &inner, if up { "up" } else { "down" }],
        );
    }

    /// Sends `signal` to every live process the lab started on `host`.
    pub fn signal_host(&mut self, host: &str, signal: Signal) {
        for started in self.started.iter_mut().filter(|s| s.host == host) {
            if matches!(started.child.try_wait(), Ok(None)) {
                let pid = Pid::from_raw(started.child.id() as i32);
                if let Err(e) = kill(pid, signal) {
                    println!("cannot signal {} ({signal}): {e}", started.name);
                }
            }
        }
    }

    /// Whether the process called `name` (the latest of that name) still runs.
    pub fn running(&mut self, name: &str) -> bool {
        self.started
            .iter_mut()
            .rev()
            .find(|s| s.name == name)
            .is_some_and(|s| matches!(s.child.try_wait(), Ok(None)))
    }

    /// Kills the process called `name` (SIGKILL) and waits for it.
    pub fn kill(&mut self, name: &str) {
        if let Some(started) = self.started.iter_mut().rev().find(|s| s.name == name) {
            if let Err(e) = started.child.kill() {
                println!("cannot kill {name}: {e}");
            }
            if let Err(e) = started.child.wait() {
                println!("cannot reap {name}: {e}");
            }
        }
    }

    /// Kills every process the lab started and returns the PIDs of any process still
    /// in its namespaces afterwards (none, when all went).
    pub fn stop_all(&mut self) -> Vec<String> {
        for started in &mut self.started {
            // Thawed first: a frozen process dies of SIGKILL too, but its children...
            let pid = Pid::from_raw(started.child.id() as i32);
            if matches!(started.child.try_wait(), Ok(None)) {
                if let Err(e) = kill(pid, Signal::SIGCONT) {
                    println!("cannot thaw {}: {e}", started.name);
                }
                if let Err(e) = started.child.kill() {
                    println!("cannot kill {}: {e}", started.name);
                }
            }
            if let Err(e) = started.child.wait() {
                println!("cannot reap {}: {e}", started.name);
            }
        }
        let mut left = Vec::new();
        let hosts: Vec<String> = self.hosts.keys().cloned().chain(["s".into()]).collect();
        for host in hosts {
            if let Ok(out) = Command::new("ip")
                .args(["netns", "pids", &self.ns(&host)])
                .output()
            {
                left.extend(
                    String::from_utf8_lossy(&out.stdout)
                        .split_whitespace()
                        .map(|pid| format!("{host}:{pid}")),
                );
            }
        }
        left
    }
}

impl Drop for Lab {
    fn drop(&mut self) {
        let left = self.stop_all();
        if !left.is_empty() {
            println!("still running in the test's namespaces, killed: {left:?}");
            for pid in left.iter().filter_map(|p| p.split_once(':')) {
                if let Err(e) = Command::new("kill").args(["-9", pid.1]).status() {
                    println!("cannot kill {}: {e}", pid.1);
                }
            }
        }
        if std::thread::panicking() {
            crate::print_log_tails(&self.logs);
        }
        let hosts: Vec<String> = self.hosts.keys().cloned().chain(["s".into()]).collect();
        for host in hosts {
            if let Err(e) = Command::new("ip")
                .args(["netns", "del", &self.ns(&host)])
                .status()
            {
                println!("cannot delete the namespace of {host}: {e}");
            }
        }
    }
}

/// Runs `ip ARGS`; panics if it fails.
fn ip(args: &[&str]) {
    run("ip", args);
}

/// Runs `ARGS` inside namespace `ns`; panics if it fails.
fn in_ns(ns: &str, args: &[&str]) {
    let mut all = vec!["netns", "exec", ns];
    all.extend_from_slice(args);
    run("ip", &all);
}

fn run(program: &str, args: &[&str]) {
    let status = Command::new(program)
        .args(args)
        .stderr(Stdio::inherit())
        .status()
        .unwrap_or_else(|e| panic!("{program} {args:?}: {e}"));
    assert!(status.success(), "{program} {args:?} failed");
}

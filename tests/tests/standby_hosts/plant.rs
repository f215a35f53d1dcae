//! The standby-hosts test's plant: hosts a, b and c on the cell network and the plant
//! segment, their routers, etcd members, controllers and holons, and what the test
//! asks of them (submits, waits on logs, the controllers' counts).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use holarchy_tests::lab::Lab;
use holarchy_tests::*;
use serde_json::Value;

/// The cell's name.
pub const CELL: &str = "t-hosts";
/// The zenoh link lease of the routers and holons.
pub const LEASE_MS: u64 = 2000;
/// The orders submitted in each round.
pub const ORDERS: usize = 100;
/// The cell network (the routers, etcd, the holons).
pub const CELL_NET: &str = "c";
/// The plant segment (the controllers, on host p).
pub const PLANT_NET: &str = "p";
/// Where orders1 keeps its journal and leader key on etcd.
pub const ETCD_PREFIX: &str = "holarchy/t-hosts/order-node/orders1";
/// How long each of robot1's actions takes on its controller: long enough that a step
/// is almost always in flight.
pub const ACTION_MS: &str = "150";

/// The processes of the test and what it measured.
pub struct Plant {
    pub lab: Lab,
    pub dir: PathBuf,
    pub etcd: PathBuf,
    /// Every order acknowledged by a submit, over all rounds.
    pub submitted: Vec<String>,
    /// How many processes were started, for unique log names (`robot1-b.3`).
    pub started: usize,
    /// The log name of robot1's latest process on each host.
    pub robot1_on: BTreeMap<String, String>,
    /// The log name of orders1's latest process on each host.
    pub orders1_on: BTreeMap<String, String>,
}

impl Plant {
    pub fn router(&self, host: &str) -> String {
        format!("tcp/{}:7447", self.lab.address(host, CELL_NET))
    }

    pub fn controller(&self, n: u32) -> String {
        format!("{}:{}", self.lab.address("p", PLANT_NET), 17700 + n)
    }

    /// `cell ARGS` on host c.
    pub fn cell(&self, args: &[&str]) -> String {
        let mut all: Vec<&str> = args.to_vec();
        let router = self.router("c");
        all.extend(["--cell", CELL, "--connect", &router]);
        self.lab.output("c", &bin("cell"), &all)
    }

    pub fn start(&mut self) {
        // Routers, each connected to the others.
        for host in ["a", "b", "c"] {
            let mut args = vec![
                "router".to_string(),
                "--listen".into(),
                self.router(host),
                "--lease-ms".into(),
                LEASE_MS.to_string(),
            ];
            for other in ["a", "b", "c"].iter().filter(|o| **o != host) {
                args.push("--connect".into());
                args.push(self.router(other));
            }
            let args: Vec<&str> = args.iter().map(String::as_str).collect();
            self.lab
                .spawn(host, &format!("router-{host}"), &bin("cell"), &args, &[]);
        }
        // etcd, a member on each host.
        let peers: Vec<String> = ["a", "b", "c"]
            .iter()
            .map(|h| format!("m{h}=http://{}:2380", self.lab.address(h, CELL_NET)))
            .collect();
        let initial = peers.join(",");
        for host in ["a", "b", "c"] {
            let address = self.lab.address(host, CELL_NET);
            let client = format!("http://{address}:2379");
            let peer = format!("http://{address}:2380");
            let data = self.dir.join(format!("etcd-{host}"));
            let etcd = self.etcd.clone();
            self.lab.spawn(
                host,
                &format!("etcd-{host}"),
                &etcd,
                &[
                    "--name",
                    &format!("m{host}"),
                    "--data-dir",
                    data.to_str().expect("utf-8"),
                    "--listen-client-urls",
                    &client,
                    "--advertise-client-urls",
                    &client,
                    "--listen-peer-urls",
                    &peer,
                    "--initial-advertise-peer-urls",
                    &peer,
                    "--initial-cluster",
                    &initial,
                    "--initial-cluster-state",
                    "new",
                    "--initial-cluster-token",
                    "holarchy-hosts",
                    "--logger",
                    "zap",
                    // As docs/deploy.md sets them on a LAN: a dead leader is replaced
                    // within the order-node's failover budget.
                    "--heartbeat-interval",
                    "50",
                    "--election-timeout",
                    "500",
                    // A member cut off and back does not depose the raft leader
                    // (docs/deploy.md): no needless lapse of the order-node's lease.
                    "--pre-vote",
                    // Its history compacted every 5 s (docs/deploy.md: 1 h), so that
                    // the run proves nothing of ours reads an old revision.
                    "--auto-compaction-mode",
                    "periodic",
                    "--auto-compaction-retention",
                    "5s",
                ],
                &[],
            );
        }
        // The controllers on the plant segment.
        for n in [1, 2] {
            let counts = self.dir.join(format!("sim{n}.counts.json"));
            let listen = self.controller(n);
            let mut args = vec![
                "--listen",
                &listen,
                "--delay-ms",
                ACTION_MS,
                "--count-file",
                counts.to_str().expect("utf-8"),
            ];
            // Both fenced, so every step id is counted; robot2 has no standby.
            args.extend(["--fenced", "--lease-ms", "1000"]);
            self.lab
                .spawn("p", &format!("sim{n}"), &bin("robot-sim"), &args, &[]);
        }
        resource_config(&self.dir, "robot1", 10_000).expect("robot1.toml");
        resource_config(&self.dir, "robot2", 10_000).expect("robot2.toml");
        one_step_product(&self.dir).expect("part.toml");
        self.write_orders_config();
        let robot1 = self.robot1("b");
        wait_for(&self.lab, &robot1, "holding the controller", 1);
        self.robot1("a");
        let robot2 = self.controller(2);
        self.holon(
            "c",
            "robot2",
            "robot2.toml",
            &["--controller", &robot2, "--standby"],
        );
        self.holon("c", "part", "part.toml", &[]);
        let orders1 = self.orders1("b");
        wait_for(&self.lab, &orders1, "serving at epoch", 1);
        self.orders1("c");
    }

    /// A unique log name for a process called `name` on `host`.
    pub fn log_name(&mut self, name: &str, host: &str) -> String {
        self.started += 1;
        format!("{name}-{host}.{}", self.started)
    }

    pub fn write_orders_config(&self) {
        let endpoints: Vec<String> = ["a", "b", "c"]
            .iter()
            .map(|h| format!("\"http://{}:2379\"", self.lab.address(h, CELL_NET)))
            .collect();
        std::fs::write(
            self.dir.join("orders1.toml"),
            format!(
                r#"
cell = "unset"
name = "orders1"
[orders]
no_resource_timeout_ms = 60000
[journal]
etcd = [{}]
etcd_prefix = "{ETCD_PREFIX}"
lease_ttl_ms = 2000
"#,
                endpoints.join(", ")
            ),
        )
        .expect("orders1.toml");
    }

    /// Starts a holon-node on `host` as `name` from `config`; returns its log name.
    pub fn holon(&mut self, host: &str, name: &str, config: &str, extra: &[&str]) -> String {
        let config = self.dir.join(config);
        let data = self.dir.join(format!("data-{host}-{name}"));
        let router = self.router(host);
        let lease = LEASE_MS.to_string();
        let mut args = vec![
            "--config",
            config.to_str().expect("utf-8"),
            "--cell",
            CELL,
            "--name",
            name,
            "--connect",
            &router,
            "--lease-ms",
            &lease,
            "--data-dir",
            data.to_str().expect("utf-8"),
        ];
        args.extend_from_slice(extra);
        let log = self.log_name(name, host);
        self.lab.spawn(
            host,
            &log,
            &bin("holon-node"),
            &args,
            &[("RUST_LOG", "info")],
        );
        log
    }

    /// Starts robot1's copy on `host` (`--standby`: the controller's claim decides);
    /// returns its log name.
    pub fn robot1(&mut self, host: &str) -> String {
        let controller = self.controller(1);
        let log = self.holon(
            host,
            "robot1",
            "robot1.toml",
            &["--controller", &controller, "--standby"],
        );
        self.robot1_on.insert(host.to_string(), log.clone());
        log
    }

    /// Starts orders1's copy on `host` (`--standby`: etcd's leader key decides);
    /// returns its log name.
    pub fn orders1(&mut self, host: &str) -> String {
        let config = self.dir.join("orders1.toml");
        let router = self.router(host);
        let lease = LEASE_MS.to_string();
        let log = self.log_name("orders1", host);
        self.lab.spawn(
            host,
            &log,
            &bin("order-node"),
            &[
                "--config",
                config.to_str().expect("utf-8"),
                "--cell",
                CELL,
                "--connect",
                &router,
                "--lease-ms",
                &lease,
                "--standby",
            ],
            &[("RUST_LOG", "info")],
        );
        self.orders1_on.insert(host.to_string(), log.clone());
        log
    }

    /// How often robot1's process on `host` said `text`.
    pub fn robot1_said(&self, host: &str, text: &str) -> usize {
        self.lab.log(&self.robot1_on[host]).matches(text).count()
    }

    /// Waits until robot1's process on `host` has said `text` once more than `before`.
    pub fn robot1_says(&self, host: &str, text: &str, before: usize) -> Instant {
        wait_for(&self.lab, &self.robot1_on[host], text, before + 1)
    }

    /// Waits until orders1's process on `host` serves.
    pub fn orders1_serves(&self, host: &str) -> Instant {
        wait_for(&self.lab, &self.orders1_on[host], "serving at epoch", 1)
    }

    /// Waits until orders1's process on `host` has exited (a deposed primary does),
    /// then starts it again as a standby. Returns how many of its journal writes etcd
    /// refused for a stale epoch (its fence at work).
    pub fn restart_deposed_orders1(&mut self, host: &str) -> usize {
        let log = self.orders1_on[host].clone();
        let deadline = Instant::now() + Duration::from_secs(60);
        while self.lab.running(&log) {
            assert!(
                Instant::now() < deadline,
                "orders1 on {host}, deposed, never exited:\n{}",
                self.lab.log(&log)
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        let said = self.lab.log(&log);
        assert!(
            said.contains("deposed"),
            "orders1 on {host} exited, but not deposed:\n{said}"
        );
        self.orders1(host);
        said.matches("write refused: deposed").count()
    }

    /// Makes b's copies the primaries again: the holders on a (robot1) and c (orders1)
    /// are killed, b's standbys take over, and the killed ones start again as standbys.
    pub fn primaries_to_b(&mut self) {
        let held = self.robot1_said("b", "holding the controller");
        let holder = self.robot1_on["a"].clone();
        self.lab.kill(&holder);
        self.robot1_says("b", "holding the controller", held);
        self.robot1("a");
        let primary = self.orders1_on["c"].clone();
        self.lab.kill(&primary);
        self.orders1_serves("b");
        let served = Instant::now();
        self.orders1("c");
        // The cell sees robot1, and an operator on c reaches the serving orders1 (its
        // row in the order-node table, which only the serving node answers: the fence
        // table lists the standby on c too), before the next round's orders.
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let status = self.cell(&["status"]);
            if status.contains("resource/robot1") && order_node_serves(&status, "orders1") {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the cell never saw b's primaries:\n{status}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        let reached = served.elapsed();
        if reached > Duration::from_secs(1) {
            println!(
                "b's primaries: an operator on c reached orders1 {:.1}s after it served",
                reached.as_secs_f64()
            );
        }
    }

    /// A controller's counts.
    pub fn counts(&self, n: u32) -> Value {
        let text = std::fs::read_to_string(self.dir.join(format!("sim{n}.counts.json")))
            .unwrap_or_default();
        serde_json::from_str(&text).unwrap_or(Value::Null)
    }

    /// Submits `n` orders of `part` and keeps their names. A refusal because the
    /// holder does not see the product yet (the routers of a host that came back still
    /// rejoining the mesh) is asked again, for at most 60 s: the round begins with a
    /// whole cell.
    pub fn submit(&mut self, n: usize) {
        let count = n.to_string();
        let mut all = vec!["submit", "part", "--count", &count];
        let router = self.router("c");
        all.extend(["--cell", CELL, "--connect", &router]);
        let asked = Instant::now();
        let mut refused = 0;
        let (out, said) = loop {
            let run = self.lab.run("c", &bin("cell"), &all);
            let errors = String::from_utf8_lossy(&run.stderr).into_owned();
            if run.status.success() || !errors.contains("no product holon") {
                let said = format!("{} (stderr: {errors})", run.status);
                break (String::from_utf8_lossy(&run.stdout).into_owned(), said);
            }
            assert!(
                asked.elapsed() < Duration::from_secs(60),
                "the order-node never saw the product: {errors}"
            );
            refused += 1;
            std::thread::sleep(Duration::from_millis(500));
        };
        if refused > 0 {
            println!(
                "the holder saw the product {:.1}s after the first submit",
                asked.elapsed().as_secs_f64()
            );
        }
        let names: Vec<String> = out
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(String::from)
            .collect();
        assert_eq!(
            names.len(),
            n,
            "submit acknowledged {} of {n}: {out}; cell submit ended {said}; the last of orders1 on b (which serves):\n{}",
            names.len(),
            self.orders1_tail("b")
        );
        self.submitted.extend(names);
    }

    /// The last 30 lines of orders1's latest process on `host` that are not DEBUG.
    pub fn orders1_tail(&self, host: &str) -> String {
        let log = self.lab.log(&self.orders1_on[host]);
        let lines: Vec<&str> = log.lines().filter(|l| !l.contains(" DEBUG ")).collect();
        lines[lines.len().saturating_sub(30)..].join("\n")
    }

    /// Waits until robot1's controller has a command received and not yet answered.
    pub fn wait_step_in_flight(&self) {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let counts = self.counts(1);
            let received = counts["received"].as_u64().unwrap_or(0);
            // A command refused for a stale epoch is not counted as received.
            let answered = counts["executed"].as_u64().unwrap_or(0);
            if received > answered {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "robot1 never had a step in flight: {counts}"
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Every acknowledged order has ended done or failed with a reason, none missing:
    /// waits (bounded) until `cell orders` shows all of them ended.
    pub fn every_order_ends(&self, round: &str) -> (usize, usize) {
        let deadline = Instant::now() + Duration::from_secs(240);
        loop {
            let out = self.cell(&["orders", "--all"]);
            let mut done = 0;
            let mut failed = 0;
            let mut missing = Vec::new();
            for name in &self.submitted {
                match out
                    .lines()
                    .find(|l| l.split_whitespace().next() == Some(name))
                {
                    Some(line) if line.contains(" done") => done += 1,
                    Some(line) if line.contains(" failed") => {
                        assert!(
                            line.split(" failed")
                                .nth(1)
                                .is_some_and(|r| !r.trim().is_empty()),
                            "{round}: a failed order without a reason: {line}"
                        );
                        failed += 1
                    }
                    Some(_) => {}
                    None => missing.push(name.clone()),
                }
            }
            if done + failed == self.submitted.len() {
                return (done, failed);
            }
            assert!(
                Instant::now() < deadline,
                "{round}: {done} done, {failed} failed of {}; missing {missing:?}; last:\n{out}",
                self.submitted.len()
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }

    /// Every step ran at most once by the controllers' counts per step id
    /// (`<order>/<step>/<attempt>#<command>`): each step id once, and per order's step
    /// at most one attempt whose every command ran (a step done twice would be two).
    /// Returns how many steps were done on the controllers.
    pub fn every_step_ran_once(&self, round: &str) -> usize {
        let mut commands_run: BTreeMap<String, BTreeMap<String, u64>> = BTreeMap::new();
        for n in [1, 2] {
            let counts = self.counts(n);
            let by_step = counts["by_step"].as_object().cloned().unwrap_or_default();
            for (step_id, count) in by_step {
                let count = count.as_u64().unwrap_or(0);
                assert_eq!(count, 1, "{round}: step id {step_id} ran {count} times");
                let (conversation, command) = step_id.split_once('#').expect("a step id");
                commands_run
                    .entry(conversation.to_string())
                    .or_default()
                    .insert(command.to_string(), count);
            }
        }
        // pick_n_place is two commands: an attempt ran its step when both ran.
        let mut done_per_step: BTreeMap<String, Vec<String>> = BTreeMap::new();
        for (conversation, commands) in &commands_run {
            if commands.len() == 2 {
                let step = conversation
                    .rsplit_once('/')
                    .map_or(conversation.as_str(), |(s, _)| s);
                done_per_step
                    .entry(step.to_string())
                    .or_default()
                    .push(conversation.clone());
            }
        }
        let twice: Vec<_> = done_per_step.iter().filter(|(_, c)| c.len() > 1).collect();
        assert!(
            twice.is_empty(),
            "{round}: steps done more than once: {twice:?}"
        );
        done_per_step.len()
    }
}

/// Waits (bounded) until the process logged as `name` has said `text` `n` times;
/// returns when.
pub fn wait_for(lab: &Lab, name: &str, text: &str, n: usize) -> Instant {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        if lab.log(name).matches(text).count() >= n {
            return Instant::now();
        }
        assert!(
            Instant::now() < deadline,
            "{name} never said {text:?} {n} times"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Whether `cell status` lists `node` in its order-node table with its counts: the
/// serving node answered (a standby answers only the fence table, without counts).
fn order_node_serves(status: &str, node: &str) -> bool {
    status
        .lines()
        .skip_while(|l| !l.starts_with("ORDER-NODE "))
        .any(|l| {
            let mut fields = l.split_whitespace();
            fields.next() == Some(node) && fields.next().is_some_and(|n| n.parse::<u64>().is_ok())
        })
}

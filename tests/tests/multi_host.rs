//! Several hosts on this machine: three network namespaces joined by veth links to a
//! bridge, a zenoh router on each (`cell router`), resources on hosts a and b, the
//! product and the order-node on host c. Orders complete across hosts; host b is cut
//! off (link down) and its booked work is rebooked on host a within the lease; the link
//! heals a few seconds after the cut and host b is seen again and receives work again.
//!
//! Needs root and iproute2; without them the test says SKIPPED and passes. Addresses
//! (10.213.77.0/24) exist only inside the test's namespaces, which are deleted at the end
//! even when the test fails.

use std::path::Path;
use std::time::{Duration, Instant};

use holarchy_tests::lab::{Lab, Network};
use holarchy_tests::*;

const LEASE_MS: u64 = 2000;
const CELL: &str = "t-multi";

/// The test's hosts a, b and c on one network, in namespaces ([`Lab`]: removed when
/// dropped, with every process the test started).
struct Hosts {
    lab: Lab,
}

impl Hosts {
    fn address(host: &str) -> &'static str {
        match host {
            "a" => "10.213.77.1",
            "b" => "10.213.77.2",
            _ => "10.213.77.3",
        }
    }

    fn router(host: &str) -> String {
        format!("tcp/{}:7447", Self::address(host))
    }

    fn setup(dir: &Path) -> Hosts {
        let network = Network {
            name: "n",
            subnet: "10.213.77",
        };
        let on: &[&str] = &["n"];
        Hosts {
            lab: Lab::new(
                "hl",
                dir,
                &[network],
                &[("a", 1, on), ("b", 2, on), ("c", 3, on)],
            ),
        }
    }

    /// Starts a command inside host `host`'s namespace, its output to `<dir>/<name>.log`.
    fn spawn(&mut self, host: &str, name: &str, program: &Path, args: &[&str]) {
        self.lab
            .spawn(host, name, program, args, &[("RUST_LOG", "info")]);
    }

    /// Runs a `cell` command on host c and returns its output.
    fn cell(&self, args: &[&str]) -> String {
        let router = Self::router("c");
        let mut all = args.to_vec();
        all.extend(["--cell", CELL, "--connect", &router]);
        self.lab.output("c", &bin("cell"), &all)
    }

    fn link(&self, host: &str, state: &str) {
        self.lab.link(host, "n", state == "up");
    }

    /// Kills every process the test started and returns the PIDs of any process still
    /// in the test's namespaces afterwards (none, when all went).
    fn stop_all(&mut self) -> Vec<String> {
        self.lab.stop_all()
    }
}

/// Waits until `check` holds on what `cell orders` prints.
fn wait_orders(
    hosts: &Hosts,
    what: &str,
    within: Duration,
    check: impl Fn(&str) -> bool,
) -> String {
    let deadline = Instant::now() + within;
    loop {
        let out = hosts.cell(&["orders"]);
        if check(&out) {
            return out;
        }
        assert!(Instant::now() < deadline, "never {what}; last:\n{out}");
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn summary(out: &str) -> String {
    out.lines().next().unwrap_or("").to_string()
}

#[test]
fn orders_cross_hosts_survive_a_partition_and_the_host_rejoins() {
    if let Err(why) = netns_available() {
        println!("SKIPPED: the multi-host test needs root and network namespaces ({why})");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let dir = dir.path();
    let mut hosts = Hosts::setup(dir);
    start_a_router_on_every_host(&mut hosts);
    start_the_holons(&mut hosts, dir);
    the_cell_assembles_across_hosts(&hosts);
    orders_run_on_host_b(&hosts);
    let cut = cut_host_b_off_and_see_its_work_rebooked(&mut hosts);
    let healed = heal_host_b(&mut hosts, cut);
    every_order_is_done(&hosts);
    host_b_is_seen_again(&hosts, healed);
    host_b_receives_work_again(&hosts, dir);
    // Stopped: no process the test started is left in its namespaces.
    let left = hosts.stop_all();
    assert!(left.is_empty(), "processes survived the test: {left:?}");
}

/// A router on every host (`cell router`), each connected to the others.
fn start_a_router_on_every_host(hosts: &mut Hosts) {
    let lease = LEASE_MS.to_string();
    for host in ["a", "b", "c"] {
        let mut args = vec![
            "router".to_string(),
            "--listen".into(),
            Hosts::router(host),
            "--lease-ms".into(),
            lease.clone(),
        ];
        for other in ["a", "b", "c"].iter().filter(|o| **o != host) {
            args.push("--connect".into());
            args.push(Hosts::router(other));
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        hosts.spawn(host, &format!("router-{host}"), &bin("cell"), &args);
    }
}

/// Resources (each after its simulator) on hosts a and b, the product and the
/// order-node on host c, all with the cell's lease; each a client of its host's router.
fn start_the_holons(hosts: &mut Hosts, dir: &Path) {
    let with_lease = |file: &str| {
        // The breaker as it was before parts moved: these hosts run no plant.
        let source = match file {
            "breaker.toml" => stationary_breaker(),
            _ => demo_config(file),
        };
        let text = std::fs::read_to_string(source).unwrap();
        let text = text.replacen(
            "multicast_scouting = false",
            &format!("multicast_scouting = false\nlease_ms = {LEASE_MS}"),
            1,
        );
        let path = dir.join(file);
        std::fs::write(&path, text).unwrap();
        path
    };
    let resources = [
        ("a", "robot1", "robot1.toml", "400"),
        ("b", "robot2", "robot1.toml", "400"),
        ("a", "inspect1", "inspect1.toml", "20"),
        ("a", "conveyor1", "conveyor1.toml", "50"),
    ];
    for (i, (host, name, config, delay)) in resources.iter().enumerate() {
        let port = (17600 + i).to_string();
        let controller = format!("127.0.0.1:{port}");
        let counts = dir.join(format!("{name}.counts.json"));
        hosts.spawn(
            host,
            &format!("{name}-sim"),
            &bin("robot-sim"),
            &[
                "--listen",
                &controller,
                "--delay-ms",
                delay,
                "--count-file",
                counts.to_str().unwrap(),
            ],
        );
        let config = with_lease(config);
        let data = dir.join(format!("data-{host}"));
        hosts.spawn(
            host,
            name,
            &bin("holon-node"),
            &[
                "--config",
                config.to_str().unwrap(),
                "--cell",
                CELL,
                "--name",
                name,
                "--controller",
                &controller,
                "--connect",
                &Hosts::router(host),
                "--data-dir",
                data.to_str().unwrap(),
            ],
        );
    }
    let breaker = with_lease("breaker.toml");
    hosts.spawn(
        "c",
        "breaker",
        &bin("holon-node"),
        &[
            "--config",
            breaker.to_str().unwrap(),
            "--cell",
            CELL,
            "--connect",
            &Hosts::router("c"),
        ],
    );
    let orders = with_lease("orders1.toml");
    let data_c = dir.join("data-c");
    hosts.spawn(
        "c",
        "orders1",
        &bin("order-node"),
        &[
            "--config",
            orders.to_str().unwrap(),
            "--cell",
            CELL,
            "--connect",
            &Hosts::router("c"),
            "--data-dir",
            data_c.to_str().unwrap(),
        ],
    );
}

/// Every holon is visible from host c.
fn the_cell_assembles_across_hosts(hosts: &Hosts) {
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        let status = hosts.cell(&["status"]);
        if status.contains("5 live holons") {
            println!("{status}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the cell never assembled across hosts:\n{status}"
        );
        std::thread::sleep(Duration::from_millis(300));
    }
}

/// Orders complete across hosts: some are booked on host b.
fn orders_run_on_host_b(hosts: &Hosts) {
    let submitted = hosts.cell(&["submit", "breaker", "--count", "10"]);
    assert_eq!(submitted.lines().count(), 10, "{submitted}");
    let on_b = wait_orders(
        hosts,
        "an order booked on host b",
        Duration::from_secs(60),
        |out| out.contains("resource/robot2"),
    );
    println!("{}", summary(&on_b));
}

/// Cuts host b off (link down): its booked work is rebooked elsewhere within the lease.
/// Returns when the cut began.
fn cut_host_b_off_and_see_its_work_rebooked(hosts: &mut Hosts) -> Instant {
    let cut = Instant::now();
    hosts.link("b", "down");
    println!("host b cut off");
    let rebooked = wait_orders(
        hosts,
        "host b's work rebooked",
        Duration::from_secs(60),
        |out| {
            summary(out).contains(": 10 orders")
                && !out
                    .lines()
                    .any(|l| l.contains("running") && l.contains("resource/robot2"))
        },
    );
    let rebook_time = cut.elapsed();
    println!(
        "no running order on host b {:.2}s after the cut (lease {LEASE_MS} ms): {}",
        rebook_time.as_secs_f64(),
        summary(&rebooked)
    );
    assert!(
        rebook_time < Duration::from_millis(LEASE_MS * 10),
        "rebooking took {rebook_time:?}"
    );
    cut
}

/// Heals host b's link; returns when.
fn heal_host_b(hosts: &mut Hosts, cut: Instant) -> Instant {
    // Heal at once: a cut of a few seconds, shorter than zenoh's former 10 s TCP linger
    // (see .cargo/config.toml), is the one that once left host b invisible for good.
    hosts.link("b", "up");
    let healed = Instant::now();
    println!(
        "host b back {:.2}s after the cut",
        cut.elapsed().as_secs_f64()
    );
    healed
}

/// All 10 orders are done.
fn every_order_is_done(hosts: &Hosts) {
    let all_done = wait_orders(
        hosts,
        "all 10 orders done",
        Duration::from_secs(120),
        |out| summary(out).contains(": 10 orders: 10 done"),
    );
    println!("{}", summary(&all_done));
}

/// Host b is seen again from host c.
fn host_b_is_seen_again(hosts: &Hosts, healed: Instant) {
    // A bound, not a figure: the routers retry their links at most 4 s apart, and a
    // connect sent while the link was down waits up to zenoh's open timeout (10 s).
    let deadline = healed + Duration::from_secs(60);
    loop {
        let status = hosts.cell(&["status"]);
        if status.contains("resource/robot2") {
            println!(
                "host b visible again {:.2}s after the heal",
                healed.elapsed().as_secs_f64()
            );
            break;
        }
        assert!(
            Instant::now() < deadline,
            "host b never rejoined:\n{status}"
        );
        std::thread::sleep(Duration::from_millis(300));
    }
}

/// New orders are executed on host b again.
fn host_b_receives_work_again(hosts: &Hosts, dir: &Path) {
    let robot2_before = std::fs::read_to_string(dir.join("robot2.counts.json")).unwrap_or_default();
    let executed = |text: &str| -> u64 {
        serde_json::from_str::<serde_json::Value>(text)
            .ok()
            .and_then(|v| v["by_action"]["pick"].as_u64())
            .unwrap_or(0)
    };
    let before = executed(&robot2_before);
    hosts.cell(&["submit", "breaker", "--count", "8"]);
    let finished = wait_orders(
        hosts,
        "all 18 orders done",
        Duration::from_secs(120),
        |out| summary(out).contains(": 18 orders: 18 done"),
    );
    println!("{}", summary(&finished));
    let after =
        executed(&std::fs::read_to_string(dir.join("robot2.counts.json")).unwrap_or_default());
    println!("robot2 picks: {before} before the heal, {after} after");
    assert!(after > before, "host b received no work after rejoining");
}

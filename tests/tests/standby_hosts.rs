//! Standby across hosts (issue 31), in network namespaces: hosts a, b and c on the cell
//! network, each also on the plant segment where the controllers live (host p). An etcd
//! member and a zenoh router on each of a, b and c. robot1 (a fenced controller) has its
//! primary on b and a standby on a; the order-node orders1 (its journal in etcd) its
//! primary on b and a standby on c; robot2 (fenced too, no standby) and the product on c.
//!
//! Three rounds, each with 100 orders running and a step of robot1's in flight at the
//! fault, each starting with both primaries on b:
//! 1. power loss of b: its processes frozen, both its links down (no FIN);
//! 2. a partition of b from both networks, healed after 5 s: the old primaries find
//!    their fence gone and step down;
//! 3. b cut from the cell but not from the plant: robot1's holder on b keeps its
//!    controller, so robot1 must not be taken over; the order-node may be.
//!
//! After every round: every acknowledged order ends done or failed with a reason, none
//! missing; every step ran at most once by the controllers' counts (per step id on the
//! fenced controller, and in all: no order's step ran on two robots); commands and
//! writes refused for a stale epoch are counted and printed. Failover times are printed,
//! never asserted (this machine is shared); docs/reliability.md keeps the measured
//! figures. Needs root, iproute2 and etcd: without them it says SKIPPED, unless
//! `HOLARCHY_REQUIRE_NETNS` / `HOLARCHY_REQUIRE_ETCD` make that a failure.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use holarchy_tests::lab::{Lab, Network};
use holarchy_tests::*;
use nix::sys::signal::Signal;

#[path = "standby_hosts/plant.rs"]
mod plant;

use plant::*;

#[test]
fn standbys_on_other_hosts_finish_every_order_with_no_step_run_twice() {
    if let Err(why) = netns_available() {
        println!("SKIPPED: the standby hosts test needs root and network namespaces ({why})");
        return;
    }
    let Some(etcd) = etcd_binary() else { return };
    let dir = tempfile::tempdir().unwrap();
    if std::env::var_os("HOLARCHY_TEST_KEEP").is_some() {
        println!("keeping {}", dir.path().display());
    }
    let dir = Keep(Some(dir));
    let networks = [
        Network {
            name: CELL_NET,
            subnet: "10.213.78",
        },
        Network {
            name: PLANT_NET,
            subnet: "10.213.79",
        },
    ];
    let lab = Lab::new(
        "hs",
        dir.path(),
        &networks,
        &[
            ("a", 1, &[CELL_NET, PLANT_NET]),
            ("b", 2, &[CELL_NET, PLANT_NET]),
            ("c", 3, &[CELL_NET, PLANT_NET]),
            ("p", 10, &[PLANT_NET]),
        ],
    );
    let mut plant = Plant {
        lab,
        dir: dir.path().to_path_buf(),
        etcd,
        submitted: Vec::new(),
        started: 0,
        robot1_on: BTreeMap::new(),
        orders1_on: BTreeMap::new(),
    };
    plant.start();
    power_loss(&mut plant);
    plant.primaries_to_b();
    partition(&mut plant);
    plant.primaries_to_b();
    cell_cut(&mut plant);
    let left = plant.lab.stop_all();
    assert!(left.is_empty(), "processes survived the test: {left:?}");
}

/// What a round ends with: every order ended, every step run at most once; printed.
/// `stale_before`: robot1's controller's count of commands refused for a stale epoch
/// before the round; `writes_refused`: the deposed order-node's journal writes refused.
/// Returns the round's stale-epoch refusals, commands and writes.
fn round_ends(plant: &Plant, round: &str, stale_before: u64, writes_refused: usize) -> u64 {
    let (done, failed) = plant.every_order_ends(round);
    // The orders that needed more than one attempt, and how each attempt ended (shown
    // before the steps are counted, so that a failure there has them).
    let detail = plant.cell(&["orders", "--all", "--detail"]);
    let mut retried = detail
        .lines()
        .filter(|l| l.starts_with(' ') && !l.contains(" done"))
        .peekable();
    if retried.peek().is_some() {
        println!("{round}: attempts that did not end done:");
        for line in retried {
            println!("  {line}");
        }
    }
    let steps_done = plant.every_step_ran_once(round);
    assert!(
        steps_done >= done,
        "{round}: {done} orders done, but the controllers did only {steps_done} steps"
    );
    let counts = plant.counts(1);
    let stale = stale_refused(plant) - stale_before;
    println!(
        "{round}: {done} done, {failed} failed of {} acknowledged, {steps_done} steps done on the controllers, none twice; robot1's controller at epoch {}, {stale} commands refused for a stale epoch in this round, {writes_refused} journal writes of the deposed order-node refused",
        plant.submitted.len(),
        counts["epoch"],
    );
    stale + writes_refused as u64
}

fn stale_refused(plant: &Plant) -> u64 {
    plant.counts(1)["stale_epoch_refused"].as_u64().unwrap_or(0)
}

/// A test directory, kept after the test when `HOLARCHY_TEST_KEEP` is set.
struct Keep(Option<tempfile::TempDir>);

impl Keep {
    fn path(&self) -> &std::path::Path {
        self.0.as_ref().expect("the directory").path()
    }
}

impl Drop for Keep {
    fn drop(&mut self) {
        if std::env::var_os("HOLARCHY_TEST_KEEP").is_some() {
            if let Some(dir) = self.0.take() {
                println!("kept {}", dir.keep().display());
            }
        }
    }
}

/// Round 1: b loses power in the middle of a step of robot1's: its processes freeze,
/// both its links go down. Then it comes back: its robot1 steps down, its orders1
/// exits deposed and starts again as a standby.
fn power_loss(plant: &mut Plant) {
    let stale = stale_refused(plant);
    plant.submit(ORDERS);
    plant.wait_step_in_flight();
    let fault = Instant::now();
    plant.lab.signal_host("b", Signal::SIGSTOP);
    plant.lab.link("b", CELL_NET, false);
    plant.lab.link("b", PLANT_NET, false);
    let robot1 = plant.robot1_says("a", "holding the controller", 0);
    let orders1 = plant.orders1_serves("c");
    println!(
        "power loss of b: robot1's standby holds the controller after {:.2}s, orders1's serves after {:.2}s",
        (robot1 - fault).as_secs_f64(),
        (orders1 - fault).as_secs_f64()
    );
    let stepped = plant.robot1_said("b", "stepped down");
    // b comes back: its old primaries find their fence gone.
    plant.lab.link("b", CELL_NET, true);
    plant.lab.link("b", PLANT_NET, true);
    plant.lab.signal_host("b", Signal::SIGCONT);
    plant.robot1_says("b", "stepped down", stepped);
    let refused = plant.restart_deposed_orders1("b");
    round_ends(plant, "power loss of b", stale, refused);
}

/// Round 2: b is cut from both networks for 5 s, its processes running; then healed.
/// The old primaries find their fence gone and step down.
fn partition(plant: &mut Plant) {
    let stale = stale_refused(plant);
    let held = plant.robot1_said("a", "holding the controller");
    let stepped = plant.robot1_said("b", "stepped down");
    plant.submit(ORDERS);
    plant.wait_step_in_flight();
    let fault = Instant::now();
    plant.lab.link("b", CELL_NET, false);
    plant.lab.link("b", PLANT_NET, false);
    let robot1 = plant.robot1_says("a", "holding the controller", held);
    let orders1 = plant.orders1_serves("c");
    println!(
        "partition of b: robot1's standby holds the controller after {:.2}s, orders1's serves after {:.2}s",
        (robot1 - fault).as_secs_f64(),
        (orders1 - fault).as_secs_f64()
    );
    let heal_at = fault + Duration::from_secs(5);
    std::thread::sleep(heal_at.saturating_duration_since(Instant::now()));
    plant.lab.link("b", CELL_NET, true);
    plant.lab.link("b", PLANT_NET, true);
    plant.robot1_says("b", "stepped down", stepped);
    let refused = plant.restart_deposed_orders1("b");
    let fenced = round_ends(plant, "partition of b", stale, refused);
    assert!(
        fenced >= 1,
        "partition of b: no command or write was refused for a stale epoch: the fence was never tested"
    );
}

/// Round 3: b is cut from the cell, not from the plant: its robot1 keeps the
/// controller, so robot1 is not taken over; orders1 is.
fn cell_cut(plant: &mut Plant) {
    let stale = stale_refused(plant);
    let held = plant.robot1_said("a", "holding the controller");
    let epoch = plant.counts(1)["epoch"].clone();
    plant.submit(ORDERS);
    plant.wait_step_in_flight();
    let fault = Instant::now();
    plant.lab.link("b", CELL_NET, false);
    let orders1 = plant.orders1_serves("c");
    println!(
        "b cut from the cell: orders1's standby serves after {:.2}s",
        (orders1 - fault).as_secs_f64()
    );
    // Well past a controller lease and a link lease: robot1's holder on b keeps its
    // claim (heartbeats on the plant), so the standby on a is never granted it.
    std::thread::sleep(Duration::from_secs(8));
    assert_eq!(
        plant.robot1_said("a", "holding the controller"),
        held,
        "robot1 was taken over while b still held the controller"
    );
    assert_eq!(
        plant.counts(1)["epoch"],
        epoch,
        "the controller granted a new epoch"
    );
    plant.lab.link("b", CELL_NET, true);
    let refused = plant.restart_deposed_orders1("b");
    round_ends(plant, "b cut from the cell", stale, refused);
}

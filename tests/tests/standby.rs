//! Standby resources (issue 31): two `holon-node --standby` processes with the same name
//! and controller, a fenced `robot-sim`; the controller's claim decides which one
//! serves. The primary is frozen (SIGSTOP: its token stays, its controller session goes
//! silent), the standby's claim is granted and it serves; the old primary, thawed, finds
//! its claim gone and steps down. Every step runs once by the simulator's counts per
//! step id. A holder that dies after its controller ran an order's step, before the
//! result reached the order: the order asks the new holder what became of its
//! conversation (the new holder asks the controller) and the step ends done, never run
//! again; so too when the holder is killed mid-step and restarted on its journal, which
//! says only `interrupted`. Bounded waits only; no timing is asserted.

use std::fs;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Result};
use holarchy_tests::*;
use nix::sys::signal::Signal;
use schemas::{HolonId, MessageType, Service};

/// The log of the holon whose files are in `dir`.
fn log(dir: &Path) -> String {
    fs::read_to_string(dir.join("robot1.log.json")).unwrap_or_default()
}

/// How often `text` occurs in the log of the holon in `dir`.
fn said(dir: &Path, text: &str) -> usize {
    log(dir).matches(text).count()
}

/// Waits (at most [`WAIT`]) until the holon in `dir` has logged `text` `n` times.
async fn wait_said(dir: &Path, text: &str, n: usize) -> Result<()> {
    let deadline = tokio::time::Instant::now() + WAIT;
    while said(dir, text) < n {
        if tokio::time::Instant::now() > deadline {
            bail!(
                "{} never logged {text:?} {n} times; its log ends:\n{}",
                dir.display(),
                tail(&log(dir))
            );
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    Ok(())
}

fn tail(text: &str) -> String {
    let lines: Vec<&str> = text.lines().collect();
    lines[lines.len().saturating_sub(15)..].join("\n")
}

/// A host of its own for one of the twins: a directory with the config `robot1.toml`.
fn host(root: &Path, name: &str) -> Result<PathBuf> {
    let dir = root.join(name);
    fs::create_dir_all(&dir)?;
    resource_config(&dir, "robot1", 5000)?;
    Ok(dir)
}

/// Starts `holon-node --standby` for robot1 on `host`'s config and journal.
fn twin(cell: &Cell, host: &Path, sim: &Sim) -> Result<Process> {
    let data = host.join("data");
    start_node(
        host,
        &host.join("robot1.toml"),
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--standby", "--data-dir", data.to_str().expect("utf-8")],
    )
}

/// Books and starts one job for `order` on robot1 and returns its result.
async fn job(cell: &Cell, order: &str) -> Result<Service> {
    let mut inbox = cell.inbox(order, 0).await?;
    cell.job("robot1", &mut inbox, order, &format!("{order}-1"))
        .await
}

/// How many liveliness tokens robot1's name has, as the router answers.
async fn tokens(cell: &Cell) -> usize {
    let holon = HolonId::resource("robot1").unwrap();
    let replies = cell
        .session
        .liveliness()
        .get(cell.keys.alive(&holon))
        .timeout(Duration::from_secs(2))
        .await
        .unwrap();
    let mut n = 0;
    while let Ok(reply) = replies.recv_async().await {
        if reply.result().is_ok() {
            n += 1;
        }
    }
    n
}

/// The fence reports of robot1's processes that answer within a second, as
/// `(role, epoch, holder_epoch)`, sorted.
async fn reports(cell: &Cell) -> Vec<(String, Option<u64>, Option<u64>)> {
    let key = format!(
        "{}/*",
        cell.keys.state(&HolonId::resource("robot1").unwrap())
    )
    .replace("/state/*", "/fence/*");
    let replies = cell
        .session
        .get(&key)
        .timeout(Duration::from_secs(1))
        .await
        .unwrap();
    let mut found = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            let report: serde_json::Value =
                serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
            found.push((
                report["role"].as_str().unwrap_or_default().to_string(),
                report["epoch"].as_u64(),
                report["holder_epoch"].as_u64(),
            ));
        }
    }
    found.sort();
    found
}

/// Waits (at most [`WAIT`]) until robot1's fence reports are `expected`.
async fn wait_reports(cell: &Cell, expected: &[(&str, Option<u64>, Option<u64>)]) {
    let expected: Vec<_> = expected
        .iter()
        .map(|(role, epoch, holder)| (role.to_string(), *epoch, *holder))
        .collect();
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let found = reports(cell).await;
        if found == expected {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "fence reports {found:?}, never {expected:?}"
        );
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn a_standby_serves_when_its_primary_freezes_and_the_thawed_primary_steps_down() {
    let root = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-standby").await.unwrap();
    let sim = Sim::start(
        root.path(),
        "robot1-sim",
        "127.0.0.1:0",
        &["--fenced", "--lease-ms", "500"],
    )
    .unwrap();
    let (a, b) = (
        host(root.path(), "a").unwrap(),
        host(root.path(), "b").unwrap(),
    );
    let robot1 = HolonId::resource("robot1").unwrap();

    // (1) The first holds the claim and serves; the second waits as a standby.
    let primary = twin(&cell, &a, &sim).unwrap();
    cell.wait_alive(&robot1).await.unwrap();
    free_at_epoch_1(&cell).await;
    wait_said(&a, "holding the controller", 1).await.unwrap();
    let standby = twin(&cell, &b, &sim).unwrap();
    wait_said(&b, "standby: another session holds the controller", 1)
        .await
        .unwrap();
    assert_eq!(said(&b, "holding the controller"), 0, "{}", log(&b));
    assert_eq!(tokens(&cell).await, 1, "the standby declared no token");
    let asking = pick_n_place(&cell.keys, MessageType::ProposalReq, "asker", "asker-1");
    let proposals = cell.proposals(&asking).await.unwrap();
    assert_eq!(proposals.len(), 1, "only the holder offers: {proposals:?}");

    // Each process says where it stands: the holder its epoch, the standby the holder's.
    wait_reports(
        &cell,
        &[("holder", Some(1), None), ("standby", None, Some(1))],
    )
    .await;

    let first = job(&cell, "o1").await.unwrap();
    assert_eq!(first.message_type, MessageType::Done, "{first:?}");
    assert_eq!(said(&b, "holding the controller"), 0, "{}", log(&b));
    assert_eq!(sim.counts()["epoch"], 1, "{}", sim.counts());

    // (2) The primary freezes: its token stays, its controller session goes silent.
    // The standby's claim is granted after the lease; it serves the next job.
    primary.signal(Signal::SIGSTOP).unwrap();
    wait_said(&b, "holding the controller", 1).await.unwrap();
    assert_eq!(sim.counts()["epoch"], 2, "{}", sim.counts());
    // Its state says which holder it is from.
    cell.wait_state("robot1", "free at epoch 2", |s| {
        s["state"] == "free" && s["epoch"] == 2
    })
    .await
    .unwrap();
    // The frozen one answers nothing; the new holder says epoch 2.
    wait_reports(&cell, &[("holder", Some(2), None)]).await;
    let second = job(&cell, "o2").await.unwrap();
    assert_eq!(second.message_type, MessageType::Done, "{second:?}");

    // (3) Thawed, the old primary finds its claim gone (the controller closed its
    // silent session, or refuses its epoch) and steps down: a standby again.
    primary.signal(Signal::SIGCONT).unwrap();
    wait_said(&a, "deposed: stepping down", 1).await.unwrap();
    wait_said(&a, "stepped down: a standby again", 1)
        .await
        .unwrap();
    wait_said(&a, "standby: another session holds the controller", 1)
        .await
        .unwrap();
    assert_eq!(said(&a, "holding the controller"), 1, "{}", log(&a));
    wait_reports(
        &cell,
        &[("holder", Some(2), None), ("standby", None, Some(2))],
    )
    .await;
    // `cell status` lists both: the holder at epoch 2 and the standby that heard of it.
    let status = std::process::Command::new(bin("cell"))
        .args([
            "status",
            "--cell",
            cell.keys.cell(),
            "--connect",
            &cell.endpoint,
        ])
        .output()
        .unwrap();
    let table = String::from_utf8_lossy(&status.stdout);
    assert!(status.status.success(), "{table}");
    let fenced: Vec<&str> = table
        .lines()
        .filter(|line| line.starts_with("resource/robot1 "))
        .collect();
    assert!(
        fenced
            .iter()
            .any(|l| l.contains(" holder ") && l.contains(" 2 ")),
        "{table}"
    );
    assert!(
        fenced
            .iter()
            .any(|l| l.contains(" standby ") && l.contains(" 2 ")),
        "{table}"
    );
    // The dashboard shows them too.
    let mut dashboard = std::process::Command::new(bin("cell"))
        .args([
            "dashboard",
            "--cell",
            cell.keys.cell(),
            "--connect",
            &cell.endpoint,
        ])
        .args(["--listen", "127.0.0.1:0"])
        .stdout(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut line = String::new();
    std::io::BufRead::read_line(
        &mut std::io::BufReader::new(dashboard.stdout.take().unwrap()),
        &mut line,
    )
    .unwrap();
    let address = line
        .trim()
        .rsplit("http://")
        .next()
        .unwrap()
        .trim_end_matches('/');
    let web = holarchy_tests::web::Web::plain(address);
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        let view = web.call("GET", "/api/view", "").json();
        let fences = view["fences"].as_array().cloned().unwrap_or_default();
        let has =
            |role: &str, field: &str| fences.iter().any(|f| f["role"] == role && f[field] == 2);
        if has("holder", "epoch") && has("standby", "holder_epoch") {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the dashboard never showed holder and standby: {fences:?}"
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    dashboard.kill().unwrap();
    dashboard.wait().unwrap();
    // What queued at it while it was frozen (o2's booking and start) it left to the
    // holder: its claim was not confirmed.
    let answered_o2: Vec<String> = log(&a)
        .lines()
        .filter(|line| line.contains("\"o2-1\"") && line.contains("\"message\":\"sent\""))
        .map(str::to_string)
        .collect();
    assert!(
        answered_o2.is_empty(),
        "the deposed one answered o2: {answered_o2:?}"
    );
    // The new holder serves on; the old one takes nothing.
    let third = job(&cell, "o3").await.unwrap();
    assert_eq!(third.message_type, MessageType::Done, "{third:?}");
    assert_eq!(said(&a, "holding the controller"), 1, "{}", log(&a));

    // (4) Every step of every job ran exactly once on the controller.
    let counts = sim.counts();
    for order in ["o1", "o2", "o3"] {
        for index in 0..2 {
            let step = format!("{order}-1#{index}");
            assert_eq!(counts["by_step"][&step], 1, "{step}: {counts}");
        }
    }
    eprintln!(
        "stale_epoch_refused: {}, epoch: {}",
        counts["stale_epoch_refused"], counts["epoch"]
    );
    drop((primary, standby));
}

#[tokio::test(flavor = "multi_thread")]
async fn standby_is_refused_when_the_controller_cannot_fence() {
    let root = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-standby-unfenced").await.unwrap();
    // kuka-eki has no [fence]: the config is refused at start, with the reason.
    let sim = Sim::start(root.path(), "robot1-sim", "127.0.0.1:0", &[]).unwrap();
    let a = host(root.path(), "a").unwrap();
    let config = a.join("robot1.toml");
    let text = fs::read_to_string(&config).unwrap().replacen(
        "[controller]\n",
        "[controller]\ndialect = \"kuka-eki\"\nfenced = true\n",
        1,
    );
    fs::write(&config, text).unwrap();
    let mut node = start_node(
        &a,
        &config,
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &[],
    )
    .unwrap();
    let status = node.wait_exit(WAIT).unwrap();
    assert!(!status.success());
    let stderr = node.stderr();
    assert!(
        stderr.contains("has no fence") && stderr.contains("standby is refused"),
        "{stderr}"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn a_holder_whose_controller_client_crashes_steps_down_and_claims_again() {
    let root = tempfile::tempdir().unwrap();
    let cell = Cell::open("t-standby-crash").await.unwrap();
    let sim = Sim::start(
        root.path(),
        "robot1-sim",
        "127.0.0.1:0",
        &["--fenced", "--lease-ms", "500"],
    )
    .unwrap();
    let a = host(root.path(), "a").unwrap();
    let node = start_node(
        &a,
        &a.join("robot1.toml"),
        cell.keys.cell(),
        &cell.endpoint,
        &sim.address,
        &["--standby", "--allow-fault-injection"],
    )
    .unwrap();
    cell.wait_alive(&HolonId::resource("robot1").unwrap())
        .await
        .unwrap();
    wait_said(&a, "holding the controller", 1).await.unwrap();

    // The interfacing component's connection held the claim: its successor reports it
    // lost, the holder steps down and claims again (the next epoch).
    let replies = cell
        .session
        .get(cell.keys.debug_crash("robot1"))
        .payload("interfacing")
        .timeout(Duration::from_secs(5))
        .await
        .unwrap();
    assert!(replies.recv_async().await.unwrap().result().is_ok());
    wait_said(&a, "deposed: stepping down", 1).await.unwrap();
    wait_said(&a, "holding the controller", 2).await.unwrap();
    cell.wait_state("robot1", "free", |s| s["state"] == "free")
        .await
        .unwrap();
    let done = job(&cell, "o1").await.unwrap();
    assert_eq!(done.message_type, MessageType::Done, "{done:?}");
    let counts = sim.counts();
    assert_eq!(counts["epoch"], 2, "{counts}");
    assert_eq!(counts["by_step"]["o1-1#0"], 1, "{counts}");
    drop(node);
}

/// A fenced robot-sim (500 ms lease) whose `place` takes a second: a step is on the
/// controller long enough to freeze or kill its holder meanwhile.
fn slow_place_sim(dir: &Path) -> Sim {
    Sim::start(
        dir,
        "robot1-sim",
        "127.0.0.1:0",
        &["--fenced", "--lease-ms", "500", "--action-ms", "place=1000"],
    )
    .unwrap()
}

/// Waits until robot1 is free and held at epoch 1.
async fn free_at_epoch_1(cell: &Cell) {
    cell.wait_state("robot1", "free at epoch 1", |s| {
        s["state"] == "free" && s["epoch"] == 1
    })
    .await
    .unwrap();
}

/// Waits until `order` ended, and asserts it is done at its first attempt; its state.
async fn done_at_attempt_1(cell: &Cell, order: &str) -> serde_json::Value {
    cell.wait_order(order, "ended", |s| {
        s.is_some_and(|s| s["status"] != "running")
    })
    .await
    .unwrap();
    let state = cell.order_state(order).await.unwrap();
    assert_eq!(state["status"], "done", "{state}");
    assert_eq!(state["attempt"], 1, "one conversation only: {state}");
    state
}

/// Asserts that the controller ran the two step ids of `order`'s first conversation
/// once each, and nothing else; its counts.
fn ran_once_as_its_first_conversation(sim: &Sim, order: &str) -> serde_json::Value {
    let counts = sim.counts();
    let first = format!("{order}/1/1");
    let by_step = counts["by_step"].as_object().cloned().unwrap_or_default();
    let ran: Vec<(String, u64)> = by_step
        .iter()
        .map(|(step, n)| (step.clone(), n.as_u64().unwrap_or(0)))
        .collect();
    assert_eq!(
        ran,
        vec![(format!("{first}#0"), 1), (format!("{first}#1"), 1)],
        "{counts}"
    );
    counts
}

/// The demo order-node's config with a step timeout of 5 s (the default is 10 min): an
/// order that hears nothing of its step gives up on it within the test.
fn impatient_orders(dir: &Path) -> PathBuf {
    let text = fs::read_to_string(demo_config("orders1.toml")).unwrap();
    assert!(text.contains("step_timeout_ms = 600000"));
    let path = dir.join("orders.toml");
    fs::write(
        &path,
        text.replace("step_timeout_ms = 600000", "step_timeout_ms = 5000"),
    )
    .unwrap();
    path
}

#[tokio::test(flavor = "multi_thread")]
async fn a_step_the_dead_holder_completed_ends_done_and_never_runs_again() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path();
    let cell = Cell::open("t-standby-outcome").await.unwrap();
    // `place` takes a second: the holder's host hangs while it runs.
    let sim = slow_place_sim(dir);
    let (a, b) = (host(dir, "a").unwrap(), host(dir, "b").unwrap());
    let robot1 = HolonId::resource("robot1").unwrap();
    let mut primary = twin(&cell, &a, &sim).unwrap();
    cell.wait_alive(&robot1).await.unwrap();
    free_at_epoch_1(&cell).await;
    let standby = twin(&cell, &b, &sim).unwrap();
    wait_said(&b, "standby: another session holds the controller", 1)
        .await
        .unwrap();
    let (_product, _orders) = cell
        .start_part_and_orders(dir, &impatient_orders(dir), &dir.join("orders-data"))
        .await
        .unwrap();
    let orders = cell.submit("part", 1).await.unwrap();
    let order = orders[0].clone();

    // (1) The step runs on the holder: pick is done, place is on the controller.
    sim.wait_executed("pick", 1).await.unwrap();
    sim.wait_received(2).await.unwrap();
    // (2) The holder's host hangs: its session goes silent, so its result can never
    // reach the order. The controller completes place for nobody, frees the claim
    // after its lease, and the standby holds the controller at epoch 2.
    primary.signal(Signal::SIGSTOP).unwrap();
    wait_said(&b, "holding the controller", 1).await.unwrap();
    cell.wait_state("robot1", "free at epoch 2", |s| {
        s["state"] == "free" && s["epoch"] == 2
    })
    .await
    .unwrap();
    // (3) The hung host dies, with the journal that held the undelivered result.
    primary.kill();
    sim.wait_executed("place", 1).await.unwrap();

    // (4) The order asks the new holder what became of its conversation; it knows
    // nothing of it, asks the controller, and says done: the step ends done.
    let state = done_at_attempt_1(&cell, &order).await;
    assert_eq!(state["rebooks"], 0, "{state}");
    assert_eq!(state["failed_attempts"], 0, "{state}");
    assert!(said(&b, "outcome asked") >= 1, "{}", log(&b));

    // (5) Every step ran exactly once on the controller, under the first conversation.
    let counts = ran_once_as_its_first_conversation(&sim, &order);
    assert_eq!(sim.executed("place"), 1, "{counts}");
    drop(standby);
}

#[tokio::test(flavor = "multi_thread")]
async fn a_holder_killed_mid_step_and_restarted_on_its_journal_reports_the_step_done() {
    let root = tempfile::tempdir().unwrap();
    let dir = root.path();
    let cell = Cell::open("t-standby-restart").await.unwrap();
    let sim = slow_place_sim(dir);
    let a = host(dir, "a").unwrap();
    let mut holder = twin(&cell, &a, &sim).unwrap();
    free_at_epoch_1(&cell).await;
    let (_product, _orders) = cell
        .start_part_and_orders(dir, &impatient_orders(dir), &dir.join("orders-data"))
        .await
        .unwrap();
    let order = cell.submit("part", 1).await.unwrap()[0].clone();

    // The holder dies while place runs; the controller completes it for nobody.
    sim.wait_executed("pick", 1).await.unwrap();
    sim.wait_received(2).await.unwrap();
    holder.kill();
    // Restarted on its journal, which says only that the job was running: it reports
    // it `interrupted`. The order asks, the holder asks the controller: done.
    let holder = twin(&cell, &a, &sim).unwrap();
    let state = done_at_attempt_1(&cell, &order).await;
    assert_eq!(state["failed_attempts"], 0, "{state}");
    let counts = ran_once_as_its_first_conversation(&sim, &order);
    assert_eq!(counts["epoch"], 2, "{counts}");
    drop(holder);
}

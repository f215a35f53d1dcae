//! Orders that move their parts (docs/material-flow.md, "Orders arrange their moves"):
//! real holons on the plant simulator, each over its own controller connection. Before
//! each step the order reserves a place at a station's port and books the conveyor to
//! take the part there; it works the step only where the part physically is (the plant
//! refuses a station's work at an empty port), and the part leaves by the exit.
//!
//! The cell is the one that deadlocks without reservations: two stations of one port
//! each, and parts crossing between them in opposite directions (one product drills
//! then mills, the other mills then drills). With its places reserved and a home for
//! every part in the buffer, every order finishes and the plant ends empty.

use std::time::Duration;

use holarchy_tests::*;
use schemas::HolonId;

#[tokio::test(flavor = "multi_thread")]
async fn crossing_parts_reserve_their_places_and_every_order_finishes() {
    let flow = FlowCell::start("t-flow", CONVEYOR).await;
    // The operator's page draws each part where it is, live (in Chromium, where there
    // is one).
    let page = match webdriver::browser_available() {
        Ok(()) => {
            let (process, address) = start_dashboard(
                flow.dir.path(),
                flow.cell.keys.cell(),
                &flow.cell.endpoint,
                &[],
            );
            let browser = webdriver::Browser::start(&flow.dir.path().join("profile")).unwrap();
            browser.goto(&format!("http://{address}/")).unwrap();
            Some((process, browser))
        }
        Err(why) => {
            println!("SKIPPED (the page's part of this test): it needs Chromium ({why})");
            None
        }
    };
    // Three of each, crossing: more parts than the buffer holds, so some wait outside.
    let mut orders = Vec::new();
    for product in ["ab", "ba", "ab", "ba", "ab", "ba"] {
        orders.extend(flow.cell.submit(product, 1).await.unwrap());
    }
    if let Some((_, browser)) = &page {
        let within = Duration::from_secs(30);
        for state in ["at", "in_transit"] {
            browser
                .wait_for(
                    &format!("#layout circle.part[data-part-state=\"{state}\"]"),
                    within,
                )
                .unwrap_or_else(|e| panic!("no part drawn {state} on the page: {e}"));
        }
        browser
            .wait_for(
                "#layout circle.part[data-part-where=\"station_a.port\"]",
                within,
            )
            .unwrap();
    }
    flow.wait_ended(&orders, Duration::from_secs(120)).await;
    flow.assert_all_done_and_plant_empty(&orders).await;
    for order in &orders {
        let state = flow.cell.order_state(order).await.unwrap();
        assert_eq!(state["failed_attempts"], 0, "{state:#}");
    }
    // What the orders did on the way, for whoever reads the test's output.
    eprintln!(
        "moves ended: {}; places reserved at stations: {}; parts sent home: {}",
        flow.count_in_orders_log("move ended"),
        flow.count_in_orders_log("a place at the station is reserved"),
        flow.count_in_orders_log("it goes back to its home"),
    );
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
}

/// A part in transit when its conveyor's holon is killed is not lost: the conveyor
/// (fenced, so its controller's record of the move's steps counts) comes back on its
/// journal and says the move was done; an order-node killed mid-move resumes its
/// orders where their parts are. Every order finishes and the plant ends empty.
#[tokio::test(flavor = "multi_thread")]
async fn parts_survive_their_conveyor_and_order_node_killed_mid_move() {
    // Slow enough to be caught on the way: a lap takes 4 s.
    let conveyor = CONVEYOR
        .replace("speed_mm_s = 4000", "speed_mm_s = 500")
        .replace(
            "connect_timeout_ms = 500",
            "connect_timeout_ms = 500\nfenced = true",
        );
    let mut flow = FlowCell::start_on(
        "t-flow-kill",
        &conveyor,
        &PLANT.replace(
            "resource = \"conveyor1\"\n",
            "resource = \"conveyor1\"\nfenced_lease_ms = 1000\n",
        ),
    )
    .await;
    let mut orders = Vec::new();
    for product in ["ab", "ba", "ab"] {
        orders.extend(flow.cell.submit(product, 1).await.unwrap());
    }
    for victim in ["conveyor1", "orders1", "conveyor1"] {
        // Wait until a part is on the conveyor, then kill.
        let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
        'moving: loop {
            for order in &orders {
                let state = flow.cell.order_state(order).await;
                if state.is_some_and(|s| s["part"]["state"] == "in_transit") {
                    break 'moving;
                }
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "no part was seen in transit"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        eprintln!(
            "killing {victim} mid-move; plant: {}",
            flow.plant.state()["in_transit"]
        );
        if victim == "orders1" {
            flow.orders.as_mut().expect("started").kill();
            flow.start_orders().await;
        } else {
            flow.resources.get_mut(victim).unwrap().kill();
            flow.start_resource(victim).await;
        }
    }
    flow.wait_ended(&orders, Duration::from_secs(150)).await;
    flow.assert_all_done_and_plant_empty(&orders).await;
}

/// An operator says on the dashboard's page that `order`'s lost part is at `at`: the
/// button on the order's row, confirmed; the page shows the order's answer, and the
/// dashboard's audit trail records it. Returns how the order records who said it.
fn say_where_on_the_page(flow: &FlowCell, order: &str, at: &str) -> &'static str {
    let trail = flow.dir.path().join("audit.jsonl");
    let (_dashboard, address) = start_dashboard(
        flow.dir.path(),
        flow.cell.keys.cell(),
        &flow.cell.endpoint,
        &["--audit", trail.to_str().unwrap()],
    );
    let browser = webdriver::Browser::start(&flow.dir.path().join("profile")).unwrap();
    browser.goto(&format!("http://{address}/")).unwrap();
    let button = format!("button[data-part-order=\"{order}\"][data-part-at=\"{at}\"]");
    let (button, _) = browser
        .wait_for(&button, Duration::from_secs(20))
        .unwrap_or_else(|e| panic!("no button for the lost part on the page: {e}"));
    browser.execute("window.confirm = () => true;").unwrap();
    browser.click(&button).unwrap();
    let answer = browser
        .find("#cancel-answer")
        .unwrap()
        .expect("the answer's place");
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    loop {
        let answer = browser.text(&answer).unwrap_or_default();
        if answer.contains(&format!("recorded: its part is at {at}")) {
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the page's answer: {answer:?}"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let audit = std::fs::read_to_string(&trail).unwrap();
    assert!(
        audit
            .lines()
            .any(|l| l.contains("\"part_found\"") && l.contains(order) && l.contains(at)),
        "{audit}"
    );
    "dashboard "
}

/// A part whose pallet stops reporting is lost: its move ended in the plant, but the
/// conveyor's controller never said so, the step timed out, and the conveyor cannot say
/// where the part is. The order holds ("in transit on X, last seen at Y") until an
/// operator, who looked, says where it is: a word that names neither end of the lost
/// move is refused and changes nothing; the right one is recorded with who said it, the
/// order goes on from there, and the plant agrees at the end.
#[tokio::test(flavor = "multi_thread")]
async fn a_lost_part_waits_for_an_operators_word_and_goes_on_from_there() {
    let conveyor = CONVEYOR.replace("command_timeout_ms = 10000", "command_timeout_ms = 2000");
    let flow = FlowCell::start("t-flow-word", &conveyor).await;
    let pallets = ["conveyor1/p1", "conveyor1/p2", "conveyor1/p3"];
    for pallet in pallets {
        assert_eq!(flow.plant.command(&format!("silence {pallet}")), "ok");
    }
    let orders = flow.cell.submit("ab", 1).await.unwrap();
    let order = &orders[0];
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    let lost = loop {
        let state = flow.cell.order_state(order).await;
        if let Some(state) = state.filter(|s| s["part"]["state"] == "lost") {
            break state;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the part was never lost; plant: {:#}",
            flow.plant.state()
        );
        tokio::time::sleep(Duration::from_millis(200)).await;
    };
    let (from, to) = (
        lost["part"]["from"].as_str().unwrap().to_string(),
        lost["part"]["to"].as_str().unwrap().to_string(),
    );
    // Where the plant says the part is: what the operator sees on the floor.
    let truth = flow.plant.state();
    let at = truth["locations"]
        .as_object()
        .unwrap()
        .iter()
        .find(|(_, parts)| {
            parts
                .as_array()
                .unwrap()
                .iter()
                .any(|p| p["part"] == order.as_str())
        })
        .map(|(location, _)| location.clone())
        .unwrap_or_else(|| panic!("the plant has {order} nowhere at rest: {truth:#}"));
    assert_eq!(
        at, to,
        "a silent pallet's move ends in the plant: {truth:#}"
    );

    // A location that is neither end of the lost move: refused, nothing changes.
    let elsewhere = ["conveyor1.buffer", "station_a.port", "station_b.port"]
        .into_iter()
        .find(|l| *l != from && *l != to)
        .unwrap();
    let refused = flow.say_part_at(order, elsewhere);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(!refused.status.success(), "{stderr}");
    assert!(
        stderr.contains(&format!("was moving from {from} to {to}"))
            && stderr.contains("nothing changed"),
        "{stderr}"
    );
    let still = flow.cell.order_state(order).await.unwrap();
    assert_eq!(still["part"], lost["part"], "{still:#}");
    assert!(still.get("part_found").is_none(), "{still:#}");

    for pallet in pallets {
        assert_eq!(flow.plant.command(&format!("report {pallet}")), "ok");
    }
    // The right word: on the page where Chromium is (the order's row offers both ends
    // of the lost move), else with `cell part`.
    let by = match webdriver::browser_available() {
        Ok(()) => say_where_on_the_page(&flow, order, &at),
        Err(why) => {
            println!("SKIPPED (the page's part of this test): it needs Chromium ({why})");
            let said = flow.say_part_at(order, &at);
            let stdout = String::from_utf8_lossy(&said.stdout);
            assert!(
                said.status.success(),
                "{}",
                String::from_utf8_lossy(&said.stderr)
            );
            assert!(
                stdout.contains(&format!("recorded: its part is at {at}")),
                "{stdout}"
            );
            "cell "
        }
    };
    // Said again: the part is no longer lost, and the refusal says where it is.
    let again = flow.say_part_at(order, &at);
    let stderr = String::from_utf8_lossy(&again.stderr);
    assert!(!again.status.success(), "{stderr}");
    assert!(stderr.contains("its part is not lost"), "{stderr}");

    flow.wait_ended(&orders, Duration::from_secs(90)).await;
    flow.assert_all_done_and_plant_empty(&orders).await;
    let state = flow.cell.order_state(order).await.unwrap();
    let words = state["part_found"].as_array().unwrap();
    assert_eq!(words.len(), 1, "{state:#}");
    assert_eq!(words[0]["location"], at.as_str());
    assert_eq!(words[0]["transporter"], "resource/conveyor1");
    assert!(
        words[0]["by"].as_str().unwrap().starts_with(by),
        "who said it: {state:#}"
    );
    // The order's audit trail shows the word.
    let detail = std::process::Command::new(bin("cell"))
        .args(["orders", "--detail", "--cell", flow.cell.keys.cell()])
        .args(["--connect", &flow.cell.endpoint])
        .output()
        .unwrap();
    let table = String::from_utf8_lossy(&detail.stdout);
    assert!(
        table.contains(&format!("    part found at {at} by {by}")),
        "{table}"
    );
}

const NEAR_AND_FAR: &str = r#"
layout = ["conveyor1.toml", "station_near.toml", "station_far.toml"]

[[controller]]
resource = "conveyor1"
listen = "127.0.0.1:0"

[[controller]]
resource = "station_near"
listen = "127.0.0.1:0"
delay_ms = 100

[[controller]]
resource = "station_far"
listen = "127.0.0.1:0"
delay_ms = 100
"#;

/// The stations an order's steps ran on, in order.
fn stations_of(state: &serde_json::Value) -> Vec<String> {
    state["completed"]
        .as_array()
        .unwrap()
        .iter()
        .map(|step| step[1].as_str().unwrap().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn the_staff_counts_the_travel_and_sends_the_part_to_the_near_station() {
    // station_far says it drills in 200 ms, station_near in 1000 ms (their nominal
    // durations); but a part needs 2 s more to get to station_far. (Contract net alone
    // ranks by the wait, the same at both: either.)
    let stations = [
        ("station_near", "drill", "sa", 1000),
        ("station_far", "drill", "sb", 200),
    ];
    let flow = FlowCell::start_with(
        "t-flow-travel",
        &slow_loop(),
        NEAR_AND_FAR,
        &stations,
        &[("dd", "drill drill")],
    )
    .await;
    let planner = HolonId::staff("planner").unwrap();
    let _staff = start_holon(
        flow.dir.path(),
        "holon-node",
        &demo_config("planner.toml"),
        "planner",
        &flow.cell,
        &[],
    )
    .unwrap();
    flow.cell.wait_alive(&planner).await.unwrap();
    let deadline = tokio::time::Instant::now() + WAIT;
    while flow.count_in_orders_log("staff appeared") == 0 {
        assert!(
            tokio::time::Instant::now() < deadline,
            "the order-node did not see the staff"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    // Without the travel the staff would advise station_far, by its 200 ms.
    let mut orders = Vec::new();
    for _ in 0..3 {
        let order = flow.cell.submit("dd", 1).await.unwrap().remove(0);
        flow.wait_ended(std::slice::from_ref(&order), WAIT).await;
        let state = flow.cell.order_state(&order).await.unwrap();
        assert_eq!(
            stations_of(&state),
            vec!["resource/station_near"; 2],
            "{state:#}"
        );
        assert!(state["advised"].as_u64() >= Some(1), "{state:#}");
        orders.push(order);
    }
    flow.assert_all_done_and_plant_empty(&orders).await;
}

/// A conveyor whose holon runs three moves at once (`[controller] jobs_at_once = 3`,
/// its plant controller `actions_at_once = 3`) has several pallets on their way at one
/// moment, as the plant sees it, and every order still finishes with each part where
/// the control believes it is. With one move at a time (the default) the plant never
/// has more than one of its moves under way: that is what the count below tells apart.
#[tokio::test(flavor = "multi_thread")]
async fn the_conveyor_moves_several_pallets_at_once() {
    // A slow loop (a lap takes 4 s), so that moves last long enough to overlap.
    let (conveyor, plant) = moving_at_once(&slow_loop(), 3);
    let flow = FlowCell::start_on("t-flow-at-once", &conveyor, &plant).await;
    let mut orders = Vec::new();
    for product in ["ab", "ba", "ab", "ba", "ab", "ba"] {
        orders.extend(flow.cell.submit(product, 1).await.unwrap());
    }
    // Watch the plant's truth while the orders run: the most of conveyor1's moves under
    // way at one moment.
    let started = std::time::Instant::now();
    let mut most_at_once = 0;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(120);
    loop {
        let truth = flow.plant.state();
        let moving = truth["in_transit"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|t| t["transporter"] == "conveyor1" && t["stopped"] != true)
            .count();
        most_at_once = most_at_once.max(moving);
        let mut running = 0;
        for order in &orders {
            let state = flow.cell.order_state(order).await;
            if state.as_ref().and_then(|s| s["status"].as_str()) == Some("running") {
                running += 1;
            }
        }
        if running == 0 {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{running} orders still run after 120 s; the plant: {truth:#}"
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
    flow.assert_all_done_and_plant_empty(&orders).await;
    eprintln!(
        "6 orders in {:.1} s; at most {most_at_once} of conveyor1's moves under way at once; moves ended: {}",
        started.elapsed().as_secs_f64(),
        flow.count_in_orders_log("move ended"),
    );
    assert!(
        most_at_once >= 2,
        "conveyor1 never had two moves under way at once (at most {most_at_once})"
    );
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
}

/// Two parts of a product that drills on station_a then mills on station_b, on a slow
/// conveyor running at `speed_mm_s` (at 250 mm/s: from station_a's stopper to the
/// buffer's, 1500 mm, 6 s; station_a to station_b 2 s; station_b to the exit 2 s), the
/// mill's pick and place taking `mill_ms` each (within the stations' 10 s command
/// timeout): every order done, the plant empty, no error logged; how many parts waited
/// at their port, and how many were sent home (each line of the order-node's log about
/// ports and homes is printed when no part waited or one went home).
async fn two_parts_drill_then_mill(name: &str, speed_mm_s: u64, mill_ms: u64) -> (usize, usize) {
    let speed = format!("speed_mm_s = {speed_mm_s}");
    let conveyor = CONVEYOR.replace("speed_mm_s = 4000", &speed);
    assert!(conveyor.contains(&speed));
    let mill = format!("delay_ms = {mill_ms}");
    let plant = PLANT
        .replacen("delay_ms = 150", "delay_ms = 200", 1)
        .replacen("delay_ms = 150", &mill, 1);
    assert!(plant.contains("delay_ms = 200") && plant.contains(&mill));
    let stations = [
        ("station_a", "drill", "sa", 400),
        ("station_b", "mill", "sb", 2 * mill_ms),
    ];
    let flow =
        FlowCell::start_with(name, &conveyor, &plant, &stations, &[("ab", "drill mill")]).await;
    let orders = flow.cell.submit("ab", 2).await.unwrap();
    flow.wait_ended(&orders, Duration::from_secs(180)).await;
    flow.assert_all_done_and_plant_empty(&orders).await;
    let waited = flow.count_in_orders_log("it waits at its port");
    let home = flow.count_in_orders_log("it goes back to its home");
    eprintln!("parts that waited at their port: {waited}; parts sent home: {home}");
    if home > 0 || waited == 0 {
        let log =
            std::fs::read_to_string(flow.dir.path().join("orders1.log.json")).unwrap_or_default();
        for line in log.lines().filter(|l| {
            ["port", "home", "move ended", "reserved", "step", "depart"]
                .iter()
                .any(|w| l.contains(w))
        }) {
            eprintln!("{line}");
        }
    }
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
    (waited, home)
}

/// A part whose next station is still busy when its step ends waits at its port for
/// that station (`orders.wait_at_port`, on by default) rather than ride the loop to
/// its home and back, while no other part waits for the station it is at: here the
/// second of two parts drills on station_a while the first mills on station_b (a slow
/// mill: 6 s, a pick and a place of 3 s each), and takes station_b once the first has
/// left, without going home. Its move home would take 6 s, more than three times what
/// it waits. (The first frees station_b's port as its pallet departs,
/// docs/material-flow.md "Departure": the mill must outlast the second part's ride in
/// and drilling, about 4.5 s after the first reached station_b, since the conveyor
/// moves one pallet at a time.)
#[tokio::test(flavor = "multi_thread")]
async fn a_part_waits_at_its_port_for_a_station_about_to_free() {
    let (waited, home) = two_parts_drill_then_mill("t-flow-port-wait", 250, 3000).await;
    assert_a_part_waited_for_station_b(waited, home, "was about to free");
}

/// A part whose next station works longer than its move home would take waits at its
/// port on while that station works, rather than ride home once its move home's time
/// is up and back when the station frees (docs/material-flow.md, "Orders arrange their
/// moves"): as above on a conveyor of 500 mm/s (a move home of 3 s), with a mill of
/// 9 s (a pick and a place of 4.5 s each), so the second part waits about 6.5 s, more
/// than its move home and less than the wait's cap of four moves home. Until
/// 2026-11-28 the second part went home after 3 s, and station_b stood idle through
/// its lap.
#[tokio::test(flavor = "multi_thread")]
async fn a_part_waits_at_its_port_while_its_next_station_works() {
    let (waited, home) = two_parts_drill_then_mill("t-flow-port-wait-works", 500, 4500).await;
    assert_a_part_waited_for_station_b(waited, home, "worked the part before it");
}

/// A part waited at its port for station_b, and none rode home while station_b
/// `was_doing` what the test says.
fn assert_a_part_waited_for_station_b(waited: usize, home: usize, was_doing: &str) {
    assert!(
        waited >= 1,
        "no part waited at its port for station_b (parts sent home: {home})"
    );
    assert_eq!(home, 0, "a part rode home while station_b {was_doing}");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_part_that_fails_its_inspection_is_recovered_and_inspected_again() {
    // (With one of the conveyor's three pallets taken out meanwhile.)
    // station_b inspects; a failed part is recovered by station_a's drill (the plan's
    // on_reject), then inspected again.
    let stations = [
        ("station_a", "drill", "sa", 1000),
        ("station_b", "inspect", "sb", 1000),
    ];
    let flow = FlowCell::start_with(
        "t-flow-recover",
        CONVEYOR,
        PLANT,
        &stations,
        &[("ai", "drill inspect>drill")],
    )
    .await;
    assert_eq!(flow.plant.command("fail station_b 1"), "ok");
    // One of the three pallets is taken out of service (two stay, as many as the
    // buffer's homes, so no part waits for one long).
    assert_eq!(flow.plant.command("retire conveyor1/p3"), "ok");
    assert!(flow
        .plant
        .command("retire conveyor1/p9")
        .starts_with("error"));
    assert!(flow.plant.command("fail nobody 1").starts_with("error"));
    assert!(flow.plant.command("fail station_b 0").starts_with("error"));
    let orders = flow.cell.submit("ai", 2).await.unwrap();
    flow.wait_ended(&orders, Duration::from_secs(120)).await;
    let mut services = Vec::new();
    for order in &orders {
        let state = flow.cell.order_state(order).await.unwrap();
        assert_eq!(state["status"], "done", "{state:#}");
        assert_eq!(state["part"]["state"], "shipped", "{state:#}");
        let completed: Vec<String> = state["completed"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| c[0].as_str().unwrap_or_default().to_string())
            .collect();
        services.push((completed, state["reworks"].as_u64()));
    }
    services.sort();
    assert_eq!(
        services,
        [
            (vec!["drill".to_string(), "inspect".into()], Some(0)),
            (
                vec![
                    "drill".to_string(),
                    "inspect".into(),
                    "drill".into(),
                    "inspect".into()
                ],
                Some(1)
            ),
        ],
        "one part recovered and inspected again, the other passed at once"
    );
    // The plant did each step where the part was, once: three drills, three
    // inspections, and every part shipped.
    let counts = flow.plant.counts();
    assert_eq!(counts["station_b"]["by_action"]["inspect"], 3, "{counts:#}");
    assert_eq!(counts["station_a"]["by_action"]["place"], 3, "{counts:#}");
    let truth = flow.plant.state();
    assert_eq!(truth["shipped"], 2, "{truth:#}");
    assert_eq!(
        truth["pallets"]["conveyor1/p3"]["at"], "retired",
        "{truth:#}"
    );
    assert_eq!(free_pallets(&truth, "conveyor1"), 2, "{truth:#}");
    assert_eq!(flow.plant.command("restore conveyor1/p3"), "ok");
    let truth = flow.plant.state();
    assert_eq!(free_pallets(&truth, "conveyor1"), 3, "{truth:#}");
    assert_eq!(
        flow.count_in_orders_log("\"ERROR\""),
        0,
        "the order-node logged errors"
    );
}

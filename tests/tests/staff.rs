//! The staff holon against real processes: orders follow its advice when the advised
//! resource proposed, ignore advice that is of no use (a resource that did not
//! propose, another conversation's, malformed, late), and lose nothing when the staff
//! is killed mid-run.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use holarchy_tests::*;
use schemas::{Advice, AdviceRequest, HolonId};

/// What the test's own advisor answers.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Answer {
    /// Advice to book this resource.
    Book(&'static str),
    /// Advice for another conversation (an old answer).
    Stale,
    /// Bytes that are not advice.
    Malformed,
    /// Advice, after the order stopped waiting.
    Late,
    /// Nothing: the query ends without a reply (a staff that cannot keep up).
    Silent,
}

/// A staff holon that answers as the test says: a real zenoh participant with the
/// staff's token and advice queryable, so orders find and ask it as they would a
/// `holon-node` staff. Returns what it was asked.
async fn advisor(
    cell: &Cell,
    answer: Arc<Mutex<Answer>>,
) -> (
    zenoh::liveliness::LivelinessToken,
    zenoh::query::Queryable<()>,
    Arc<Mutex<Vec<AdviceRequest>>>,
) {
    let staff = HolonId::staff("fake").unwrap();
    let asked = Arc::new(Mutex::new(Vec::new()));
    let queryable = cell
        .session
        .declare_queryable(cell.keys.advice("fake"))
        .callback({
            let asked = asked.clone();
            move |query| {
                let request: AdviceRequest =
                    serde_json::from_slice(&query.payload().unwrap().to_bytes()).unwrap();
                asked.lock().unwrap().push(request.clone());
                let answer = *answer.lock().unwrap();
                if answer == Answer::Silent {
                    return; // dropped: the asker's query ends with no reply
                }
                let advice = |resource: &str, conversation_id: String| Advice {
                    v: 1,
                    staff: staff.clone(),
                    order: request.order.clone(),
                    conversation_id,
                    resource: Some(HolonId::resource(resource).unwrap()),
                    forecast_done: None,
                    late_by_ms: None,
                    route: vec![],
                    why: "the test says so".into(),
                };
                let payload = match answer {
                    Answer::Book(resource) => {
                        serde_json::to_vec(&advice(resource, request.conversation_id.clone()))
                            .unwrap()
                    }
                    Answer::Late => {
                        serde_json::to_vec(&advice("slow", request.conversation_id.clone()))
                            .unwrap()
                    }
                    Answer::Stale => {
                        serde_json::to_vec(&advice("slow", "an-old-conversation".into())).unwrap()
                    }
                    Answer::Malformed => b"{\"resource\": 7}".to_vec(),
                    Answer::Silent => unreachable!("returned above"),
                };
                std::thread::spawn(move || {
                    use zenoh::Wait;
                    if answer == Answer::Late {
                        std::thread::sleep(Duration::from_millis(3 * ADVICE_TIMEOUT_MS));
                    }
                    // A late reply may find the query gone: that is the point.
                    let _late_or_sent = query.reply(query.key_expr().clone(), payload).wait();
                });
            }
        })
        .await
        .unwrap();
    let token = cell
        .session
        .liveliness()
        .declare_token(cell.keys.alive(&HolonId::staff("fake").unwrap()))
        .await
        .unwrap();
    (token, queryable, asked)
}

/// How long the tests' order-node waits for advice (`orders.advice_timeout_ms`): the
/// demo's 20 ms is not a bound a loaded test machine always keeps. A late advisor
/// answers after three times this.
const ADVICE_TIMEOUT_MS: u64 = 500;

/// Two robots offering pick_n_place (`fast` and `slow`, their simulators with the
/// given action delays), the product `part` and the order-node `orders1`.
struct TwoRobots {
    cell: Cell,
    dir: tempfile::TempDir,
    fast: Resource,
    slow: Resource,
    /// The product and the order-node (last), stopped when dropped.
    processes: Vec<Process>,
}

impl TwoRobots {
    /// Waits (at most [`WAIT`]) until the order-node has seen a staff holon: it asks for
    /// advice from then on.
    async fn order_node_sees_staff(&self) {
        let orders = self
            .processes
            .last()
            .expect("the order-node is started last");
        let deadline = tokio::time::Instant::now() + WAIT;
        while !orders.stderr().contains("staff appeared") {
            assert!(
                tokio::time::Instant::now() < deadline,
                "the order-node did not see the staff within {WAIT:?}: {}",
                orders.stderr()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

async fn two_robots(name: &str, fast_ms: u64, slow_ms: u64) -> TwoRobots {
    let dir = tempfile::tempdir().unwrap();
    let cell = Cell::open(name).await.unwrap();
    let path = dir.path();
    let robot = |name: &'static str, delay_ms: u64| {
        cell.resource(path, name)
            .sim_flags(&["--delay-ms", &delay_ms.to_string()])
            .command_timeout_ms(10_000)
            .start()
    };
    let fast = robot("fast", fast_ms).await.unwrap();
    let slow = robot("slow", slow_ms).await.unwrap();
    // The demo's order-node, waiting longer for advice (the tests count advised orders).
    let demo = std::fs::read_to_string(demo_config("orders1.toml")).unwrap();
    assert!(demo.contains("advice_timeout_ms = 20\n"));
    let orders_config = path.join("orders1.toml");
    std::fs::write(
        &orders_config,
        demo.replace(
            "advice_timeout_ms = 20\n",
            &format!("advice_timeout_ms = {ADVICE_TIMEOUT_MS}\n"),
        ),
    )
    .unwrap();
    let (part, orders) = cell
        .start_part_and_orders(path, &orders_config, &path.join("orders-data"))
        .await
        .unwrap();
    TwoRobots {
        cell,
        dir,
        fast,
        slow,
        processes: vec![part, orders],
    }
}

/// Submits `count` orders of `part` one after another, each after the last is done,
/// and returns each one's final state.
async fn one_by_one(cell: &Cell, count: u32) -> Vec<serde_json::Value> {
    let mut states = Vec::new();
    for _ in 0..count {
        let order = cell.submit("part", 1).await.unwrap().remove(0);
        cell.wait_order(&order, "done", |s| s.is_some_and(|s| s["status"] == "done"))
            .await
            .unwrap();
        states.push(cell.order_state(&order).await.unwrap());
    }
    states
}

fn resources(states: &[serde_json::Value]) -> Vec<String> {
    states
        .iter()
        .map(|s| s["completed"][0][1].as_str().unwrap().to_string())
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn orders_follow_usable_advice_and_go_by_contract_net_otherwise() {
    let cell = two_robots("t-staff-advice", 0, 0).await;
    let answer = Arc::new(Mutex::new(Answer::Book("slow")));
    let (_token, _queryable, asked) = advisor(&cell.cell, answer.clone()).await;
    cell.order_node_sees_staff().await;

    // Advice for a resource that proposed is followed: every order books `slow`.
    let followed = one_by_one(&cell.cell, 4).await;
    assert_eq!(resources(&followed), vec!["resource/slow"; 4]);
    assert!(followed.iter().all(|s| s["advised"] == 1), "{followed:?}");
    {
        let asked = asked.lock().unwrap();
        assert_eq!(asked.len(), 4);
        assert_eq!(asked[0].steps.len(), 1);
        assert_eq!(asked[0].steps[0].service_type, "pick_n_place");
        assert_eq!(asked[0].order.kind(), schemas::HolonKind::Order);
    }

    // Advice that is no use is ignored, and the order goes by contract net at once.
    for useless in [
        Answer::Book("vanished"),
        Answer::Stale,
        Answer::Malformed,
        Answer::Late,
    ] {
        *answer.lock().unwrap() = useless;
        let states = one_by_one(&cell.cell, 2).await;
        for state in &states {
            assert_eq!(state["advised"], 0, "{useless:?}: {state}");
            assert_eq!(state["status"], "done", "{useless:?}: {state}");
        }
    }
    let log = std::fs::read_to_string(cell.dir.path().join("orders1.stderr")).unwrap_or_default();
    for why in [
        "advice ignored: the advised resource did not propose",
        "for another order or conversation",
        "malformed advice",
        "gave no advice in time",
    ] {
        assert!(
            log.contains(why),
            "the order-node's log lacks {why:?}: {log}"
        );
    }
    // A staff that answers nothing three times in a row is not asked for a while:
    // the next orders go by contract net at once.
    // (An answer first: it clears the two late ones from the count.)
    *answer.lock().unwrap() = Answer::Book("slow");
    one_by_one(&cell.cell, 1).await;
    *answer.lock().unwrap() = Answer::Silent;
    let asked_before = asked.lock().unwrap().len();
    let states = one_by_one(&cell.cell, 5).await;
    assert!(states.iter().all(|s| s["status"] == "done"), "{states:?}");
    assert_eq!(
        asked.lock().unwrap().len() - asked_before,
        3,
        "asked after the pause began"
    );
    let log = std::fs::read_to_string(cell.dir.path().join("orders1.stderr")).unwrap_or_default();
    assert!(log.contains("answered none of the last asks"), "{log}");
    // Every step ran once: 4 + 1 followed, 8 + 5 by contract net.
    assert_eq!(
        cell.fast.sim.executed("pick") + cell.slow.sim.executed("pick"),
        18
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn the_staff_learns_the_fast_robot_and_killing_it_loses_nothing() {
    let cell = two_robots("t-staff-kill", 20, 150).await;
    let dir = cell.dir.path();
    let mut staff = start_holon(
        dir,
        "holon-node",
        &demo_config("planner.toml"),
        "planner",
        &cell.cell,
        &[],
    )
    .unwrap();
    let planner = HolonId::staff("planner").unwrap();
    cell.cell.wait_alive(&planner).await.unwrap();
    cell.order_node_sees_staff().await;

    // Orders one by one: both robots say 1000 ms (nominal); the staff measures the
    // one it advised, finds it fast, and keeps sending the work there (contract net
    // alone sees two idle robots alike and picks either).
    let states = one_by_one(&cell.cell, 8).await;
    assert!(states.iter().all(|s| s["advised"] == 1), "{states:?}");
    // The staff republishes its state once a second at most: wait for this last one.
    let mut state = cell.cell.ask_state(&planner).await.unwrap();
    for _ in 0..30 {
        if state["advised"].as_u64() >= Some(8) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
        state = cell.cell.ask_state(&planner).await.unwrap();
    }
    let learned = &state["learned"];
    let fast = &learned["resource/fast"]["services"]["pick_n_place"];
    let measured = fast["mean_ms"].as_f64().unwrap();
    assert!(
        measured < 1000.0 && fast["samples"].as_u64() >= Some(4),
        "fast measured at {measured} ms, below its nominal 1000: {state}"
    );
    assert_eq!(resources(&states), vec!["resource/fast"; 8]);
    assert!(state["advised"].as_u64().unwrap() >= 8, "{state}");

    // Twenty orders at once; the staff is killed while they run. None is lost, no
    // step runs twice, and the orders after the kill go by contract net alone.
    let orders = cell.cell.submit("part", 20).await.unwrap();
    cell.cell
        .wait_order(&orders[2], "done", |s| {
            s.is_some_and(|s| s["status"] == "done")
        })
        .await
        .unwrap();
    staff.kill();
    cell.cell.wait_gone(&planner).await.unwrap();
    for order in &orders {
        cell.cell
            .wait_order(order, "done", |s| s.is_some_and(|s| s["status"] == "done"))
            .await
            .unwrap();
    }
    assert_eq!(
        cell.fast.sim.executed("pick") + cell.slow.sim.executed("pick"),
        28
    );
    assert_eq!(
        cell.fast.sim.executed("place") + cell.slow.sim.executed("place"),
        28
    );
}

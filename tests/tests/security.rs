//! The secure cell: mutual TLS and access control, with the real binaries (`cell certs`,
//! `cell up`, `holon-node`, `order-node`, `robot-sim`, `cell submit`/`cancel`).
//!
//! Scenario: issue a PKI, bring the cell up, then try what each identity may and may
//! not do, as a new user and an attacker on the plant network would, checking the
//! effects on the holons' states and the controllers' counts.

use std::process::Command;
use std::time::Duration;

use holarchy_tests::secure_cell::secure_cell;
use holarchy_tests::*;
use schemas::{CellKeys, HolonId, MessageType, OrderSnapshot, OrderStatus, Service};
use zenoh::query::ConsolidationMode;

const CELL: &str = "sec";

/// Every reply to a get (no consolidation), errors as `Err(text)`.
async fn ask(
    session: &zenoh::Session,
    key: &str,
    payload: Vec<u8>,
) -> Vec<Result<Vec<u8>, String>> {
    let replies = session
        .get(key)
        .payload(payload)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
        .unwrap();
    let mut out = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        out.push(match reply.result() {
            Ok(sample) => Ok(sample.payload().to_bytes().into_owned()),
            Err(err) => Err(err
                .payload()
                .try_to_string()
                .unwrap_or_default()
                .into_owned()),
        });
    }
    out
}

/// Asks as an identity the access control lets through and returns its replies, at least
/// one: the control for a check that another identity gets no reply at all on `key` (a
/// denied query is dropped, unanswered), so that check cannot pass because nobody serves
/// `key` or the message is misaddressed.
async fn answered(
    session: &zenoh::Session,
    key: &str,
    payload: Vec<u8>,
    who: &str,
) -> Vec<Result<Vec<u8>, String>> {
    let replies = ask(session, key, payload).await;
    assert!(
        !replies.is_empty(),
        "{who} got no reply on {key}, which it may query: the denials seen there prove nothing"
    );
    replies
}

/// Every order of the cell, listed a page at a time (readers may ask
/// `host/order-node/*/orders`); the listing must be complete.
async fn orders(session: &zenoh::Session, keys: &CellKeys) -> Vec<OrderSnapshot> {
    match ::cell::client::listing::all_orders(session, keys, Duration::from_secs(5)).await {
        Ok(orders) => orders,
        Err(e) => {
            let again = holon::presence::tokens(
                session,
                &keys.host("order-node", "*"),
                Duration::from_secs(5),
            )
            .await;
            panic!("an observer lists every order: {e:#}; the tokens asked again: {again:?}")
        }
    }
}

async fn wait_orders_final(
    session: &zenoh::Session,
    keys: &CellKeys,
    names: &[String],
) -> Vec<OrderSnapshot> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    loop {
        let all = orders(session, keys).await;
        let mine: Vec<OrderSnapshot> = all
            .into_iter()
            .filter(|o| names.contains(&o.holon.name().to_string()))
            .collect();
        if mine.len() == names.len() && mine.iter().all(|o| o.status.is_final()) {
            return mine;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "orders not finished: {mine:#?}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn submitted(output: &std::process::Output) -> Vec<String> {
    assert!(
        output.status.success(),
        "cell submit: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_string)
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn the_secure_cell_obeys_only_its_own_identities_by_role() {
    let dir = tempfile::tempdir().unwrap();
    let cell = secure_cell(dir.path(), CELL);
    let keys = cell.keys.clone();

    // An observer sees the whole cell come up.
    let observer = cell
        .session_as(&cell.pki(), "observer.default", holon::Mode::Client)
        .await
        .expect("the observer connects with its certificate");
    for name in ["robot1", "robot2", "inspect1", "conveyor1"] {
        let robot = HolonId::resource(name).unwrap();
        assert!(
            holon::presence::wait_alive(&observer, &keys, &robot, WAIT)
                .await
                .unwrap(),
            "{robot} did not come up; see {}",
            dir.path().join("logs").display()
        );
    }
    assert!(
        holon::presence::wait_token(&observer, &keys.host("order-node", "orders1"), WAIT)
            .await
            .unwrap()
    );
    let state = ask(
        &observer,
        &keys.state(&HolonId::resource("robot1").unwrap()),
        Vec::new(),
    )
    .await;
    assert!(
        matches!(state.first(), Some(Ok(_))),
        "observer reads states: {state:?}"
    );

    // Orders complete under mutual TLS and access control, submitted by the operator.
    let first = submitted(&cell.cell_command(&["submit", "breaker", "--count", "3"]));
    assert_eq!(first.len(), 3);
    let done = wait_orders_final(&observer, &keys, &first).await;
    assert!(
        done.iter().all(|o| o.status == OrderStatus::Done),
        "{done:#?}"
    );
    let executed_after_orders = cell.total_executed();
    assert_eq!(
        executed_after_orders,
        3 * 4,
        "3 breakers: move, pick, place, inspect each"
    );

    // Without TLS, or with a certificate of another CA, nothing connects.
    let plain = holon::ZenohSettings {
        mode: holon::Mode::Client,
        connect: vec![cell.endpoint.replace("tls/", "tcp/")],
        ..Default::default()
    }
    .open("x", Duration::from_secs(3))
    .await;
    assert!(plain.is_err(), "a client without TLS connected");
    let other = tempfile::tempdir().unwrap();
    std::fs::write(
        other.path().join("cell.toml"),
        format!("cell = \"{CELL}\"\n[[process]]\nname = \"x\"\nprogram = \"x\"\n"),
    )
    .unwrap();
    assert!(Command::new(bin("cell"))
        .arg("certs")
        .arg(other.path())
        .status()
        .unwrap()
        .success());
    let foreign = cell
        .session_as(
            &other.path().join("pki"),
            "operator.default",
            holon::Mode::Client,
        )
        .await;
    assert!(foreign.is_err(), "a certificate of another CA was accepted");
    let refused = Command::new(bin("cell"))
        .args([
            "submit",
            "breaker",
            "--cell",
            CELL,
            "--connect",
            &cell.endpoint,
            "--timeout-ms",
            "2000",
        ])
        .arg("--pki")
        .arg(other.path().join("pki"))
        .output()
        .unwrap();
    assert!(!refused.status.success());

    // A running order to attack: robot1 and robot2 are booked by orders of their own.
    let victims = submitted(&cell.cell_command(&["submit", "breaker", "--count", "2"]));
    let robot1 = HolonId::resource("robot1").unwrap();
    let victim = &victims[0];
    let executed_before_attacks = cell.total_executed();

    // The observer may not submit, cancel, book, start or reach an inbox.
    let as_observer = cell.cell_command(&["submit", "breaker", "--identity", "observer.default"]);
    assert!(
        !as_observer.status.success(),
        "an observer submitted orders"
    );
    let cancel_as_observer =
        // Denied by access control, it reaches no order-node: asked again until the
        // timeout, then refused.
        cell.cell_command(&["cancel", victim, "--identity", "observer.default"]);
    let refused = String::from_utf8_lossy(&cancel_as_observer.stderr);
    assert!(
        !cancel_as_observer.status.success() && refused.contains("may not cancel"),
        "an observer cancelled an order, or was refused for another reason: {refused}"
    );
    // Nor say where an order's part is: denied, its word reaches no order-node, where
    // an operator's is answered (refused: this cell's orders move no parts, and the
    // victim may have ended).
    let word = |identity: &str| {
        let said = cell.cell_command(&[
            "part",
            victim,
            "--at",
            "robot1.port",
            "--identity",
            identity,
        ]);
        assert!(!said.status.success());
        String::from_utf8_lossy(&said.stderr).into_owned()
    };
    let observers = word("observer.default");
    assert!(
        observers.contains("may not say where parts are"),
        "{observers}"
    );
    let operators = word("operator.default");
    assert!(
        operators.contains("the order-node refused (invalid)"),
        "{operators}"
    );
    let intruder = HolonId::order("intruder-1").unwrap();
    let booking = Service::request(
        MessageType::BookingReq,
        "pick_n_place",
        "intruder-1/1/1",
        intruder.clone(),
    )
    .with_reply_to(keys.inbox("intruder-1"));
    let start = Service::request(
        MessageType::Start,
        "pick_n_place",
        "intruder-1/1/1",
        intruder.clone(),
    )
    .with_reply_to(keys.inbox("intruder-1"));
    // Access control drops a denied query without an answer, so no reply at all is the
    // outcome to check; that robot1's and robot2's services answer an identity allowed
    // to ask (the spare order-node `probe`: a `start` of a conversation never booked,
    // refused and without effect) shows that the silence is the denial.
    let probe = cell
        .session_as(&cell.pki(), "order-node.probe", holon::Mode::Client)
        .await
        .expect("the spare order-node identity connects");
    for resource in ["robot1", "robot2"] {
        answered(
            &probe,
            &keys.service(resource),
            start.to_json(),
            "the order-node probe",
        )
        .await;
    }
    // What became of a conversation: an order-node may ask it (robot1 never heard of
    // this one: `unknown`), an observer may not (no reply at all).
    let outcome = schemas::OutcomeRequest::new("intruder-1/1/1", "pick_n_place", intruder.clone());
    let told = answered(
        &probe,
        &keys.outcome("robot1"),
        outcome.to_json(),
        "the order-node probe",
    )
    .await;
    let reply = schemas::OutcomeReply::from_json(told[0].as_ref().unwrap()).unwrap();
    assert_eq!(reply.outcome, schemas::Outcome::Unknown, "{reply:?}");
    probe.close().await.unwrap();
    let replies = ask(&observer, &keys.outcome("robot1"), outcome.to_json()).await;
    assert!(
        replies.is_empty(),
        "the observer reached robot1's outcome: {replies:?}"
    );
    for message in [&booking, &start] {
        let replies = ask(&observer, &keys.service("robot1"), message.to_json()).await;
        assert!(
            replies.is_empty(),
            "the observer reached robot1's service: {replies:?}"
        );
    }
    let fake_done = |provider: &str, conversation: &str| {
        let mut done = Service::request(
            MessageType::Done,
            "inspect",
            conversation,
            HolonId::order(victim).unwrap(),
        );
        done.provider = Some(HolonId::resource(provider).unwrap());
        done.info = serde_json::json!({"results": {"inspect": "inspect_pass"}})
            .as_object()
            .cloned()
            .unwrap();
        done.to_json()
    };
    // Unanswered because denied: the same inbox answers robot9's fake results below.
    for step in 1..=3 {
        let replies = ask(
            &observer,
            &keys.inbox(victim),
            fake_done("inspect1", &format!("{victim}/{step}/1")),
        )
        .await;
        assert!(
            replies.is_empty(),
            "the observer reached an order's inbox: {replies:?}"
        );
    }
    // Nor claim another order's booking to cancel it: those robot1 holds now, and the
    // victim's first step (whether or not it is still booked, so that one is always
    // tried).
    let snapshot = ask(&observer, &keys.state(&robot1), Vec::new()).await;
    let Some(Ok(payload)) = snapshot.first() else {
        panic!("the observer cannot read robot1's state: {snapshot:?}");
    };
    let state: serde_json::Value = serde_json::from_slice(payload).unwrap();
    // The observer reads the cell's layout, every resource's part of it (`cell layout`).
    let mut parts: Vec<String> = ask(&observer, &keys.layout_all(), Vec::new())
        .await
        .into_iter()
        .map(|reply| {
            let bytes = reply.unwrap_or_else(|e| panic!("a layout part refused: {e}"));
            schemas::layout::LayoutPart::from_json(&bytes)
                .unwrap()
                .holon
        })
        .collect();
    parts.sort();
    assert_eq!(parts, ["conveyor1", "inspect1", "robot1", "robot2"]);
    let mut cancels = vec![Service::request(
        MessageType::BookingCancel,
        "pick_n_place",
        &format!("{victim}/1/1"),
        HolonId::order(victim).unwrap(),
    )];
    for entry in state["agenda"].as_array().cloned().unwrap_or_default() {
        let requester: HolonId = entry["requester"].as_str().unwrap().parse().unwrap();
        cancels.push(Service::request(
            MessageType::BookingCancel,
            entry["service_type"].as_str().unwrap(),
            entry["conversation_id"].as_str().unwrap(),
            requester,
        ));
    }
    for cancel in cancels {
        let replies = ask(&observer, &keys.service("robot1"), cancel.to_json()).await;
        assert!(
            replies.is_empty(),
            "the observer reached robot1's service with a cancel: {replies:?}"
        );
    }

    // PackML commands are the operators': the operator's Unhold (refused in Execute by
    // robot1 itself, nothing changes) is answered, so the observer's silence is the
    // denial.
    let packml =
        |command| serde_json::to_vec(&schemas::PackmlRequest::command(command, "a test")).unwrap();
    let operator = cell
        .session_as(&cell.pki(), "operator.default", holon::Mode::Client)
        .await
        .expect("the operator connects");
    let refused = answered(
        &operator,
        &keys.packml("robot1"),
        packml(schemas::PackmlCommand::Unhold),
        "the operator",
    )
    .await;
    assert!(
        matches!(&refused[0], Ok(body) if String::from_utf8_lossy(body).contains("not_in_state")),
        "{refused:?}"
    );
    operator.close().await.unwrap();
    let replies = ask(
        &observer,
        &keys.packml("robot1"),
        packml(schemas::PackmlCommand::Hold),
    )
    .await;
    assert!(replies.is_empty(), "the observer held robot1: {replies:?}");

    // A resource identity (a spare: robot9) may not submit, book another resource,
    // declare another resource's keys or an order's inbox, or fake a result.
    let robot9 = cell
        .session_as(&cell.pki(), "resource.robot9", holon::Mode::Peer)
        .await
        .expect("a spare resource identity connects");
    let replies = ask(
        &robot9,
        &keys.packml("robot1"),
        packml(schemas::PackmlCommand::Abort),
    )
    .await;
    assert!(replies.is_empty(), "robot9 aborted robot1: {replies:?}");
    let snapshot = ask(&observer, &keys.state(&robot1), Vec::new()).await;
    let Some(Ok(payload)) = snapshot.first() else {
        panic!("the observer cannot read robot1's state: {snapshot:?}");
    };
    let state: serde_json::Value = serde_json::from_slice(payload).unwrap();
    assert_eq!(state["packml"]["state"], "execute", "{state}");
    let work = serde_json::to_vec(&schemas::WorkOrder {
        product: "breaker".into(),
        count: 1,
        priority: 0,
        due: None,
        queue: false,
        submit_id: None,
    })
    .unwrap();
    // Denied, so unanswered (robot2's service answered the probe above; the order-node
    // answers the operator's submits, before and after).
    assert!(
        ask(&robot9, &keys.orders_submit(), work).await.is_empty(),
        "a resource submitted orders"
    );
    assert!(
        ask(&robot9, &keys.service("robot2"), booking.to_json())
            .await
            .is_empty(),
        "a resource booked another"
    );
    // A result for the victim from robot9 (which it never booked) is allowed through (a
    // resource delivers results to inboxes) and refused by the order, or by its node
    // once it has finished: a refusal must arrive, and nothing else.
    for step in 1..=3 {
        let replies = ask(
            &robot9,
            &keys.inbox(victim),
            fake_done("robot9", &format!("{victim}/{step}/1")),
        )
        .await;
        assert!(
            !replies.is_empty(),
            "nobody answered a result from robot9 in {victim}'s inbox: no refusal to check"
        );
        for reply in &replies {
            let refusal = reply
                .as_ref()
                .err()
                .and_then(|text| serde_json::from_str::<schemas::ErrorReply>(text).ok());
            assert!(
                refusal.is_some_and(|r| r.code.as_str() == "not_booked"),
                "an order did not refuse (not_booked) a result from a resource it did not book: {replies:?}"
            );
        }
    }

    // Squatting: queryables on others' keys and another resource's token.
    let intercepted = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let mut squats = Vec::new();
    for key in [
        keys.inbox("*"),
        keys.service("robot1"),
        keys.offer("pick_n_place", "robot1"),
        keys.state(&robot1),
    ] {
        let counter = intercepted.clone();
        squats.push(
            robot9
                .declare_queryable(&key)
                .callback(move |query| {
                    counter.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                    use zenoh::Wait;
                    let _ = query
                        .reply(query.key_expr().clone(), b"squatted".to_vec())
                        .wait();
                })
                .await
                .unwrap(),
        );
    }
    let _fake_token = robot9
        .liveliness()
        .declare_token(keys.alive(&HolonId::resource("robot8").unwrap()))
        .await
        .unwrap();
    // The attacked orders and a new one run to the end with every step really executed.
    let after = submitted(&cell.cell_command(&["submit", "breaker"]));
    let mut all: Vec<String> = victims.clone();
    all.extend(after);
    let finished = wait_orders_final(&observer, &keys, &all).await;
    assert!(
        finished.iter().all(|o| o.status == OrderStatus::Done),
        "{finished:#?}"
    );
    assert!(
        finished.iter().all(|o| o.completed.len() == 3),
        "{finished:#?}"
    );
    assert_eq!(
        cell.total_executed() - executed_before_attacks,
        3 * 4,
        "each of the 3 orders executed its 4 controller commands, nothing more"
    );
    assert_eq!(
        intercepted.load(std::sync::atomic::Ordering::SeqCst),
        0,
        "squatted queryables were reached"
    );
    let alive = holon::presence::alive_holons(&observer, &keys, Duration::from_secs(2))
        .await
        .unwrap();
    assert!(
        !alive
            .iter()
            .any(|h| h.name() == "robot8" || h.name() == "robot9"),
        "a token of another identity was accepted: {alive:?}"
    );
    drop(squats);
    robot9.close().await.unwrap();

    // Quotas: a work order over the per-submit limit is refused and creates nothing.
    let before = orders(&observer, &keys).await.len();
    let over = cell.cell_command(&["submit", "breaker", "--count", "1001"]);
    assert!(!over.status.success());
    assert!(
        String::from_utf8_lossy(&over.stderr).contains("max_orders_per_submit"),
        "{}",
        String::from_utf8_lossy(&over.stderr)
    );
    assert_eq!(orders(&observer, &keys).await.len(), before);

    // The operator cancels an order: it ends as cancelled and leaves no booking behind.
    let to_cancel = submitted(&cell.cell_command(&["submit", "breaker", "--count", "4"]));
    let last = to_cancel.last().unwrap();
    let cancelled = cell.cell_command(&["cancel", last]);
    assert!(
        cancelled.status.success(),
        "{}",
        String::from_utf8_lossy(&cancelled.stderr)
    );
    let ended = wait_orders_final(&observer, &keys, &to_cancel).await;
    let cancelled_order = ended.iter().find(|o| o.holon.name() == last).unwrap();
    assert_eq!(
        cancelled_order.status,
        OrderStatus::Cancelled,
        "{cancelled_order:#?}"
    );
    for name in ["robot1", "robot2", "inspect1", "conveyor1"] {
        let state = ask(
            &observer,
            &keys.state(&HolonId::resource(name).unwrap()),
            Vec::new(),
        )
        .await;
        let state: serde_json::Value = serde_json::from_slice(state[0].as_ref().unwrap()).unwrap();
        let stale: Vec<_> = state["agenda"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|b| b["requester"].as_str() == Some(&format!("order/{last}")))
            .collect();
        assert!(
            stale.is_empty(),
            "{name} keeps a booking of the cancelled order: {stale:?}"
        );
    }
    observer.close().await.unwrap();
}

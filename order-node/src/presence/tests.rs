//! The presence's task on a zenoh session of its own (no links): what it publishes
//! follows the tokens and states, and a full mailbox loses nothing for good.

use std::time::Duration;

use schemas::{CellKeys, HolonId, HolonKind};

use super::{task, Presence, TurnNews};

async fn session() -> zenoh::Session {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("scouting/multicast/enabled", "false"),
        ("listen/endpoints", "[]"),
    ] {
        config.insert_json5(key, value).unwrap();
    }
    zenoh::open(config).await.unwrap()
}

fn snapshot(resource: &HolonId, state: &str, agenda: &[&str]) -> Vec<u8> {
    let snapshot = super::model::tests::snapshot_of(resource, state, "ready", agenda);
    serde_json::to_vec(&snapshot).unwrap()
}

/// Waits (at most 5 s) until `what` holds.
async fn until(presence: &Presence, what: impl Fn(&Presence) -> bool) {
    tokio::time::timeout(Duration::from_secs(5), async {
        while !what(presence) {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await
    .expect("the presence's task published it within 5 s");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn orders_read_what_the_task_heard() {
    let session = session().await;
    let keys = CellKeys::new("t").unwrap();
    let robot = HolonId::resource("robot1").unwrap();
    let presence = Presence::follow(&session, &keys).await.unwrap();
    let mut changes = presence.changes();
    let appearances = presence.appearances();
    assert!(!presence.is_alive(&robot));
    let token = session
        .liveliness()
        .declare_token(keys.alive(&robot))
        .await
        .unwrap();
    until(&presence, |p| p.is_alive(&robot)).await;
    assert_eq!(changes.recv().await.unwrap(), (robot.clone(), true));
    assert!(
        appearances.has_changed().unwrap(),
        "orders that found none woken"
    );

    let turn = presence.turn(&robot, "c/1/1");
    tokio::pin!(turn);
    let early = tokio::time::timeout(Duration::from_millis(50), &mut turn).await;
    assert!(early.is_err(), "nothing published yet: {early:?}");
    let state_key = keys.state(&robot);
    session
        .put(&state_key, snapshot(&robot, "free", &["c/1/1", "d/1/1"]))
        .await
        .unwrap();
    let news = tokio::time::timeout(Duration::from_secs(5), &mut turn).await;
    assert_eq!(news.unwrap(), TurnNews::Turn);
    assert_eq!(presence.queue(&robot, 0), Some(2));
    // What it offers, and whether it works for a part waiting at another's port.
    assert_eq!(
        presence.services_of(&robot),
        vec!["pick_n_place".to_string()]
    );
    let other = HolonId::resource("robot2").unwrap();
    assert!(!presence.working_for("pick_n_place", &other), "free");
    let mut working =
        super::model::tests::snapshot_of(&robot, "busy", "ready", &["c/1/1", "d/1/1"]);
    working.current = Some(schemas::CurrentJobView {
        requester: HolonId::order("o-2").unwrap(),
        conversation_id: "e/1/1".into(),
        service_type: "pick_n_place".into(),
        step: None,
        program: None,
        started_at: None,
    });
    session
        .put(&state_key, serde_json::to_vec(&working).unwrap())
        .await
        .unwrap();
    until(&presence, |p| p.working_for("pick_n_place", &other)).await;
    assert!(
        !presence.working_for("pick_n_place", &robot),
        "not the asker's own"
    );
    assert!(!presence.working_for("inspect", &other), "not offered");

    // A freed place wakes one waiting order.
    let mut appearances = presence.appearances();
    session
        .put(&state_key, snapshot(&robot, "busy", &["d/1/1"]))
        .await
        .unwrap();
    tokio::time::timeout(
        Duration::from_secs(5),
        presence.appeared_or_room(&mut appearances),
    )
    .await
    .expect("woken for the freed place");

    token.undeclare().await.unwrap();
    until(&presence, |p| !p.is_alive(&robot)).await;
    assert_eq!(changes.recv().await.unwrap(), (robot.clone(), false));

    let staff = HolonId::new(HolonKind::Staff, "s1").unwrap();
    let _staff_token = session
        .liveliness()
        .declare_token(keys.alive(&staff))
        .await
        .unwrap();
    until(&presence, |p| p.staff().as_ref() == Some(&staff)).await;
}

/// A mailbox of one: the delete that finds it full is lost, counted, and recovered by
/// the resynchronisation (a query of the tokens).
#[tokio::test(flavor = "multi_thread", worker_threads = 1)]
async fn a_lost_token_delete_is_recovered_by_a_resynchronisation() {
    let session = session().await;
    let keys = CellKeys::new("t").unwrap();
    let robot = HolonId::resource("robot1").unwrap();
    let presence = task::start(&session, &keys, 1).await.unwrap();
    let token = session
        .liveliness()
        .declare_token(keys.alive(&robot))
        .await
        .unwrap();
    until(&presence, |p| p.is_alive(&robot)).await;
    // On the runtime's one worker, which the task needs too: the task cannot drain
    // the mailbox between these, so the first snapshot fills it and the rest and the
    // delete are lost.
    let burst = {
        let (session, state_key) = (session.clone(), keys.state(&robot));
        let snapshot = snapshot(&robot, "free", &[]);
        tokio::spawn(async move {
            for _ in 0..3 {
                session.put(&state_key, snapshot.clone()).await.unwrap();
            }
            token.undeclare().await.unwrap();
        })
    };
    burst.await.unwrap();
    until(&presence, |p| !p.is_alive(&robot)).await;
    assert!(
        presence.lost_events() > 0,
        "the delete was lost, not delivered"
    );
}

use super::*;
use crate::context::Progress;
use crate::journal::OrderJournal;
use holon::journal::{Durability, Journal};
use std::path::{Path, PathBuf};

/// A directory of its own for one test, removed when it ends.
struct TestDir(PathBuf);

impl TestDir {
    fn new(test: &str) -> TestDir {
        let dir = std::env::temp_dir().join(format!(
            "order-node-host-{test}-{}-{}",
            std::process::id(),
            schemas::unix_ms()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        TestDir(dir)
    }
}

impl Drop for TestDir {
    fn drop(&mut self) {
        if let Err(e) = std::fs::remove_dir_all(&self.0) {
            eprintln!("cannot remove {}: {e}", self.0.display());
        }
    }
}

/// A host of node `n1` with no task running, on a zenoh session of its own (no
/// links), with a journal in `dir` if given.
async fn host(dir: Option<&Path>) -> Host {
    let config = OrderNodeConfig::parse(
        "cell = \"t\"\nname = \"n1\"\n[zenoh]\nmode = \"peer\"\n",
        "n1.toml",
        Default::default(),
    )
    .unwrap();
    let mut zenoh_config = zenoh::Config::default();
    for (key, value) in [
        ("scouting/multicast/enabled", "false"),
        ("listen/endpoints", "[]"),
    ] {
        zenoh_config.insert_json5(key, value).unwrap();
    }
    let session = zenoh::open(zenoh_config).await.unwrap();
    let presence = crate::presence::Presence::follow(&session, &config.keys)
        .await
        .unwrap();
    let journal = dir.map(|dir| {
        Arc::new(OrderJournal::Local(
            Journal::open(dir, "order-node-n1.sqlite", Durability::ProcessCrash).unwrap(),
        ))
    });
    let (freed, appeared) = presence.room_news();
    Host::new(
        config.clone(),
        Arc::new(OrderContext {
            line: crate::station_line::StationLine::start(freed, appeared),
            homes: Default::default(),
            session,
            keys: config.keys.clone(),
            settings: config.orders,
            presence,
            inboxes: Default::default(),
            rounds: tokio::sync::Semaphore::new(1),
            idle: Default::default(),
            journal,
            journal_waiters: tokio::sync::Semaphore::new(crate::context::JOURNAL_WAITERS),
            journal_failing: Default::default(),
            bookings_in_flight: Default::default(),
            advice_pause: Default::default(),
            layout: Default::default(),
        }),
        Finished::new(),
        Default::default(),
        1,
    )
}

/// Hosts order `n1-<n>` in memory as its creation would (without its task),
/// journalled; returns the writer of its progress, as its task would hold it.
fn running(host: &mut Host, n: u64) -> Progress {
    let name = format!("n1-{n}");
    let progress = OrderProgress::new(HolonId::order(&name).unwrap(), "breaker", 3);
    host.context.save(&progress).unwrap();
    let (writer, view) = Progress::new(progress);
    host.orders.insert(
        name,
        Hosted {
            progress: view,
            operator_cancel: CancellationToken::new(),
            cancel_asks: crate::cancel::mailbox().0,
            part_words: crate::part_word::mailbox().0,
        },
    );
    host.next = host.next.max(n + 1);
    writer
}

/// What the node answers to a read of every order's state, without the time of
/// the answer (`at`).
fn states(host: &Host) -> Vec<(String, serde_json::Value)> {
    read_states(host, &host.config.keys.node_orders("n1", "state"))
}

/// What the node answers to a read of one order's state (by its own key).
fn state_of(host: &Host, name: &str) -> Vec<(String, serde_json::Value)> {
    read_states(
        host,
        &host.config.keys.state(&HolonId::order(name).unwrap()),
    )
}

fn read_states(host: &Host, key: &str) -> Vec<(String, serde_json::Value)> {
    let all = KeyExpr::try_from(key.to_string()).unwrap();
    host.snapshots_matching(&all)
        .into_iter()
        .map(|(key, payload)| {
            let mut state: serde_json::Value = serde_json::from_slice(&payload).unwrap();
            state.as_object_mut().unwrap().remove("at").unwrap();
            (key, state)
        })
        .collect()
}

async fn cancel_reply(host: &Host, name: &str) -> Result<Vec<u8>, String> {
    host.cancel(name)
        .await
        .map(|reply| serde_json::to_vec(&reply).unwrap())
        .map_err(|(code, why)| format!("{code}: {why}"))
}

/// A cancel is the order's task's to record: the node asks, the task writes the
/// journal and answers, once; without a running task the node answers
/// `unavailable` and writes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cancel_is_recorded_by_the_orders_own_task() {
    let dir = TestDir::new("cancel");
    let mut host = host(Some(&dir.0)).await;
    let progress = running(&mut host, 1);
    let refused = host.cancel("n1-1").await.unwrap_err();
    assert_eq!(refused.0, ErrorCode::Unavailable, "{refused:?}");
    assert!(!progress.get().cancel_requested);

    let (asks, mailbox) = crate::cancel::mailbox();
    let operator_cancel = CancellationToken::new();
    host.orders.get_mut("n1-1").unwrap().cancel_asks = asks;
    let task = {
        let (ctx, stop) = (host.context.clone(), operator_cancel.clone());
        tokio::spawn(
            async move { crate::cancel::answer_cancels(&ctx, &progress, mailbox, &stop).await },
        )
    };
    let reply = host.cancel("n1-1").await.unwrap();
    assert!(reply.cancelled, "{reply:?}");
    assert!(operator_cancel.is_cancelled());
    assert!(host.progress("n1-1").unwrap().unwrap().cancel_requested);
    let journal = host.context.journal.as_ref().unwrap();
    let recorded: OrderProgress = journal.get(ORDER_RECORD, "n1-1").unwrap().unwrap();
    assert!(recorded.cancel_requested, "journalled before the answer");
    // Asked again: the same answer, nothing new to record.
    assert!(host.cancel("n1-1").await.unwrap().cancelled);
    host.orders.remove("n1-1");
    task.await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_finished_order_leaves_memory_and_is_answered_from_the_journal() {
    let dir = TestDir::new("answered");
    let mut host = host(Some(&dir.0)).await;
    let done = running(&mut host, 1);
    running(&mut host, 2);
    host.context
        .commit(&done, |p| p.fail("no plan".into()))
        .await
        .unwrap();
    let (states_before, cancel_before) = (states(&host), cancel_reply(&host, "n1-1").await);
    let progress_before = host.progress("n1-1").unwrap().unwrap();
    assert_eq!(states_before.len(), 2);

    host.retire("n1-1");
    host.retire("n1-2"); // unfinished: stays
    assert!(!host.orders.contains_key("n1-1"));
    assert!(host.orders.contains_key("n1-2"));
    assert!(host.finished.contains_key(&1));
    drop(done);
    assert_eq!(
        states(&host),
        states_before[1..],
        "a read of every order's state gets the orders in memory"
    );
    assert_eq!(
        state_of(&host, "n1-1"),
        states_before[..1],
        "a read of a finished order's own state reads it from the journal"
    );
    assert_eq!(host.progress("n1-1").unwrap().unwrap(), progress_before);
    assert_eq!(
        cancel_reply(&host, "n1-1").await,
        cancel_before,
        "refused as before"
    );
    let refused: CancelReply = serde_json::from_slice(cancel_before.as_ref().unwrap()).unwrap();
    assert!(!refused.cancelled);
    assert!(!host.forgotten("n1-1"));
    assert_eq!(
        cancel_reply(&host, "n1-9").await,
        Err("unknown_order: n1-9 is not an order of n1".to_string())
    );
    assert_eq!(host.unfinished(), 1);

    // After a restart (the journal reopened), the same answers.
    drop(host);
    let mut host = self::host(Some(&dir.0)).await;
    let crate::recovery::Recovered {
        hosted: recovered,
        finished,
        ..
    } = crate::recovery::recover(host.context.journal.as_ref().unwrap(), "n1").unwrap();
    assert_eq!(
        recovered.len(),
        1,
        "only the unfinished order is read whole"
    );
    assert_eq!(finished.keys().collect::<Vec<_>>(), [&1]);
    host.finished = finished;
    host.next = 3;
    let mut tasks = Tasks::default();
    let cancel = CancellationToken::new();
    cancel.cancel(); // the unfinished order's task stops at once
    host.resume(recovered, &[], &mut tasks, &cancel);
    assert!(!host.orders.contains_key("n1-1"));
    assert_eq!(states(&host), states_before[1..]);
    assert_eq!(state_of(&host, "n1-1"), states_before[..1]);
    assert_eq!(cancel_reply(&host, "n1-1").await, cancel_before);
    while tasks.set.join_next().await.is_some() {}
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_listing_pages_running_orders_then_finished_ones_newest_first() {
    use schemas::{OrderFilter, OrderListRequest, PageCursor};
    let dir = TestDir::new("pages");
    let mut host = host(Some(&dir.0)).await;
    for n in 1..=6 {
        let progress = running(&mut host, n);
        if n <= 3 {
            host.context
                .commit(&progress, |p| p.fail("no plan".into()))
                .await
                .unwrap();
            host.retire(&format!("n1-{n}"));
        }
    }
    let names = |page: &schemas::OrderPage| -> Vec<String> {
        page.orders
            .iter()
            .map(|o| o.holon.name().to_string())
            .collect()
    };
    let first = OrderListRequest::first(OrderFilter::All, 2);
    let page = host.page(&first);
    assert_eq!((page.counts.running, page.counts.failed), (3, 3));
    assert_eq!(names(&page), ["n1-4", "n1-5"]);
    assert_eq!(page.next, Some(PageCursor::AfterRunning(5)));
    let page = host.page(&first.after(page.next.unwrap()));
    assert_eq!(
        names(&page),
        ["n1-6", "n1-3"],
        "the finished ones newest first"
    );
    assert_eq!(page.next, Some(PageCursor::AfterFinished(3)));
    let page = host.page(&first.after(page.next.unwrap()));
    assert_eq!(names(&page), ["n1-2", "n1-1"]);
    assert_eq!(page.next, None, "the last page");
    assert_eq!(page.unreadable, 0);

    let failed = host.page(&OrderListRequest::first(
        OrderFilter::Status(schemas::OrderStatus::Failed),
        10,
    ));
    assert_eq!(names(&failed), ["n1-3", "n1-2", "n1-1"]);
    let running = host.page(&OrderListRequest::first(OrderFilter::Running, 10));
    assert_eq!(
        (names(&running), running.next),
        (vec!["n1-4".into(), "n1-5".into(), "n1-6".into()], None)
    );
    let counts = host.page(&OrderListRequest::first(OrderFilter::All, 0));
    assert!(counts.orders.is_empty() && counts.next.is_none());
    assert_eq!(counts.counts.total(), 6);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn after_the_retention_the_journal_forgets_a_finished_order() {
    let dir = TestDir::new("forgets");
    let mut host = host(Some(&dir.0)).await;
    let old = running(&mut host, 1);
    let recent = running(&mut host, 2);
    host.context
        .commit(&old, |p| {
            p.cancel();
            p.finished_at = Some(schemas::unix_ms() - 10_000);
        })
        .await
        .unwrap();
    host.context.commit(&recent, |p| p.cancel()).await.unwrap();
    host.retire("n1-1");
    host.retire("n1-2");
    assert!(host.orders.is_empty());

    assert_eq!(host.forget_finished(Duration::from_secs(5)), 1);
    let journal = host.context.journal.clone().unwrap();
    assert_eq!(
        journal
            .get::<OrderProgress>(crate::context::ORDER_RECORD, "n1-1")
            .unwrap(),
        None,
        "out of the journal"
    );
    assert!(journal
        .get::<OrderProgress>(crate::context::ORDER_RECORD, "n1-2")
        .unwrap()
        .is_some());
    assert!(host.forgotten("n1-1"));
    assert!(!host.forgotten("n1-2"));
    assert_eq!(host.progress("n1-1").unwrap(), None);
    assert!(cancel_reply(&host, "n1-1").await.is_err());
    assert!(state_of(&host, "n1-1").is_empty());
    assert_eq!(state_of(&host, "n1-2").len(), 1);
    let listed = host.page(&schemas::OrderListRequest::default());
    assert_eq!(listed.orders.len(), 1, "{listed:?}");
    assert_eq!(listed.orders[0].holon.name(), "n1-2");
    assert_eq!(host.forget_finished(Duration::from_secs(5)), 0);
}

/// An order finished before ends were stamped (an older journal) is stamped, and
/// read from the journal like the others.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_old_journal_opens_and_answers() {
    let dir = TestDir::new("old");
    let mut old = OrderProgress::new(HolonId::order("n1-1").unwrap(), "breaker", 3);
    old.fail("no plan".into());
    old.finished_at = None;
    {
        let journal =
            Journal::open(&dir.0, "order-node-n1.sqlite", Durability::ProcessCrash).unwrap();
        journal
            .put(crate::context::ORDER_RECORD, "n1-1", &old)
            .unwrap();
    }
    let mut host = host(Some(&dir.0)).await;
    host.next = 2;
    let crate::recovery::Recovered {
        hosted: recovered,
        finished,
        ..
    } = crate::recovery::recover(host.context.journal.as_ref().unwrap(), "n1").unwrap();
    assert!(finished.is_empty(), "its end was not recorded: read whole");
    let mut tasks = Tasks::default();
    host.resume(recovered, &[], &mut tasks, &CancellationToken::new());
    assert!(tasks.set.is_empty());
    assert!(host.orders.is_empty());
    let read = host.progress("n1-1").unwrap().unwrap();
    assert!(read.finished_at.is_some(), "stamped in the journal");
    assert_eq!(read.status, old.status);
    assert_eq!(state_of(&host, "n1-1").len(), 1);
    assert!(!cancel_reply(&host, "n1-1").await.unwrap().is_empty());
}

/// Without a journal there is nowhere else to read a finished order from: it stays
/// in memory until the retention ends, as before.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_a_journal_finished_orders_stay_in_memory() {
    let mut host = host(None).await;
    let done = running(&mut host, 1);
    host.context.commit(&done, |p| p.cancel()).await.unwrap();
    let before = states(&host);
    host.retire("n1-1");
    assert!(host.orders.contains_key("n1-1"));
    assert!(host.finished.is_empty());
    assert_eq!(states(&host), before);
    assert_eq!(
        host.forget_finished(Duration::from_secs(3600)),
        0,
        "ended just now: kept for the hour"
    );
}

/// Ends the order tasks the executor started (real ones) without telling the
/// machine, and gives order `name` a task that fails at once.
fn a_failing_task(tasks: &mut Tasks, name: &str) {
    tasks.names.clear();
    tasks.set.abort_all();
    tasks.set.detach_all();
    let handle = tasks
        .set
        .spawn(async { Err(OrderError::Other("the robot fell over".into())) });
    tasks.names.insert(handle.id(), name.to_string());
}

#[tokio::test(flavor = "multi_thread")]
async fn a_failing_order_is_restarted_within_its_intensity_then_fails_alone() {
    let mut host = host(None).await;
    let _failing = running(&mut host, 1);
    let _other = running(&mut host, 2);
    let mut tasks = Tasks::default();
    let now = tokio::time::Instant::now();
    for name in ["n1-1", "n1-2"] {
        let added = Event::Added {
            child: name.to_string(),
            restart: RestartType::Transient,
        };
        tasks.supervision.handle(added, now);
    }
    let cancel = CancellationToken::new();
    cancel.cancel();
    for _ in 0..=ORDER_RESTARTS.max_restarts {
        a_failing_task(&mut tasks, "n1-1");
        let joined = tasks.set.join_next_with_id().await.unwrap();
        task_ended(&mut host, joined, &mut tasks, &cancel).await;
    }
    let failed = host.progress("n1-1").unwrap().unwrap();
    assert!(failed.status.is_final(), "{failed:?}");
    assert!(
        failed
            .reason
            .as_deref()
            .is_some_and(|r| r.contains("more than 3 times")),
        "{failed:?}"
    );
    assert!(
        !host.progress("n1-2").unwrap().unwrap().status.is_final(),
        "the other order runs on"
    );
    assert_eq!(
        tasks.supervision.len(),
        1,
        "only the failed order is forgotten"
    );
}

#[tokio::test(flavor = "multi_thread")]
async fn a_journal_fault_is_a_pause_not_a_failure() {
    let mut host = host(None).await;
    let _progress = running(&mut host, 1);
    let mut tasks = Tasks::default();
    let added = Event::Added {
        child: "n1-1".to_string(),
        restart: RestartType::Transient,
    };
    tasks.supervision.handle(added, tokio::time::Instant::now());
    let cancel = CancellationToken::new();
    cancel.cancel();
    for _ in 0..=2 * ORDER_RESTARTS.max_restarts {
        tasks.names.clear();
        tasks.set.abort_all();
        tasks.set.detach_all();
        let handle = tasks
            .set
            .spawn(async { Err(OrderError::Journal("disk full".into())) });
        tasks.names.insert(handle.id(), "n1-1".to_string());
        let joined = tasks.set.join_next_with_id().await.unwrap();
        task_ended(&mut host, joined, &mut tasks, &cancel).await;
        assert_eq!(tasks.names.len(), 1, "resumed after a pause");
    }
    assert!(!host.progress("n1-1").unwrap().unwrap().status.is_final());
    assert_eq!(tasks.supervision.len(), 1);
}

//! A holon process's zenoh runs its work on one pool (`app`; one thread in a holon-node,
//! two in an order-node), not on its five runtimes' six threads; a `ZENOH_RUNTIME` the
//! user set is left alone, and one a holarchy parent set for itself is not inherited. Each
//! test is a process of its own (zenoh reads the variable once per process): this file
//! runs its one test in a child process per case.

use std::process::Command;
use std::time::Duration;

/// The names of this process's threads.
fn thread_names() -> Vec<String> {
    std::fs::read_dir("/proc/self/task")
        .expect("/proc/self/task")
        .flatten()
        .filter_map(|task| std::fs::read_to_string(task.path().join("comm")).ok())
        .map(|name| name.trim().to_string())
        .collect()
}

/// A peer session listening on `listen` and connecting to `connect`.
async fn peer(listen: Vec<String>, connect: Vec<String>) -> zenoh::Session {
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Peer,
        listen,
        connect,
        ..Default::default()
    };
    settings
        .open("zenoh-runtime-test", Duration::from_secs(10))
        .await
        .expect("a session opens")
}

/// Opens a session (as a holon does, after `configure`) and prints the zenoh threads.
#[test]
fn child_opens_a_session() {
    let Ok(case) = std::env::var("HOLON_ZENOH_RUNTIME_CASE") else {
        return; // only as the child of the test below
    };
    use holon::zenoh_runtime::Pool;
    match case.as_str() {
        "user" => std::env::set_var("ZENOH_RUNTIME", "(rx: (worker_threads: 3))"),
        // An order-node's child (a holon-node started by it): the parent's setting is
        // in the environment, marked as set by holarchy.
        "inherited" => holon::zenoh_runtime::configure(Pool::OrderNode),
        _ => {}
    }
    let pool = match case.as_str() {
        "order-node" => Pool::OrderNode,
        _ => Pool::Holon,
    };
    holon::zenoh_runtime::configure(pool);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        // Two sessions joined by a link, so that zenoh reads and writes one.
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let endpoint = format!("tcp/127.0.0.1:{port}");
        let session = peer(vec![endpoint.clone()], vec![]).await;
        let other = peer(vec![], vec![endpoint]).await;
        let echo = session.declare_queryable("t/echo").await.unwrap();
        let answering = tokio::spawn(async move {
            while let Ok(query) = echo.recv_async().await {
                query.reply("t/echo", "pong").await.unwrap();
            }
        });
        // A get before the queryable is known here returns at once with no reply.
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        loop {
            let replies = other.get("t/echo").await.unwrap();
            if let Ok(reply) = replies.recv_async().await {
                assert!(reply.result().is_ok());
                break;
            }
            assert!(tokio::time::Instant::now() < deadline, "no reply in 10 s");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        answering.abort();
        // A thread names itself once it runs: read the names once they stop changing.
        let zenoh_threads = || {
            let mut names: Vec<String> = thread_names()
                .into_iter()
                .filter(|n| {
                    ["app-", "rx-", "tx-", "acc-", "net-"]
                        .iter()
                        .any(|p| n.starts_with(p))
                })
                .collect();
            names.sort();
            names
        };
        let mut names = zenoh_threads();
        for _ in 0..20 {
            tokio::time::sleep(Duration::from_millis(100)).await;
            let now = zenoh_threads();
            if now == names {
                break;
            }
            names = now;
        }
        println!("ZENOH_RUNTIME={}", std::env::var("ZENOH_RUNTIME").unwrap());
        println!("threads={}", names.join(","));
        other.close().await.unwrap();
        session.close().await.unwrap();
    });
}

/// Runs [`child_opens_a_session`] in a child process for `case`; its output.
fn child(case: &str) -> String {
    let out = Command::new(std::env::current_exe().unwrap())
        .args([
            "--exact",
            "child_opens_a_session",
            "--nocapture",
            "--test-threads",
            "1",
        ])
        .env("HOLON_ZENOH_RUNTIME_CASE", case)
        .env_remove("ZENOH_RUNTIME")
        .env_remove(holon::zenoh_runtime::SET_BY_HOLARCHY_ENV)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).to_string();
    assert!(
        out.status.success(),
        "{case}: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    text
}

/// The zenoh threads a child printed.
fn threads(out: &str) -> Vec<&str> {
    out.lines()
        .find_map(|l| l.strip_prefix("threads="))
        .unwrap_or_else(|| panic!("{out}"))
        .split(',')
        .collect()
}

/// Runs `case` in a child, checks that it ran with `pool`'s setting, on zenoh's `app`
/// pool and one `tx` thread of its own (none of the other three runtimes), and returns
/// its `app` threads.
fn on_pool(case: &str, pool: holon::zenoh_runtime::Pool) -> Vec<String> {
    let out = child(case);
    let setting = format!("ZENOH_RUNTIME={}\n", pool.setting());
    assert!(out.contains(&setting), "{case}: {out}");
    let names: Vec<String> = threads(&out).into_iter().map(String::from).collect();
    assert!(
        names.iter().all(|t| t.starts_with("app-") || t == "tx-0"),
        "{case}: {out}"
    );
    // The link's writer never waits for the pool: a reply that finds the link's
    // queue full blocks its thread until the writer drained it.
    assert!(names.iter().any(|t| t == "tx-0"), "{case}: {out}");
    names
        .into_iter()
        .filter(|t| t.starts_with("app-"))
        .collect()
}

#[test]
fn zenoh_runs_on_one_pool_unless_the_user_says_otherwise() {
    use holon::zenoh_runtime::Pool;
    // A holon-node: one worker (a blocking task may add an app-N thread of the pool's
    // blocking threads).
    assert_eq!(
        on_pool("ours", Pool::Holon).first().map(String::as_str),
        Some("app-0")
    );
    // An order-node: two workers.
    assert!(on_pool("order-node", Pool::OrderNode).starts_with(&["app-0".into(), "app-1".into()]));
    // A holon-node started by a holarchy process that set its own: its own setting.
    on_pool("inherited", Pool::Holon);

    let user = child("user");
    assert!(
        user.contains("ZENOH_RUNTIME=(rx: (worker_threads: 3))"),
        "{user}"
    );
    assert!(user.contains("rx-0,rx-1,rx-2"), "{user}");
    assert!(user.contains("tx-0"), "{user}");
}

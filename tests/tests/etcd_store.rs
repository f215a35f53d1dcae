//! The order-node's store on etcd (issue 31, step 1), against a real cluster of three
//! etcd members on loopback: one holder at a time with growing epochs, a deposed
//! holder's writes refused by etcd and nothing of them stored, writes that commit with
//! a member dead or the raft leader dead, a dead holder replaced by its standby, and the
//! cost of a fenced write against a SQLite journal's.
//!
//! Skipped (SKIPPED printed) without `/usr/bin/etcd`, unless `HOLARCHY_REQUIRE_ETCD` is
//! set. The tests run one at a time (each starts its own cluster), so the figures they
//! print are not those of three clusters on two cores.

use std::time::{Duration, Instant};

use holarchy_tests::*;
use holon::etcd::{Candidate, ElectionConfig, EtcdError, FencedStore, Leader, TlsFiles};
use serde_json::{json, Value};

static ONE_AT_A_TIME: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

const PREFIX: &str = "holarchy/test/order-node/orders";

/// The fixture that holds a leader key in a process of its own.
const HOLDER: &str = env!("CARGO_BIN_EXE_etcd-holder");

/// The lease TTL of the elections here (the default).
const TTL: Duration = Duration::from_secs(2);

fn candidate(cluster: &EtcdCluster, name: &str) -> Candidate {
    Candidate::new(cluster.client(), ElectionConfig::new(PREFIX, name))
}

/// Campaigns until won, at most [`WAIT`].
async fn win(candidate: &Candidate) -> Leader {
    tokio::time::timeout(WAIT, candidate.campaign(std::future::pending()))
        .await
        .expect("won within WAIT")
        .expect("campaign")
        .expect("not cancelled")
}

/// A campaign in its own task.
fn campaign_in_background(candidate: Candidate) -> tokio::task::JoinHandle<Leader> {
    tokio::spawn(async move { win(&candidate).await })
}

async fn cluster() -> Option<EtcdCluster> {
    let etcd = etcd_binary()?;
    Some(
        EtcdCluster::start(&etcd, 3)
            .await
            .expect("a 3-member etcd cluster"),
    )
}

fn order(by: &str, n: u32) -> Value {
    json!({"by": by, "n": n, "steps": ["drill", "mill", "inspect"]})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_holder_at_a_time_and_epochs_grow() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(cluster) = cluster().await else {
        return;
    };
    let (a, b) = (candidate(&cluster, "host-a"), candidate(&cluster, "host-b"));
    let mut first = campaign_in_background(a.clone());
    let mut second = campaign_in_background(b.clone());
    // Exactly one wins; the other stands by.
    let (winner, mut standby, winner_name) = tokio::time::timeout(WAIT, async {
        tokio::select! {
            won = &mut first => (won.unwrap(), second, "host-a"),
            won = &mut second => (won.unwrap(), first, "host-b"),
        }
    })
    .await
    .expect("one candidate wins");
    let holder = a.holder().await.unwrap().expect("a holder");
    assert_eq!(holder.candidate, winner_name);
    assert_eq!(holder.epoch, winner.epoch());
    tokio::time::sleep(Duration::from_millis(1500)).await;
    assert!(
        !standby.is_finished(),
        "the second candidate won while the first held the key"
    );
    assert!(!winner.is_deposed(), "the holder keeps its key alive");
    // A campaign is cancelled while it waits.
    let third = candidate(&cluster, "host-c");
    let cancelled = tokio::time::timeout(
        WAIT,
        third.campaign(tokio::time::sleep(Duration::from_millis(300))),
    )
    .await
    .expect("a cancelled campaign returns")
    .unwrap();
    assert!(cancelled.is_none(), "a cancelled campaign wins nothing");
    // The holder resigns: the standby wins at once, at a greater epoch.
    let first_epoch = winner.epoch();
    let resigned_store = winner.store();
    let resigned = Instant::now();
    winner.resign().await.unwrap();
    let next = tokio::time::timeout(WAIT, &mut standby)
        .await
        .expect("the standby wins after a resignation")
        .unwrap();
    println!(
        "after a resignation the standby won in {:?}",
        resigned.elapsed()
    );
    let refused = resigned_store
        .put("order", "o1", &order("resigned", 1))
        .await
        .unwrap_err();
    assert!(refused.to_string().contains("resigned"), "{refused}");
    assert!(
        next.epoch() > first_epoch,
        "epoch {} after {first_epoch}",
        next.epoch()
    );
    // The first campaigns again and wins once the second is gone; greater again.
    let again = campaign_in_background(if winner_name == "host-a" { a } else { b });
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert!(!again.is_finished(), "won while the key was held");
    let second_epoch = next.epoch();
    drop(next);
    let third = tokio::time::timeout(WAIT, again).await.unwrap().unwrap();
    assert!(third.epoch() > second_epoch);
    println!("epochs: {first_epoch} < {second_epoch} < {}", third.epoch());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deposed_holders_writes_are_refused_and_change_nothing() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(cluster) = cluster().await else {
        return;
    };
    let a = win(&candidate(&cluster, "host-a")).await;
    let store_a = a.store();
    store_a.put("order", "o1", &order("a", 1)).await.unwrap();
    store_a
        .put_all([("order", "o2", &order("a", 2)), ("meta", "next", &json!(3))])
        .await
        .unwrap();
    // A store fenced on the epoch alone: it cannot know it is deposed, etcd must refuse.
    let blind = FencedStore::new(cluster.client(), PREFIX, a.epoch());
    // a's lease ends behind its back (as when it expires while a is frozen) and b wins.
    assert!(cluster.client().lease_revoke(a.lease()).await.unwrap());
    let b = win(&candidate(&cluster, "host-b")).await;
    assert!(b.epoch() > a.epoch());
    let store_b = b.store();
    store_b.put("order", "o1", &order("b", 10)).await.unwrap();

    for (what, refused) in [
        ("put", blind.put("order", "o1", &order("a", 99)).await),
        ("new record", blind.put("order", "o9", &order("a", 9)).await),
        ("delete", blind.delete("order", ["o2"]).await),
        (
            "batch",
            blind
                .put_all([("order", "o3", &order("a", 3)), ("meta", "next", &json!(4))])
                .await,
        ),
    ] {
        match refused {
            Err(EtcdError::Deposed { epoch, holder, .. }) => {
                assert_eq!(epoch, a.epoch());
                assert!(holder.contains("host-b"), "{what}: {holder}");
                assert!(holder.contains(&b.epoch().to_string()), "{what}: {holder}");
            }
            other => panic!("{what} of a deposed holder: {other:?}"),
        }
    }
    // Nothing of them is in the store.
    let orders: Vec<(String, Value)> = store_b.list("order").await.unwrap();
    assert_eq!(
        orders,
        vec![
            ("o1".to_string(), order("b", 10)),
            ("o2".to_string(), order("a", 2))
        ]
    );
    assert_eq!(store_b.get::<u32>("meta", "next").await.unwrap(), Some(3));

    // a hears it is deposed, and its own store then refuses without asking etcd.
    let why = tokio::time::timeout(WAIT, a.deposed()).await.unwrap();
    println!("a deposed: {why}");
    let refused = store_a
        .put("order", "o1", &order("a", 7))
        .await
        .unwrap_err();
    assert!(
        matches!(&refused, EtcdError::Deposed { holder, .. } if holder.contains("stepped down")),
        "{refused}"
    );
    assert!(!b.is_deposed());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_store_commits_with_one_member_dead() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(mut cluster) = cluster().await else {
        return;
    };
    // The member to kill is a follower, and first in the client's list: the client must
    // fail over to the next.
    let leader = cluster.raft_leader().await.unwrap();
    let dead = (leader + 1) % 3;
    let mut endpoints = cluster.endpoints();
    endpoints.rotate_left(dead);
    let client = holon::etcd::Client::new(holon::etcd::ClientConfig::new(endpoints)).unwrap();
    let holder = win(&Candidate::new(
        client.clone(),
        ElectionConfig::new(PREFIX, "host-a"),
    ))
    .await;
    let store = holder.store();
    for n in 0..10 {
        store
            .put("order", &format!("before-{n}"), &order("a", n))
            .await
            .unwrap();
    }
    cluster.kill(dead);
    let killed = Instant::now();
    // The first write may go out on the kept-open connection to the dead member before
    // the client has seen it close: sent and never answered, it is `Uncertain` (the
    // client cannot know whether the member took it before it died, and does not guess).
    // Its caller sends the same record again, as an order-node's requester would ask
    // again; that one, and every other write, must commit on the two members left.
    let mut uncertain = 0;
    for n in 0..20 {
        let (id, record) = (format!("after-{n}"), order("a", n));
        match store.put("order", &id, &record).await {
            Ok(()) => {}
            Err(EtcdError::Uncertain { .. }) if n == 0 => {
                uncertain += 1;
                store
                    .put("order", &id, &record)
                    .await
                    .unwrap_or_else(|e| panic!("write {n} sent again with 2 of 3 members: {e}"));
            }
            Err(e) => panic!("write {n} with 2 of 3 members: {e}"),
        }
    }
    println!(
        "20 fenced writes with member {dead} dead: {:?} ({uncertain} uncertain, sent again)",
        killed.elapsed()
    );
    store.delete("order", ["before-0"]).await.unwrap();
    let orders: Vec<(String, Value)> = store.list("order").await.unwrap();
    assert_eq!(orders.len(), 29);
    assert!(
        !holder.is_deposed(),
        "the holder keeps its lease with 2 of 3"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_holder_is_replaced_by_its_standby() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(cluster) = cluster().await else {
        return;
    };
    // The primary is a process of its own, which is killed.
    let mut primary = EtcdHolder::start(HOLDER, &cluster, PREFIX, "host-a").unwrap();
    let epoch = primary.epoch;
    FencedStore::new(cluster.client(), PREFIX, epoch)
        .put("order", "o1", &order("a", 1))
        .await
        .unwrap();
    let standby = campaign_in_background(candidate(&cluster, "host-b"));
    tokio::time::sleep(Duration::from_millis(700)).await;
    assert!(!standby.is_finished(), "won while the primary lived");
    // SIGKILL: its keep-alives stop, its lease is not revoked (the gateway's connections
    // carry no session): etcd expires it after the TTL.
    primary.process.kill();
    let died = Instant::now();
    let next = tokio::time::timeout(WAIT, standby).await.unwrap().unwrap();
    let failover = died.elapsed();
    println!("the standby took over {failover:?} after the holder was killed (lease TTL {TTL:?})");
    assert!(
        failover < TTL + Duration::from_secs(3),
        "took {failover:?} (TTL {TTL:?})"
    );
    assert!(next.epoch() > epoch);
    // The standby reads what the primary wrote, and writes on.
    let store = next.store();
    assert_eq!(
        store.get::<Value>("order", "o1").await.unwrap(),
        Some(order("a", 1))
    );
    store.put("order", "o1", &order("b", 2)).await.unwrap();
    let stale = FencedStore::new(cluster.client(), PREFIX, epoch);
    assert!(matches!(
        stale.put("order", "o1", &order("a", 3)).await,
        Err(EtcdError::Deposed { .. })
    ));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_store_works_after_the_raft_leader_dies() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(mut cluster) = cluster().await else {
        return;
    };
    let a = candidate(&cluster, "host-a");
    let mut holder = win(&a).await;
    let mut store = holder.store();
    let first_epoch = holder.epoch();
    store.put("order", "o0", &order("a", 0)).await.unwrap();
    let raft_leader = cluster.raft_leader().await.unwrap();
    cluster.kill(raft_leader);
    let killed = Instant::now();
    // Writes fail (no raft leader) or are uncertain until etcd has elected a new one;
    // then they commit.
    let mut failures = Vec::new();
    let n = 1;
    loop {
        assert!(
            killed.elapsed() < WAIT,
            "no write committed within {WAIT:?}: {failures:?}"
        );
        match store.put("order", &format!("o{n}"), &order("a", n)).await {
            Ok(()) => break,
            Err(EtcdError::Deposed { .. }) => {
                // The holder could not renew its lease during the raft election and
                // stepped down: it campaigns again, at a new epoch.
                println!("the holder stepped down before a write committed; campaigning again");
                holder = win(&a).await;
                store = holder.store();
            }
            Err(e) => {
                assert!(e.is_transient(), "{e}");
                failures.push(e.to_string());
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    }
    println!(
        "first write committed {:?} after the raft leader died ({} failed before: {failures:?})",
        killed.elapsed(),
        failures.len()
    );
    let new_leader = cluster.raft_leader().await.unwrap();
    assert_ne!(new_leader, raft_leader);
    // A holder whose keep-alives were held up by the raft election may still step down
    // (until its last confirmed one is a TTL old); after that, it holds or it campaigns
    // again, and every write commits.
    tokio::time::sleep(TTL).await;
    let stepped_down = holder.is_deposed() || holder.epoch() != first_epoch;
    if holder.is_deposed() {
        holder = win(&a).await;
        store = holder.store();
    }
    println!(
        "the holder {} (epoch {first_epoch}, now {})",
        if stepped_down {
            "stepped down during the raft election and won again"
        } else {
            "held on through the raft election"
        },
        holder.epoch()
    );
    for m in n + 1..n + 11 {
        store
            .put("order", &format!("o{m}"), &order("a", m))
            .await
            .unwrap();
    }
    let orders: Vec<(String, Value)> = store.list("order").await.unwrap();
    assert_eq!(orders.len(), 12, "{orders:?}");
    assert!(!holder.is_deposed());
}

/// The host that dies holds both the primary and etcd's raft leader: etcd elects a new
/// raft leader first, which extends every lease by its election timeout, and then the
/// primary's lease expires.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_holder_dead_with_the_raft_leader_is_replaced() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(mut cluster) = cluster().await else {
        return;
    };
    let mut primary = EtcdHolder::start(HOLDER, &cluster, PREFIX, "host-a").unwrap();
    let epoch = primary.epoch;
    let standby = campaign_in_background(candidate(&cluster, "host-b"));
    tokio::time::sleep(Duration::from_millis(700)).await;
    assert!(!standby.is_finished());
    let raft_leader = cluster.raft_leader().await.unwrap();
    cluster.kill(raft_leader);
    primary.process.kill();
    let died = Instant::now();
    let next = tokio::time::timeout(WAIT, standby).await.unwrap().unwrap();
    let failover = died.elapsed();
    println!(
        "the standby took over {failover:?} after the holder died with etcd's raft leader (lease TTL {TTL:?}, etcd election timeout 1 s)"
    );
    assert!(
        failover < TTL + Duration::from_secs(6),
        "took {failover:?} (TTL {TTL:?})"
    );
    assert!(next.epoch() > epoch);
    next.store()
        .put("order", "o1", &order("b", 1))
        .await
        .unwrap();
}

/// Milliseconds per write, sorted: (mean, median, 99th percentile).
fn figures(mut samples: Vec<Duration>) -> (f64, f64, f64) {
    samples.sort();
    let ms = |d: Duration| d.as_secs_f64() * 1000.0;
    let mean = samples.iter().map(|d| ms(*d)).sum::<f64>() / samples.len() as f64;
    let median = ms(samples[samples.len() / 2]);
    let p99 = ms(samples[(samples.len() * 99 / 100).min(samples.len() - 1)]);
    (mean, median, p99)
}

/// How long each of `writes` fenced writes of an order record took, one after another.
async fn timed_writes(store: &FencedStore, writes: u32) -> Vec<Duration> {
    let mut samples = Vec::new();
    for n in 0..writes {
        let started = Instant::now();
        store
            .put("order", &format!("o{n}"), &order("a", n))
            .await
            .unwrap();
        samples.push(started.elapsed());
    }
    samples
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fenced_write_costs_against_a_sqlite_put() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(cluster) = cluster().await else {
        return;
    };
    const WRITES: u32 = 200;
    let holder = win(&candidate(&cluster, "host-a")).await;
    let store = holder.store();
    let etcd = timed_writes(&store, WRITES).await;
    let dir = tempfile::tempdir().unwrap();
    let journal = holon::journal::Journal::open(
        dir.path(),
        "j.sqlite",
        holon::journal::Durability::default(),
    )
    .unwrap();
    let mut sqlite = Vec::new();
    for n in 0..WRITES {
        let started = Instant::now();
        journal
            .put("order", &format!("o{n}"), &order("a", n))
            .unwrap();
        sqlite.push(started.elapsed());
    }
    // Writers at the same time, as an order-node's orders write: etcd batches their
    // proposals; the journal shares commits (group commit).
    const WRITERS: u32 = 8;
    let started = Instant::now();
    let tasks: Vec<_> = (0..WRITERS)
        .map(|w| {
            let store = store.clone();
            tokio::spawn(async move {
                for n in 0..WRITES / WRITERS {
                    store
                        .put("order", &format!("w{w}-{n}"), &order("a", n))
                        .await
                        .unwrap();
                }
            })
        })
        .collect();
    for task in tasks {
        task.await.unwrap();
    }
    let etcd_concurrent = started.elapsed();
    let journal = std::sync::Arc::new(journal);
    let started = Instant::now();
    let threads: Vec<_> = (0..WRITERS)
        .map(|w| {
            let journal = journal.clone();
            std::thread::spawn(move || {
                for n in 0..WRITES / WRITERS {
                    journal
                        .put("order", &format!("w{w}-{n}"), &order("a", n))
                        .unwrap();
                }
            })
        })
        .collect();
    for thread in threads {
        thread.join().unwrap();
    }
    let sqlite_concurrent = started.elapsed();
    let (mean, median, p99) = figures(etcd);
    println!(
        "fenced etcd write (3 members on loopback, one writer): mean {mean:.2} ms, median {median:.2} ms, p99 {p99:.2} ms"
    );
    let (mean, median, p99) = figures(sqlite);
    println!(
        "SQLite journal put (power_loss, one writer): mean {mean:.2} ms, median {median:.2} ms, p99 {p99:.2} ms"
    );
    let per_second = |d: Duration| f64::from(WRITES) / d.as_secs_f64();
    println!(
        "{WRITERS} writers at once, {WRITES} records: etcd {etcd_concurrent:?} ({:.0}/s), SQLite {sqlite_concurrent:?} ({:.0}/s)",
        per_second(etcd_concurrent),
        per_second(sqlite_concurrent)
    );
    assert_eq!(
        store.list::<Value>("order").await.unwrap().len(),
        2 * WRITES as usize
    );
}

/// A cell's PKI as `cell certs` issues it, from a manifest with one etcd member's host
/// (`etcd.local`, for every member here: they all run on loopback) and the order-node
/// `order-node.orders1`.
fn cell_pki(dir: &std::path::Path) -> std::path::PathBuf {
    std::fs::write(
        dir.join("cell.toml"),
        "cell = \"t\"\n[pki]\netcd_hosts = [\"local\"]\n[[process]]\nname = \"orders1\"\n\
         program = \"order-node\"\nidentity = \"order-node.orders1\"\n",
    )
    .unwrap();
    let said =
        cell::security::certs::run(dir, &cell::security::certs::CertsOptions::default()).unwrap();
    assert!(
        said.iter().any(|l| l.starts_with("issued etcd.local")),
        "{said:?}"
    );
    dir.join("pki")
}

/// The files of `identity` in `pki`, trusting `ca`.
fn tls_files(ca: &std::path::Path, pki: &std::path::Path, identity: &str) -> TlsFiles {
    TlsFiles {
        ca: ca.join("ca.pem"),
        certificate: pki.join(format!("{identity}.pem")),
        key: pki.join(format!("{identity}.key")),
    }
}

/// A put of `key` over TLS by hand (rustls, HTTP/1 written out), trusting `ca` and
/// presenting `client`'s certificate if given: the reply's status line, or why none came.
fn raw_put(
    endpoint: &str,
    ca: &std::path::Path,
    client: Option<&TlsFiles>,
    key: &str,
) -> Result<String, String> {
    use base64::Engine;
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
    use std::io::{Read, Write};
    let authority = endpoint.trim_start_matches("https://");
    let mut roots = rustls::RootCertStore::empty();
    for cert in CertificateDer::pem_file_iter(ca).unwrap() {
        roots.add(cert.unwrap()).unwrap();
    }
    let provider = std::sync::Arc::new(rustls::crypto::ring::default_provider());
    let builder = rustls::ClientConfig::builder_with_provider(provider)
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots);
    let config = match client {
        Some(files) => builder
            .with_client_auth_cert(
                CertificateDer::pem_file_iter(&files.certificate)
                    .unwrap()
                    .map(Result::unwrap)
                    .collect(),
                PrivateKeyDer::from_pem_file(&files.key).unwrap(),
            )
            .unwrap(),
        None => builder.with_no_client_auth(),
    };
    let name = ServerName::try_from("127.0.0.1").unwrap();
    let mut connection = rustls::ClientConnection::new(std::sync::Arc::new(config), name).unwrap();
    let mut tcp = std::net::TcpStream::connect(authority).map_err(|e| e.to_string())?;
    tcp.set_read_timeout(Some(WAIT)).unwrap();
    tcp.set_write_timeout(Some(WAIT)).unwrap();
    let mut tls = rustls::Stream::new(&mut connection, &mut tcp);
    let b64 = |text: &str| base64::engine::general_purpose::STANDARD.encode(text);
    let body = json!({"key": b64(key), "value": b64("intruder")}).to_string();
    let request = format!(
        "POST /v3/kv/put HTTP/1.1\r\nHost: {authority}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    tls.write_all(request.as_bytes())
        .map_err(|e| e.to_string())?;
    let mut reply = Vec::new();
    tls.read_to_end(&mut reply).map_err(|e| e.to_string())?;
    let reply = String::from_utf8_lossy(&reply);
    Ok(reply.lines().next().unwrap_or("").to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_mutual_tls_only_the_cells_certificates_get_in() {
    let _serial = ONE_AT_A_TIME.lock().await;
    let Some(etcd) = etcd_binary() else {
        return;
    };
    let cell_dir = tempfile::tempdir().unwrap();
    let pki = cell_pki(cell_dir.path());
    // Another cell's PKI: the same identities, another CA.
    let other_dir = tempfile::tempdir().unwrap();
    let other = cell_pki(other_dir.path());
    let node = tls_files(&pki, &pki, "order-node.orders1");
    let members = MemberTls {
        certificate: pki.join("etcd.local.pem"),
        key: pki.join("etcd.local.key"),
        trusted_ca: pki.join("ca.pem"),
    };
    // Started and ready: every member answered the node's client over TLS.
    let cluster = EtcdCluster::start_tls(&etcd, 3, members, node.clone())
        .await
        .expect("a 3-member etcd cluster on TLS");
    assert!(cluster
        .endpoints()
        .iter()
        .all(|e| e.starts_with("https://")));
    let good = candidate(&cluster, "host-a");
    let leader_key = good.config().leader_key();

    // Refused: no client certificate; a certificate of another CA; a client that does
    // not trust the members' CA. Nothing they tried is in the store.
    let endpoint = &cluster.endpoints()[0];
    let status = raw_put(endpoint, &pki.join("ca.pem"), None, &leader_key);
    assert!(
        !status.as_ref().is_ok_and(|s| s.contains(" 200 ")),
        "a client without a certificate: {status:?}"
    );
    println!("no certificate: {status:?}");
    let strangers = [
        (
            "a certificate of another CA",
            tls_files(&pki, &other, "order-node.orders1"),
        ),
        (
            "a client trusting another CA",
            tls_files(&other, &pki, "order-node.orders1"),
        ),
    ];
    for (who, files) in strangers {
        let client = cluster.client_with(Some(files)).unwrap();
        let intruder = Candidate::new(client.clone(), ElectionConfig::new(PREFIX, "intruder"));
        let error = intruder.try_once().await.unwrap_err();
        println!("{who}: {error}");
        assert!(
            matches!(error, EtcdError::Unreachable { .. }),
            "{who}: {error}"
        );
        let blind = FencedStore::new(client, PREFIX, 1);
        let error = blind
            .put("order", "o1", &order("intruder", 1))
            .await
            .unwrap_err();
        assert!(
            matches!(
                error,
                EtcdError::Unreachable { .. } | EtcdError::Uncertain { .. }
            ),
            "{who}: {error}"
        );
        if who.contains("trusting") {
            assert!(
                error.to_string().contains("TLS handshake failed"),
                "{error}"
            );
        }
    }
    assert_eq!(good.holder().await.unwrap(), None, "nobody holds the key");

    // The node's client holds the key and writes, fenced; its write is read back.
    let holder = win(&good).await;
    let store = holder.store();
    store.put("order", "o1", &order("a", 1)).await.unwrap();
    assert_eq!(
        store.list::<Value>("order").await.unwrap(),
        vec![("o1".to_string(), order("a", 1))]
    );
    // The same put by hand goes in with the node's certificate: the refusal above was
    // the missing certificate's, not the request's.
    let status = raw_put(
        endpoint,
        &pki.join("ca.pem"),
        Some(&node),
        &format!("{PREFIX}/x"),
    );
    assert!(
        status.as_ref().is_ok_and(|s| s.contains(" 200 ")),
        "{status:?}"
    );
    let holder_now = good.holder().await.unwrap().expect("a holder");
    assert_eq!(
        (holder_now.candidate.as_str(), holder_now.epoch),
        ("host-a", holder.epoch())
    );

    // What a fenced write costs over TLS (connections are reused: no handshake each).
    const WRITES: u32 = 100;
    let (mean, median, p99) = figures(timed_writes(&store, WRITES).await);
    println!(
        "fenced write over mutual TLS, {WRITES} in a row: mean {mean:.2} ms, median \
         {median:.2} ms, p99 {p99:.2} ms"
    );
}

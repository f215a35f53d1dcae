//! The etcd section: a journal write fenced on a leader key's epoch, committed by a
//! cluster of three etcd members on loopback (the order-node's store with a standby,
//! docs/reliability.md), set beside the SQLite journal commit of the floors.

use std::time::Instant;

use anyhow::{Context, Result};
use holarchy_tests::{etcd_binary, EtcdCluster};
use holon::etcd::{Candidate, ElectionConfig};
use serde_json::json;

use crate::run::Run;
use crate::stats::Latency;

/// `run.samples` fenced writes of a booking-sized record, one at a time; skipped (with
/// a note) where there is no etcd.
pub async fn section(run: &mut Run) -> Result<()> {
    let Some(etcd) = etcd_binary() else {
        println!("etcd section skipped: no etcd (apt-get install etcd-server)");
        return Ok(());
    };
    let cluster = EtcdCluster::start(&etcd, 3).await?;
    let candidate = Candidate::new(
        cluster.client(),
        ElectionConfig::new("holarchy/bench/order-node/orders", "bench"),
    );
    let holder = tokio::time::timeout(
        holarchy_tests::WAIT,
        candidate.campaign(std::future::pending()),
    )
    .await
    .context("no leader key won in time")??
    .context("the campaign ended without a win")?;
    let store = holder.store();
    let mut times = Vec::with_capacity(run.samples);
    let started = Instant::now();
    for i in 0..run.samples {
        // About the size of the floors' booking record, different every time.
        let record = json!({
            "conversation_id": format!("bench/{i}/1"),
            "skill": "pick_n_place",
            "params": {"from": "tray-1", "to": "fixture-2", "part": format!("p{i}")},
            "order": "bench", "priority": 0, "deadline_ms": 60000,
        });
        let t = Instant::now();
        store
            .put("booking", &format!("b{}", i % 64), &record)
            .await?;
        times.push(t.elapsed());
    }
    let etcd = Latency::new(times, started.elapsed());
    let sqlite = &run.journal_floor.0;
    run.table.add(
        "journal write fenced on etcd (3 members, loopback)",
        etcd.p50_p99(),
        format!(
            "SQLite power_loss p50 {:.0} us, p99 {:.0} us",
            sqlite.pct(0.5),
            sqlite.pct(0.99)
        ),
        json!({"etcd": etcd.json(), "sqlite_power_loss": sqlite.json()}),
    );
    Ok(())
}

//! `bench all`: the floors, then every section `--only` picks, the table and its JSON.

use std::path::Path;

use anyhow::{bail, Context, Result};
use serde_json::{json, Value};

use crate::{
    booking, cycle, dashboard, erlang, etcd, floors::floors, holon, lease, moves, opcua, orders,
    rebook, robots, scale, throughput, tls,
};

/// The most resource holons the dashboard section runs (`--scale` beyond it still
/// applies to the scale section).
const DASHBOARD_HOLONS: usize = 100;

/// The sections `--only` can pick; the floors always run (every figure's baseline).
const SECTIONS: &[&str] = &[
    "booking",
    "tls",
    "cycle",
    "holon",
    "rebook",
    "lease",
    "throughput",
    "robots",
    "orders",
    "scale",
    "dashboard",
    "opcua",
    "etcd",
    "moves",
    "erlang",
];

/// `bench all`: the floors, then the sections `only` names (all when empty); the table's
/// JSON goes to `out`.
pub async fn run(
    out: &Path,
    samples: usize,
    scale: usize,
    only: &[String],
    erlang_peer: Option<&Path>,
    moves: &moves::Sizes,
) -> Result<()> {
    for section in only {
        if !SECTIONS.contains(&section.as_str()) {
            bail!(
                "unknown section {section:?} (one of {})",
                SECTIONS.join(", ")
            );
        }
    }
    let wants = |section: &str| only.is_empty() || only.iter().any(|s| s == section);
    let tempdir = tempfile::tempdir()?;
    // HOLARCHY_BENCH_KEEP=1 keeps the run's directory (configs, journals, every
    // process's log) for a look afterwards.
    let dir = if std::env::var_os("HOLARCHY_BENCH_KEEP").is_some() {
        let kept = tempdir.keep();
        println!("keeping the run's files in {}", kept.display());
        kept
    } else {
        tempdir.path().to_path_buf()
    };
    let mut run = floors(&dir, samples).await?;
    if wants("booking") {
        booking::section(&mut run).await?;
    }
    if wants("tls") {
        tls::section(&mut run).await?;
    }
    if wants("cycle") {
        cycle::section(&mut run).await?;
    }
    if wants("erlang") {
        erlang::section(&mut run, erlang_peer)?;
    }
    if wants("holon") {
        holon::section(&mut run).await?;
    }
    if wants("rebook") {
        rebook::section(&mut run).await?;
    }
    if wants("lease") {
        lease::section(&mut run).await?;
    }
    if wants("throughput") {
        throughput::section(&mut run).await?;
    }
    if wants("robots") {
        robots::section(&mut run).await?;
    }
    if wants("orders") {
        orders::section(&mut run, 1000).await?;
    }
    if wants("scale") && scale > 0 {
        scale::section(&mut run, scale).await?;
    }
    if wants("dashboard") && scale > 0 {
        // At most 100 holons: 1,000 orders whose proposal rounds each ask every holon
        // saturate 2 cores long before that (at 300, a submit got no answer in 5 s);
        // the page's figures are what this section measures, not the cell's.
        dashboard::section(&mut run, scale.min(DASHBOARD_HOLONS), 1000).await?;
    }
    if wants("opcua") {
        opcua::section(&mut run).await?;
    }
    if wants("etcd") {
        etcd::section(&mut run).await?;
    }
    if wants("moves") {
        moves::section(&mut run, moves).await?;
    }

    let machine = json!({
        "cores": std::thread::available_parallelism().map(|n| n.get()).unwrap_or(0),
        "profile": holarchy_tests::bin_dir().file_name().map(|n| n.to_string_lossy().into_owned()),
        "sections": if only.is_empty() { SECTIONS.to_vec() } else { only.iter().map(String::as_str).collect() },
    });
    let mut json = std::mem::take(&mut run.table.json);
    json.insert("machine".into(), machine);
    std::fs::write(out, serde_json::to_string_pretty(&Value::Object(json))?)
        .with_context(|| format!("cannot write {}", out.display()))?;
    println!("\nJSON written to {}", out.display());
    Ok(())
}

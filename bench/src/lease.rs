//! The lease section: a frozen process, which only the lease detects.

use anyhow::Result;
use holarchy_tests::resource_config;
use nix::sys::signal::{kill, Signal};
use nix::unistd::Pid;
use schemas::HolonId;
use serde_json::json;

use crate::cells::{detect_kill, router};
use crate::run::Run;

/// A frozen process: only the lease detects it.
pub async fn section(run: &mut Run) -> Result<()> {
    let lease_cell = router("bench-lease", Some(1000)).await?;
    let config = resource_config(&run.dir, "frozen", 5000)?;
    let mut frozen = holarchy_tests::start_node(
        &run.dir,
        &config,
        "bench-lease",
        &lease_cell.endpoint,
        &run.sim.address,
        &["--lease-ms", "1000"],
    )?;
    lease_cell.wait_alive(&HolonId::resource("frozen")?).await?;
    let stopped = detect_kill(
        &lease_cell,
        &mut frozen,
        &HolonId::resource("frozen")?,
        Signal::SIGSTOP,
    )
    .await?;
    let _ = kill(Pid::from_raw(frozen.pid()), Signal::SIGKILL);
    frozen.kill();
    run.table.add(
        "failure detection: SIGSTOP to token gone",
        format!("{:.0} ms", stopped.as_secs_f64() * 1e3),
        "lease 1000 ms".into(),
        json!({"ms": stopped.as_secs_f64() * 1e3, "lease_ms": 1000}),
    );
    Ok(())
}

//! The seed's resource holon in Erlang/OTP, side by side in the same run: the peer's
//! own `run.sh` (an order node and a resource node joined by Erlang distribution, and
//! a controller simulator over TCP), whose figures are set beside ours as ratios.
//!
//! The peer's code stays where it is (`--erlang-peer DIR`); without the option, or
//! without `erl` on the PATH (`apt-get install erlang-nox erlang-dev`), the section
//! says so in the table and measures nothing.

use std::path::Path;
use std::process::Command;

use anyhow::{anyhow, bail, Context, Result};
use serde_json::json;

use crate::run::Run;

/// One figure of the peer's: `erlang NAME p50=.. p99=.. mean=.. RATE=.. n=..`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeerFigure {
    pub p50_us: f64,
    pub p99_us: f64,
    /// Per second: booking+cancel pairs, or cycles.
    pub rate: f64,
}

/// What the peer's run printed.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerRun {
    pub booking: PeerFigure,
    pub cycle: PeerFigure,
    /// The resource node's `beam.smp`.
    pub resource_rss_kib: Option<u64>,
    pub startup_to_ready_ms: Option<f64>,
}

/// Reads the peer's output.
pub fn parse(output: &str) -> Result<PeerRun> {
    let figure = |name: &str| -> Result<PeerFigure> {
        let line = output
            .lines()
            .find(|l| l.starts_with(&format!("erlang {name} ")))
            .ok_or_else(|| anyhow!("the peer printed no {name}"))?;
        let field = |key: &str| -> Result<f64> {
            line.split_whitespace()
                .find_map(|f| f.strip_prefix(&format!("{key}=")))
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| anyhow!("no {key} in {line:?}"))
        };
        Ok(PeerFigure {
            p50_us: field("p50")?,
            p99_us: field("p99")?,
            rate: field("rate")?,
        })
    };
    let after = |prefix: &str| -> Option<&str> {
        output
            .lines()
            .find_map(|l| l.split_whitespace().find_map(|f| f.strip_prefix(prefix)))
    };
    Ok(PeerRun {
        booking: figure("booking_rtt_us")?,
        cycle: figure("cycle_us")?,
        resource_rss_kib: after("resource=").and_then(|v| v.parse().ok()),
        startup_to_ready_ms: after("startup_to_ready_ms=").and_then(|v| v.parse().ok()),
    })
}

/// Runs the peer (`DIR/run.sh`) with `bookings` booking pairs and `cycles` cycles.
fn run_peer(dir: &Path, bookings: usize, cycles: usize) -> Result<PeerRun> {
    let script = dir.join("run.sh");
    if !script.exists() {
        bail!("{} does not exist", script.display());
    }
    let output = Command::new("bash")
        .arg(&script)
        .env("NB", bookings.to_string())
        .env("NC", cycles.to_string())
        .env("NREC", "0")
        .output()
        .with_context(|| format!("cannot run {}", script.display()))?;
    let text = String::from_utf8_lossy(&output.stdout);
    if !output.status.success() {
        bail!(
            "{} failed ({}): {}{}",
            script.display(),
            output.status,
            text,
            String::from_utf8_lossy(&output.stderr)
        );
    }
    parse(&text)
}

/// Whether `erl` is on the PATH.
fn erl_installed() -> bool {
    Command::new("erl")
        .args(["-noshell", "-eval", "halt()."])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// The peer's booking and cycle beside ours (measured earlier in this run).
pub fn section(run: &mut Run, peer: Option<&Path>) -> Result<()> {
    let skip = |run: &mut Run, why: String| {
        println!("(the Erlang peer: {why})");
        run.table.add(
            "Erlang/OTP peer (the seed's resource holon)",
            "skipped".into(),
            why,
            json!(null),
        );
    };
    let Some(peer) = peer else {
        skip(run, "no --erlang-peer DIR given".into());
        return Ok(());
    };
    if !erl_installed() {
        skip(
            run,
            "erl is not installed (apt-get install erlang-nox erlang-dev)".into(),
        );
        return Ok(());
    }
    let erlang = run_peer(peer, run.samples, run.samples / 4)?;
    let versus = |ours: Option<(f64, f64)>, theirs: &PeerFigure| match ours {
        Some((p50, p99)) => format!(
            "ours {:.2}x at p50 ({p50:.0} us), {:.2}x at p99",
            p50 / theirs.p50_us,
            p99 / theirs.p99_us
        ),
        None => "ours not measured in this run".into(),
    };
    run.table.add(
        "Erlang/OTP peer: booking round trip",
        format!(
            "p50 {:.0} us, p99 {:.0} us, {:.0} book+cancel/s",
            erlang.booking.p50_us, erlang.booking.p99_us, erlang.booking.rate
        ),
        versus(run.ours.booking, &erlang.booking),
        json!({"p50_us": erlang.booking.p50_us, "p99_us": erlang.booking.p99_us, "rate_per_s": erlang.booking.rate}),
    );
    run.table.add(
        "Erlang/OTP peer: service cycle (book, start -> done)",
        format!(
            "p50 {:.0} us, p99 {:.0} us, {:.0} cycles/s",
            erlang.cycle.p50_us, erlang.cycle.p99_us, erlang.cycle.rate
        ),
        format!(
            "starting on its turn {}; with a separate start {}; ours also acknowledge done",
            versus(run.ours.cycle, &erlang.cycle),
            versus(run.ours.cycle_by_request, &erlang.cycle)
        ),
        json!({"p50_us": erlang.cycle.p50_us, "p99_us": erlang.cycle.p99_us, "rate_per_s": erlang.cycle.rate}),
    );
    run.table.add(
        "Erlang/OTP peer: resource node",
        format!(
            "{} resident (beam.smp)",
            erlang
                .resource_rss_kib
                .map_or("?".into(), |k| format!("{:.1} MiB", k as f64 / 1024.0))
        ),
        format!(
            "start to ready {}",
            erlang
                .startup_to_ready_ms
                .map_or("?".into(), |ms| format!("{ms:.0} ms"))
        ),
        json!({"rss_kib": erlang.resource_rss_kib, "startup_to_ready_ms": erlang.startup_to_ready_ms}),
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_the_peers_output() {
        let output = "erlang booking_rtt_us p50=33.1 p99=350.2 mean=40.0 rate=9000 n=5000 p90=50.0 max=900.0\n\
            erlang booking_cancel_rtt_us p50=30.0 p99=300.0 mean=35.0 all_round_trips_per_s=18000 n=5000 p90=40.0 max=800.0\n\
            erlang cycle_us p50=451.0 p99=3160.0 mean=500.0 rate=1734 n=2000 p90=600.0 max=5000.0\n\
            erlang rss_kb resource=38000 order=30000 robot_sim=25000\n\
            erlang startup_to_ready_ms=812.5\n";
        let run = parse(output).unwrap();
        assert_eq!(run.booking.p50_us, 33.1);
        assert_eq!(run.booking.rate, 9000.0);
        assert_eq!(run.cycle.p99_us, 3160.0);
        assert_eq!(run.resource_rss_kib, Some(38000));
        assert_eq!(run.startup_to_ready_ms, Some(812.5));
        assert!(parse("erlang cycle_us p50=1 p99=2 rate=3\n").is_err());
    }
}

//! Process sampling from /proc: memory (resident, proportional, anonymous), threads
//! and CPU time of a process.

use std::time::Duration;

use anyhow::{anyhow, Result};

/// Proportional memory (KiB) of a process: its private pages plus its share of the
/// pages it shares (the binary's code, mapped by every holon process), from /proc.
pub fn proportional(pid: i32) -> Result<u64> {
    let rollup = std::fs::read_to_string(format!("/proc/{pid}/smaps_rollup"))?;
    rollup
        .lines()
        .find(|l| l.starts_with("Pss:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| anyhow!("no Pss in /proc/{pid}/smaps_rollup"))
}

/// Resident memory (KiB) and threads of a process, from /proc.
pub fn footprint(pid: i32) -> Result<(u64, u64)> {
    Ok((status_field(pid, "VmRSS:")?, status_field(pid, "Threads:")?))
}

/// One number of /proc/PID/status (`VmRSS:`, `RssAnon:`, `Threads:`...).
pub fn status_field(pid: i32, name: &str) -> Result<u64> {
    std::fs::read_to_string(format!("/proc/{pid}/status"))?
        .lines()
        .find(|l| l.starts_with(name))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| anyhow!("no {name} in /proc/{pid}/status"))
}

/// The time a process's threads have been on a CPU, in ns (`/proc/PID/task/*/schedstat`).
/// Precise for short bursts, where [`cpu_time`] counts 10 ms ticks; threads that ended
/// are not counted, so it suits a process's first moments (its start), not a long run.
pub fn on_cpu(pid: i32) -> Result<Duration> {
    let mut total = Duration::ZERO;
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))? {
        let schedstat = std::fs::read_to_string(task?.path().join("schedstat"))?;
        let ns: u64 = schedstat
            .split_whitespace()
            .next()
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| anyhow!("unreadable schedstat of {pid}"))?;
        total += Duration::from_nanos(ns);
    }
    Ok(total)
}

/// CPU time (user + system) a process has used, from /proc: every thread it ever ran,
/// in 10 ms ticks (fine over a run of seconds; see [`on_cpu`] for a start).
pub fn cpu_time(pid: i32) -> Result<Duration> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat"))?;
    // Fields after the command name (which may hold spaces) start at ") ".
    let rest = stat
        .rsplit_once(") ")
        .map(|(_, r)| r)
        .ok_or_else(|| anyhow!("unreadable /proc/{pid}/stat"))?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: u64 = fields[11].parse::<u64>()? + fields[12].parse::<u64>()?;
    let per_second = nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)?.unwrap_or(100) as u64;
    Ok(Duration::from_secs_f64(ticks as f64 / per_second as f64))
}

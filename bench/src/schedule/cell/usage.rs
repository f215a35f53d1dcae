//! What each process of a cell run used: its CPU time and its resident memory (the
//! largest seen and the last), sampled from /proc while the run goes on.
//!
//! The processes are `cell up` itself (it runs the cell's router) and every process it
//! started, named as its manifest names them (from the "started NAME (pid N)" lines of
//! `cell up`'s output), and any station the bench hot-added. A process restarted
//! during the run counts under its name: its CPU times add up, its memory is the
//! largest of its lives.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use crate::process::{cpu_time, status_field};

/// How often the processes are sampled.
const EVERY: Duration = Duration::from_secs(2);

/// One process's use over a run.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize)]
pub struct ProcessUsage {
    /// Its name in the manifest (`cell up` for the supervisor and router).
    pub name: String,
    /// CPU time (user and system), every life of it added up, in s.
    pub cpu_s: f64,
    /// The largest resident memory seen, in KiB.
    pub peak_rss_kib: u64,
    /// Its resident memory at the last sample, in KiB.
    pub last_rss_kib: u64,
}

/// The processes to sample: pid to name, as they are known.
#[derive(Debug, Clone, Default)]
pub struct Watched {
    /// The pids named so far (a restarted process keeps its name under a new pid).
    named: BTreeMap<i32, String>,
}

impl Watched {
    /// Watches `pid` as `name`.
    pub fn add(&mut self, pid: u32, name: &str) {
        self.named.insert(pid as i32, name.to_string());
    }

    /// Adds the processes that `cell up` said it started in `log`.
    fn read_log(&mut self, log: &str) {
        for line in log.lines() {
            if let Some((name, pid)) = started(line) {
                self.named.insert(pid, name.to_string());
            }
        }
    }
}

/// A "started NAME (pid N)" line's name and pid.
fn started(line: &str) -> Option<(&str, i32)> {
    let rest = &line[line.find("started ")? + "started ".len()..];
    let (name, rest) = rest.split_once(" (pid ")?;
    let pid = rest.split(')').next()?.parse().ok()?;
    (pid > 0).then_some((name, pid))
}

/// Samples a run's processes on a thread of its own until stopped.
pub struct Sampler {
    /// What has been measured so far, per pid (name, cpu, peak, last).
    seen: Arc<Mutex<BTreeMap<i32, ProcessUsage>>>,
    /// Processes to add as the bench starts them.
    watched: Arc<Mutex<Watched>>,
    stop: Arc<std::sync::atomic::AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Sampler {
    /// Starts sampling `cell up` (pid `up`) and what its output `log` says it started.
    pub fn start(up: u32, log: PathBuf) -> Sampler {
        let mut watched = Watched::default();
        watched.add(up, "cell up");
        let watched = Arc::new(Mutex::new(watched));
        let seen = Arc::new(Mutex::new(BTreeMap::new()));
        let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let thread = {
            let (watched, seen, stop) = (watched.clone(), seen.clone(), stop.clone());
            std::thread::spawn(move || {
                while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                    sample(&log, &watched, &seen);
                    std::thread::sleep(EVERY);
                }
            })
        };
        Sampler {
            seen,
            watched,
            stop,
            thread: Some(thread),
        }
    }

    /// Watches a process the bench started itself (a hot-added station).
    pub fn add(&self, pid: u32, name: &str) {
        self.watched
            .lock()
            .expect("the sampler's watch list")
            .add(pid, name);
    }

    /// Takes a last sample (call it before the processes stop) and ends the sampling:
    /// each name's use, in the order first seen.
    pub fn finish(mut self, log: &Path) -> Vec<ProcessUsage> {
        sample(log, &self.watched, &self.seen);
        self.stop.store(true, std::sync::atomic::Ordering::Relaxed);
        if let Some(thread) = self.thread.take() {
            if thread.join().is_err() {
                eprintln!("the process sampler panicked: its figures may be short");
            }
        }
        let seen = self.seen.lock().expect("the sampler's figures");
        by_name(seen.iter().map(|(pid, usage)| (*pid, usage.clone())))
    }
}

/// One sample of every watched process still alive.
fn sample(log: &Path, watched: &Mutex<Watched>, seen: &Mutex<BTreeMap<i32, ProcessUsage>>) {
    let named = {
        let mut watched = watched.lock().expect("the sampler's watch list");
        if let Ok(text) = std::fs::read_to_string(log) {
            watched.read_log(&text);
        }
        watched.named.clone()
    };
    for (pid, name) in named {
        // A process that has exited keeps its last sample.
        let (Ok(cpu), Ok(rss)) = (cpu_time(pid), status_field(pid, "VmRSS:")) else {
            continue;
        };
        let mut seen = seen.lock().expect("the sampler's figures");
        let usage = seen.entry(pid).or_insert_with(|| ProcessUsage {
            name: name.clone(),
            ..ProcessUsage::default()
        });
        usage.cpu_s = cpu.as_secs_f64();
        usage.peak_rss_kib = usage.peak_rss_kib.max(rss);
        usage.last_rss_kib = rss;
    }
}

/// Each name's use over its pids (in pid order: a restart's life after the first's).
fn by_name(per_pid: impl Iterator<Item = (i32, ProcessUsage)>) -> Vec<ProcessUsage> {
    let mut names: Vec<ProcessUsage> = Vec::new();
    for (_, usage) in per_pid {
        match names.iter_mut().find(|u| u.name == usage.name) {
            Some(total) => {
                total.cpu_s += usage.cpu_s;
                total.peak_rss_kib = total.peak_rss_kib.max(usage.peak_rss_kib);
                total.last_rss_kib = usage.last_rss_kib;
            }
            None => names.push(usage),
        }
    }
    names
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_started_line_names_its_process() {
        assert_eq!(
            started("[   1.234s] started m1 (pid 4242)"),
            Some(("m1", 4242))
        );
        assert_eq!(
            started("started orders1 (pid 77) as the standby"),
            Some(("orders1", 77))
        );
        assert_eq!(started("started m1 (pid 0)"), None);
        assert_eq!(started("m1 exited (status 1)"), None);
    }

    #[test]
    fn a_restarted_process_adds_its_lives_up() {
        let usage = |name: &str, cpu_s, peak, last| ProcessUsage {
            name: name.into(),
            cpu_s,
            peak_rss_kib: peak,
            last_rss_kib: last,
        };
        let totals = by_name(
            [
                (10, usage("m1", 1.5, 9000, 8000)),
                (11, usage("plant", 4.0, 20000, 20000)),
                (30, usage("m1", 0.5, 7000, 7000)),
            ]
            .into_iter(),
        );
        assert_eq!(
            totals,
            vec![
                usage("m1", 2.0, 9000, 7000),
                usage("plant", 4.0, 20000, 20000)
            ]
        );
    }

    #[test]
    fn this_process_is_sampled() {
        let dir = tempfile::tempdir().unwrap();
        let log = dir.path().join("cell-up.log");
        std::fs::write(&log, "").unwrap();
        let sampler = Sampler::start(std::process::id(), log.clone());
        let usage = sampler.finish(&log);
        assert_eq!(usage.len(), 1);
        assert_eq!(usage[0].name, "cell up");
        assert!(usage[0].peak_rss_kib > 0);
    }
}

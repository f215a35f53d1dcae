//! What the chaos runs share (tests/tests/chaos.rs, tests/tests/material_chaos.rs): a
//! seeded source of randomness for choosing victims and moments, the holon processes
//! a driver kills and starts again.

use std::path::{Path, PathBuf};

use crate::{start_holon, Cell, Process};

/// xorshift64*: enough randomness for choosing victims and moments, replayable from
/// its seed.
pub struct Rng(u64);

impl Rng {
    /// Seeded from `HOLARCHY_CHAOS_SEED`, or from the clock (printed by the caller so
    /// that the run can be replayed).
    pub fn seeded() -> (Rng, u64) {
        let seed = std::env::var("HOLARCHY_CHAOS_SEED")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| schemas::unix_ms() | 1);
        (Rng(seed), seed)
    }

    pub fn draw(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// A number in `0..n`.
    pub fn below(&mut self, n: u64) -> u64 {
        self.draw() % n
    }
}

/// A holon process a driver kills, and how to start it again.
pub struct Victim {
    /// The holon's name (its config's, and its log files').
    pub name: String,
    /// Its binary (`holon-node`, `order-node`).
    pub program: &'static str,
    /// Its config file.
    pub config: PathBuf,
    /// Its arguments beyond the config.
    pub extra: Vec<String>,
    /// Its liveliness key: it serves again once this is seen.
    pub ready_key: String,
    /// The running incarnation.
    pub process: Process,
    /// How often it was killed.
    pub kills: usize,
}

impl Victim {
    /// Starts the holon's first incarnation in `dir`.
    pub fn start(
        dir: &Path,
        cell: &Cell,
        name: &str,
        program: &'static str,
        config: PathBuf,
        extra: Vec<String>,
        ready_key: String,
    ) -> Victim {
        let args: Vec<&str> = extra.iter().map(String::as_str).collect();
        let process = start_holon(dir, program, &config, name, cell, &args).unwrap();
        Victim {
            name: name.into(),
            program,
            config,
            extra,
            ready_key,
            process,
            kills: 0,
        }
    }

    /// Starts it again (after a kill), keeping the former incarnation's stderr as
    /// `<name>.stderr.<kills>`.
    pub fn restart(&mut self, dir: &Path, cell: &Cell) {
        let args: Vec<&str> = self.extra.iter().map(String::as_str).collect();
        let kept = dir.join(format!("{}.stderr.{}", self.name, self.kills));
        if let Err(e) = std::fs::rename(&self.process.stderr_path, kept) {
            eprintln!("{}'s stderr not kept: {e}", self.name);
        }
        self.process =
            start_holon(dir, self.program, &self.config, &self.name, cell, &args).unwrap();
    }
}

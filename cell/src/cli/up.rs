//! `cell up` and `cell upgrade`: the process supervisor of a cell host ([`cell::up`]),
//! and the upgrade of one of its processes while it runs.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, Result};

/// `cell up --check DIR`: prints the layout the manifest's configs state together;
/// true when it has no problem.
pub fn check(dir: &Path) -> Result<bool> {
    let cell = cell::up::manifest::Manifest::load(dir)?.cell;
    let (layout, sources) = cell::client::layout::from_manifest(dir)?;
    print!("{}", cell::client::layout::render(&cell, &layout, &sources));
    Ok(layout.problems.is_empty())
}

/// `cell up DIR`: supervises this host's processes until Ctrl-C or SIGTERM, the plant
/// at `time_scale` if given (else as the manifest says).
pub async fn run(dir: &Path, host: &str, time_scale: Option<schemas::TimeScale>) -> Result<bool> {
    let shutdown = holon::shutdown_on_signals();
    cell::up::run_scaled(dir, host, time_scale, shutdown).await
}

/// `cell upgrade`: which process, and its new build or config.
#[derive(Debug, clap::Args)]
pub struct UpgradeArgs {
    /// The process's name in the manifest (e.g. robot1, orders1, breaker).
    pub name: String,
    /// The manifest's directory, as given to `cell up`.
    #[arg(long, default_value = ".", value_name = "DIR")]
    pub dir: PathBuf,
    /// The host `cell up --host` runs (default local).
    #[arg(long, default_value = "local")]
    pub host: String,
    /// The new program (default: the one running).
    #[arg(long, value_name = "PATH")]
    pub binary: Option<PathBuf>,
    /// The new config file, replacing the value of the process's --config
    /// (relative paths are relative to DIR, as in the manifest).
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// How long the running process may take to finish its running step and hand
    /// over; it refuses, and runs on, if it cannot within this.
    #[arg(long, default_value_t = 60_000, value_name = "MS")]
    pub wait_ms: u64,
}

/// Asks the running `cell up` to upgrade the process, and prints how it went.
pub async fn upgrade(args: UpgradeArgs) -> Result<bool> {
    // A binary given relative to here means here; cell up runs elsewhere.
    let binary = args
        .binary
        .map(|b| {
            if b.components().count() > 1 {
                std::path::absolute(&b)
            } else {
                Ok(b)
            }
        })
        .transpose()?;
    let request = cell::up::upgrade::UpgradeRequest {
        name: args.name,
        binary,
        config: args.config,
        wait_ms: args.wait_ms,
    };
    let outcome = cell::up::upgrade::ask(&args.dir, &args.host, &request).await?;
    if !outcome.ok {
        return Err(anyhow!("{}", outcome.message));
    }
    println!("{}", outcome.message);
    Ok(true)
}

//! A test fixture: a successor for `cell upgrade --binary` that takes a resource holon
//! over and then never serves, as a new build that hangs after its predecessor let go
//! would. It takes `holon-node`'s command line (`--config`, `--cell`, `--connect`,
//! `--data-dir`, `--take-over-wait-ms`; others are ignored), passes `--check`, asks the
//! running holon to hand over, prints the answer, and then waits forever, ignoring
//! SIGTERM, so that its supervisor has to kill it.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, bail, Context, Result};
use schemas::{CellKeys, HolonId};

const HELP: &str = "never-serving-successor: a test fixture, not for a cell.

Stands in for holon-node as the successor in `cell upgrade NAME --binary PATH` (installed
as PATH/holon-node): it asks the running resource holon to hand over, and once released
never serves, and ignores SIGTERM. The upgrade tests use it to prove that the running
holon exits 1 and `cell up` kills the successor and starts the holon again.

Flags (those of holon-node it reads; others are ignored):
  --config FILE             the resource's config (its `name`)
  --cell NAME               the cell
  --connect ENDPOINT        the router (repeatable)
  --data-dir DIR            the journal's directory (the running holon checks it)
  --take-over-wait-ms MS    how long the running holon may finish its step (10000)
  --check                   exit 0 at once
  -h, --help                this text";

/// What it needs of `holon-node`'s command line.
#[derive(Default)]
struct Args {
    /// `--config`: the resource's config, for its name.
    config: Option<PathBuf>,
    /// `--cell`: the cell's name.
    cell: Option<String>,
    /// `--connect`: the router's endpoint.
    connect: Vec<String>,
    /// `--data-dir`: the journal's directory, which the predecessor checks.
    data_dir: Option<PathBuf>,
    /// `--take-over-wait-ms`: how long the predecessor may take to finish its step.
    wait_ms: u64,
    /// `--check`: only say the command line is fine.
    check: bool,
}

fn parse() -> Result<Args> {
    let mut args = Args {
        wait_ms: 10_000,
        ..Args::default()
    };
    let mut words = std::env::args().skip(1);
    while let Some(word) = words.next() {
        let mut value = || {
            words
                .next()
                .with_context(|| format!("{word} needs a value"))
        };
        match word.as_str() {
            "--config" => args.config = Some(value()?.into()),
            "--cell" => args.cell = Some(value()?),
            "--connect" => args.connect.push(value()?),
            "--data-dir" => args.data_dir = Some(value()?.into()),
            "--take-over-wait-ms" => args.wait_ms = value()?.parse()?,
            "--check" => args.check = true,
            "--help" | "-h" => {
                println!("{HELP}");
                std::process::exit(0);
            }
            // holon-node's other flags (`--controller ADDR`, `--take-over`) do not matter.
            "--controller" => {
                value()?;
            }
            _ => {}
        }
    }
    Ok(args)
}

/// The resource's `name = "..."` from its config.
fn holon_name(config: &std::path::Path) -> Result<String> {
    let text =
        std::fs::read_to_string(config).with_context(|| format!("read {}", config.display()))?;
    text.lines()
        .find_map(|line| {
            let value = line.trim().strip_prefix("name")?.trim().strip_prefix('=')?;
            Some(value.trim().trim_matches('"').to_string())
        })
        .ok_or_else(|| anyhow!("{} has no name", config.display()))
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> Result<()> {
    let args = parse()?;
    if args.check {
        return Ok(());
    }
    let (Some(config), Some(cell)) = (&args.config, &args.cell) else {
        bail!("--config and --cell are required");
    };
    let name = holon_name(config)?;
    let settings = holon::ZenohSettings {
        mode: holon::Mode::Client,
        connect: args.connect.clone(),
        ..holon::ZenohSettings::default()
    };
    let session = settings
        .open(&name, Duration::from_secs(20))
        .await
        .map_err(|e| anyhow!("open zenoh: {e}"))?;
    let holon = HolonId::resource(&name)?;
    let keys = CellKeys::new(cell)?;
    let data_dir = match &args.data_dir {
        Some(dir) => Some(std::fs::canonicalize(dir).context("the data dir")?),
        None => None,
    };
    let request = holon::takeover::Request {
        successor: holon::presence::Holder::this_process(&session),
        version: "0.0.0-never-serves".into(),
        data_dir,
        wait_ms: args.wait_ms,
    };
    let taken = holon::takeover::take_over(
        &session,
        &keys.alive(&holon),
        &format!("resource/{name}"),
        &request,
    )
    .await?;
    eprintln!("never-serving successor of {name}: {taken:?}; now it hangs");
    let mut terminate = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())?;
    loop {
        terminate.recv().await;
        eprintln!("never-serving successor of {name}: SIGTERM ignored");
    }
}

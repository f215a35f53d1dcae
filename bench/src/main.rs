//! `bench`: how fast a holarchy books, executes, reconfigures and recovers, against the
//! middleware floor measured in the same run. Every figure comes from real processes on
//! loopback (robot-sim, holon-node, order-node, and two echo helpers of this binary).
//!
//!     cargo run --release -p bench -- all            # the whole table, JSON in bench-results.json
//!
//! Topology, as in a cell: this process runs the zenoh router; every holon is a client
//! of it (the echo helper a peer). The floors use the same path as the holons: one link
//! from this process's router session; `scale` measures the path across the router.

mod all;
mod booking;
mod cells;
mod codec_client;
mod controller;
mod controller_faults;
mod cycle;
mod dashboard;
mod echo;
mod erlang;
mod etcd;
mod floors;
mod holon;
mod lease;
mod moves;
mod opcua;
mod orders;
mod process;
mod rebook;
mod robots;
mod run;
mod scale;
mod schedule;
mod soak;
mod stats;
mod throughput;
mod tls;
mod upgrade;

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};

#[derive(Debug, Parser)]
#[command(
    name = "bench",
    version,
    about = "holarchy's benchmarks (see docs/benchmarks.md)"
)]
struct Args {
    #[command(subcommand)]
    command: Commands,
}

#[derive(Debug, Subcommand)]
enum Commands {
    /// Run every benchmark, print the table and write it as JSON.
    All {
        /// Where the JSON goes.
        #[arg(long, default_value = "bench-results.json")]
        out: PathBuf,
        /// Round trips per latency figure.
        #[arg(long, default_value_t = 2000)]
        samples: usize,
        /// Resource holon processes for the scale and dashboard figures (0 skips them;
        /// the dashboard section runs at most 100).
        #[arg(long, default_value_t = 100)]
        scale: usize,
        /// Run only these sections (comma-separated; the floors always run): booking,
        /// tls, cycle, erlang, holon, rebook, lease, throughput, robots, orders, scale,
        /// dashboard, opcua, etcd, moves.
        #[arg(long, value_delimiter = ',')]
        only: Vec<String>,
        #[command(flatten)]
        moves: MovesArgs,
        /// The seed's resource holon in Erlang/OTP (a directory with its run.sh): run it
        /// in the same sitting and set our booking and cycle beside it (needs `erl`;
        /// skipped with a note otherwise).
        #[arg(long, value_name = "DIR")]
        erlang_peer: Option<PathBuf>,
    },
    /// What material flow costs (docs/benchmarks.md, "Material flow's costs"): the
    /// floors, today's booking and cycle rows, then the moves section (a transport
    /// booking, an order's cycle with moves against without, many parts in flight),
    /// all in one sitting. The same as `all --only booking,cycle,moves`.
    Moves {
        /// Where the JSON goes.
        #[arg(long, default_value = "moves-results.json")]
        out: PathBuf,
        /// Round trips per latency figure (the order cycles are a fiftieth of it, at
        /// least 10 of each).
        #[arg(long, default_value_t = 2000)]
        samples: usize,
        #[command(flatten)]
        moves: MovesArgs,
    },
    /// The scheduling benchmark: each scenario's order stream run by contract net alone
    /// and with a staff holon, for several seeds (docs/scheduling.md).
    Schedule {
        /// Scenario files (default: every deploy/scenarios/*.toml).
        #[arg(long = "scenario", value_name = "FILE")]
        scenarios: Vec<PathBuf>,
        /// Seeds per scenario; each seed's orders run in both modes.
        #[arg(long, default_value_t = 3)]
        seeds: u64,
        /// Where the JSON goes.
        #[arg(long, default_value = "schedule-results.json")]
        out: PathBuf,
        /// A cell scenario's time scale (1 to 1000), overriding the scenario's
        /// `time_scale`: plant time runs FACTOR times as fast as the wall clock.
        #[arg(long, value_name = "FACTOR")]
        time_scale: Option<u32>,
        /// Run a cell scenario in this mode only: contract-net or staff (default both).
        #[arg(long, value_name = "MODE")]
        mode: Option<String>,
        /// Where a cell scenario's Gantt charts go (one SVG per run).
        #[arg(long, value_name = "DIR", default_value = "schedule-charts")]
        charts: PathBuf,
    },
    /// The upgrade benchmark: robot1, the order-node and the product replaced while
    /// orders run, by a planned hand-over (--take-over) and, as the baseline, by SIGTERM
    /// and a new start; how long each is away and robot1 starts no job
    /// (docs/benchmarks.md, "Upgrades").
    Upgrade {
        /// Rounds per way.
        #[arg(long, default_value_t = 5)]
        rounds: usize,
        /// Where the JSON goes.
        #[arg(long, default_value = "upgrade-results.json")]
        out: PathBuf,
    },
    /// The soak: two robots, a product and an order-node with a journal on disk, waves
    /// of orders and an operator listing them every half second, for a long time; every
    /// process's memory sampled every 10 s (docs/reliability.md, "Memory while
    /// running").
    Soak {
        /// How long waves are submitted.
        #[arg(long, default_value_t = 30)]
        minutes: u64,
        /// Orders per wave.
        #[arg(long, default_value_t = 40)]
        wave: u32,
        /// Seconds between waves.
        #[arg(long, default_value_t = 5)]
        every_s: u64,
        /// Minutes after which memory is expected flat (its growth is fitted after).
        #[arg(long, default_value_t = 3)]
        settle: u64,
        /// Where the summary goes (JSON; the samples beside it as CSV).
        #[arg(long, default_value = "soak-results.json")]
        out: PathBuf,
    },
    /// The controller fault campaign (issue 41): a cell's resource on a dialect kept
    /// busy with orders while robot-sim plays its faults in rotation, one kind per
    /// phase, restarted every --restart-s; checks that nothing is written to a stopped
    /// controller, that reconnects keep the backoff, that every failed step's reason
    /// carries the controller's words, and that every order ends. Exits non-zero on any
    /// miss (docs/dialects.md, section 7.8; docs/benchmarks.md).
    ControllerFaults {
        /// How long the phases run in all (then a clean robot-sim until no order runs).
        #[arg(long, default_value_t = 60.0)]
        minutes: f64,
        /// Seconds per phase (one kind of fault each, in rotation).
        #[arg(long, default_value_t = 300)]
        phase_s: u64,
        /// robot-sim is stopped and started again this often within a phase.
        #[arg(long, default_value_t = 60)]
        restart_s: u64,
        /// Orders kept running.
        #[arg(long, default_value_t = 3)]
        in_flight: u64,
        /// The dialect of the controller (a file, or a shipped name).
        #[arg(long, default_value = "deploy/dialects/examples/job-ack-end.toml")]
        dialect: String,
        /// Where the summary goes (JSON; a row per phase beside it as CSV).
        #[arg(long, default_value = "controller-faults.json")]
        out: PathBuf,
    },
    /// (helper) A TCP echo server: prints `listening on ADDR`.
    EchoTcp {
        #[arg(long, default_value = "127.0.0.1:0")]
        listen: String,
    },
    /// (helper) A zenoh peer with a queryable that answers every query with its payload.
    EchoZenoh {
        #[arg(long)]
        connect: String,
        #[arg(long)]
        key: String,
    },
}

/// How the moves section is sized.
#[derive(Debug, clap::Args)]
struct MovesArgs {
    /// Moves section: transporters (one transfer per station) of the parts-in-flight
    /// figure.
    #[arg(long, default_value_t = 20)]
    transporters: usize,
    /// Moves section: parts (one-step orders whose parts move) submitted at once, per
    /// wave.
    #[arg(long, default_value_t = 200)]
    in_flight: u32,
    /// Moves section: waves of them, one after the other (memory is read after each).
    #[arg(long, default_value_t = 3)]
    waves: usize,
}

impl MovesArgs {
    fn sizes(&self) -> moves::Sizes {
        moves::Sizes {
            transporters: self.transporters.max(1),
            in_flight: self.in_flight.max(1),
            waves: self.waves.max(1),
        }
    }
}

fn main() -> Result<()> {
    let args = Args::parse();
    // Zenoh's runtimes as the holons set them (before any thread), so that the floors,
    // the bench's own order and the holons it measures run zenoh alike: the echo helper
    // answers as a holon-node does, the bench asks as an order-node does.
    ::holon::zenoh_runtime::configure(match args.command {
        Commands::EchoZenoh { .. } => ::holon::zenoh_runtime::Pool::Holon,
        _ => ::holon::zenoh_runtime::Pool::OrderNode,
    });
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(run(args))
}

async fn run(args: Args) -> Result<()> {
    match args.command {
        Commands::All {
            out,
            samples,
            scale,
            only,
            moves,
            erlang_peer,
        } => {
            all::run(
                &out,
                samples,
                scale,
                &only,
                erlang_peer.as_deref(),
                &moves.sizes(),
            )
            .await
        }
        Commands::Moves {
            out,
            samples,
            moves,
        } => {
            let only = ["booking", "cycle", "moves"].map(String::from);
            all::run(&out, samples, 0, &only, None, &moves.sizes()).await
        }
        Commands::Schedule {
            scenarios,
            seeds,
            out,
            time_scale,
            mode,
            charts,
        } => {
            let modes = match mode.as_deref() {
                None => vec![schedule::CellMode::ContractNet, schedule::CellMode::Staff],
                Some("contract-net") => vec![schedule::CellMode::ContractNet],
                Some("staff") => vec![schedule::CellMode::Staff],
                Some(other) => bail!("--mode {other}: contract-net or staff"),
            };
            if time_scale.is_some_and(|f| !(1..=1000).contains(&f)) {
                bail!("--time-scale: from 1 to 1000");
            }
            let cells = schedule::CellOptions {
                time_scale,
                modes,
                charts,
            };
            let scenarios = if scenarios.is_empty() {
                let dir = holarchy_tests::workspace_root().join("deploy/scenarios");
                let mut found: Vec<PathBuf> = std::fs::read_dir(&dir)
                    .with_context(|| format!("cannot list {}", dir.display()))?
                    .flatten()
                    .map(|e| e.path())
                    .filter(|p| p.extension().is_some_and(|e| e == "toml"))
                    .collect();
                found.sort();
                found
            } else {
                scenarios
            };
            schedule::run(&scenarios, seeds, &out, &cells).await
        }
        Commands::Upgrade { rounds, out } => upgrade::run(rounds, &out).await,
        Commands::Soak {
            minutes,
            wave,
            every_s,
            settle,
            out,
        } => {
            let soak = soak::Soak {
                minutes,
                wave,
                every_s,
                settle,
            };
            soak::run(&soak, &out).await
        }
        Commands::ControllerFaults {
            minutes,
            phase_s,
            restart_s,
            in_flight,
            dialect,
            out,
        } => {
            let campaign = controller_faults::Campaign {
                minutes,
                phase_s: phase_s.max(1),
                restart_s: restart_s.max(1),
                in_flight: in_flight.max(1),
                dialect,
            };
            controller_faults::run(&campaign, &out).await
        }
        Commands::EchoTcp { listen } => echo::echo_tcp(&listen).await,
        Commands::EchoZenoh { connect, key } => echo::echo_zenoh(&connect, &key).await,
    }
}

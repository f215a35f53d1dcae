//! `robot-sim`: a robot controller simulator speaking holarchy's TCP/XML protocol.

use std::io::Write;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use robot_bridge::sim::{SimConfig, Simulator};
use tokio_util::sync::CancellationToken;

/// A robot controller simulator: the TCP server a resource holon's bridge connects to.
///
/// Prints `listening on ADDR` on stdout once it accepts connections, and
/// `executed N commands` when it stops (SIGTERM or Ctrl-C). Command numbers in the
/// fault flags count every command received by the process, from 1.
#[derive(Debug, Parser)]
#[command(name = "robot-sim", version)]
struct Args {
    /// Address to listen on; port 0 picks a free port (printed on the first line).
    #[arg(long, default_value = "127.0.0.1:7600")]
    listen: String,
    /// How long each action takes, in milliseconds (unless --action-ms names it).
    #[arg(long, default_value_t = 0)]
    delay_ms: u64,
    /// How long one action takes, in milliseconds, e.g. `pick=300` (repeatable): a
    /// robot fast at some work and slow at other.
    #[arg(long, value_name = "ACTION=MS", value_parser = parse_action_ms)]
    action_ms: Vec<(String, u64)>,
    /// What a change of program costs, in milliseconds: added to the first command
    /// whose PROGRAM (the job's product variant) differs from the last program run.
    #[arg(long, default_value_t = 0)]
    changeover_ms: u64,
    /// Answer every Nth command with an `error` result (not executed).
    #[arg(long, value_name = "N")]
    error_every: Option<u64>,
    /// Close each connection when its (N+1)th command arrives (not executed).
    #[arg(long, value_name = "N")]
    close_after: Option<u64>,
    /// Stop replying after N commands (later commands are neither answered nor executed).
    #[arg(long, value_name = "N")]
    hang_after: Option<u64>,
    /// Answer the (N+1)th command with malformed XML (once; not executed).
    #[arg(long, value_name = "N")]
    garbage_after: Option<u64>,
    /// Answer every Nth `inspect` with `inspect_fail` instead of `inspect_pass`.
    #[arg(long, value_name = "N")]
    inspect_fail_every: Option<u64>,
    /// When the (N+1)th command arrives, report a fault instead of executing it.
    #[arg(long, value_name = "N")]
    fault_after: Option<u64>,
    /// The state reported by --fault-after: fault or estop.
    #[arg(long, default_value = "fault", value_name = "fault|estop")]
    fault_state: schemas::ControllerState,
    /// How long the fault lasts before the controller reports ready again, in ms.
    #[arg(long, default_value_t = 2000)]
    fault_for_ms: u64,
    /// Keep the command counts in this JSON file, rewritten after every command:
    /// {"executed":N,"received":N,"connections":N,"by_action":{"pick":N,...}}.
    #[arg(long, value_name = "PATH")]
    count_file: Option<PathBuf>,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    use std::io::IsTerminal;
    // Lines are written by a thread of their own, off the command path; none is dropped,
    // and the rest are written out when `_logs` drops at the end of `main`.
    let (stderr, _logs) = tracing_appender::non_blocking::NonBlockingBuilder::default()
        .lossy(false)
        // The queue is allocated whole: the default (128,000 lines) is 4 MiB.
        .buffered_lines_limit(1024)
        .finish(std::io::stderr());
    tracing_subscriber::fmt()
        .with_writer(stderr)
        // Colour codes only on a terminal, never in a redirected log file.
        .with_ansi(std::io::stderr().is_terminal())
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .init();
    let config = SimConfig {
        delay: Duration::from_millis(args.delay_ms),
        action_delays: args
            .action_ms
            .iter()
            .map(|(action, ms)| (action.clone(), Duration::from_millis(*ms)))
            .collect(),
        changeover: Duration::from_millis(args.changeover_ms),
        error_every: args.error_every,
        close_after: args.close_after,
        hang_after: args.hang_after,
        garbage_after: args.garbage_after,
        inspect_fail_every: args.inspect_fail_every,
        fault_after: args.fault_after,
        fault_state: Some(args.fault_state),
        fault_for: Duration::from_millis(args.fault_for_ms),
        count_file: args.count_file,
    };
    let simulator = Simulator::bind(&args.listen, config)
        .await
        .with_context(|| format!("cannot listen on {}", args.listen))?;
    let address = simulator.local_addr()?;
    let stats = simulator.stats();
    println!("listening on {address}");
    let shutdown = CancellationToken::new();
    tokio::spawn({
        let shutdown = shutdown.clone();
        async move {
            let mut term =
                tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
                    .expect("SIGTERM handler");
            tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            }
            shutdown.cancel();
        }
    });
    simulator.run(shutdown).await;
    // The reader of our stdout may be gone (a launcher that only read the first line).
    let _ = writeln!(std::io::stdout(), "executed {} commands", stats.executed());
    Ok(())
}

/// `--action-ms`: `ACTION=MS`.
fn parse_action_ms(text: &str) -> Result<(String, u64), String> {
    let (action, ms) = text
        .split_once('=')
        .ok_or_else(|| format!("{text:?} is not ACTION=MS"))?;
    if action.is_empty() {
        return Err(format!("{text:?} names no action"));
    }
    let ms = ms
        .parse()
        .map_err(|_| format!("{text:?}: MS must be a whole number of milliseconds"))?;
    Ok((action.to_string(), ms))
}

//! `robot-sim`: a robot controller simulator speaking any controller dialect.

use std::io::Write;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use robot_bridge::dialect::{Dialect, Role};
use robot_bridge::sim::{SimConfig, Simulator};

/// A robot controller simulator: the TCP server a resource holon's bridge connects to
/// (or, for a dialect whose controller connects, the client that dials the holon).
///
/// Prints `listening on ADDR` (or `dialling ADDR`) on stdout once it serves, and
/// `executed N commands` when it stops (SIGTERM or Ctrl-C; with `, aborted M` when the
/// dialect's abort stopped M actions). Command numbers in the
/// fault flags count every action begun by the process, from 1.
#[derive(Debug, Parser)]
#[command(name = "robot-sim", version)]
struct Args {
    /// Address to listen on; port 0 picks a free port (printed on the first line).
    #[arg(long, default_value = "127.0.0.1:7600")]
    listen: String,
    /// The controller protocol spoken: a shipped dialect (holarchy-xml, kuka-eki,
    /// ur-dashboard, simple-message) or a dialect file (a path with a `/` or ending in
    /// .toml). Default holarchy-xml.
    #[arg(long, value_name = "NAME|FILE", default_value = "holarchy-xml")]
    dialect: String,
    /// Check the dialect (that it is valid and that robot-sim can speak it), print
    /// `dialect NAME is valid`, and exit: 0 if it is, 2 with the field and the problem
    /// if not. What is valid but likely a mistake (no `abort`) is said on stderr as
    /// `robot-sim: warning: ...`, and the exit is still 0.
    #[arg(long)]
    check: bool,
    /// Dial the holon at this address instead of listening (for a dialect whose
    /// controller connects; required by such a dialect).
    #[arg(long, value_name = "ADDR")]
    connect: Option<String>,
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
    /// Answer the (N+1)th command with bytes the dialect does not describe (once; not
    /// executed).
    #[arg(long, value_name = "N")]
    garbage_after: Option<u64>,
    /// Answer the (N+1)th command with a message over the dialect's size limit (once;
    /// not executed).
    #[arg(long, value_name = "N")]
    oversize_after: Option<u64>,
    /// Answer the (N+1)th command's messages with another id than its own (its id with a
    /// 9 after it: ACK 239 for JOB 23), where the dialect's replies echo one (once;
    /// executed).
    #[arg(long, value_name = "N")]
    wrong_id_after: Option<u64>,
    /// Begin the (N+1)th command and reset the connection (RST) halfway through it
    /// (not executed).
    #[arg(long, value_name = "N")]
    reset_after: Option<u64>,
    /// Write every message in pieces of 1 to 3 bytes.
    #[arg(long)]
    fragment: bool,
    /// Write messages together: an acknowledgement with the result that follows it,
    /// and (a dialect that pushes its state) a status with every reply.
    #[arg(long)]
    merge: bool,
    /// Answer every Nth `inspect` with `inspect_fail` instead of `inspect_pass`.
    #[arg(long, value_name = "N")]
    inspect_fail_every: Option<u64>,
    /// When the (N+1)th command arrives, report a fault instead of executing it: the
    /// controller is stopped for --fault-for-ms (pushed: it says so at once; polled: its
    /// status polls are answered with the status reply that says the fault), and refuses
    /// every command of the sequence meanwhile (answered with its failed reply, counted
    /// in the count file's refused_while_stopped).
    #[arg(long, value_name = "N")]
    fault_after: Option<u64>,
    /// Every Nth command faults the controller as --fault-after does (fault, ready
    /// again after --fault-for-ms, fault again at the next Nth): a rehearsal that goes on.
    #[arg(long, value_name = "N")]
    fault_every: Option<u64>,
    /// Every Nth command takes the controller into a state the dialect does not
    /// describe, for --fault-for-ms: the command is not executed (as --fault-every),
    /// and its state is said in the status reply that says ready with HOMING for the
    /// state's word (`STATE IDLE` -> `STATE HOMING`; a holon reads it as a protocol
    /// error); commands of the sequence meanwhile are refused and counted in
    /// refused_while_stopped. Refused at start for a dialect whose status cannot be
    /// said so (a binary one).
    #[arg(long, value_name = "N")]
    unknown_state_every: Option<u64>,
    /// The state reported by --fault-after and --fault-every: fault or estop.
    #[arg(long, default_value = "fault", value_name = "fault|estop")]
    fault_state: schemas::ControllerState,
    /// How long the fault lasts before the controller reports ready again, in ms.
    #[arg(long, default_value_t = 2000)]
    fault_for_ms: u64,
    /// Keep the command counts in this JSON file, rewritten after each command (the
    /// commands of 2 ms share one write; read it once it stays the same for a moment):
    /// {"executed":N,"received":N,"aborted":N,"refused_while_stopped":N,"connections":N,
    /// "changeovers":N,"by_action":{"pick":N,...}} (aborted: actions the dialect's abort
    /// stopped; refused_while_stopped: commands of the sequence that came during a
    /// --fault-after fault or e-stop, refused with the failed reply and not executed).
    #[arg(long, value_name = "PATH")]
    count_file: Option<PathBuf>,
    /// Fence for standby holons (docs/controller-protocol.md, "Fencing (standby)"): one
    /// live session at a time holds the claim (CLAIM -> an epoch, +1 per grant, going on
    /// from the count file's "epoch" after a restart); a command must carry the
    /// holder's EPOCH (else it is refused `stale_epoch`, counted, not executed); a STEP
    /// id runs at most once (a repeat gets the stored outcome); STEP_STATUS answers a
    /// step's state. The count file adds "epoch", "stale_epoch_refused" and "by_step".
    /// Without it the fence's messages are refused `not_fenced` and EPOCH/STEP are
    /// ignored. Needs a dialect with a [fence] (holarchy-xml).
    #[arg(long)]
    fenced: bool,
    /// How many actions the controller runs at once on one connection (at least 1), as
    /// a conveyor's PLC moves several pallets at once: each ends at its own time and is
    /// answered with its own reply, matched to its command by ID; a command that comes
    /// while N are under way waits until one ends. More than 1 needs a dialect whose
    /// replies carry the command's id (correlation "id", e.g. holarchy-xml) and whose
    /// actions end by a reply, not a poll; else refused at start.
    #[arg(long, default_value_t = 1, value_name = "N")]
    actions_at_once: usize,
    /// With --fenced: the session lease in ms: a holder silent this long (no heartbeat,
    /// no command) loses the claim and its connection is closed.
    #[arg(long, default_value_t = 1000, value_name = "MS")]
    lease_ms: u64,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let dialect = match Dialect::load(&args.dialect, None)
        .map_err(|e| e.to_string())
        .and_then(|d| {
            d.check_simulatable()
                .map(|()| d)
                .map_err(|e| format!("{}: {e}", args.dialect))
        }) {
        Ok(dialect) => dialect,
        Err(why) => {
            eprintln!("robot-sim: {why}");
            std::process::exit(2);
        }
    };
    if args.fenced && !dialect.fencing_supported() {
        eprintln!(
            "robot-sim: the dialect {} cannot fence (it has no [fence]): --fenced needs one that can, e.g. holarchy-xml",
            dialect.name
        );
        std::process::exit(2);
    }
    if args.unknown_state_every.is_some()
        && dialect
            .undescribed_status(robot_bridge::sim::UNDESCRIBED_STATE)
            .is_none()
    {
        eprintln!(
            "robot-sim: --unknown-state-every: the dialect {} has no status reply in words robot-sim can change to a state it does not describe",
            dialect.name
        );
        std::process::exit(2);
    }
    if args.fenced && args.lease_ms == 0 {
        eprintln!("robot-sim: --lease-ms must be more than 0");
        std::process::exit(2);
    }
    if let Err(e) = SimConfig::check_actions_at_once(args.actions_at_once, &dialect) {
        eprintln!("robot-sim: --actions-at-once: {e}");
        std::process::exit(2);
    }
    if args.check {
        for warning in dialect.warnings() {
            eprintln!("robot-sim: warning: {warning}");
        }
        println!("dialect {} is valid", dialect.name);
        return Ok(());
    }
    let dials = dialect.role == Role::ControllerConnects;
    if dials && args.connect.is_none() {
        eprintln!(
            "robot-sim: in the dialect {} the controller connects to the holon: give --connect ADDR",
            dialect.name
        );
        std::process::exit(2);
    }
    if !dials && args.connect.is_some() {
        eprintln!(
            "robot-sim: in the dialect {} the controller listens: give --listen, not --connect",
            dialect.name
        );
        std::process::exit(2);
    }
    let _logs = robot_bridge::sim::process::log_to_stderr()
        .context("cannot start the log writer thread")?;
    let config = sim_config(&args, dialect);
    let simulator = match &args.connect {
        Some(address) => {
            println!("dialling {address}");
            Simulator::dialing(address, config)
        }
        None => {
            let simulator = Simulator::bind(&args.listen, config)
                .await
                .with_context(|| format!("cannot listen on {}", args.listen))?;
            println!("listening on {}", simulator.local_addr()?);
            simulator
        }
    };
    let stats = simulator.stats();
    let shutdown = robot_bridge::sim::process::stop_on_signals();
    simulator.run(shutdown).await;
    // The reader of our stdout may be gone (a launcher that only read the first line).
    let aborted = match stats.aborted() {
        0 => String::new(),
        n => format!(", aborted {n}"),
    };
    let _ = writeln!(
        std::io::stdout(),
        "executed {} commands{aborted}",
        stats.executed()
    );
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

/// The simulator's settings as the command line gives them, speaking `dialect`.
fn sim_config(args: &Args, dialect: Arc<Dialect>) -> SimConfig {
    SimConfig {
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
        fault_every: args.fault_every,
        fault_state: Some(args.fault_state),
        fault_for: Duration::from_millis(args.fault_for_ms),
        unknown_state_every: args.unknown_state_every,
        count_file: args.count_file.clone(),
        dialect: Some(dialect),
        reset_after: args.reset_after,
        oversize_after: args.oversize_after,
        wrong_id_after: args.wrong_id_after,
        fragment: args.fragment,
        merge: args.merge,
        abort_too_late: false,
        fence_lease: args.fenced.then(|| Duration::from_millis(args.lease_ms)),
        physics: None,
        actions_at_once: args.actions_at_once,
    }
}

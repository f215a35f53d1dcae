//! `plant-sim`: the cell's plant, simulated once for all its controllers.

use std::path::PathBuf;

use anyhow::Context;
use clap::Parser;
use robot_bridge::plant::{Outputs, PlantSim};

/// The cell's plant, simulated once for all its controllers (docs/material-flow.md,
/// "The plant"): every controller of the plant file on its own address in its own
/// dialect, as robot-sim serves one, over one physical state. A transporter's move
/// (a command naming the part and where it goes: holarchy-xml's PART, FROM and TO)
/// runs track by track and ends when the part is there; a pallet sent to a full port
/// waits at its stopper, holding its track; a station told to work on a part that is
/// not at its port fails with a physical error.
///
/// Prints `controller RESOURCE listening on ADDR` for each controller, then `plant
/// ready`; where every part and pallet is goes to the state file (JSON, rewritten
/// after every change), with the plant's memory: killed and started again on the same
/// state file, the plant goes on from where it was (pallets on their way go on; each
/// fenced controller knows its steps again; docs/material-flow.md, "When the plant
/// simulator dies"). Runs until SIGTERM or Ctrl-C. Exits 2 when the plant file, its
/// layout or the memory in its state file is invalid, with the reason.
#[derive(Debug, Parser)]
#[command(name = "plant-sim", version)]
struct Args {
    /// The plant file (deploy/cells/demo/plant.toml documents it): the resource configs
    /// whose [layout] make the plant, and its controllers.
    #[arg(long, value_name = "FILE")]
    plant: PathBuf,
    /// Where to write where everything is, overriding the plant file's state_file. If
    /// the file is there, the plant resumes from the memory in it (unless --fresh); one
    /// that holds no plant memory, or a memory that does not fit the layout, is refused.
    #[arg(long, value_name = "PATH")]
    state_file: Option<PathBuf>,
    /// Start an empty plant (no part anywhere, every pallet free, plant time 0),
    /// forgetting the memory in the state file, which is written anew.
    #[arg(long)]
    fresh: bool,
    /// Write every action the controllers run here, one JSON line each as it ends
    /// (resource, action, part, carrier, begin_ms and end_ms in plant time, done),
    /// overriding the plant file's trace_file; the file is emptied at start, unless the
    /// plant resumes from its memory: then it is written on (docs/material-flow.md,
    /// "The plant's trace").
    #[arg(long, value_name = "PATH")]
    trace: Option<PathBuf>,
    /// Serve the control port here (HOST:PORT; port 0: a free one, printed): one
    /// command a line: `where` (the state as JSON), `waits` (what waits, since when,
    /// and whether the plant is deadlocked), `counts` (what each controller executed),
    /// `jam CONVEYOR.STOPPER` and `clear ...` (the
    /// track ending at that stopper: no pallet enters or leaves it while jammed),
    /// `silence PALLET` and `report PALLET` (a pallet that stops reporting: its
    /// moves end in the plant without its controller saying so), `retire PALLET` and
    /// `restore PALLET` (a pallet out of service once free, and back; a move that
    /// finds no free pallet waits for one), `estop RESOURCE MS`
    /// (its controller e-stopped for MS ms), `cut RESOURCE` (every link to its
    /// controller closed at once; what it does goes on), `fail RESOURCE N` (its next N
    /// inspections answered `inspect_fail`). No access control: keep it on loopback.
    #[arg(long, value_name = "HOST:PORT")]
    control: Option<String>,
    /// Check the plant file, its layout and its controllers' dialects, print `plant
    /// FILE is valid`, and exit (listening nowhere): 0 if it is, 2 with the reason if not.
    #[arg(long)]
    check: bool,
    /// Run the plant FACTOR times faster than real time (from 1 to 1000; default 1):
    /// every action's time (`delay_ms`, `action_ms`) and every move's travel take
    /// 1/FACTOR of their plant time, and e-stops of the control port (MS) too. What the
    /// plant reports (the state file's and `waits`' times) is plant time. The fenced
    /// controllers' leases and the protocol's timeouts are not plant time and stay as
    /// configured. The resource holons driving it must run at the same factor
    /// (`holon-node --time-scale`).
    #[arg(long, value_name = "FACTOR", default_value = "1")]
    time_scale: schemas::TimeScale,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    if args.check {
        // Checked as it would start; nothing written, nothing listened on.
        let files = Outputs {
            state_file: args.state_file,
            trace_file: None,
            fresh: args.fresh,
        };
        match robot_bridge::plant::prepare(&args.plant, files, args.time_scale) {
            Ok(_) => {
                println!("plant {} is valid", args.plant.display());
                return Ok(());
            }
            Err(e) => {
                eprintln!("plant-sim: {e}");
                std::process::exit(2);
            }
        }
    }
    let _logs = robot_bridge::sim::process::log_to_stderr()
        .context("cannot start the log writer thread")?;
    let plant = match PlantSim::bind(
        &args.plant,
        Outputs {
            state_file: args.state_file,
            trace_file: args.trace,
            fresh: args.fresh,
        },
        args.control.as_deref(),
        args.time_scale,
    )
    .await
    {
        Ok(plant) => plant,
        Err(e) => {
            eprintln!("plant-sim: {e}");
            std::process::exit(2);
        }
    };
    for (resource, address) in plant.addresses() {
        println!("controller {resource} listening on {address}");
    }
    if let Some(address) = plant.control_address() {
        println!("control port listening on {address}");
    }
    println!("plant ready");
    let shutdown = robot_bridge::sim::process::stop_on_signals();
    plant.run(shutdown).await;
    Ok(())
}

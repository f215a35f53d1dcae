//! `holon-node`: runs one resource holon as its own process.

use std::process::ExitCode;

use clap::Parser;
use holon_node::holon_config::HolonConfig;
use holon_node::identity::Overrides;

/// Runs one holon: a resource (a robot, an inspection station, a conveyor) that takes
/// Service requests over zenoh and drives its controller over TCP/XML, a product that
/// answers with its process plan, or a staff holon that advises orders where to book.
/// The config's `kind` says which.
///
/// The holon is ready when its liveliness token holarchy/<cell>/alive/resource/<name>
/// appears. SIGTERM or Ctrl-C stops it cleanly (token withdrawn, components stopped in
/// reverse order, controller connection closed) with exit code 0. It exits 1 when its
/// config is invalid or its components fail more often than the restart intensity allows.
#[derive(Debug, Parser)]
#[command(name = "holon-node", version, after_help = holon::cli::ENVIRONMENT_HELP)]
struct Args {
    #[command(flatten)]
    common: holon::cli::CommonArgs,
    /// The robot controller's HOST:PORT, overriding controller.address (resources).
    #[arg(long, value_name = "HOST:PORT")]
    controller: Option<String>,
    /// Declare holarchy/<cell>/resource/<name>/debug/crash, which makes a component
    /// panic on request (for tests and demonstrations of supervision; never in production).
    #[arg(long)]
    allow_fault_injection: bool,
    /// Claim the controller before serving (as `[controller] fenced = true`): a resource
    /// of the same name and controller may run beside this one, on another host; the one
    /// that holds the controller's claim serves, the other waits as a standby (its name's
    /// token is not declared) and takes over when the holder's controller session goes
    /// silent. A holder the controller deposes steps down and waits again. The dialect
    /// must fence; else start is refused with the reason. Not with --take-over.
    #[arg(long)]
    standby: bool,
    /// Check the config and exit without starting: `FILE: ok (KIND/NAME)` and 0, or 1
    /// with the reason. What is valid but likely a mistake (a resource's dialect without
    /// an `abort`) is said on stderr as a warning; the exit is still 0. A resource's
    /// `[layout]` is checked on its own and listed (what it names of other holons is
    /// checked with theirs: `cell layout --check DIR`).
    #[arg(long)]
    check: bool,
    /// (Resources) The plant this resource drives runs FACTOR times faster than real time (a
    /// simulated plant, `plant-sim --time-scale`; from 1 to 1000, default 1): the
    /// durations the config gives in plant time (each service's `nominal_duration_ms`,
    /// the `[layout]`'s conveyor speed and `dock_ms`, a transfer's `move_ms`) are
    /// counted in 1/FACTOR of them, so that proposals and travel estimates are in the
    /// wall time the plant takes. Network timers (timeouts, leases, retries) are not
    /// plant time and stay as configured. Every resource of a cell must run at its
    /// plant's factor (`cell up` passes the manifest's `time_scale`).
    #[arg(long, value_name = "FACTOR", default_value = "1")]
    time_scale: schemas::TimeScale,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let (format, log_file) = (args.common.log_format, args.common.log_file.clone());
    holon::process_main(
        "holon-node",
        holon::zenoh_runtime::Pool::Holon,
        format,
        log_file.as_deref(),
        |shutdown| run(args, shutdown),
    )
}

async fn run(args: Args, shutdown: tokio_util::sync::CancellationToken) -> anyhow::Result<()> {
    let overrides = Overrides {
        common: args.common.overrides(),
        controller: args.controller,
        allow_fault_injection: args.allow_fault_injection,
        standby: args.standby,
        time_scale: args.time_scale,
    };
    let config = HolonConfig::load(&args.common.config, overrides)?;
    if args.check {
        if let HolonConfig::Resource(resource) = &config {
            for warning in resource.controller.dialect.warnings() {
                eprintln!(
                    "holon-node: {}: warning: controller.dialect: {warning}",
                    args.common.config.display()
                );
            }
        }
        println!("{}: ok ({})", args.common.config.display(), config.holon());
        if let HolonConfig::Resource(resource) = &config {
            for line in resource
                .layout
                .iter()
                .flat_map(schemas::layout::LayoutPart::describe)
            {
                println!("  layout: {line}");
            }
        }
        return Ok(());
    }
    match config {
        HolonConfig::Resource(config) => holon_node::node::run(*config, shutdown).await?,
        HolonConfig::Product(config) => holon_node::product::run(config, shutdown).await?,
        HolonConfig::Staff(config) => holon_node::staff::node::run(config, shutdown).await?,
    }
    Ok(())
}

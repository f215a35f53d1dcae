//! `cell`: the operator's command.

use std::process::ExitCode;

use clap::Parser;
use holon::LogFormat;

mod cli;
mod client_args;
mod commands;

use anyhow::Result;
use commands::{Args, Commands};

fn main() -> ExitCode {
    // Keys, journals, logs and the files `cell up` writes for its processes are their
    // owner's alone.
    holon::owner_only_files();
    let args = Args::parse();
    if matches!(
        args.command,
        Commands::Status { .. }
            | Commands::Orders { .. }
            | Commands::Submit { .. }
            | Commands::Cancel { .. }
            | Commands::Part { .. }
            | Commands::Carrier { .. }
            | Commands::Packml { .. }
    ) {
        // A client command piped into `head` or `grep -q` stops quietly when the reader
        // goes, like any Unix tool, instead of panicking on a broken pipe.
        // SAFETY: set before any thread starts; the default action needs no handler.
        if let Err(e) = unsafe {
            nix::sys::signal::signal(
                nix::sys::signal::Signal::SIGPIPE,
                nix::sys::signal::SigHandler::SigDfl,
            )
        } {
            eprintln!("cell: cannot restore SIGPIPE: {e}");
        }
    }
    // The command's own output is what it prints; its logs go to stderr at warn unless
    // RUST_LOG says otherwise (zenoh's own warnings, e.g. a query to a host that was cut
    // off, are not the operator's). The holons `cell up` starts keep their own default
    // (info) in their log files: RUST_LOG is passed on only when the user set it.
    // Dropped last (declared first): the last lines are written out before the exit.
    // `cell opcua` is a server: its own start, logins and refusals are worth a line.
    let default_filter = if let Commands::Opcua(opcua) = &args.command {
        if opcua.pki.is_some() {
            "info,zenoh=error,opcua_server=warn,opcua_core=warn,opcua_crypto=warn,opcua_nodes=warn,opcua_types=warn"
        } else {
            // No security, so no certificate: async-opcua's lines saying so are noise.
            "info,zenoh=error,opcua_server=warn,opcua_server::server=error,opcua_core=warn,opcua_core::comms::secure_channel=off,opcua_crypto=warn,opcua_crypto::certificate_store=off,opcua_nodes=warn,opcua_types=warn"
        }
    } else if matches!(&args.command, Commands::Demo(demo) if demo.opcua && !demo.secure) {
        // The demo's plain OPC UA server has no certificate, by design.
        "warn,zenoh=error,opcua_server::server=error,opcua_core::comms::secure_channel=off,opcua_crypto::certificate_store=off"
    } else {
        "warn,zenoh=error"
    };
    let _logs = match holon::logging::init(LogFormat::Text, None, default_filter) {
        Ok(guard) => guard,
        Err(e) => {
            eprintln!("cell: {e}");
            return ExitCode::FAILURE;
        }
    };
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("cell: cannot start the tokio runtime: {e}");
            return ExitCode::FAILURE;
        }
    };
    match runtime.block_on(run(args)) {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("cell: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// Runs the command; true: exit 0, false: exit 1 (what failed is already printed).
async fn run(args: Args) -> Result<bool> {
    match args.command {
        Commands::Demo(args) => cli::demo::run(args).await,
        Commands::Dashboard(args) => cli::dashboard::run(args).await,
        Commands::Opcua(args) => cli::opcua::run(args).await,
        Commands::Users(args) => {
            cell::security::users::cli::run(args)?;
            Ok(true)
        }
        Commands::Up {
            dir, check: true, ..
        } => cli::up::check(&dir),
        Commands::Up {
            dir,
            host,
            time_scale,
            ..
        } => cli::up::run(&dir, &host, time_scale).await,
        Commands::Upgrade(args) => cli::up::upgrade(args).await,
        Commands::Router(args) => cli::router::run(args).await,
        Commands::Orders(args) => cli::orders::list(args).await,
        Commands::Submit(args) => cli::orders::submit(args).await,
        Commands::Cancel { order, client } => cli::orders::cancel(&order, &client).await,
        Commands::Part { order, at, client } => cli::orders::part(&order, at, &client).await,
        Commands::Carrier {
            resource,
            carrier,
            back,
            client,
            ..
        } => cli::orders::carrier(&resource, &carrier, back, &client).await,
        Commands::Packml(args) => cli::packml::run(args).await,
        Commands::Layout { json, client } => cli::status::layout(json, &client).await,
        Commands::Status { client } => cli::status::status(&client).await,
        Commands::Certs { dir, force, renew } => {
            let options = cell::security::certs::CertsOptions { force, renew };
            for line in cell::security::certs::run(&dir, &options)? {
                println!("{line}");
            }
            Ok(true)
        }
    }
}

//! The command line of `cell`: its subcommands ([`commands`]), and one file per command
//! (or a few close ones) with its flags and what it does with them, calling the library.
//! [`run`] dispatches a parsed command to its handler.

pub mod client_args;
pub mod commands;
pub mod dashboard;
pub mod demo;
pub mod opcua;
pub mod orders;
pub mod packml;
pub mod router;
pub mod status;
pub mod up;

use anyhow::Result;

use commands::{Args, Commands};

/// Runs the command; true: exit 0, false: exit 1 (what failed is already printed).
pub async fn run(args: Args) -> Result<bool> {
    match args.command {
        Commands::Demo(args) => demo::run(args).await,
        Commands::Dashboard(args) => dashboard::run(args).await,
        Commands::Opcua(args) => opcua::run(args).await,
        Commands::Users(args) => {
            cell::security::users::cli::run(args)?;
            Ok(true)
        }
        Commands::Up {
            dir, check: true, ..
        } => up::check(&dir),
        Commands::Up { dir, host, .. } => up::run(&dir, &host).await,
        Commands::Upgrade(args) => up::upgrade(args).await,
        Commands::Router(args) => router::run(args).await,
        Commands::Orders(args) => orders::list(args).await,
        Commands::Submit(args) => orders::submit(args).await,
        Commands::Cancel { order, client } => orders::cancel(&order, &client).await,
        Commands::Packml(args) => packml::run(args).await,
        Commands::Layout { json, client } => status::layout(json, &client).await,
        Commands::Status { client } => status::status(&client).await,
        Commands::Certs { dir, force, renew } => {
            let options = cell::security::certs::CertsOptions { force, renew };
            for line in cell::security::certs::run(&dir, &options)? {
                println!("{line}");
            }
            Ok(true)
        }
    }
}

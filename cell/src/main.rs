//! `cell`: the operator's command.

use std::process::ExitCode;
use std::time::Duration;

use anyhow::{anyhow, Result};
use clap::Parser;
use holon::LogFormat;

mod client_args;
mod commands;

use client_args::{close, OBSERVER, OPERATOR};
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
    let default_filter = if let Commands::Opcua { pki, .. } = &args.command {
        if pki.is_some() {
            "info,zenoh=error,opcua_server=warn,opcua_core=warn,opcua_crypto=warn,opcua_nodes=warn,opcua_types=warn"
        } else {
            // No security, so no certificate: async-opcua's lines saying so are noise.
            "info,zenoh=error,opcua_server=warn,opcua_server::server=error,opcua_core=warn,opcua_core::comms::secure_channel=off,opcua_crypto=warn,opcua_crypto::certificate_store=off,opcua_nodes=warn,opcua_types=warn"
        }
    } else if matches!(
        &args.command,
        Commands::Demo {
            opcua: true,
            secure: false,
            ..
        }
    ) {
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

async fn run(args: Args) -> Result<bool> {
    match args.command {
        Commands::Demo {
            cell,
            orders,
            delay_ms,
            inspect_fail_every,
            no_hot_add,
            dir,
            secure,
            dashboard,
            listen,
            keep,
            staff,
            opcua,
            opcua_listen,
        } => {
            let shutdown = holon::shutdown_on_signals();
            let options = cell::demo::DemoOptions {
                cell,
                orders,
                action_delay: Duration::from_millis(delay_ms),
                inspect_fail_every,
                hot_add: !no_hot_add,
                dir,
                secure,
                dashboard: dashboard.then_some(listen),
                keep,
                staff,
                opcua: opcua.then_some(opcua_listen),
            };
            cell::demo::run(options, shutdown).await
        }
        Commands::Dashboard {
            listen,
            operator,
            host_names,
            users,
            audit,
            session_idle_s,
            session_max_s,
            part_wait_alarm_s,
            tls,
            no_tls,
            tls_cert,
            tls_key,
            client,
        } => {
            let (identity, operator) = cell::dashboard::connect_as(
                client.pki.is_some(),
                client.identity.as_deref(),
                operator,
            )?;
            let pki = client.pki.as_deref();
            let users = users.or_else(|| pki.map(cell::users::default_path));
            let audit = audit.or_else(|| {
                users
                    .as_deref()
                    .and_then(|u| u.parent())
                    .map(|dir| dir.join(cell::audit::FILE_NAME))
            });
            let tls = cell::dashboard::https_files(
                pki,
                &identity,
                tls,
                no_tls,
                tls_cert.zip(tls_key),
                listen,
            )?;
            let config = cell::dashboard::DashboardConfig {
                keys: client.keys()?,
                zenoh: client.settings(),
                identity,
                listen,
                operator,
                host_names,
                users,
                audit,
                sessions: cell::dashboard::session::SessionLimits {
                    idle: Duration::from_secs(session_idle_s),
                    absolute: Duration::from_secs(session_max_s),
                },
                tls,
                part_wait_alarm: Duration::from_secs(part_wait_alarm_s),
            };
            cell::dashboard::run(config, holon::shutdown_on_signals()).await?;
            Ok(true)
        }
        Commands::Opcua {
            listen,
            cell,
            connect,
            pki,
            identity,
            users,
            audit,
            trust,
        } => {
            if let (Some(client), Some(pki)) = (&trust, &pki) {
                let path = cell::opcua::security::trust(pki, client)?;
                println!("trusted {} as {}", client.display(), path.display());
                return Ok(true);
            }
            if connect.is_empty() {
                return Err(anyhow!("--connect ENDPOINT: a zenoh router of the cell"));
            }
            let identity = identity.unwrap_or_else(|| "operator.opcua".to_string());
            if pki.is_some() {
                let (role, _) = cell::access::parse_identity(&identity)?;
                if role != cell::access::Role::Operator {
                    return Err(anyhow!(
                        "the OPC UA server joins as an operator.* identity (its methods command resources), not as {identity}"
                    ));
                }
            }
            let config = cell::opcua::OpcuaConfig {
                keys: schemas::CellKeys::new(&cell)?,
                zenoh: holon::ZenohSettings {
                    mode: holon::Mode::Client,
                    connect,
                    tls: pki.as_ref().map(|pki| holon::tls::TlsSettings {
                        pki: Some(pki.clone()),
                        ..holon::tls::TlsSettings::default()
                    }),
                    ..holon::ZenohSettings::default()
                },
                identity,
                listen,
                pki,
                users,
                audit,
            };
            cell::opcua::run(config, holon::shutdown_on_signals()).await?;
            Ok(true)
        }
        Commands::Users(args) => {
            cell::users::cli::run(args)?;
            Ok(true)
        }
        Commands::Up {
            dir, check: true, ..
        } => {
            let cell = cell::manifest::Manifest::load(&dir)?.cell;
            let (layout, sources) = cell::layout::from_manifest(&dir)?;
            print!("{}", cell::layout::render(&cell, &layout, &sources));
            Ok(layout.problems.is_empty())
        }
        Commands::Up { dir, host, .. } => {
            let shutdown = holon::shutdown_on_signals();
            cell::up::run(&dir, &host, shutdown).await
        }
        Commands::Upgrade {
            name,
            dir,
            host,
            binary,
            config,
            wait_ms,
        } => {
            // A binary given relative to here means here; cell up runs elsewhere.
            let binary = binary
                .map(|b| {
                    if b.components().count() > 1 {
                        std::path::absolute(&b)
                    } else {
                        Ok(b)
                    }
                })
                .transpose()?;
            let request = cell::upgrade::UpgradeRequest {
                name,
                binary,
                config,
                wait_ms,
            };
            let outcome = cell::upgrade::ask(&dir, &host, &request).await?;
            if !outcome.ok {
                return Err(anyhow!("{}", outcome.message));
            }
            println!("{}", outcome.message);
            Ok(true)
        }
        Commands::Router {
            config,
            listen,
            connect,
            lease_ms,
            pki,
            identity,
            cell,
            name,
        } => {
            let shutdown = holon::shutdown_on_signals();
            let options = cell::router::RouterOptions {
                config,
                listen,
                connect,
                lease_ms,
                pki,
                identity,
                cell: cell.as_deref().map(schemas::CellKeys::new).transpose()?,
                name,
            };
            cell::router::run(options, shutdown).await?;
            Ok(true)
        }
        Commands::Orders {
            detail,
            status,
            finished,
            all,
            client,
        } => {
            let keys = client.keys()?;
            let session = client.session(OBSERVER).await?;
            let options = cell::orders::OrdersOptions {
                filter: status,
                finished: (!all).then_some(finished),
                detail,
            };
            let mut out = std::io::stdout().lock();
            let complete = cell::orders::print(
                &session,
                &keys,
                &client.cell,
                &options,
                client.timeout(),
                &mut out,
            )
            .await;
            drop(out);
            close(session).await;
            complete
        }
        Commands::Submit {
            product,
            count,
            priority,
            due_in,
            queue,
            client,
        } => {
            let keys = client.keys()?;
            let work = schemas::WorkOrder {
                product,
                count,
                priority,
                due: due_in.map(|d| schemas::unix_ms() + d.as_millis() as u64),
                queue,
            };
            work.validate()?;
            let session = client.session(OPERATOR).await?;
            let by = client.who_asks();
            let ids = cell::submit::submit(&session, &keys, &work, &by, client.timeout()).await?;
            println!("{}", ids.join("\n"));
            close(session).await;
            Ok(true)
        }
        Commands::Cancel { order, client } => {
            let keys = client.keys()?;
            schemas::HolonId::order(&order)?;
            let session = client.session(OPERATOR).await?;
            let by = client.who_asks();
            let reply = cell::status::cancel(&session, &keys, &order, &by, client.timeout()).await;
            close(session).await;
            let reply = reply?;
            println!("{}: {}", reply.order, reply.detail);
            Ok(true)
        }
        Commands::Part { order, at, client } => {
            let keys = client.keys()?;
            schemas::HolonId::order(&order)?;
            let at = schemas::layout::LocationId::try_from(at).map_err(|e| anyhow!("--at: {e}"))?;
            let session = client.session(OPERATOR).await?;
            let by = client.who_asks();
            let told =
                cell::part_word::tell(&session, &keys, &order, &at, &by, client.timeout()).await;
            close(session).await;
            let reply = told?;
            println!("{}: {}", reply.order, reply.detail);
            Ok(true)
        }
        Commands::Packml {
            resource,
            command,
            mode,
            job,
            info,
            wait_ms,
            client,
        } => {
            let keys = client.keys()?;
            let by = client.who_asks();
            if let Some(service_type) = job {
                let info: serde_json::Map<String, serde_json::Value> = serde_json::from_str(&info)
                    .map_err(|e| anyhow!("--info is not a JSON object: {e}"))?;
                let request = schemas::PackmlRequest::job(
                    schemas::packml::JobRequest { service_type, info },
                    &by,
                );
                let session = client.session(OPERATOR).await?;
                let ended = cell::packml::run_job(
                    &session,
                    &keys,
                    &resource,
                    &request,
                    client.timeout(),
                    Duration::from_millis(wait_ms),
                )
                .await;
                close(session).await;
                return match ended? {
                    Ok(job) => {
                        println!(
                            "{resource}: {} {}: {}",
                            job.conversation_id,
                            job.service_type,
                            job.outcome
                                .as_deref()
                                .unwrap_or("still running (see cell packml)")
                        );
                        Ok(job.done)
                    }
                    Err(reply) => {
                        println!("{}", cell::packml::render_reply(&resource, &reply));
                        Ok(false)
                    }
                };
            }
            let request = match (command, mode) {
                (Some(command), _) => Some(schemas::PackmlRequest::command(command, &by)),
                (None, Some(mode)) => Some(schemas::PackmlRequest::mode(mode, &by)),
                (None, None) => None,
            };
            let Some(request) = request else {
                let session = client.session(OBSERVER).await?;
                let state = cell::packml::state(&session, &keys, &resource, client.timeout()).await;
                close(session).await;
                print!(
                    "{}",
                    cell::packml::render_state(&state?, schemas::unix_ms())
                );
                return Ok(true);
            };
            let session = client.session(OPERATOR).await?;
            let reply =
                cell::packml::ask(&session, &keys, &resource, &request, client.timeout()).await;
            close(session).await;
            let reply = reply?;
            println!("{}", cell::packml::render_reply(&resource, &reply));
            Ok(reply.refused.is_none())
        }
        Commands::Layout { json, client } => {
            let keys = client.keys()?;
            let session = client.session(OBSERVER).await?;
            let layout = cell::layout::live(&session, &keys, client.timeout()).await;
            close(session).await;
            let layout = layout?;
            if json {
                println!("{}", serde_json::to_string_pretty(&layout)?);
            } else {
                print!(
                    "{}",
                    cell::layout::render(&client.cell, &layout, &Default::default())
                );
            }
            Ok(true)
        }
        Commands::Status { client } => {
            let keys = client.keys()?;
            let session = client.session(OBSERVER).await?;
            let rows = cell::status::collect(&session, &keys, client.timeout()).await?;
            let nodes = cell::status::order_nodes(&session, &keys, client.timeout()).await;
            let fences = cell::status::fences(&session, &keys, client.timeout()).await;
            let node_fences = cell::status::node_fences(&session, &keys, client.timeout()).await;
            print!("{}", cell::status::render(&client.cell, &rows));
            match fences {
                Ok(fences) => print!("{}", cell::status::render_fences(&fences)),
                Err(e) => println!("fenced resources: cannot ask ({e})"),
            }
            match node_fences {
                Ok(reports) => print!("{}", cell::status::render_node_fences(&reports)),
                Err(e) => println!("fenced order-nodes: cannot ask ({e})"),
            }
            match nodes {
                Ok(nodes) => print!("{}", cell::status::render_order_nodes(&nodes)),
                Err(e) => println!("order-nodes: cannot ask ({e})"),
            }
            close(session).await;
            Ok(true)
        }
        Commands::Certs { dir, force, renew } => {
            let options = cell::certs::CertsOptions { force, renew };
            for line in cell::certs::run(&dir, &options)? {
                println!("{line}");
            }
            Ok(true)
        }
    }
}

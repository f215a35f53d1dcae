//! `cell packml`: a resource's PackML state shown, a command or mode change asked, or
//! one maintenance job run ([`cell::client::packml`]).

use std::time::Duration;

use anyhow::{anyhow, Result};

use crate::client_args::{close, ClientArgs, OBSERVER, OPERATOR};

/// `cell packml`: the resource, and what to show or command.
#[derive(Debug, clap::Args)]
pub struct PackmlArgs {
    /// The resource, e.g. robot1.
    pub resource: String,
    /// The command; none: show the state.
    pub command: Option<schemas::PackmlCommand>,
    /// Change the unit mode instead.
    #[arg(long, conflicts_with = "command")]
    pub mode: Option<schemas::UnitMode>,
    /// Run one job of this service type now (Maintenance mode only: the resource
    /// must be in Execute, in Maintenance, with nothing running), and wait for its
    /// end: prints how it ended, exits 1 unless done.
    #[arg(long, value_name = "SERVICE_TYPE", conflicts_with_all = ["command", "mode"])]
    pub job: Option<String>,
    /// The job's info as JSON, as a booking's would carry it (its poses, program),
    /// e.g. '{"pick": {"x": 1, "y": 2, "z": 3}, "place": {"x": 4, "y": 5, "z": 6}}'.
    #[arg(long, value_name = "JSON", requires = "job", default_value = "{}")]
    pub info: String,
    /// How long to wait for the job's end, in milliseconds.
    #[arg(long, value_name = "MS", requires = "job", default_value_t = 60_000)]
    pub wait_ms: u64,
    #[command(flatten)]
    pub client: ClientArgs,
}

/// Runs a job (`--job`), asks a command or mode, or shows the state.
pub async fn run(args: PackmlArgs) -> Result<bool> {
    let by = args.client.who_asks();
    if let Some(service_type) = args.job {
        return job(
            &args.resource,
            service_type,
            &args.info,
            args.wait_ms,
            &by,
            &args.client,
        )
        .await;
    }
    let request = match (args.command, args.mode) {
        (Some(command), _) => Some(schemas::PackmlRequest::command(command, &by)),
        (None, Some(mode)) => Some(schemas::PackmlRequest::mode(mode, &by)),
        (None, None) => None,
    };
    match request {
        Some(request) => ask(&args.resource, &request, &args.client).await,
        None => show(&args.resource, &args.client).await,
    }
}

/// Runs one job of `service_type` and prints how it ended; true when done.
async fn job(
    resource: &str,
    service_type: String,
    info: &str,
    wait_ms: u64,
    by: &str,
    client: &ClientArgs,
) -> Result<bool> {
    let keys = client.keys()?;
    let info: serde_json::Map<String, serde_json::Value> =
        serde_json::from_str(info).map_err(|e| anyhow!("--info is not a JSON object: {e}"))?;
    let request =
        schemas::PackmlRequest::job(schemas::packml::JobRequest { service_type, info }, by);
    let session = client.session(OPERATOR).await?;
    let ended = cell::client::packml::run_job(
        &session,
        &keys,
        resource,
        &request,
        client.timeout(),
        Duration::from_millis(wait_ms),
    )
    .await;
    close(session).await;
    match ended? {
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
            println!("{}", cell::client::packml::render_reply(resource, &reply));
            Ok(false)
        }
    }
}

/// Prints the resource's state.
async fn show(resource: &str, client: &ClientArgs) -> Result<bool> {
    let keys = client.keys()?;
    let session = client.session(OBSERVER).await?;
    let state = cell::client::packml::state(&session, &keys, resource, client.timeout()).await;
    close(session).await;
    print!(
        "{}",
        cell::client::packml::render_state(&state?, schemas::unix_ms())
    );
    Ok(true)
}

/// Asks a command or mode change and prints the answer; true unless refused.
async fn ask(
    resource: &str,
    request: &schemas::PackmlRequest,
    client: &ClientArgs,
) -> Result<bool> {
    let keys = client.keys()?;
    let session = client.session(OPERATOR).await?;
    let reply =
        cell::client::packml::ask(&session, &keys, resource, request, client.timeout()).await;
    close(session).await;
    let reply = reply?;
    println!("{}", cell::client::packml::render_reply(resource, &reply));
    Ok(reply.refused.is_none())
}

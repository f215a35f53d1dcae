//! `cell packml`: a resource's PackML state, and commands to it (docs/packml.md).
//!
//! A command is asked once, never again on its own: PackML commands are not idempotent
//! (a second Hold is refused in Holding). The resource must be alive first: a query
//! that reaches no queryable returns at once with no answer, which would say nothing
//! about whether the command took.

use std::time::Duration;

use anyhow::{anyhow, bail, Result};
use schemas::packml::OperatorJob;
use schemas::{CellKeys, HolonId, PackmlReply, PackmlRequest, ResourceSnapshot};

/// Sends `request` to `resource` and returns its answer (which may be a refusal).
pub async fn ask(
    session: &zenoh::Session,
    keys: &CellKeys,
    resource: &str,
    request: &PackmlRequest,
    timeout: Duration,
) -> Result<PackmlReply> {
    let holon = HolonId::resource(resource)?;
    if !alive(session, keys, &holon, timeout).await? {
        bail!("{holon} is not in the cell (no liveliness token): nothing was asked");
    }
    let key = keys.packml(resource);
    let mut replies = session
        .get(&key)
        .payload(serde_json::to_vec(request)?)
        .timeout(timeout)
        .with(holon::query::replies())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let Some(reply) = replies.recv().await else {
        bail!(
            "{holon} did not answer within {timeout:?}; the command may or may not have taken: see `cell packml {resource}`"
        );
    };
    match reply.result() {
        Ok(sample) => Ok(serde_json::from_slice(&sample.payload().to_bytes())
            .map_err(|e| anyhow!("{holon} answered what is not a PackML reply: {e}"))?),
        Err(err) => {
            let text = err.payload().try_to_string().unwrap_or_default();
            match schemas::ErrorReply::from_json(text.as_bytes()) {
                Some(e) => bail!("{holon} refused the request ({}): {}", e.code, e.message),
                None => bail!("{holon} refused the request: {text}"),
            }
        }
    }
}

/// The resource's state snapshot (its PackML figures are in `packml`).
pub async fn state(
    session: &zenoh::Session,
    keys: &CellKeys,
    resource: &str,
    timeout: Duration,
) -> Result<ResourceSnapshot> {
    let holon = HolonId::resource(resource)?;
    let mut replies = session
        .get(keys.state(&holon))
        .timeout(timeout)
        .with(holon::query::replies())
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let reply = replies
        .recv()
        .await
        .ok_or_else(|| anyhow!("{holon} did not answer (is it in the cell?)"))?;
    let sample = reply.result().map_err(|e| {
        anyhow!(
            "{holon}: {}",
            e.payload().try_to_string().unwrap_or_default()
        )
    })?;
    Ok(serde_json::from_slice(&sample.payload().to_bytes())?)
}

/// Whether `holon`'s liveliness token is in the cell.
async fn alive(
    session: &zenoh::Session,
    keys: &CellKeys,
    holon: &HolonId,
    timeout: Duration,
) -> Result<bool> {
    let key = keys.alive(holon);
    let tokens = session
        .liveliness()
        .get(&key)
        .timeout(timeout)
        .await
        .map_err(|e| anyhow!("{e}"))?;
    if tokens.recv_async().await.is_ok() {
        return Ok(true);
    }
    // A query of the tokens can miss one that a subscriber with history sees (a holon
    // started again under its name a moment ago, as the router answers): asked that way
    // too, briefly, before the resource is said to be gone.
    holon::presence::wait_token(session, &key, timeout.min(TOKEN_SEEN_WITHIN))
        .await
        .map_err(|e| anyhow!("{e}"))
}

/// How long a resource's token is looked for a second time, with a subscriber.
const TOKEN_SEEN_WITHIN: Duration = Duration::from_secs(2);

/// Runs an operator's single job on `resource` (in Maintenance mode) and waits, at most
/// `patience`, for its end: the [`OperatorJob`] as the resource's state reports it
/// (`outcome` none if it had not ended by then), or the refusal.
pub async fn run_job(
    session: &zenoh::Session,
    keys: &CellKeys,
    resource: &str,
    request: &PackmlRequest,
    timeout: Duration,
    patience: Duration,
) -> Result<Result<OperatorJob, PackmlReply>> {
    let holon = HolonId::resource(resource)?;
    // Subscribed before asking: the job's end may be published at once.
    let states = session
        .declare_subscriber(keys.state(&holon))
        .await
        .map_err(|e| anyhow!("{e}"))?;
    let reply = ask(session, keys, resource, request, timeout).await?;
    let Some(conversation) = reply.job.clone() else {
        return Ok(Err(reply));
    };
    let ended = |snapshot: &ResourceSnapshot| {
        snapshot
            .packml
            .as_ref()
            .and_then(|p| p.operator_job.clone())
            .filter(|job| job.conversation_id == conversation)
    };
    let deadline = tokio::time::Instant::now() + patience;
    let mut last = None;
    loop {
        let sample = match tokio::time::timeout_at(deadline, states.recv_async()).await {
            Ok(Ok(sample)) => sample,
            Ok(Err(e)) => bail!("{holon}'s state could not be followed: {e}"),
            Err(_) => break,
        };
        let Ok(snapshot) = serde_json::from_slice::<ResourceSnapshot>(&sample.payload().to_bytes())
        else {
            continue;
        };
        if let Some(job) = ended(&snapshot) {
            if job.outcome.is_some() {
                return Ok(Ok(job));
            }
            last = Some(job);
        }
    }
    // Not seen to end: as the resource says now.
    let now = state(session, keys, resource, timeout).await.ok();
    Ok(Ok(now.as_ref().and_then(ended).or(last).unwrap_or(
        OperatorJob {
            conversation_id: conversation,
            service_type: request
                .job
                .as_ref()
                .map(|j| j.service_type.clone())
                .unwrap_or_default(),
            by: request.by.clone().unwrap_or_default(),
            at: 0,
            outcome: None,
            done: false,
        },
    )))
}

/// One line for an answer: `robot1: Held (11), Production` or the refusal.
pub fn render_reply(resource: &str, reply: &PackmlReply) -> String {
    let now = format!(
        "{} ({}), {}",
        reply.state.name(),
        reply.state_number,
        reply.mode.name()
    );
    match &reply.detail {
        Some(why) => format!("{resource}: refused: {why}; it stays {now}"),
        None => format!("{resource}: {now}"),
    }
}

/// A resource's PackML figures, one per line.
pub fn render_state(snapshot: &ResourceSnapshot, now_ms: u64) -> String {
    let name = snapshot.holon.name();
    let Some(p) = &snapshot.packml else {
        return format!("{name}: no PackML state (a holon built before PackML)\n");
    };
    let mut out = format!(
        "{name}: {} ({}), {} mode, for {:.1} s\n",
        p.state.name(),
        p.state_number,
        p.mode.name(),
        now_ms.saturating_sub(p.since) as f64 / 1000.0
    );
    if p.state_requested != p.state {
        out.push_str(&format!("  heading for: {}\n", p.state_requested.name()));
    }
    out.push_str(&format!(
        "  processed: {}  defective: {}\n",
        p.processed, p.defective
    ));
    if let Some(reason) = &p.stop_reason {
        out.push_str(&format!(
            "  stop reason: {} ({}) at {}\n",
            reason.message, reason.id, reason.at
        ));
    }
    if let Some(job) = &p.operator_job {
        out.push_str(&format!(
            "  operator job: {} {} by {}: {}\n",
            job.conversation_id,
            job.service_type,
            job.by,
            job.outcome.as_deref().unwrap_or("running")
        ));
    }
    let commands: Vec<&str> = p.commands.iter().map(|c| c.name()).collect();
    out.push_str(&format!("  commands now: {}\n", commands.join(", ")));
    let times: Vec<String> = p
        .cumulative_ms
        .iter()
        .filter(|(_, ms)| **ms > 0)
        .map(|(state, ms)| format!("{} {:.1} s", state.name(), *ms as f64 / 1000.0))
        .collect();
    if !times.is_empty() {
        out.push_str(&format!("  time before: {}\n", times.join(", ")));
    }
    out
}

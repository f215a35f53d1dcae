//! What an operator does from the page: submit and cancel orders, acknowledge alarms,
//! command resources. Each action is checked against the user's role and the
//! dashboard's own, carried out, and recorded in the audit trail with who, from where,
//! what and how it ended, refusals included.

use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use tracing::info;

use super::gate::Who;
use super::http::{refused, Refusal};
use super::{Command, Shared};
use crate::audit::{AuditAction, AuditOutcome, AuditRecord};

/// How long the cell has to answer an action.
const ANSWER_WITHIN: Duration = Duration::from_secs(5);

/// Why `who` may not operate, if they may not: the refusal, recorded.
fn may_operate(
    shared: &Shared,
    who: &Who,
    action: AuditAction,
    target: Option<&str>,
) -> Result<(), Refusal> {
    let why = if !shared.operator {
        "this dashboard is read-only (it joined the cell as an observer; start it with --operator or an operator.* identity)".to_string()
    } else if !who.role.may_operate() {
        format!("{} is an observer: observers change nothing", who.who)
    } else {
        return Ok(());
    };
    let mut record = AuditRecord::now(
        &who.who,
        &who.from.to_string(),
        action,
        AuditOutcome::Refused(why.clone()),
    );
    record.target = target.map(String::from);
    shared.gate.record(record);
    Err(Refusal {
        status: StatusCode::FORBIDDEN,
        why,
    })
}

/// Records what `who` did and how it ended.
fn record(
    shared: &Shared,
    who: &Who,
    action: AuditAction,
    target: Option<&str>,
    detail: Option<serde_json::Value>,
    outcome: AuditOutcome,
) {
    let mut record = AuditRecord::now(&who.who, &who.from.to_string(), action, outcome);
    record.target = target.map(String::from);
    record.detail = detail;
    shared.gate.record(record);
}

/// Who commands, as the holons log it: the dashboard's identity and the user.
fn by(shared: &Shared, who: &Who) -> String {
    format!("dashboard {} for {}", shared.identity, who.who)
}

/// `POST /api/alarms/{id}/ack`.
pub async fn acknowledge(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(id): Path<u64>,
) -> Response {
    let target = id.to_string();
    let action = AuditAction::AcknowledgeAlarm;
    if let Err(refusal) = may_operate(&shared, &who, action, Some(&target)) {
        return refusal.into_response();
    }
    match shared
        .commands
        .send(Command::Acknowledge {
            id,
            by: who.who.clone(),
        })
        .await
    {
        Ok(()) => {
            info!(user = %who.who, alarm = id, "alarm acknowledged");
            record(
                &shared,
                &who,
                action,
                Some(&target),
                None,
                AuditOutcome::Done,
            );
            StatusCode::NO_CONTENT.into_response()
        }
        Err(_) => {
            let why = "the dashboard is stopping";
            record(
                &shared,
                &who,
                action,
                Some(&target),
                None,
                AuditOutcome::Failed(why.into()),
            );
            refused(StatusCode::SERVICE_UNAVAILABLE, why)
        }
    }
}

/// `POST /api/orders`'s body.
#[derive(Debug, Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields)]
pub struct SubmitForm {
    product: String,
    #[serde(default = "one")]
    count: u32,
    #[serde(default)]
    queue: bool,
    /// -1000 to 1000, higher first.
    #[serde(default)]
    priority: i32,
    /// Due this many seconds from now (optional).
    #[serde(default)]
    due_in_s: Option<u64>,
}

fn one() -> u32 {
    1
}

/// `POST /api/orders`: the new orders' names.
pub async fn submit(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Json(form): Json<SubmitForm>,
) -> Response {
    let action = AuditAction::Submit;
    let detail = serde_json::to_value(&form).ok();
    if let Err(refusal) = may_operate(&shared, &who, action, None) {
        return refusal.into_response();
    }
    let work = schemas::WorkOrder {
        product: form.product,
        count: form.count,
        priority: form.priority,
        due: form
            .due_in_s
            .map(|s| schemas::unix_ms().saturating_add(s.saturating_mul(1000))),
        queue: form.queue,
    };
    if let Err(e) = work.validate() {
        let why = e.to_string();
        record(
            &shared,
            &who,
            action,
            None,
            detail,
            AuditOutcome::Refused(why.clone()),
        );
        return refused(StatusCode::BAD_REQUEST, &why);
    }
    match crate::submit::submit(
        &shared.session,
        &shared.keys,
        &work,
        &by(&shared, &who),
        ANSWER_WITHIN,
    )
    .await
    {
        Ok(orders) => {
            info!(user = %who.who, by = %by(&shared, &who), orders = ?orders, product = %work.product, "work order submitted");
            record(
                &shared,
                &who,
                action,
                Some(&orders.join(",")),
                detail,
                AuditOutcome::Done,
            );
            Json(serde_json::json!({ "orders": orders })).into_response()
        }
        Err(e @ crate::ask::AskError::Refused { .. }) => {
            let why = e.to_string();
            let outcome = AuditOutcome::Refused(why.clone());
            record(&shared, &who, action, None, detail, outcome);
            refused(StatusCode::CONFLICT, &why)
        }
        Err(e) => {
            let why = e.to_string();
            let outcome = AuditOutcome::Failed(why.clone());
            record(&shared, &who, action, None, detail, outcome);
            refused(StatusCode::BAD_GATEWAY, &why)
        }
    }
}

/// `POST /api/orders/{name}/cancel`: the order-node's answer.
pub async fn cancel(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
) -> Response {
    let action = AuditAction::Cancel;
    if let Err(refusal) = may_operate(&shared, &who, action, Some(&name)) {
        return refusal.into_response();
    }
    if let Err(e) = schemas::HolonId::order(&name) {
        let why = e.to_string();
        record(
            &shared,
            &who,
            action,
            Some(&name),
            None,
            AuditOutcome::Refused(why.clone()),
        );
        return refused(StatusCode::BAD_REQUEST, &why);
    }
    match crate::status::cancel(
        &shared.session,
        &shared.keys,
        &name,
        &by(&shared, &who),
        ANSWER_WITHIN,
    )
    .await
    {
        Ok(reply) => {
            info!(user = %who.who, by = %by(&shared, &who), order = %name, cancelled = reply.cancelled, "cancel asked");
            let outcome = if reply.cancelled {
                AuditOutcome::Done
            } else {
                AuditOutcome::Refused(reply.detail.clone())
            };
            record(&shared, &who, action, Some(&name), None, outcome);
            Json(reply).into_response()
        }
        Err(e @ crate::ask::AskError::Refused { .. }) => {
            let why = e.to_string();
            let outcome = AuditOutcome::Refused(why.clone());
            record(&shared, &who, action, Some(&name), None, outcome);
            refused(StatusCode::CONFLICT, &why)
        }
        Err(e) => {
            let why = e.to_string();
            let outcome = AuditOutcome::Failed(why.clone());
            record(&shared, &who, action, Some(&name), None, outcome);
            refused(StatusCode::BAD_GATEWAY, &why)
        }
    }
}

/// `POST /api/resources/{name}/packml`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PackmlForm {
    command: schemas::PackmlCommand,
}

/// `POST /api/resources/{name}/packml`: the resource's answer, or its refusal (409).
pub async fn packml(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
    Json(form): Json<PackmlForm>,
) -> Response {
    let action = AuditAction::Packml;
    let detail = Some(serde_json::json!({ "command": form.command }));
    if let Err(refusal) = may_operate(&shared, &who, action, Some(&name)) {
        return refusal.into_response();
    }
    if let Err(e) = schemas::validate_name("resource", &name) {
        let why = e.to_string();
        record(
            &shared,
            &who,
            action,
            Some(&name),
            detail,
            AuditOutcome::Refused(why.clone()),
        );
        return refused(StatusCode::BAD_REQUEST, &why);
    }
    let request = schemas::PackmlRequest::command(form.command, &by(&shared, &who));
    match crate::packml::ask(
        &shared.session,
        &shared.keys,
        &name,
        &request,
        ANSWER_WITHIN,
    )
    .await
    {
        Ok(reply) if reply.refused.is_some() => {
            let why = reply.detail.clone().unwrap_or_default();
            record(
                &shared,
                &who,
                action,
                Some(&name),
                detail,
                AuditOutcome::Refused(why.clone()),
            );
            (
                StatusCode::CONFLICT,
                Json(serde_json::json!({ "error": why, "reply": reply })),
            )
                .into_response()
        }
        Ok(reply) => {
            record(
                &shared,
                &who,
                action,
                Some(&name),
                detail,
                AuditOutcome::Done,
            );
            Json(reply).into_response()
        }
        Err(e) => {
            let why = format!("{e:#}");
            record(
                &shared,
                &who,
                action,
                Some(&name),
                detail,
                AuditOutcome::Failed(why.clone()),
            );
            refused(StatusCode::BAD_GATEWAY, &why)
        }
    }
}

//! What an operator does from the page: submit and cancel orders, acknowledge alarms,
//! command resources. Each action is checked against the user's role and the
//! dashboard's own, carried out, and recorded in the audit trail with who, from where,
//! what and how it ended, refusals included ([`Act`]).

use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use tracing::info;

use super::gate::Who;
use super::refusal::{refused, Refusal};
use super::{Command, Shared};
use crate::client::ask::AskError;
use crate::security::audit::{AuditAction, AuditOutcome, AuditRecord};

/// How long the cell has to answer an action.
const ANSWER_WITHIN: Duration = Duration::from_secs(5);

/// One action of one user, from its check to its answer: every way it ends is
/// recorded once in the audit trail, with the answer the page gets.
struct Act<'a> {
    /// The dashboard.
    shared: &'a Shared,
    /// Who acts.
    who: &'a Who,
    /// What.
    action: AuditAction,
    /// On what (an order, a resource, an alarm), when known.
    target: Option<String>,
    /// The request's particulars, as given.
    detail: Option<serde_json::Value>,
}

impl<'a> Act<'a> {
    /// `who`'s `action` on `target`: refused (and recorded) unless both the user's role
    /// and the dashboard's own identity may operate.
    fn begin(
        shared: &'a Shared,
        who: &'a Who,
        action: AuditAction,
        target: Option<&str>,
        detail: Option<serde_json::Value>,
    ) -> Result<Act<'a>, Refusal> {
        let act = Act {
            shared,
            who,
            action,
            target: target.map(String::from),
            detail,
        };
        if !shared.operator {
            return Err(act.refusal(
                StatusCode::FORBIDDEN,
                "this dashboard is read-only (it joined the cell as an observer; start it with --operator or an operator.* identity)".into(),
            ));
        }
        if !who.role.may_operate() {
            let why = format!("{} is an observer: observers change nothing", who.who);
            return Err(act.refusal(StatusCode::FORBIDDEN, why));
        }
        Ok(act)
    }

    /// Who commands, as the holons log it: the dashboard's identity and the user.
    fn by(&self) -> String {
        format!("dashboard {} for {}", self.shared.identity, self.who.who)
    }

    /// Records how the action ended.
    fn record(&self, outcome: AuditOutcome) {
        let mut record = AuditRecord::now(
            &self.who.who,
            &self.who.from.to_string(),
            self.action,
            outcome,
        );
        record.target = self.target.clone();
        record.detail = self.detail.clone();
        self.shared.gate.record(record);
    }

    /// Done: recorded, and `answer` for the page.
    fn done(&self, answer: Response) -> Response {
        self.record(AuditOutcome::Done);
        answer
    }

    /// Refused (the cell did not change): recorded, answered with `status`.
    fn refuse(&self, status: StatusCode, why: String) -> Response {
        self.refusal(status, why).into_response()
    }

    /// The same, as a value.
    fn refusal(&self, status: StatusCode, why: String) -> Refusal {
        self.record(AuditOutcome::Refused(why.clone()));
        Refusal { status, why }
    }

    /// Tried and failed: recorded, answered with `status`.
    fn fail(&self, status: StatusCode, why: String) -> Response {
        self.record(AuditOutcome::Failed(why.clone()));
        refused(status, &why)
    }

    /// An order-node's refusal (409), or a failure to reach one (502).
    fn asked(&self, error: AskError) -> Response {
        match error {
            AskError::Refused { .. } => self.refuse(StatusCode::CONFLICT, error.to_string()),
            _ => self.fail(StatusCode::BAD_GATEWAY, error.to_string()),
        }
    }
}

/// `POST /api/alarms/{id}/ack`.
pub async fn acknowledge(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(id): Path<u64>,
) -> Response {
    let target = id.to_string();
    let act = match Act::begin(
        &shared,
        &who,
        AuditAction::AcknowledgeAlarm,
        Some(&target),
        None,
    ) {
        Ok(act) => act,
        Err(refusal) => return refusal.into_response(),
    };
    let by = who.who.clone();
    match shared.commands.send(Command::Acknowledge { id, by }).await {
        Ok(()) => {
            info!(user = %who.who, alarm = id, "alarm acknowledged");
            act.done(StatusCode::NO_CONTENT.into_response())
        }
        Err(_) => act.fail(
            StatusCode::SERVICE_UNAVAILABLE,
            "the dashboard is stopping".into(),
        ),
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
    /// A name for the work order (optional, `WorkOrder::submit_id`): posted again
    /// under it (a double click, a retry), the same orders and no more. The page
    /// gives one to each work order filled in.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    submit_id: Option<String>,
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
    let detail = serde_json::to_value(&form).ok();
    let mut act = match Act::begin(&shared, &who, AuditAction::Submit, None, detail) {
        Ok(act) => act,
        Err(refusal) => return refusal.into_response(),
    };
    let work = schemas::WorkOrder {
        product: form.product,
        count: form.count,
        priority: form.priority,
        due: form
            .due_in_s
            .map(|s| schemas::unix_ms().saturating_add(s.saturating_mul(1000))),
        queue: form.queue,
        submit_id: form.submit_id,
    };
    if let Err(e) = work.validate() {
        return act.refuse(StatusCode::BAD_REQUEST, e.to_string());
    }
    let by = act.by();
    match crate::client::submit::submit(&shared.session, &shared.keys, &work, &by, ANSWER_WITHIN)
        .await
    {
        Ok(orders) => {
            info!(user = %who.who, %by, orders = ?orders, product = %work.product, "work order submitted");
            act.target = Some(orders.join(","));
            act.done(Json(serde_json::json!({ "orders": orders })).into_response())
        }
        Err(e) => act.asked(e),
    }
}

/// `POST /api/orders/{name}/cancel`: the order-node's answer.
pub async fn cancel(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
) -> Response {
    let act = match Act::begin(&shared, &who, AuditAction::Cancel, Some(&name), None) {
        Ok(act) => act,
        Err(refusal) => return refusal.into_response(),
    };
    if let Err(e) = schemas::HolonId::order(&name) {
        return act.refuse(StatusCode::BAD_REQUEST, e.to_string());
    }
    let by = act.by();
    match crate::client::status::cancel(&shared.session, &shared.keys, &name, &by, ANSWER_WITHIN)
        .await
    {
        Ok(reply) => {
            info!(user = %who.who, %by, order = %name, cancelled = reply.cancelled, "cancel asked");
            if reply.cancelled {
                act.done(Json(reply).into_response())
            } else {
                act.record(AuditOutcome::Refused(reply.detail.clone()));
                Json(reply).into_response()
            }
        }
        Err(e) => act.asked(e),
    }
}

/// `POST /api/orders/{name}/part`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PartForm {
    /// Where the lost part is: one end of its lost move (`robot1.port`).
    at: String,
}

/// `POST /api/orders/{name}/part`: an operator says where the order's lost part is
/// (docs/material-flow.md, section 2); the order-node's answer, or its refusal (409).
pub async fn part_found(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
    Json(form): Json<PartForm>,
) -> Response {
    let detail = Some(serde_json::json!({ "at": form.at }));
    let act = match Act::begin(&shared, &who, AuditAction::PartFound, Some(&name), detail) {
        Ok(act) => act,
        Err(refusal) => return refusal.into_response(),
    };
    if let Err(e) = schemas::HolonId::order(&name) {
        return act.refuse(StatusCode::BAD_REQUEST, e.to_string());
    }
    let at = match schemas::layout::LocationId::try_from(form.at) {
        Ok(at) => at,
        Err(e) => return act.refuse(StatusCode::BAD_REQUEST, e),
    };
    let by = act.by();
    let told = crate::client::part_word::tell(
        &shared.session,
        &shared.keys,
        &name,
        &at,
        &by,
        ANSWER_WITHIN,
    );
    match told.await {
        Ok(reply) => {
            info!(user = %who.who, %by, order = %name, %at, "said where a lost part is");
            act.done(Json(reply).into_response())
        }
        Err(e) => act.asked(e),
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
    let detail = Some(serde_json::json!({ "command": form.command }));
    let act = match Act::begin(&shared, &who, AuditAction::Packml, Some(&name), detail) {
        Ok(act) => act,
        Err(refusal) => return refusal.into_response(),
    };
    if let Err(e) = schemas::validate_name("resource", &name) {
        return act.refuse(StatusCode::BAD_REQUEST, e.to_string());
    }
    let request = schemas::PackmlRequest::command(form.command, &act.by());
    match crate::client::packml::ask(
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
            act.record(AuditOutcome::Refused(why.clone()));
            (
                StatusCode::CONFLICT,
                Json(serde_json::json!({ "error": why, "reply": reply })),
            )
                .into_response()
        }
        Ok(reply) => act.done(Json(reply).into_response()),
        Err(e) => act.fail(StatusCode::BAD_GATEWAY, format!("{e:#}")),
    }
}

//! Admins manage the cell's users from the page: list, add, change a password or a
//! role, remove. The same users file as `cell users` (and the OPC UA server), changed
//! under its lock; every change is recorded in the audit trail and ends the changed
//! user's sessions.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use tracing::info;

use super::gate::Who;
use super::refusal::{refused, Refusal};
use super::Shared;
use crate::security::audit::{AuditAction, AuditOutcome, AuditRecord};
use crate::security::users::{self, Role};

/// The users file, if `who` may manage users: or the refusal (recorded when it refuses
/// a change, `action`).
fn may_manage(
    shared: &Shared,
    who: &Who,
    action: Option<AuditAction>,
    target: Option<&str>,
) -> Result<std::path::PathBuf, Refusal> {
    let (status, why) = match &shared.gate.config.users {
        Some(path) if who.role.may_manage_users() => return Ok(path.clone()),
        Some(_) => (
            StatusCode::FORBIDDEN,
            format!("{} is not an admin: only admins manage users", who.who),
        ),
        None => (
            StatusCode::NOT_FOUND,
            "this dashboard has no users file (start it with --users FILE, or --pki)".to_string(),
        ),
    };
    if let Some(action) = action {
        let mut record = AuditRecord::now(
            &who.who,
            &who.from.to_string(),
            action,
            AuditOutcome::Refused(why.clone()),
        );
        record.target = target.map(String::from);
        shared.gate.record(record);
    }
    Err(Refusal { status, why })
}

/// Changes the users file with `change` and records it: the answer.
async fn change_users(
    shared: &Shared,
    who: &Who,
    action: AuditAction,
    name: &str,
    detail: Option<serde_json::Value>,
    change: impl FnOnce(&mut users::Users) -> Result<(), users::UsersError> + Send + 'static,
) -> Response {
    let path = match may_manage(shared, who, Some(action), Some(name)) {
        Ok(path) => path,
        Err(refusal) => return refusal.into_response(),
    };
    let changed = tokio::task::spawn_blocking(move || users::change(&path, change)).await;
    let (outcome, response) = match changed {
        Ok(Ok(())) => {
            shared.gate.end_sessions_of(name);
            info!(user = %who.who, changed = name, action = ?action, "users file changed");
            (AuditOutcome::Done, StatusCode::NO_CONTENT.into_response())
        }
        Ok(Err(e)) => {
            let why = e.to_string();
            (
                AuditOutcome::Refused(why.clone()),
                refused(StatusCode::CONFLICT, &why),
            )
        }
        Err(e) => {
            let why = format!("the change ended abnormally: {e}");
            (
                AuditOutcome::Failed(why.clone()),
                refused(StatusCode::INTERNAL_SERVER_ERROR, &why),
            )
        }
    };
    let mut record = AuditRecord::now(&who.who, &who.from.to_string(), action, outcome).on(name);
    record.detail = detail;
    shared.gate.record(record);
    response
}

/// `GET /api/users`: every user's name and role (never a hash).
pub async fn list(State(shared): State<Arc<Shared>>, Extension(who): Extension<Who>) -> Response {
    if let Err(refusal) = may_manage(&shared, &who, None, None) {
        return refusal.into_response();
    }
    let users = shared.gate.users();
    let rows: Vec<serde_json::Value> = users
        .iter()
        .map(|u| serde_json::json!({ "name": u.name, "role": u.role }))
        .collect();
    Json(rows).into_response()
}

/// `POST /api/users`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewUser {
    name: String,
    role: Role,
    password: String,
}

/// `POST /api/users`: adds a user.
pub async fn add(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Json(new): Json<NewUser>,
) -> Response {
    let name = new.name.clone();
    let detail = Some(serde_json::json!({ "role": new.role }));
    change_users(
        &shared,
        &who,
        AuditAction::UserAdd,
        &name,
        detail,
        move |users| users.add(&new.name, new.role, &new.password),
    )
    .await
}

/// `POST /api/users/{name}/password`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewPassword {
    password: String,
}

/// `POST /api/users/{name}/password`: sets a user's password.
pub async fn password(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
    Json(new): Json<NewPassword>,
) -> Response {
    let target = name.clone();
    change_users(
        &shared,
        &who,
        AuditAction::UserPassword,
        &target,
        None,
        move |users| users.set_password(&name, &new.password),
    )
    .await
}

/// `POST /api/users/{name}/role`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewRole {
    role: Role,
}

/// `POST /api/users/{name}/role`: sets a user's role.
pub async fn role(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
    Json(new): Json<NewRole>,
) -> Response {
    let target = name.clone();
    let detail = Some(serde_json::json!({ "role": new.role }));
    change_users(
        &shared,
        &who,
        AuditAction::UserRole,
        &target,
        detail,
        move |users| users.set_role(&name, new.role).map(|_| ()),
    )
    .await
}

/// `POST /api/users/{name}/remove`: removes a user.
pub async fn remove(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
    Path(name): Path<String>,
) -> Response {
    let target = name.clone();
    change_users(
        &shared,
        &who,
        AuditAction::UserRemove,
        &target,
        None,
        move |users| users.remove(&name).map(|_| ()),
    )
    .await
}

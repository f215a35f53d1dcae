//! The dashboard's web server: the page, its live updates, the JSON API and `/metrics`.
//!
//! | route | what |
//! |---|---|
//! | `GET /` | the page (embedded; no external asset) |
//! | `GET /events` | server-sent events: `view`, the whole view, at once and after every change (at most every 250 ms) |
//! | `GET /api/view`, `/api/holons`, `/api/orders`, `/api/alarms`, `/api/events` | JSON |
//! | `POST /api/orders` | submit a work order, `{"product", "count", "queue"}` (operator dashboards only) |
//! | `POST /api/alarms/{id}/ack` | acknowledge an alarm (operator dashboards only) |
//! | `POST /api/resources/{name}/packml` | a PackML command, `{"command": "hold"}` (operator dashboards only): the resource's answer, or why it refused (409) |
//! | `GET /metrics` | Prometheus text format |
//!
//! Every request passes [`super::guard`] first: its `Host` must be the dashboard's own,
//! and a change (POST) must come from the dashboard's own page (`Origin`) as JSON.

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::stream::{self, Stream};
use serde::Deserialize;
use tracing::warn;

use super::{metrics, Command, Shared, View};

/// The page: HTML, CSS and script in one file, compiled in.
const PAGE: &str = include_str!("page.html");

/// The routes, behind the [`guard`](super::guard) that keeps other sites out.
pub fn router(shared: Arc<Shared>, guard: Arc<super::guard::Guard>) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/events", get(events))
        .route("/api/view", get(view))
        .route("/api/holons", get(holons))
        .route("/api/orders", get(orders).post(submit))
        .route("/api/alarms", get(alarms))
        .route("/api/alarms/{id}/ack", post(acknowledge))
        .route("/api/resources/{name}/packml", post(packml))
        .route("/api/events", get(event_log))
        .route("/metrics", get(prometheus))
        .with_state(shared)
        .layer(axum::middleware::from_fn_with_state(
            guard,
            super::guard::check,
        ))
}

fn current(shared: &Shared) -> Arc<View> {
    shared.view.borrow().clone()
}

async fn page() -> Html<&'static str> {
    Html(PAGE)
}

async fn events(
    State(shared): State<Arc<Shared>>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let mut views = shared.view.clone();
    views.mark_changed();
    let updates = stream::unfold(views, |mut views| async move {
        views.changed().await.ok()?;
        let view = views.borrow_and_update().clone();
        let event = match Event::default().event("view").json_data(&*view) {
            Ok(event) => event,
            Err(e) => {
                warn!(error = %e, "cannot encode the view for a page");
                Event::default().comment("the view could not be encoded")
            }
        };
        Some((Ok(event), views))
    });
    Sse::new(updates).keep_alive(KeepAlive::new().interval(Duration::from_secs(10)))
}

async fn view(State(shared): State<Arc<Shared>>) -> Json<View> {
    Json((*current(&shared)).clone())
}

async fn holons(State(shared): State<Arc<Shared>>) -> Response {
    Json(&current(&shared).holons).into_response()
}

async fn orders(State(shared): State<Arc<Shared>>) -> Response {
    Json(&current(&shared).orders).into_response()
}

async fn alarms(State(shared): State<Arc<Shared>>) -> Response {
    Json(&current(&shared).alarms).into_response()
}

async fn event_log(State(shared): State<Arc<Shared>>) -> Response {
    Json(&current(&shared).events).into_response()
}

async fn prometheus(State(shared): State<Arc<Shared>>) -> Response {
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        metrics::render(&current(&shared)),
    )
        .into_response()
}

fn refused(status: StatusCode, message: &str) -> Response {
    (status, Json(serde_json::json!({ "error": message }))).into_response()
}

const READ_ONLY: &str =
    "this dashboard is read-only (start it with --operator to submit and acknowledge)";

async fn acknowledge(State(shared): State<Arc<Shared>>, Path(id): Path<u64>) -> Response {
    if !shared.operator {
        return refused(StatusCode::FORBIDDEN, READ_ONLY);
    }
    match shared.commands.send(Command::Acknowledge(id)).await {
        Ok(()) => StatusCode::NO_CONTENT.into_response(),
        Err(_) => refused(StatusCode::SERVICE_UNAVAILABLE, "the dashboard is stopping"),
    }
}

#[derive(Debug, Deserialize)]
struct SubmitForm {
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

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PackmlForm {
    command: schemas::PackmlCommand,
}

async fn packml(
    State(shared): State<Arc<Shared>>,
    Path(name): Path<String>,
    Json(form): Json<PackmlForm>,
) -> Response {
    if !shared.operator {
        return refused(StatusCode::FORBIDDEN, READ_ONLY);
    }
    if let Err(e) = schemas::validate_name("resource", &name) {
        return refused(StatusCode::BAD_REQUEST, &e.to_string());
    }
    let by = format!("dashboard {}", shared.identity);
    let request = schemas::PackmlRequest::command(form.command, &by);
    match crate::packml::ask(
        &shared.session,
        &shared.keys,
        &name,
        &request,
        Duration::from_secs(5),
    )
    .await
    {
        Ok(reply) if reply.refused.is_some() => {
            let why = reply.detail.clone().unwrap_or_default();
            (
                StatusCode::CONFLICT,
                Json(serde_json::json!({ "error": why, "reply": reply })),
            )
                .into_response()
        }
        Ok(reply) => Json(reply).into_response(),
        Err(e) => refused(StatusCode::BAD_GATEWAY, &format!("{e:#}")),
    }
}

fn one() -> u32 {
    1
}

async fn submit(State(shared): State<Arc<Shared>>, Json(form): Json<SubmitForm>) -> Response {
    if !shared.operator {
        return refused(StatusCode::FORBIDDEN, READ_ONLY);
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
        return refused(StatusCode::BAD_REQUEST, &e.to_string());
    }
    match crate::submit::submit(&shared.session, &shared.keys, &work, Duration::from_secs(5)).await
    {
        Ok(orders) => Json(serde_json::json!({ "orders": orders })).into_response(),
        Err(e) => refused(StatusCode::BAD_GATEWAY, &format!("{e:#}")),
    }
}

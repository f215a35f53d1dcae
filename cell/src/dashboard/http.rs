//! The dashboard's web server: the page, its live updates, the JSON API and `/metrics`.
//!
//! | route | who | what |
//! |---|---|---|
//! | `GET /login`, `POST /api/login` | anybody | the login page; `{"name", "password"}` opens a session (cookie) |
//! | `POST /api/logout` | logged in | ends the session |
//! | `GET /api/me` | logged in | who, the role, what the page may offer |
//! | `GET /` | logged in | the page (embedded; no external asset) |
//! | `GET /events` | logged in | server-sent events: `view`, the whole view, at once and after every change (at most every 250 ms); ends with the session |
//! | `GET /api/view`, `/api/holons`, `/api/orders`, `/api/alarms`, `/api/events` | logged in | JSON |
//! | `GET /api/orders/history?node=N&status=S&before=B&limit=L` | logged in | a page of order-node N's finished orders from its journal, newest first (`status`: finished, done, scrapped, failed or cancelled; `before`: an order number, the previous page's last; `limit` at most 200): the node's `OrderPage` (`schemas::listing`), 502 with why when it does not answer |
//! | `GET /metrics` | logged in | Prometheus text format |
//! | `POST /api/orders` | operator | submit a work order, `{"product", "count", "queue", "priority", "due_in_s"}` |
//! | `POST /api/orders/{name}/cancel` | operator | cancel an order |
//! | `POST /api/alarms/{id}/ack` | operator | acknowledge an alarm |
//! | `POST /api/resources/{name}/packml` | operator | a PackML command, `{"command": "hold"}`: the resource's answer, or why it refused (409) |
//! | `GET /api/audit`, `/api/audit.jsonl` | operator | the audit trail: the newest 500 records, newest first; the whole trail as JSON lines |
//! | `GET /api/users`, `POST /api/users`, `POST /api/users/{name}/password`, `/role`, `/remove` | admin | the users ([`super::people`]) |
//!
//! Every request passes [`super::guard`] first (its `Host` must be the dashboard's
//! own, a change must come from the dashboard's own page as JSON, and plain HTTP is
//! sent to HTTPS when the dashboard serves it), then [`super::gate`] (who it is).

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Extension, Json, Router};
use futures_util::stream::{self, Stream};
use tracing::warn;

use super::gate::{self, Gate, Who};
use super::refusal::{refused, Refusal};
use super::{actions, metrics, people, Shared, View};

/// The page: HTML, CSS and script in one file, compiled in.
const PAGE: &str = include_str!("page.html");

/// How many audit records `GET /api/audit` returns.
const AUDIT_SHOWN: usize = 500;

/// The routes, behind the [`guard`](super::guard) that keeps other sites out and the
/// [`gate`] that finds who asks.
pub fn router(shared: Arc<Shared>, guard: Arc<super::guard::Guard>) -> Router {
    let gate = shared.gate.clone();
    Router::new()
        .route("/", get(page))
        .route("/login", get(gate::login_page))
        .route("/api/login", post(gate::login))
        .route("/api/logout", post(gate::logout))
        .route("/api/me", get(me))
        .route("/events", get(events))
        .route("/api/view", get(view))
        .route("/api/holons", get(holons))
        .route("/api/orders", get(orders).post(actions::submit))
        .route("/api/orders/history", get(history))
        .route("/api/orders/{name}/cancel", post(actions::cancel))
        .route("/api/orders/{name}/part", post(actions::part_found))
        .route("/api/alarms", get(alarms))
        .route("/api/alarms/{id}/ack", post(actions::acknowledge))
        .route("/api/resources/{name}/packml", post(actions::packml))
        .route("/api/events", get(event_log))
        .route("/api/audit", get(audit))
        .route("/api/audit.jsonl", get(audit_export))
        .route("/api/users", get(people::list).post(people::add))
        .route("/api/users/{name}/password", post(people::password))
        .route("/api/users/{name}/role", post(people::role))
        .route("/api/users/{name}/remove", post(people::remove))
        .route("/metrics", get(prometheus))
        .layer(axum::middleware::from_fn_with_state(
            gate.clone(),
            gate::authenticate,
        ))
        .layer(Extension(gate))
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

async fn me(State(shared): State<Arc<Shared>>, Extension(who): Extension<Who>) -> Response {
    Json(gate::me(&shared.gate, &who, shared.operator)).into_response()
}

async fn events(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let mut views = shared.view.clone();
    views.mark_changed();
    let gate = shared.gate.clone();
    let updates = stream::unfold((views, gate, who), |(mut views, gate, who)| async move {
        views.changed().await.ok()?;
        // The stream ends with the session: the page then finds it must log in again.
        if !gate.still_in(&who) {
            return None;
        }
        let view = views.borrow_and_update().clone();
        let event = match Event::default().event("view").json_data(&*view) {
            Ok(event) => event,
            Err(e) => {
                warn!(error = %e, "cannot encode the view for a page");
                Event::default().comment("the view could not be encoded")
            }
        };
        Some((Ok(event), (views, gate, who)))
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

/// What `GET /api/orders/history` asks for.
#[derive(Debug, Default, PartialEq)]
struct HistoryQuery {
    /// The order-node.
    node: String,
    /// `finished` (default) or one final status.
    status: Option<String>,
    /// Orders numbered below this one (the previous page's last).
    before: Option<u64>,
    /// At most this many (default 50, at most 200).
    limit: Option<u32>,
}

impl HistoryQuery {
    /// Reads `node=N&status=S&before=B&limit=L` (names, statuses and numbers: nothing
    /// that needs decoding); an unknown or malformed parameter is refused.
    fn parse(query: &str) -> Result<HistoryQuery, String> {
        let mut read = HistoryQuery::default();
        for pair in query.split('&').filter(|p| !p.is_empty()) {
            let (key, value) = pair.split_once('=').unwrap_or((pair, ""));
            let number = |what: &str| {
                value
                    .parse::<u64>()
                    .map_err(|_| format!("{what} must be a number, not {value:?}"))
            };
            match key {
                "node" => read.node = value.to_string(),
                "status" => read.status = Some(value.to_string()),
                "before" => read.before = Some(number("before")?),
                "limit" => read.limit = Some(number("limit")?.min(u32::MAX as u64) as u32),
                other => {
                    return Err(format!(
                        "unknown parameter {other:?} (node, status, before, limit)"
                    ))
                }
            }
        }
        Ok(read)
    }
}

/// A page of a node's finished orders, read from its journal by the node
/// ([`crate::client::listing::page`]): the page shows the newest it heard of, and older ones
/// a page at a time from here.
async fn history(State(shared): State<Arc<Shared>>, uri: axum::http::Uri) -> Response {
    let query = match HistoryQuery::parse(uri.query().unwrap_or("")) {
        Ok(query) => query,
        Err(why) => return refused(StatusCode::BAD_REQUEST, &why),
    };
    let filter = match query.status.as_deref().unwrap_or("finished") {
        "running" => Err("the history is of finished orders".to_string()),
        status => schemas::OrderFilter::parse(status),
    };
    let filter = match filter {
        Ok(filter) => filter,
        Err(why) => return refused(StatusCode::BAD_REQUEST, &why),
    };
    if schemas::validate_name("order-node", &query.node).is_err() {
        return refused(
            StatusCode::BAD_REQUEST,
            &format!("{:?} is not an order-node's name", query.node),
        );
    }
    let mut request = schemas::OrderListRequest::first(filter, query.limit.unwrap_or(50));
    request.after = query.before.map(schemas::PageCursor::AfterFinished);
    match crate::client::listing::page(
        &shared.session,
        &shared.keys,
        &query.node,
        &request,
        HISTORY_TIMEOUT,
    )
    .await
    {
        Ok(page) => Json(page).into_response(),
        Err(e) => refused(
            StatusCode::BAD_GATEWAY,
            &format!("order-node {}: {e}", query.node),
        ),
    }
}

/// How long `GET /api/orders/history` waits for the node's page.
const HISTORY_TIMEOUT: Duration = Duration::from_secs(5);

async fn alarms(State(shared): State<Arc<Shared>>) -> Response {
    Json(&current(&shared).alarms).into_response()
}

async fn event_log(State(shared): State<Arc<Shared>>) -> Response {
    Json(&current(&shared).events).into_response()
}

async fn prometheus(State(shared): State<Arc<Shared>>) -> Response {
    let mut text = metrics::render(&current(&shared));
    text.push_str(&metrics::render_gate(&shared.gate));
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], text).into_response()
}

/// Whether `who` may read the audit trail: the trail, or the refusal.
fn audit_path<'a>(gate: &'a Gate, who: &Who) -> Result<&'a std::path::Path, Refusal> {
    let Some(trail) = &gate.audit else {
        return Err(Refusal {
            status: StatusCode::NOT_FOUND,
            why: "this dashboard keeps no audit trail (it has no users file and no --audit)".into(),
        });
    };
    if !who.role.may_operate() {
        return Err(Refusal {
            status: StatusCode::FORBIDDEN,
            why: format!(
                "{} is an observer: the audit trail is for operators and admins",
                who.who
            ),
        });
    }
    Ok(trail.path())
}

async fn audit(State(shared): State<Arc<Shared>>, Extension(who): Extension<Who>) -> Response {
    let path = match audit_path(&shared.gate, &who) {
        Ok(path) => path.to_path_buf(),
        Err(refusal) => return refusal.into_response(),
    };
    match tokio::task::spawn_blocking(move || crate::security::audit::newest(&path, AUDIT_SHOWN))
        .await
    {
        Ok(Ok(records)) => Json(records).into_response(),
        Ok(Err(e)) => refused(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
        Err(e) => refused(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

async fn audit_export(
    State(shared): State<Arc<Shared>>,
    Extension(who): Extension<Who>,
) -> Response {
    let path = match audit_path(&shared.gate, &who) {
        Ok(path) => path.to_path_buf(),
        Err(refusal) => return refusal.into_response(),
    };
    match tokio::fs::read(&path).await {
        Ok(bytes) => (
            [
                (header::CONTENT_TYPE, "application/jsonl"),
                (
                    header::CONTENT_DISPOSITION,
                    "attachment; filename=\"audit.jsonl\"",
                ),
            ],
            bytes,
        )
            .into_response(),
        Err(e) => refused(
            StatusCode::INTERNAL_SERVER_ERROR,
            &format!("cannot read the audit trail {}: {e}", path.display()),
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::HistoryQuery;

    #[test]
    fn a_history_query_reads_its_parameters_and_refuses_others() {
        assert_eq!(
            HistoryQuery::parse("node=orders1&status=failed&before=120&limit=50").unwrap(),
            HistoryQuery {
                node: "orders1".into(),
                status: Some("failed".into()),
                before: Some(120),
                limit: Some(50),
            }
        );
        assert!(HistoryQuery::parse("node=orders1&before=x")
            .unwrap_err()
            .contains("before must be a number"));
        assert!(HistoryQuery::parse("node=o&page=2")
            .unwrap_err()
            .contains("unknown parameter"));
    }
}

//! Who may reach the dashboard: a web page of another site may not, through an
//! operator's browser.
//!
//! | request | checked | refused with |
//! |---|---|---|
//! | any | its `Host` is the dashboard's own: an IP address (v4 or v6), `localhost` when it listens on loopback or every address, or a name it was given, with the port it listens on | 421 Misdirected Request (a DNS-rebound page names its own site) |
//! | one that changes something (every method but GET and HEAD) | an `Origin` header naming this very host and port (the page's own, which a browser always sends with a POST) | 403 (a cross-site form or script) |
//! | the same | a JSON body (`content-type: application/json`, which a cross-site form cannot send) | 415 |
//!
//! Every answer carries headers that keep it out of other sites' frames and stop a
//! browser from guessing types (`X-Frame-Options: DENY`, `Content-Security-Policy:
//! frame-ancestors 'none'`, `X-Content-Type-Options: nosniff`, `Referrer-Policy:
//! same-origin`).
//!
//! A dashboard that serves HTTPS answers a plain HTTP request (on the same port) only
//! with a redirect (308) to the same path over HTTPS, once its `Host` passed.
//!
//! Who may do what is the [`gate`](super::gate)'s business, after this: anyone who
//! reaches the port with a tool of their own is not a web page, and only a login
//! stops them.

use std::net::{IpAddr, SocketAddr};
use std::sync::Arc;

use axum::extract::{ConnectInfo, Request, State};
use axum::http::{header, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use axum::Json;
use tracing::warn;

use super::listener::Peer;

/// The names and port the dashboard answers to.
#[derive(Debug, Clone)]
pub struct Guard {
    /// The port it listens on (a `Host` without one means 80).
    port: u16,
    /// Whether `localhost` is one of its names (it listens on loopback or everywhere).
    localhost: bool,
    /// Other names it answers to, lower case.
    names: Vec<String>,
    /// Whether it serves HTTPS (plain HTTP is then only redirected).
    https: bool,
}

impl Guard {
    /// A guard for a dashboard bound to `bound`, also answering to `names`.
    pub fn new(bound: SocketAddr, names: &[String], https: bool) -> Guard {
        Guard {
            https,
            port: bound.port(),
            localhost: bound.ip().is_loopback() || bound.ip().is_unspecified(),
            names: names.iter().map(|n| n.to_ascii_lowercase()).collect(),
        }
    }

    /// Whether `host` (a `Host` header's value) names this dashboard.
    pub fn host_allowed(&self, host: &str) -> bool {
        let Some((name, port)) = split_host(host) else {
            return false;
        };
        if port != self.port {
            return false;
        }
        let name = name.to_ascii_lowercase();
        name.parse::<IpAddr>().is_ok()
            || (self.localhost && name == "localhost")
            || self.names.contains(&name)
    }

    /// Why a request may not go on, if it may not.
    fn refusal(&self, request: &Request) -> Option<(StatusCode, String)> {
        let host = request
            .headers()
            .get(header::HOST)
            .and_then(|h| h.to_str().ok())
            .unwrap_or("");
        if !self.host_allowed(host) {
            return Some((
                StatusCode::MISDIRECTED_REQUEST,
                format!("this dashboard does not answer to the host {host:?}"),
            ));
        }
        if matches!(*request.method(), Method::GET | Method::HEAD) {
            return None;
        }
        let origin = request
            .headers()
            .get(header::ORIGIN)
            .and_then(|o| o.to_str().ok());
        let same = origin
            .and_then(|o| o.split_once("://").map(|(_, rest)| rest))
            .is_some_and(|authority| authority.eq_ignore_ascii_case(host));
        if !same {
            return Some((
                StatusCode::FORBIDDEN,
                format!(
                    "a change must come from this dashboard's own page (Origin {}), not {}",
                    host,
                    origin.unwrap_or("a request without Origin")
                ),
            ));
        }
        let json = request
            .headers()
            .get(header::CONTENT_TYPE)
            .and_then(|c| c.to_str().ok())
            .is_some_and(|c| c.to_ascii_lowercase().starts_with("application/json"));
        if !json {
            return Some((
                StatusCode::UNSUPPORTED_MEDIA_TYPE,
                "a change must be sent as application/json".into(),
            ));
        }
        None
    }
}

/// Splits `name:port`, `[v6]:port` or a bare name (port 80).
fn split_host(host: &str) -> Option<(&str, u16)> {
    if let Some(rest) = host.strip_prefix('[') {
        let (v6, after) = rest.split_once(']')?;
        let port = match after.strip_prefix(':') {
            Some(port) => port.parse().ok()?,
            None if after.is_empty() => 80,
            None => return None,
        };
        return Some((v6, port));
    }
    match host.rsplit_once(':') {
        Some((name, port)) => Some((name, port.parse().ok()?)),
        None if !host.is_empty() => Some((host, 80)),
        None => None,
    }
}

/// The middleware: refuses what [`Guard`] refuses, and adds the safety headers to
/// every answer.
pub async fn check(
    State(guard): State<Arc<Guard>>,
    ConnectInfo(peer): ConnectInfo<Peer>,
    request: Request,
    next: Next,
) -> Response {
    let mut response = match guard.refusal(&request) {
        Some((status, why)) => {
            warn!(method = %request.method(), path = %request.uri().path(), status = status.as_u16(), reason = %why, from = %peer.address, "dashboard request refused");
            (status, Json(serde_json::json!({ "error": why }))).into_response()
        }
        None if guard.https && !peer.tls => to_https(&request),
        None => next.run(request).await,
    };
    let headers = response.headers_mut();
    headers.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    headers.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static("frame-ancestors 'none'"),
    );
    headers.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    headers.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("same-origin"),
    );
    response
}

/// The same request's address over HTTPS, as a redirect (its `Host` passed the check).
fn to_https(request: &Request) -> Response {
    let host = request
        .headers()
        .get(header::HOST)
        .and_then(|h| h.to_str().ok())
        .unwrap_or("");
    let path = request.uri().path_and_query().map_or("/", |p| p.as_str());
    let location = format!("https://{host}{path}");
    match HeaderValue::from_str(&location) {
        Ok(location) => (
            StatusCode::PERMANENT_REDIRECT,
            [(header::LOCATION, location)],
            "this dashboard serves HTTPS only\n",
        )
            .into_response(),
        Err(_) => StatusCode::BAD_REQUEST.into_response(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guard(bound: &str) -> Guard {
        Guard::new(
            bound.parse().unwrap(),
            &["Dashboard.Plant".to_string()],
            false,
        )
    }

    #[test]
    fn its_own_addresses_and_names_are_allowed() {
        let g = guard("127.0.0.1:8080");
        for host in [
            "127.0.0.1:8080",
            "localhost:8080",
            "LOCALHOST:8080",
            "10.1.2.3:8080",
            "[::1]:8080",
            "dashboard.plant:8080",
        ] {
            assert!(g.host_allowed(host), "{host}");
        }
    }

    #[test]
    fn other_names_ports_and_garbage_are_refused() {
        let g = guard("127.0.0.1:8080");
        for host in [
            "evil.example:8080",
            "127.0.0.1:8081",
            "127.0.0.1",
            "localhost",
            "",
            "[::1",
            "127.0.0.1:port",
            "dashboard.plant.evil.example:8080",
        ] {
            assert!(!g.host_allowed(host), "{host}");
        }
        // localhost only when it listens on loopback (or everywhere).
        let lan = guard("10.1.2.3:80");
        assert!(!lan.host_allowed("localhost:80"));
        assert!(lan.host_allowed("10.1.2.3"));
        assert!(guard("0.0.0.0:80").host_allowed("localhost"));
    }

    fn request(method: Method, host: &str, origin: Option<&str>, json: bool) -> Request {
        let mut builder = Request::builder()
            .method(method)
            .uri("/api/orders")
            .header(header::HOST, host);
        if let Some(origin) = origin {
            builder = builder.header(header::ORIGIN, origin);
        }
        if json {
            builder = builder.header(header::CONTENT_TYPE, "application/json");
        }
        builder.body(axum::body::Body::empty()).unwrap()
    }

    #[test]
    fn a_change_needs_its_own_origin_and_json() {
        let g = guard("127.0.0.1:8080");
        let status = |r: Request| g.refusal(&r).map(|(s, _)| s.as_u16());
        let own = Some("http://127.0.0.1:8080");
        assert_eq!(
            status(request(Method::GET, "127.0.0.1:8080", None, false)),
            None
        );
        assert_eq!(
            status(request(Method::POST, "127.0.0.1:8080", own, true)),
            None
        );
        assert_eq!(
            status(request(
                Method::POST,
                "evil.example:8080",
                Some("http://evil.example:8080"),
                true
            )),
            Some(421)
        );
        for origin in [
            None,
            Some("http://evil.example"),
            Some("http://127.0.0.1:8081"),
            Some("null"),
        ] {
            assert_eq!(
                status(request(Method::POST, "127.0.0.1:8080", origin, true)),
                Some(403),
                "{origin:?}"
            );
        }
        assert_eq!(
            status(request(Method::POST, "127.0.0.1:8080", own, false)),
            Some(415)
        );
    }
}

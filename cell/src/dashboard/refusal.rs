//! How the dashboard says no: a status and why, answered as `{"error": why}`.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;

/// An answer that refuses, with why.
pub fn refused(status: StatusCode, message: &str) -> Response {
    (status, Json(serde_json::json!({ "error": message }))).into_response()
}

/// A request refused: its status and why (answered as `{"error": why}`).
#[derive(Debug)]
pub struct Refusal {
    pub status: StatusCode,
    pub why: String,
}

impl IntoResponse for Refusal {
    fn into_response(self) -> Response {
        refused(self.status, &self.why)
    }
}

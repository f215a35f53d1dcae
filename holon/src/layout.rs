//! Asking for the cell's layout (docs/material-flow.md): every serving resource answers
//! its own part on `resource/<name>/layout`. `cell layout`, the dashboard and a
//! transporter's layout component ask this way.

use std::time::Duration;

use schemas::layout::LayoutPart;
use schemas::CellKeys;

/// What the serving resources answered.
#[derive(Debug, Default)]
pub struct Answered {
    /// Each resource's part.
    pub parts: Vec<LayoutPart>,
    /// Answers that are not a layout part: the key and why.
    pub unreadable: Vec<String>,
}

/// Asks every serving resource for its part of the layout, waiting at most `timeout`.
pub async fn ask(
    session: &zenoh::Session,
    keys: &CellKeys,
    timeout: Duration,
) -> Result<Answered, zenoh::Error> {
    let mut replies = session
        .get(keys.layout_all())
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(timeout)
        .with(crate::query::replies())
        .await?;
    let mut answered = Answered::default();
    while let Some(reply) = replies.recv().await {
        let Ok(sample) = reply.result() else { continue };
        match LayoutPart::from_json(&sample.payload().to_bytes()) {
            Ok(part) => answered.parts.push(part),
            Err(e) => answered.unreadable.push(format!(
                "{}: an answer that is not a layout part: {e}",
                sample.key_expr()
            )),
        }
    }
    Ok(answered)
}

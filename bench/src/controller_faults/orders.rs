//! The orders of the campaign, as an operator reads them: each one's end and each failed
//! attempt's reason (`cell orders --detail`: the order's snapshot from its order-node).

use std::collections::BTreeMap;

use holarchy_tests::Cell;
use serde_json::{json, Value};

use super::phases::{CHECKABLE, SPOKEN, UNSPOKEN};
use super::PhaseReport;

/// A failed attempt's detail, `failed on resource/robot1: REASON (DETAIL)`: its reason
/// and what follows it.
fn reason_of(detail: &str) -> (&str, &str) {
    let rest = detail.split_once(": ").map_or(detail, |(_, rest)| rest);
    match rest.split_once(" (") {
        Some((reason, said)) => (reason, said),
        None => (rest, ""),
    }
}

/// Whether an attempt's `detail` tells the operator why in the controller's words
/// (where it spoke) or says what happened (where it did not): None if it does, else
/// what is missing.
pub fn words_missing(detail: &str) -> Option<String> {
    let (reason, said) = reason_of(detail);
    if let Some((_, words)) = SPOKEN.iter().find(|(r, _)| *r == reason) {
        return (!words.iter().any(|w| said.contains(w)))
            .then(|| format!("{reason} without the controller's words: {detail:?}"));
    }
    if UNSPOKEN.contains(&reason) {
        return said
            .is_empty()
            .then(|| format!("{reason} without saying what happened: {detail:?}"));
    }
    None
}

/// Reads every order's end and attempts, counts failed attempts per phase (by when they
/// ended) and adds what is wrong to `violations`. Returns the orders' figures.
pub async fn judge(
    cell: &Cell,
    submitted: &[String],
    reports: &mut [PhaseReport],
    violations: &mut Vec<String>,
) -> Value {
    let mut by_status: BTreeMap<String, u64> = BTreeMap::new();
    let mut failed_reasons: BTreeMap<String, u64> = BTreeMap::new();
    let mut missing_words = Vec::new();
    // One detail of each reason, as the operator read it.
    let mut examples: BTreeMap<String, String> = BTreeMap::new();
    for (i, order) in submitted.iter().enumerate() {
        let Some(state) = cell.order_state(order).await else {
            violations.push(format!("{order}: lost (no order-node knows it)"));
            *by_status.entry("lost".into()).or_default() += 1;
            continue;
        };
        let status = state["status"].as_str().unwrap_or("?").to_string();
        *by_status.entry(status.clone()).or_default() += 1;
        let reason = state["reason"].as_str().unwrap_or("");
        match status.as_str() {
            "done" => {}
            "failed" if !reason.is_empty() => {
                let key = reason_of(reason.rsplit_once("; last on ").map_or(reason, |(_, r)| r)).0;
                *failed_reasons.entry(key.to_string()).or_default() += 1;
            }
            "failed" => violations.push(format!("{order}: failed without a reason")),
            other => violations.push(format!("{order}: {other} at the end (stuck): {state}")),
        }
        let attempts = state["attempts"].as_array().cloned().unwrap_or_default();
        if i == 0 && (status != "done" || attempts.len() != 1) {
            violations.push(format!(
                "the first job after the clean start was not done at once: {state}"
            ));
        }
        for attempt in attempts.iter().filter(|a| a["end"] == "failed") {
            let detail = attempt["detail"].as_str().unwrap_or("");
            let at = attempt["at"].as_u64().unwrap_or(0);
            let (why, _) = reason_of(detail);
            examples
                .entry(why.to_string())
                .or_insert_with(|| detail.to_string());
            let phase = reports
                .iter_mut()
                .find(|r| at >= r.from_ms && at <= r.to_ms);
            let (phase_no, kind) = match phase {
                Some(r) => {
                    *r.failed_attempts.entry(why.to_string()).or_default() += 1;
                    if words_missing(detail).is_some() {
                        r.reasons_without_words += 1;
                    }
                    (r.phase as i64, r.kind.clone())
                }
                None => (-1, String::new()),
            };
            if let Some(missing) = words_missing(detail) {
                missing_words.push(format!("{order}: {missing}"));
            }
            if CHECKABLE.contains(&why) {
                violations.push(format!(
                    "{order}: a step failed for a reason --check could have seen: {detail:?}"
                ));
            }
            if phase_no == 0 {
                violations.push(format!(
                    "{order}: a step failed in the clean start's phase ({kind}), without faults: {detail:?}"
                ));
            }
        }
    }
    if !missing_words.is_empty() {
        violations.push(format!(
            "{} failed attempts without the controller's words, e.g. {:?}",
            missing_words.len(),
            &missing_words[..missing_words.len().min(3)]
        ));
    }
    json!({
        "submitted": submitted.len(),
        "by_status": by_status,
        "failed_orders_by_last_reason": failed_reasons,
        "attempts_without_words": missing_words.len(),
        "failed_attempt_examples": examples,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_controllers_words_are_looked_for_where_it_spoke() {
        assert_eq!(
            words_missing("failed on resource/robot1: controller_error (pick failed: simulated error (--error-every))"),
            None
        );
        assert!(words_missing("failed on resource/robot1: controller_error").is_some());
        assert_eq!(
            words_missing("failed on resource/robot1: controller_protocol_error (the controller broke the protocol: a message the dialect job-ack-end does not describe: \"STATE HOMING\")"),
            None
        );
        assert!(words_missing("failed on resource/robot1: controller_timeout").is_some());
        assert_eq!(
            words_missing("failed on resource/robot1: controller_timeout (no reply within 2s)"),
            None
        );
        assert_eq!(
            words_missing("failed on resource/robot1: start refused: unavailable"),
            None
        );
    }
}

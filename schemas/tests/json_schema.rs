//! The checked-in JSON Schema must match the Rust types. To refresh it after a change:
//! `HOLARCHY_BLESS=1 cargo test -p schemas --test json_schema`.

use std::path::PathBuf;

#[test]
fn service_schema_file_is_current() {
    schema_file_is_current("service.schema.json", schemas::service_json_schema());
}

#[test]
fn advice_schema_file_is_current() {
    let generated = schemas::advice_json_schema();
    schema_file_is_current("advice.schema.json", generated.clone());
    for field in ["conversation_id", "steps", "forecast_done", "route", "why"] {
        assert!(generated.contains(field), "the schema lacks {field}");
    }
}

#[test]
fn outcome_schema_file_is_current_and_names_the_outcomes() {
    let generated = schemas::outcome_json_schema();
    schema_file_is_current("outcome.schema.json", generated.clone());
    for value in ["done", "failed", "running", "never_reached", "unknown"] {
        assert!(
            generated.contains(&format!("\"{value}\"")),
            "the schema lacks {value}"
        );
    }
}

#[test]
fn listing_schema_file_is_current_and_names_the_cursors() {
    let generated = schemas::listing_json_schema();
    schema_file_is_current("listing.schema.json", generated.clone());
    for name in [
        "after_running",
        "after_finished",
        "counts",
        "next",
        "unreadable",
    ] {
        assert!(generated.contains(name), "the schema lacks {name}");
    }
}

#[test]
fn resource_state_schema_file_is_current_and_names_the_states() {
    let generated = schemas::resource_state_json_schema();
    schema_file_is_current("resource-state.schema.json", generated.clone());
    for value in [
        "init",
        "free",
        "busy",
        "disconnected",
        "ready",
        "fault",
        "estop",
    ] {
        assert!(
            generated.contains(&format!("\"{value}\"")),
            "the schema lacks {value}"
        );
    }
}

fn schema_file_is_current(file: &str, generated: String) {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("json")
        .join(file);
    if std::env::var_os("HOLARCHY_BLESS").is_some() {
        std::fs::write(&path, &generated).unwrap();
    }
    let on_disk = std::fs::read_to_string(&path).unwrap_or_default();
    assert!(
        on_disk == generated,
        "{} is stale; regenerate it with HOLARCHY_BLESS=1 cargo test -p schemas --test json_schema",
        path.display()
    );
}

#[test]
fn schema_describes_every_field() {
    let schema: serde_json::Value = serde_json::from_str(&schemas::service_json_schema()).unwrap();
    let props = schema["properties"].as_object().unwrap();
    for field in [
        "v",
        "message_type",
        "service_type",
        "conversation_id",
        "requester",
        "provider",
        "reply_to",
        "result",
        "reason",
        "info",
    ] {
        assert!(props.contains_key(field), "schema lacks {field}");
    }
}

#[test]
fn layout_schema_file_is_current_and_names_the_roles() {
    let generated = schemas::layout_json_schema();
    schema_file_is_current("layout.schema.json", generated.clone());
    for value in [
        "port",
        "input",
        "output",
        "buffer",
        "entry",
        "exit",
        "entry_exit",
        "conveyor",
        "transfer",
    ] {
        assert!(
            generated.contains(&format!("\"{value}\"")),
            "the schema lacks {value}"
        );
    }
}

//! The values a message carries, by placeholder name, and the dialect's enum tables.
//!
//! A command's values come from the step ([`command_values`]): `id`, `action`, `program`
//! (when the job names one), `pose` (present, empty) with `x y z a b c` (when the step has
//! a position), and `info.KEY` for every scalar field of the job's `info`. A reply adds
//! what the controller says: `result`, `message`, `state`, or any of the command's names
//! it echoes.

use std::collections::BTreeMap;

use schemas::RobotCommand;

/// Values by placeholder name, as text.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Values(BTreeMap<String, String>);

impl Values {
    pub fn get(&self, name: &str) -> Option<&str> {
        self.0.get(name).map(String::as_str)
    }

    pub fn contains(&self, name: &str) -> bool {
        self.0.contains_key(name)
    }

    pub fn set(&mut self, name: &str, value: String) {
        self.0.insert(name.to_string(), value);
    }

    pub fn remove(&mut self, name: &str) -> Option<String> {
        self.0.remove(name)
    }

    /// Adds every value of `other` this one lacks.
    pub fn fill_from(&mut self, other: &Values) {
        for (k, v) in &other.0 {
            self.0.entry(k.clone()).or_insert_with(|| v.clone());
        }
    }

    pub fn iter(&self) -> impl Iterator<Item = (&str, &str)> {
        self.0.iter().map(|(k, v)| (k.as_str(), v.as_str()))
    }
}

/// The names a command's values may have (besides `info.KEY`).
pub const COMMAND_NAMES: &[&str] = &[
    "id", "action", "program", "pose", "x", "y", "z", "a", "b", "c", "epoch", "step", "name",
];

/// The names only a controller's message carries.
pub const REPLY_NAMES: &[&str] = &[
    "result",
    "message",
    "state",
    "lease_ms",
    "reason",
    "step_state",
];

/// Whether `name` may be a command's value.
pub fn is_command_name(name: &str) -> bool {
    COMMAND_NAMES.contains(&name) || name.strip_prefix("info.").is_some_and(|k| !k.is_empty())
}

/// Whether `name` may be a reply's value.
pub fn is_reply_name(name: &str) -> bool {
    is_command_name(name) || REPLY_NAMES.contains(&name)
}

/// How numbers and booleans are written.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ValueFormat {
    /// Digits after the decimal point; None: the shortest text that reads back the same
    /// number, always with a fractional part (`100.0`, `0.1`, `1e16`).
    pub decimals: Option<usize>,
    pub true_text: String,
    pub false_text: String,
}

impl Default for ValueFormat {
    fn default() -> Self {
        ValueFormat {
            decimals: None,
            true_text: "true".into(),
            false_text: "false".into(),
        }
    }
}

impl ValueFormat {
    pub fn number(&self, value: f64) -> String {
        match self.decimals {
            Some(d) => format!("{value:.d$}"),
            None => format!("{value:?}"),
        }
    }
}

/// The values of one controller command.
pub fn command_values(command: &RobotCommand, format: &ValueFormat) -> Values {
    let mut values = Values::default();
    values.set("id", command.id.to_string());
    values.set("action", command.action.clone());
    if let Some(program) = &command.program {
        values.set("program", program.clone());
    }
    if let Some(pose) = &command.pos {
        values.set("pose", String::new());
        for (name, v) in [
            ("x", pose.x),
            ("y", pose.y),
            ("z", pose.z),
            ("a", pose.a),
            ("b", pose.b),
            ("c", pose.c),
        ] {
            values.set(name, format.number(v));
        }
    }
    for (key, value) in &command.info {
        let text = match value {
            serde_json::Value::String(s) => s.clone(),
            serde_json::Value::Bool(true) => format.true_text.clone(),
            serde_json::Value::Bool(false) => format.false_text.clone(),
            serde_json::Value::Number(n) => match n.as_f64() {
                Some(f) if !n.is_i64() && !n.is_u64() => format.number(f),
                _ => n.to_string(),
            },
            _ => continue, // objects, arrays and null have no text form
        };
        values.set(&format!("info.{key}"), text);
    }
    values
}

/// The dialect's enum tables: `[enums.NAME]`, each mapping a value to its wire form(s).
/// The first wire form is the one written; any of them is read back.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Enums(BTreeMap<String, BTreeMap<String, Vec<String>>>);

impl Enums {
    pub fn insert(&mut self, table: &str, value: &str, wire: Vec<String>) {
        self.0
            .entry(table.to_string())
            .or_default()
            .insert(value.to_string(), wire);
    }

    pub fn has_table(&self, table: &str) -> bool {
        self.0.contains_key(table)
    }

    /// The values a table maps.
    pub fn keys(&self, table: &str) -> Vec<&str> {
        self.0
            .get(table)
            .map(|t| t.keys().map(String::as_str).collect())
            .unwrap_or_default()
    }

    pub fn tables(&self) -> impl Iterator<Item = (&str, &BTreeMap<String, Vec<String>>)> {
        self.0.iter().map(|(k, v)| (k.as_str(), v))
    }

    pub fn encode<'a>(&'a self, table: &str, value: &str) -> Result<&'a str, String> {
        let entries = self
            .0
            .get(table)
            .ok_or_else(|| format!("there is no enum table {table:?}"))?;
        entries
            .get(value)
            .and_then(|w| w.first())
            .map(String::as_str)
            .ok_or_else(|| format!("{value:?} has no entry in [enums.{table}]"))
    }

    /// The first value a table maps (in the order of the file's keys as read).
    pub fn first_value(&self, table: &str) -> Option<&str> {
        self.0.get(table)?.keys().next().map(String::as_str)
    }

    pub fn decode<'a>(&'a self, table: &str, wire: &str) -> Result<&'a str, String> {
        let entries = self
            .0
            .get(table)
            .ok_or_else(|| format!("there is no enum table {table:?}"))?;
        entries
            .iter()
            .find(|(_, w)| w.iter().any(|w| w == wire))
            .map(|(v, _)| v.as_str())
            .ok_or_else(|| format!("{wire:?} is not a value of [enums.{table}]"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use schemas::Pose;

    #[test]
    fn a_command_gives_its_values() {
        let mut info = BTreeMap::new();
        info.insert("part".to_string(), serde_json::json!("b2"));
        info.insert("count".to_string(), serde_json::json!(3));
        info.insert("fast".to_string(), serde_json::json!(true));
        info.insert("pick".to_string(), serde_json::json!({"x": 1}));
        let command = RobotCommand {
            id: 7,
            action: "pick".into(),
            pos: Some(Pose {
                x: 1.5,
                ..Pose::default()
            }),
            program: None,
            info,
        };
        let format = ValueFormat {
            decimals: Some(2),
            true_text: "TRUE".into(),
            false_text: "FALSE".into(),
        };
        let values = command_values(&command, &format);
        assert_eq!(values.get("x"), Some("1.50"));
        assert_eq!(values.get("pose"), Some(""));
        assert_eq!(values.get("info.part"), Some("b2"));
        assert_eq!(values.get("info.count"), Some("3"));
        assert_eq!(values.get("info.fast"), Some("TRUE"));
        assert!(!values.contains("info.pick"));
        assert!(!values.contains("program"));
        assert_eq!(ValueFormat::default().number(100.0), "100.0");
    }
}

//! Holon ids (`<kind>/<name>`), names and cell names.

use std::borrow::Cow;
use std::fmt;
use std::str::FromStr;

use schemars::{json_schema, JsonSchema, Schema, SchemaGenerator};
use serde::{Deserialize, Serialize};

use crate::SchemaError;

/// The longest name we accept, so that keys and log lines stay readable.
pub const MAX_NAME_LEN: usize = 64;

/// The pattern every name (holon name, cell name, service type) must match.
pub const NAME_PATTERN: &str = "^[a-z0-9][a-z0-9_-]*$";

/// Checks a name against `[a-z0-9][a-z0-9_-]*` (at most [`MAX_NAME_LEN`] bytes).
pub fn validate_name(what: &'static str, name: &str) -> Result<(), SchemaError> {
    let invalid = |why: &str| SchemaError::InvalidName {
        what,
        name: name.to_string(),
        why: why.to_string(),
    };
    let mut bytes = name.bytes();
    match bytes.next() {
        None => return Err(invalid("it is empty")),
        Some(b) if !(b.is_ascii_lowercase() || b.is_ascii_digit()) => {
            return Err(invalid("it must start with a-z or 0-9"))
        }
        _ => {}
    }
    if name.len() > MAX_NAME_LEN {
        return Err(invalid("it is longer than 64 bytes"));
    }
    if !bytes.all(|b| b.is_ascii_lowercase() || b.is_ascii_digit() || b == b'_' || b == b'-') {
        return Err(invalid("only a-z, 0-9, '_' and '-' are allowed"));
    }
    Ok(())
}

/// The PROSA kind of a holon.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum HolonKind {
    Resource,
    Product,
    Order,
    Staff,
}

impl HolonKind {
    pub const ALL: [HolonKind; 4] = [
        HolonKind::Resource,
        HolonKind::Product,
        HolonKind::Order,
        HolonKind::Staff,
    ];

    pub fn as_str(self) -> &'static str {
        match self {
            HolonKind::Resource => "resource",
            HolonKind::Product => "product",
            HolonKind::Order => "order",
            HolonKind::Staff => "staff",
        }
    }
}

impl fmt::Display for HolonKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for HolonKind {
    type Err = SchemaError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        HolonKind::ALL
            .into_iter()
            .find(|k| k.as_str() == s)
            .ok_or_else(|| SchemaError::InvalidHolonId {
                id: s.to_string(),
                why: "kind must be resource, product, order or staff".into(),
            })
    }
}

/// A holon's id, `<kind>/<name>`, e.g. `resource/robot1`. Serialized as that string.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub struct HolonId {
    kind: HolonKind,
    name: String,
}

impl HolonId {
    pub fn new(kind: HolonKind, name: &str) -> Result<Self, SchemaError> {
        validate_name("holon name", name)?;
        Ok(HolonId {
            kind,
            name: name.to_string(),
        })
    }

    pub fn resource(name: &str) -> Result<Self, SchemaError> {
        Self::new(HolonKind::Resource, name)
    }

    pub fn staff(name: &str) -> Result<Self, SchemaError> {
        Self::new(HolonKind::Staff, name)
    }

    pub fn order(name: &str) -> Result<Self, SchemaError> {
        Self::new(HolonKind::Order, name)
    }

    pub fn kind(&self) -> HolonKind {
        self.kind
    }

    pub fn name(&self) -> &str {
        &self.name
    }
}

impl fmt::Display for HolonId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.kind, self.name)
    }
}

impl FromStr for HolonId {
    type Err = SchemaError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let (kind, name) = s
            .split_once('/')
            .ok_or_else(|| SchemaError::InvalidHolonId {
                id: s.to_string(),
                why: "expected <kind>/<name>".into(),
            })?;
        let kind: HolonKind = kind.parse().map_err(|_| SchemaError::InvalidHolonId {
            id: s.to_string(),
            why: "kind must be resource, product, order or staff".into(),
        })?;
        HolonId::new(kind, name).map_err(|e| SchemaError::InvalidHolonId {
            id: s.to_string(),
            why: e.to_string(),
        })
    }
}

impl TryFrom<String> for HolonId {
    type Error = SchemaError;
    fn try_from(s: String) -> Result<Self, Self::Error> {
        s.parse()
    }
}

impl From<HolonId> for String {
    fn from(id: HolonId) -> String {
        id.to_string()
    }
}

impl JsonSchema for HolonId {
    fn schema_name() -> Cow<'static, str> {
        "HolonId".into()
    }

    fn json_schema(_: &mut SchemaGenerator) -> Schema {
        json_schema!({
            "type": "string",
            "description": "A holon id, <kind>/<name>, e.g. resource/robot1.",
            "pattern": "^(resource|product|order|staff)/[a-z0-9][a-z0-9_-]*$",
            "maxLength": 73
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_prints_ids() {
        let id: HolonId = "resource/robot1".parse().unwrap();
        assert_eq!(id.kind(), HolonKind::Resource);
        assert_eq!(id.name(), "robot1");
        assert_eq!(id.to_string(), "resource/robot1");
        let json = serde_json::to_string(&id).unwrap();
        assert_eq!(json, "\"resource/robot1\"");
        assert_eq!(serde_json::from_str::<HolonId>(&json).unwrap(), id);
    }

    #[test]
    fn rejects_bad_ids() {
        for bad in [
            "",
            "robot1",
            "machine/robot1",
            "resource/",
            "resource/Robot1",
            "resource/_r",
            "resource/r 1",
            "resource/r/1",
            "resource/r*",
        ] {
            assert!(bad.parse::<HolonId>().is_err(), "{bad:?} was accepted");
        }
        let long = format!("order/{}", "a".repeat(65));
        assert!(long.parse::<HolonId>().is_err());
        assert!(serde_json::from_str::<HolonId>("\"order/O-1\"").is_err());
    }

    #[test]
    fn names_follow_the_pattern() {
        for good in ["a", "0", "robot-1", "o_17", "x".repeat(64).as_str()] {
            validate_name("test", good).unwrap();
        }
        for bad in ["", "-a", "_a", "A", "a.b", "a/b", "é"] {
            assert!(validate_name("test", bad).is_err(), "{bad:?}");
        }
    }
}

//! Binary messages: a fixed list of typed fields (after the length prefix, which the
//! framing handles), in the spirit of ROS-Industrial's simple_message.
//!
//! Each field has a type (`i16 u16 i32 u32 i64 u64 f32 f64`, or `str` of a fixed number
//! of bytes, NUL-padded) and a value: a literal (`2100`), a placeholder (`{id}`,
//! `{action:action_code}`), and optionally a `default` written when the placeholder has
//! no value (a command without a pose). A message read must have exactly the layout's
//! length, and every literal field its value.

use serde::Deserialize;

use super::framing::ByteOrder;
use super::template::Template;
use super::values::{Enums, ValueFormat, Values};

/// The type of one field.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FieldType {
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
    Str,
}

/// One field as the dialect file writes it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldSection {
    #[serde(rename = "type")]
    pub kind: FieldType,
    pub value: String,
    /// For `str`: its size in bytes.
    pub bytes: Option<usize>,
    /// Written when the value's placeholder has none.
    pub default: Option<String>,
}

#[derive(Debug, Clone)]
struct Field {
    kind: FieldType,
    size: usize,
    value: Template,
    default: Option<String>,
}

/// A binary message template.
#[derive(Debug, Clone)]
pub struct BinaryTemplate {
    fields: Vec<Field>,
    order: ByteOrder,
    /// Shown in messages about it.
    pub text: String,
}

fn size_of(kind: FieldType) -> usize {
    match kind {
        FieldType::I16 | FieldType::U16 => 2,
        FieldType::I32 | FieldType::U32 | FieldType::F32 => 4,
        FieldType::I64 | FieldType::U64 | FieldType::F64 => 8,
        FieldType::Str => 0,
    }
}

fn put_int(out: &mut Vec<u8>, bytes: [u8; 8], size: usize, order: ByteOrder) {
    // `bytes` is the value's little-endian form.
    let part = &bytes[..size];
    match order {
        ByteOrder::Little => out.extend_from_slice(part),
        ByteOrder::Big => out.extend(part.iter().rev()),
    }
}

fn get_bytes(input: &[u8], order: ByteOrder) -> [u8; 8] {
    let mut le = [0u8; 8];
    match order {
        ByteOrder::Little => le[..input.len()].copy_from_slice(input),
        ByteOrder::Big => {
            for (i, b) in input.iter().rev().enumerate() {
                le[i] = *b;
            }
        }
    }
    le
}

impl BinaryTemplate {
    pub fn parse(fields: &[FieldSection], order: ByteOrder) -> Result<BinaryTemplate, String> {
        if fields.is_empty() {
            return Err("a binary message needs at least one field".into());
        }
        let mut parsed = Vec::new();
        for (i, f) in fields.iter().enumerate() {
            let at = format!("fields[{i}]");
            let size = match (f.kind, f.bytes) {
                (FieldType::Str, Some(n)) if (1..=4096).contains(&n) => n,
                (FieldType::Str, _) => {
                    return Err(format!(
                        "{at}.bytes: a str field needs a size of 1 to 4096 bytes"
                    ))
                }
                (_, Some(_)) => return Err(format!("{at}.bytes: only a str field has a size")),
                (kind, None) => size_of(kind),
            };
            let value = Template::parse(&f.value).map_err(|e| format!("{at}.value: {e}"))?;
            if value.literal().is_none() && value.single_value().is_none() {
                return Err(format!(
                    "{at}.value: a binary field holds a literal or one placeholder, not {:?}",
                    f.value
                ));
            }
            let field = Field {
                kind: f.kind,
                size,
                value,
                default: f.default.clone(),
            };
            if let Some(literal) = field.value.literal() {
                encode_value(&field, literal, order, &mut Vec::new())
                    .map_err(|e| format!("{at}.value: {e}"))?;
            }
            if let Some(default) = &field.default {
                encode_value(&field, default, order, &mut Vec::new())
                    .map_err(|e| format!("{at}.default: {e}"))?;
            }
            parsed.push(field);
        }
        Ok(BinaryTemplate {
            fields: parsed,
            order,
            text: format!("{} fields", fields.len()),
        })
    }

    pub fn templates(&self) -> impl Iterator<Item = &Template> {
        self.fields.iter().map(|f| &f.value)
    }

    /// The message's length in bytes.
    pub fn size(&self) -> usize {
        self.fields.iter().map(|f| f.size).sum()
    }

    pub fn render(&self, values: &Values, enums: &Enums) -> Result<Vec<u8>, String> {
        let mut out = Vec::with_capacity(self.size());
        for (i, field) in self.fields.iter().enumerate() {
            let text = match (field.value.literal(), field.value.single_value()) {
                (Some(literal), _) => literal.to_string(),
                (None, Some((name, table))) => match (values.get(name), &field.default) {
                    (Some(v), _) => match table {
                        Some(table) => enums.encode(table, v)?.to_string(),
                        None => v.to_string(),
                    },
                    (None, Some(default)) => default.clone(),
                    (None, None) => return Err(format!("fields[{i}]: no value for {{{name}}}")),
                },
                (None, None) => unreachable!("checked at parse"),
            };
            encode_value(field, &text, self.order, &mut out)
                .map_err(|e| format!("fields[{i}]: {e}"))?;
        }
        Ok(out)
    }

    /// Reads `message` as this layout: `Ok(Err(why))` when it has another shape, `Err`
    /// when a value breaks an enum.
    pub fn capture(
        &self,
        message: &[u8],
        enums: &Enums,
        format: &ValueFormat,
    ) -> Result<Result<Values, String>, String> {
        if message.len() != self.size() {
            return Ok(Err(format!("{} bytes, not {}", message.len(), self.size())));
        }
        let mut values = Values::default();
        let mut at = 0;
        for (i, field) in self.fields.iter().enumerate() {
            let raw = &message[at..at + field.size];
            at += field.size;
            let text = decode_value(field, raw, self.order, format)
                .map_err(|e| format!("fields[{i}]: {e}"))?;
            if let Some(literal) = field.value.literal() {
                let mut expected = Vec::new();
                encode_value(field, literal, self.order, &mut expected).expect("checked at parse");
                if expected != raw {
                    return Ok(Err(format!("fields[{i}] is {text}, not {literal}")));
                }
                continue;
            }
            if let Some(default) = &field.default {
                let mut written = Vec::new();
                encode_value(field, default, self.order, &mut written).expect("checked at parse");
                if written == raw {
                    continue; // the default: no value
                }
            }
            if field.kind == FieldType::Str && text.is_empty() {
                continue; // no value
            }
            if !field.value.capture(&text, enums, &mut values)? {
                return Ok(Err(format!("fields[{i}] is {text}")));
            }
        }
        Ok(Ok(values))
    }
}

fn encode_value(
    field: &Field,
    text: &str,
    order: ByteOrder,
    out: &mut Vec<u8>,
) -> Result<(), String> {
    let bad = |what: &str| format!("{text:?} is not {what}");
    match field.kind {
        FieldType::Str => {
            let bytes = text.as_bytes();
            if bytes.len() > field.size {
                return Err(format!("{text:?} is longer than {} bytes", field.size));
            }
            if bytes.contains(&0) {
                return Err(format!("{text:?} holds a NUL byte"));
            }
            out.extend_from_slice(bytes);
            out.resize(out.len() + field.size - bytes.len(), 0);
        }
        FieldType::F32 => {
            let v: f32 = text.trim().parse().map_err(|_| bad("a number"))?;
            put_int(out, (v.to_bits() as u64).to_le_bytes(), 4, order);
        }
        FieldType::F64 => {
            let v: f64 = text.trim().parse().map_err(|_| bad("a number"))?;
            put_int(out, v.to_bits().to_le_bytes(), 8, order);
        }
        FieldType::I16 => {
            let v: i16 = text.trim().parse().map_err(|_| bad("a 16-bit integer"))?;
            put_int(out, (v as i64).to_le_bytes(), 2, order);
        }
        FieldType::U16 => {
            let v: u16 = text
                .trim()
                .parse()
                .map_err(|_| bad("an unsigned 16-bit integer"))?;
            put_int(out, (v as u64).to_le_bytes(), 2, order);
        }
        FieldType::I32 => {
            let v: i32 = text.trim().parse().map_err(|_| bad("a 32-bit integer"))?;
            put_int(out, (v as i64).to_le_bytes(), 4, order);
        }
        FieldType::U32 => {
            let v: u32 = text
                .trim()
                .parse()
                .map_err(|_| bad("an unsigned 32-bit integer"))?;
            put_int(out, (v as u64).to_le_bytes(), 4, order);
        }
        FieldType::I64 => {
            let v: i64 = text.trim().parse().map_err(|_| bad("a 64-bit integer"))?;
            put_int(out, v.to_le_bytes(), 8, order);
        }
        FieldType::U64 => {
            let v: u64 = text
                .trim()
                .parse()
                .map_err(|_| bad("an unsigned 64-bit integer"))?;
            put_int(out, v.to_le_bytes(), 8, order);
        }
    }
    Ok(())
}

fn decode_value(
    field: &Field,
    raw: &[u8],
    order: ByteOrder,
    format: &ValueFormat,
) -> Result<String, String> {
    let le = if field.kind == FieldType::Str {
        [0u8; 8]
    } else {
        get_bytes(raw, order)
    };
    Ok(match field.kind {
        FieldType::Str => {
            let end = raw.iter().position(|&b| b == 0).unwrap_or(raw.len());
            if raw[end..].iter().any(|&b| b != 0) {
                return Err("a string field has bytes after its NUL padding".into());
            }
            String::from_utf8(raw[..end].to_vec())
                .map_err(|_| "a string field is not UTF-8".to_string())?
        }
        FieldType::F32 => {
            let v = f32::from_bits(u32::from_le_bytes(le[..4].try_into().expect("4 bytes")));
            if !v.is_finite() {
                return Err("a number field is not finite".into());
            }
            format.number(v as f64)
        }
        FieldType::F64 => {
            let v = f64::from_bits(u64::from_le_bytes(le));
            if !v.is_finite() {
                return Err("a number field is not finite".into());
            }
            format.number(v)
        }
        FieldType::I16 => (i16::from_le_bytes(le[..2].try_into().expect("2 bytes"))).to_string(),
        FieldType::U16 => (u16::from_le_bytes(le[..2].try_into().expect("2 bytes"))).to_string(),
        FieldType::I32 => (i32::from_le_bytes(le[..4].try_into().expect("4 bytes"))).to_string(),
        FieldType::U32 => (u32::from_le_bytes(le[..4].try_into().expect("4 bytes"))).to_string(),
        FieldType::I64 => i64::from_le_bytes(le).to_string(),
        FieldType::U64 => u64::from_le_bytes(le).to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(kind: FieldType, value: &str) -> FieldSection {
        FieldSection {
            kind,
            value: value.into(),
            bytes: if kind == FieldType::Str {
                Some(8)
            } else {
                None
            },
            default: None,
        }
    }

    #[test]
    fn renders_and_reads_back_in_either_order() {
        for order in [ByteOrder::Big, ByteOrder::Little] {
            let mut x = field(FieldType::F32, "{x}");
            x.default = Some("0".into());
            let t = BinaryTemplate::parse(
                &[
                    field(FieldType::I32, "2100"),
                    field(FieldType::U64, "{id}"),
                    field(FieldType::I16, "{action:code}"),
                    x,
                    field(FieldType::Str, "{program}"),
                ],
                order,
            )
            .unwrap();
            let mut enums = Enums::default();
            enums.insert("code", "pick", vec!["-3".into()]);
            let format = ValueFormat::default();
            let mut values = Values::default();
            values.set("id", "18446744073709551615".into());
            values.set("action", "pick".into());
            values.set("x", "1.5".into());
            values.set("program", "b2".into());
            let bytes = t.render(&values, &enums).unwrap();
            assert_eq!(bytes.len(), 4 + 8 + 2 + 4 + 8);
            assert_eq!(
                t.capture(&bytes, &enums, &format).unwrap(),
                Ok(values.clone())
            );
            let mut short = bytes.clone();
            short.pop();
            assert!(t.capture(&short, &enums, &format).unwrap().is_err());
            let mut other = bytes.clone();
            other[if order == ByteOrder::Big { 3 } else { 0 }] ^= 1;
            assert!(t.capture(&other, &enums, &format).unwrap().is_err());
            values.remove("x");
            let bytes = t.render(&values, &enums).unwrap();
            assert_eq!(t.capture(&bytes, &enums, &format).unwrap(), Ok(values));
        }
    }

    #[test]
    fn says_what_is_wrong_with_a_layout() {
        let order = ByteOrder::Big;
        assert!(BinaryTemplate::parse(&[field(FieldType::I16, "70000")], order).is_err());
        assert!(BinaryTemplate::parse(&[field(FieldType::I32, "a {id}")], order).is_err());
        let mut s = field(FieldType::Str, "{program}");
        s.bytes = None;
        assert!(BinaryTemplate::parse(&[s], order).is_err());
        assert!(BinaryTemplate::parse(&[], order).is_err());
    }
}

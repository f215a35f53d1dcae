//! A message template: literal text with placeholders, rendered one way and matched the
//! other.
//!
//! | syntax | meaning |
//! |---|---|
//! | `{name}` | the value `name` (`id`, `action`, `x`, `info.part`, `result`, ...) |
//! | `{name:table}` | the value `name` written as the dialect's `[enums.table]` says (`pick` -> `1`) |
//! | `{?name}...{/name}` | the text between, only when `name` has a value (`{?pose}`, `{?program}`) |
//! | `{{` and `}}` | a literal `{` and `}` |
//!
//! Rendering fills the placeholders (a value outside a section that has none is an
//! error); matching compiles the template to an anchored regular expression whose groups
//! capture the placeholders, so a reply the dialect describes as `Loading program:
//! {action:urp}` gives back the action it names. The expression is compiled when a
//! template is first matched, not when it is parsed: it is made of escaped literals and
//! fixed groups, so it cannot fail, and most templates (those a process only writes, a
//! literal, a lone value) are never matched by one. A holon's start compiles none.

use std::sync::OnceLock;

use regex::Regex;

use super::values::{Enums, Values};

/// One piece of a template.
#[derive(Debug, Clone, PartialEq)]
pub enum Piece {
    Literal(String),
    /// A placeholder: the value's name and the enum table that encodes it, if any.
    Value {
        name: String,
        table: Option<String>,
    },
    /// Text present only when `name` has a value.
    Section {
        name: String,
        body: Vec<Piece>,
    },
}

/// How values are written into the text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Escape {
    /// As they are (text lines, binary fields).
    Plain,
    /// XML-escaped (`<` -> `&lt;` ...).
    Xml,
}

/// A parsed template with its matcher.
#[derive(Debug, Clone)]
pub struct Template {
    /// The text as written in the dialect file (for messages).
    pub source: String,
    /// The literals, placeholders and sections, in order.
    pieces: Vec<Piece>,
    /// The anchored matcher, compiled from `pieces` when first needed; group `i + 1`
    /// captures `captures[i]`.
    matcher: OnceLock<Regex>,
    /// The placeholder of each capture group, in order: (name, table).
    captures: Vec<(String, Option<String>)>,
}

/// What is wrong with a template, or why a value cannot be rendered.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TemplateError {
    #[error("unclosed placeholder at byte {0} (a literal brace is written {{{{ or }}}})")]
    Unclosed(usize),
    #[error("a lone '}}' at byte {0} (a literal brace is written }}}})")]
    LoneBrace(usize),
    #[error(
        "{{{0}}} is not a placeholder name (letters, digits, _ and ., starting with a letter)"
    )]
    BadName(String),
    #[error("section {{?{0}}} is never closed with {{/{0}}}")]
    UnclosedSection(String),
    #[error("{{/{0}}} closes no open section")]
    StrayClose(String),
    #[error("no value for {{{0}}}")]
    Missing(String),
    #[error("{0}")]
    Enum(String),
}

fn valid_name(name: &str) -> bool {
    let mut chars = name.chars();
    chars.next().is_some_and(|c| c.is_ascii_lowercase())
        && chars.all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '.')
        && !name.ends_with('.')
}

fn parse_pieces(text: &str) -> Result<Vec<Piece>, TemplateError> {
    // A stack of open sections: (name, pieces so far).
    let mut stack: Vec<(String, Vec<Piece>)> = vec![(String::new(), Vec::new())];
    let mut literal = String::new();
    let bytes = text.as_bytes();
    let mut i = 0;
    let flush = |literal: &mut String, stack: &mut Vec<(String, Vec<Piece>)>| {
        if !literal.is_empty() {
            let top = stack.last_mut().expect("the root is never popped");
            top.1.push(Piece::Literal(std::mem::take(literal)));
        }
    };
    while i < bytes.len() {
        match bytes[i] {
            b'{' if bytes.get(i + 1) == Some(&b'{') => {
                literal.push('{');
                i += 2;
            }
            b'}' if bytes.get(i + 1) == Some(&b'}') => {
                literal.push('}');
                i += 2;
            }
            b'}' => return Err(TemplateError::LoneBrace(i)),
            b'{' => {
                let end = text[i..]
                    .find('}')
                    .map(|p| p + i)
                    .ok_or(TemplateError::Unclosed(i))?;
                let inner = &text[i + 1..end];
                flush(&mut literal, &mut stack);
                if let Some(name) = inner.strip_prefix('?') {
                    if !valid_name(name) {
                        return Err(TemplateError::BadName(inner.into()));
                    }
                    stack.push((name.to_string(), Vec::new()));
                } else if let Some(name) = inner.strip_prefix('/') {
                    if stack.len() < 2 || stack.last().map(|s| s.0.as_str()) != Some(name) {
                        return Err(TemplateError::StrayClose(name.into()));
                    }
                    let (name, body) = stack.pop().expect("checked above");
                    let top = stack.last_mut().expect("the root is never popped");
                    top.1.push(Piece::Section { name, body });
                } else {
                    let (name, table) = match inner.split_once(':') {
                        Some((name, table)) => (name, Some(table.to_string())),
                        None => (inner, None),
                    };
                    if !valid_name(name) || table.as_deref().is_some_and(|t| !valid_name(t)) {
                        return Err(TemplateError::BadName(inner.into()));
                    }
                    let top = stack.last_mut().expect("the root is never popped");
                    top.1.push(Piece::Value {
                        name: name.to_string(),
                        table,
                    });
                }
                i = end + 1;
            }
            _ => {
                // Copy one UTF-8 character.
                let c = text[i..].chars().next().expect("i is a char boundary");
                literal.push(c);
                i += c.len_utf8();
            }
        }
    }
    flush(&mut literal, &mut stack);
    if stack.len() > 1 {
        let open = stack.pop().expect("len > 1").0;
        return Err(TemplateError::UnclosedSection(open));
    }
    Ok(stack.pop().expect("the root").1)
}

fn pattern(pieces: &[Piece], captures: &mut Vec<(String, Option<String>)>, out: &mut String) {
    for piece in pieces {
        match piece {
            Piece::Literal(text) => out.push_str(&regex::escape(text)),
            Piece::Value { name, table } => {
                captures.push((name.clone(), table.clone()));
                out.push_str("(.*?)");
            }
            Piece::Section { body, .. } => {
                out.push_str("(?:");
                pattern(body, captures, out);
                out.push_str(")?");
            }
        }
    }
}

/// The anchored expression that matches `pieces` whole, and the placeholder each of its
/// groups captures, in order.
fn expression(pieces: &[Piece]) -> (String, Vec<(String, Option<String>)>) {
    let mut captures = Vec::new();
    let mut expression = String::from("(?s)^");
    pattern(pieces, &mut captures, &mut expression);
    expression.push('$');
    (expression, captures)
}

impl Template {
    /// Parses `text`.
    pub fn parse(text: &str) -> Result<Template, TemplateError> {
        let pieces = parse_pieces(text)?;
        let (_, captures) = expression(&pieces);
        Ok(Template {
            source: text.to_string(),
            pieces,
            matcher: OnceLock::new(),
            captures,
        })
    }

    /// The anchored matcher, compiled on first use.
    fn matcher(&self) -> &Regex {
        self.matcher.get_or_init(|| {
            let (expression, _) = expression(&self.pieces);
            Regex::new(&expression).expect("escaped literals and fixed groups")
        })
    }

    /// Every placeholder and section name, with its enum table if any.
    pub fn names(&self) -> Vec<(String, Option<String>)> {
        fn walk(pieces: &[Piece], out: &mut Vec<(String, Option<String>)>) {
            for piece in pieces {
                match piece {
                    Piece::Literal(_) => {}
                    Piece::Value { name, table } => out.push((name.clone(), table.clone())),
                    Piece::Section { name, body } => {
                        out.push((format!("?{name}"), None));
                        walk(body, out);
                    }
                }
            }
        }
        let mut out = Vec::new();
        walk(&self.pieces, &mut out);
        out
    }

    /// Whether the template is plain text with no placeholder.
    pub fn literal(&self) -> Option<&str> {
        match self.pieces.as_slice() {
            [] => Some(""),
            [Piece::Literal(text)] => Some(text),
            _ => None,
        }
    }

    /// The template's one placeholder, when it is nothing else (`{id}`).
    pub fn single_value(&self) -> Option<(&str, Option<&str>)> {
        match self.pieces.as_slice() {
            [Piece::Value { name, table }] => Some((name, table.as_deref())),
            _ => None,
        }
    }

    /// Renders with `values`; each value goes through its enum table and then `escape`.
    pub fn render(
        &self,
        values: &Values,
        enums: &Enums,
        escape: Escape,
    ) -> Result<String, TemplateError> {
        self.render_from(&|name| values.get(name), enums, escape)
    }

    /// Renders with the values `lookup` finds (e.g. a reply's, then its command's).
    pub fn render_from<'v>(
        &self,
        lookup: &dyn Fn(&str) -> Option<&'v str>,
        enums: &Enums,
        escape: Escape,
    ) -> Result<String, TemplateError> {
        fn walk<'v>(
            pieces: &[Piece],
            lookup: &dyn Fn(&str) -> Option<&'v str>,
            enums: &Enums,
            escape: Escape,
            out: &mut String,
        ) -> Result<(), TemplateError> {
            for piece in pieces {
                match piece {
                    Piece::Literal(text) => out.push_str(text),
                    Piece::Value { name, table } => {
                        let value =
                            lookup(name).ok_or_else(|| TemplateError::Missing(name.clone()))?;
                        let wire = match table {
                            Some(table) => {
                                enums.encode(table, value).map_err(TemplateError::Enum)?
                            }
                            None => value,
                        };
                        match escape {
                            Escape::Plain => out.push_str(wire),
                            Escape::Xml => out.push_str(&quick_xml::escape::escape(wire)),
                        }
                    }
                    Piece::Section { name, body } => {
                        if lookup(name).is_some() {
                            walk(body, lookup, enums, escape, out)?;
                        }
                    }
                }
            }
            Ok(())
        }
        let mut out = String::with_capacity(self.source.len() + 32);
        walk(&self.pieces, lookup, enums, escape, &mut out)?;
        Ok(out)
    }

    /// Matches `text` whole; on a match, the captured values (decoded through their enum
    /// tables) are added to `values`. `Ok(false)`: the text does not have this shape;
    /// `Err`: it has, but a captured value is not in its enum table.
    pub fn capture(&self, text: &str, enums: &Enums, values: &mut Values) -> Result<bool, String> {
        // The common shapes without the regular expression: a literal, one value.
        match self.pieces.as_slice() {
            [] => return Ok(text.is_empty()),
            [Piece::Literal(literal)] => return Ok(text == literal),
            [Piece::Value { name, table }] => {
                let value = match table {
                    Some(table) => enums.decode(table, text)?.to_string(),
                    None => text.to_string(),
                };
                if let Some(earlier) = values.get(name) {
                    if earlier != value {
                        return Err(format!(
                            "{name} is {earlier:?} in one place and {value:?} in another"
                        ));
                    }
                }
                values.set(name, value);
                return Ok(true);
            }
            _ => {}
        }
        let Some(found) = self.matcher().captures(text) else {
            return Ok(false);
        };
        for (i, (name, table)) in self.captures.iter().enumerate() {
            let Some(group) = found.get(i + 1) else {
                continue; // in a section that is absent
            };
            let value = match table {
                Some(table) => enums.decode(table, group.as_str())?.to_string(),
                None => group.as_str().to_string(),
            };
            if let Some(earlier) = values.get(name) {
                if earlier != value {
                    return Err(format!(
                        "{name} is {earlier:?} in one place and {value:?} in another"
                    ));
                }
            }
            values.set(name, value);
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_and_captures_the_same_values() {
        let mut enums = Enums::default();
        enums.insert("urp", "pick", vec!["pick.urp".into()]);
        let t = Template::parse("load {action:urp}{?program} for {program}{/program}").unwrap();
        let mut values = Values::default();
        values.set("action", "pick".into());
        assert_eq!(
            t.render(&values, &enums, Escape::Plain).unwrap(),
            "load pick.urp"
        );
        values.set("program", "b2".into());
        let text = t.render(&values, &enums, Escape::Plain).unwrap();
        assert_eq!(text, "load pick.urp for b2");
        let mut back = Values::default();
        assert_eq!(t.capture(&text, &enums, &mut back), Ok(true));
        assert_eq!(back, values);
        assert_eq!(t.capture("unload pick.urp", &enums, &mut back), Ok(false));
        let mut other = Values::default();
        assert!(t.capture("load weld.urp", &enums, &mut other).is_err());
    }

    #[test]
    fn says_what_is_wrong() {
        let error = |t: &str| Template::parse(t).unwrap_err();
        assert_eq!(error("a {id"), TemplateError::Unclosed(2));
        assert_eq!(error("a }"), TemplateError::LoneBrace(2));
        assert_eq!(
            error("{?pose}x"),
            TemplateError::UnclosedSection("pose".into())
        );
        assert_eq!(error("x{/pose}"), TemplateError::StrayClose("pose".into()));
        assert_eq!(
            error("{Bad Name}"),
            TemplateError::BadName("Bad Name".into())
        );
        let t = Template::parse("{{literal}} {id}").unwrap();
        assert_eq!(
            t.render(&Values::default(), &Enums::default(), Escape::Plain),
            Err(TemplateError::Missing("id".into()))
        );
    }
}

//! XML messages: a template written as the document itself, placeholders in text and
//! attribute values, `{?name}...{/name}` around elements that may be absent.
//!
//! Writing renders the template text, each value XML-escaped. Reading parses the
//! document (no DOCTYPE, no entities but the predefined five) and walks it against the
//! template's shape: the root's name must be the template's; each element of the template
//! is looked for by name among its parent's children (the first one counts; others, and
//! elements the template does not name, are ignored, as are attributes it does not
//! name); text is compared trimmed. An element in a section may be missing; any other
//! element or attribute missing means the document is not this message.

use quick_xml::events::Event;
use quick_xml::Reader;

use super::template::{Escape, Template};
use super::values::{Enums, Values};
use crate::codec::Element;

/// The shape of one element of a template.
#[derive(Debug, Clone)]
pub struct Shape {
    name: String,
    attributes: Vec<(String, Template)>,
    /// The element's text, if the template gives any.
    text: Option<Template>,
    /// Child shapes, each with the section it is in (may be absent) if any.
    children: Vec<(Shape, Option<String>)>,
}

/// An XML message template.
#[derive(Debug, Clone)]
pub struct XmlTemplate {
    pub text: Template,
    root: Shape,
}

fn template(text: &str) -> Result<Template, String> {
    Template::parse(text).map_err(|e| e.to_string())
}

impl XmlTemplate {
    pub fn parse(source: &str) -> Result<XmlTemplate, String> {
        let text = template(source)?;
        let mut reader = Reader::from_str(source);
        reader.config_mut().check_end_names = true;
        // Open elements, and the section each new child would be in.
        let mut stack: Vec<Shape> = Vec::new();
        let mut section: Vec<Option<String>> = vec![None];
        let mut root = None;
        let open = |e: &quick_xml::events::BytesStart<'_>| -> Result<Shape, String> {
            let name = String::from_utf8(e.name().as_ref().to_vec()).map_err(|e| e.to_string())?;
            let mut attributes = Vec::new();
            for a in e.attributes() {
                let a = a.map_err(|e| e.to_string())?;
                let key = String::from_utf8(a.key.as_ref().to_vec()).map_err(|e| e.to_string())?;
                let value = a.unescape_value().map_err(|e| e.to_string())?;
                attributes.push((key, template(&value)?));
            }
            Ok(Shape {
                name,
                attributes,
                text: None,
                children: Vec::new(),
            })
        };
        loop {
            let event = reader
                .read_event()
                .map_err(|e| format!("not well-formed XML: {e}"))?;
            match event {
                Event::Start(e) => {
                    stack.push(open(&e)?);
                    section.push(None);
                }
                Event::Empty(e) => {
                    let shape = open(&e)?;
                    match stack.last_mut() {
                        Some(parent) => parent
                            .children
                            .push((shape, section.last().cloned().flatten())),
                        None => root = Some(shape),
                    }
                }
                Event::End(_) => {
                    let shape = stack.pop().ok_or("an end tag closes nothing")?;
                    if let Some(Some(open)) = section.pop() {
                        return Err(format!(
                            "section {{?{open}}} is not closed in <{}>",
                            shape.name
                        ));
                    }
                    match stack.last_mut() {
                        Some(parent) => parent
                            .children
                            .push((shape, section.last().cloned().flatten())),
                        None => root = Some(shape),
                    }
                }
                Event::Text(t) => {
                    let t = t.decode().map_err(|e| e.to_string())?;
                    let trimmed = t.trim();
                    if trimmed.is_empty() {
                        continue;
                    }
                    let Some(element) = stack.last_mut() else {
                        return Err("text outside the root element".into());
                    };
                    // Section markers between child elements, or the element's text.
                    match section_markers(trimmed) {
                        Some(markers) => {
                            for (open, name) in markers {
                                let current = section.last_mut().expect("one per open element");
                                match (open, current.as_deref()) {
                                    (true, None) => *current = Some(name),
                                    (true, Some(other)) => {
                                        return Err(format!("{{?{name}}} opens inside {{?{other}}} in <{}>: sections of elements do not nest", element.name))
                                    }
                                    (false, Some(open)) if open == name => *current = None,
                                    (false, _) => {
                                        return Err(format!("{{/{name}}} closes no open section in <{}>", element.name))
                                    }
                                }
                            }
                        }
                        None => element.text = Some(template(trimmed)?),
                    }
                }
                Event::GeneralRef(_) => {
                    return Err(
                        "entities are not allowed in a template (write the character)".into(),
                    )
                }
                Event::CData(_) | Event::DocType(_) | Event::PI(_) => {
                    return Err(
                        "CDATA, DOCTYPE and processing instructions are not allowed in a template"
                            .into(),
                    )
                }
                Event::Decl(_) | Event::Comment(_) => {}
                Event::Eof => break,
            }
        }
        let root = root.ok_or("no root element")?;
        Ok(XmlTemplate { text, root })
    }

    /// The root element's name.
    pub fn root_name(&self) -> &str {
        &self.root.name
    }

    pub fn render(&self, values: &Values, enums: &Enums) -> Result<String, String> {
        self.text
            .render(values, enums, Escape::Xml)
            .map_err(|e| e.to_string())
    }

    /// Reads `element` as this message: `Ok(None)` when it has another shape (with why).
    pub fn capture(
        &self,
        element: &Element,
        enums: &Enums,
    ) -> Result<Result<Values, String>, String> {
        let mut values = Values::default();
        match walk(&self.root, element, enums, &mut values)? {
            Ok(()) => Ok(Ok(values)),
            Err(why) => Ok(Err(why)),
        }
    }
}

/// Reads text made only of section markers (`{/program}{?pose}`): (opens, name) each.
fn section_markers(text: &str) -> Option<Vec<(bool, String)>> {
    let mut markers = Vec::new();
    let mut rest = text.trim();
    while !rest.is_empty() {
        let open = if rest.starts_with("{?") {
            true
        } else if rest.starts_with("{/") {
            false
        } else {
            return None;
        };
        let end = rest.find('}')?;
        markers.push((open, rest[2..end].to_string()));
        rest = rest[end + 1..].trim_start();
    }
    Some(markers)
}

/// Matches one element: `Err` is a value that breaks an enum (an error), `Ok(Err)` a
/// document of another shape.
fn walk(
    shape: &Shape,
    element: &Element,
    enums: &Enums,
    values: &mut Values,
) -> Result<Result<(), String>, String> {
    if shape.name != element.name {
        return Ok(Err(format!("<{}> is not <{}>", element.name, shape.name)));
    }
    for (key, template) in &shape.attributes {
        let Some(value) = element.attribute(key) else {
            return Ok(Err(format!("<{}> lacks the attribute {key}", shape.name)));
        };
        if !template.capture(value.trim(), enums, values)? {
            return Ok(Err(format!("<{}> has {key}={value:?}", shape.name)));
        }
    }
    if let Some(template) = &shape.text {
        let text = element.text.trim();
        if !template.capture(text, enums, values)? {
            return Ok(Err(format!("<{}> holds {text:?}", shape.name)));
        }
    }
    for (child, section) in &shape.children {
        match element.child(&child.name) {
            Some(found) => {
                if let Err(why) = walk(child, found, enums, values)? {
                    return Ok(Err(why));
                }
                if let Some(section) = section {
                    if !values.contains(section) {
                        values.set(section, String::new());
                    }
                }
            }
            None if section.is_some() => {}
            None => {
                return Ok(Err(format!("<{}> lacks <{}>", shape.name, child.name)));
            }
        }
    }
    Ok(Ok(()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::parse_tree;

    const CMD: &str = r#"<ROBOT_CMD><ID>{id}</ID><ACTION>{action}</ACTION>{?program}<PROGRAM>{program}</PROGRAM>{/program}{?pose}<POS X="{x}" Y="{y}"></POS>{/pose}</ROBOT_CMD>"#;

    #[test]
    fn renders_and_reads_back() {
        let t = XmlTemplate::parse(CMD).unwrap();
        let enums = Enums::default();
        let mut values = Values::default();
        values.set("id", "3".into());
        values.set("action", "a<b".into());
        assert_eq!(
            t.render(&values, &enums).unwrap(),
            "<ROBOT_CMD><ID>3</ID><ACTION>a&lt;b</ACTION></ROBOT_CMD>"
        );
        values.set("pose", String::new());
        values.set("x", "1.0".into());
        values.set("y", "-2.5".into());
        let text = t.render(&values, &enums).unwrap();
        let back = t
            .capture(&parse_tree(text.as_bytes()).unwrap(), &enums)
            .unwrap()
            .unwrap();
        assert_eq!(back, values);
        let other = parse_tree(b"<ROBOT_CMD><ACTION>x</ACTION></ROBOT_CMD>").unwrap();
        assert_eq!(
            t.capture(&other, &enums).unwrap(),
            Err("<ROBOT_CMD> lacks <ID>".to_string())
        );
    }

    #[test]
    fn says_what_is_wrong_with_a_template() {
        assert!(XmlTemplate::parse("<A><B></A>").is_err());
        assert!(XmlTemplate::parse("<A>{?x}<B/></A>").is_err());
        assert!(XmlTemplate::parse("<A>{?x}{?y}<B/>{/y}{/x}</A>")
            .unwrap_err()
            .contains("do not nest"));
        assert!(XmlTemplate::parse("<A>&custom;</A>").is_err());
        assert!(XmlTemplate::parse("no xml").is_err());
    }
}

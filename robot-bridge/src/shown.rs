//! How a controller's message is shown in a log line or an error: text escaped, not
//! hex, where the framing carries text.

/// A message as shown in a log or an error, bounded: a text line or an XML document as
/// text, quoted and escaped (`"\x01garbage \xff\xfe"`: a control character or a byte
/// that is not UTF-8 escaped, the rest as it came), a binary message in hex.
pub fn shown(frame: &[u8], binary: bool) -> String {
    let head = &frame[..frame.len().min(120)];
    let text = if binary {
        head.iter().map(|b| format!("{b:02x}")).collect::<String>()
    } else {
        escaped(head)
    };
    if frame.len() > head.len() {
        format!("{text}... ({} bytes)", frame.len())
    } else {
        text
    }
}

/// Bytes as a quoted, escaped string: valid UTF-8 as Rust's `{:?}` writes a string,
/// each byte that is not as `\xNN`.
pub fn escaped(bytes: &[u8]) -> String {
    let mut out = String::from("\"");
    for chunk in bytes.utf8_chunks() {
        for c in chunk.valid().chars() {
            out.extend(c.escape_debug());
        }
        for b in chunk.invalid() {
            out.push_str(&format!("\\x{b:02x}"));
        }
    }
    out.push('"');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn text_is_shown_escaped_binary_in_hex() {
        assert_eq!(shown(b"HELLO", false), "\"HELLO\"");
        assert_eq!(
            shown(b"\x01garbage \xff\xfe", false),
            "\"\\u{1}garbage \\xff\\xfe\""
        );
        assert_eq!(shown(b"STATE \"X\"\r", false), "\"STATE \\\"X\\\"\\r\"");
        assert_eq!(shown(b"\xde\xad", true), "dead");
        let long = vec![b'x'; 200];
        assert!(shown(&long, false).ends_with("... (200 bytes)"));
    }
}

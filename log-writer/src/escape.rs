//! One event, one line: what a client sent (a product name with a newline, a terminal
//! escape sequence in a user name) cannot split a log line, forge the next one, or drive
//! the terminal that shows it. Every control character of an event's text but its
//! final newline and tabs is written escaped: `\n`, `\r`, `\x1b`, `\u{85}`.
//!
//! A terminal that shows colours keeps the escape character (the formatter's own
//! colour codes are made of it); a file, a pipe and JSON lines never do.

/// Whether `byte` starts something to escape (a C0 control other than a tab, DEL, or
/// the lead byte of a C1 control in UTF-8).
fn suspect(byte: u8) -> bool {
    (byte < 0x20 && byte != b'\t') || byte == 0x7f || byte == 0xc2
}

/// `line` with its control characters escaped (the final newline kept); `keep_esc`
/// keeps the escape character (a colour terminal). Returns the line as it was when it
/// holds nothing to escape.
pub fn escaped(line: &[u8], keep_esc: bool) -> std::borrow::Cow<'_, [u8]> {
    let (body, end) = match line.strip_suffix(b"\n") {
        Some(body) => (body, &b"\n"[..]),
        None => (line, &b""[..]),
    };
    if !body.iter().any(|&b| suspect(b) && !(keep_esc && b == 0x1b)) {
        return std::borrow::Cow::Borrowed(line);
    }
    let mut out = Vec::with_capacity(line.len() + 16);
    let mut bytes = body.iter().copied().peekable();
    while let Some(byte) = bytes.next() {
        match byte {
            b'\n' => out.extend_from_slice(b"\\n"),
            b'\r' => out.extend_from_slice(b"\\r"),
            0x1b if keep_esc => out.push(byte),
            0xc2 => match bytes.peek() {
                // U+0080..U+009F, the C1 controls (CSI among them).
                Some(&next) if (0x80..=0x9f).contains(&next) => {
                    bytes.next();
                    out.extend_from_slice(format!("\\u{{{next:x}}}").as_bytes());
                }
                _ => out.push(byte),
            },
            b if suspect(b) => out.extend_from_slice(format!("\\x{b:02x}").as_bytes()),
            b => out.push(b),
        }
    }
    out.extend_from_slice(end);
    std::borrow::Cow::Owned(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_client_cannot_split_forge_or_colour_a_line() {
        let forged = "product=\"x\nINFO forged line\r\x1b[31mred\x07\u{9b}2J\u{e9}\"\n";
        let line = escaped(forged.as_bytes(), false);
        assert_eq!(
            std::str::from_utf8(&line).unwrap(),
            "product=\"x\\nINFO forged line\\r\\x1b[31mred\\x07\\u{9b}2J\u{e9}\"\n"
        );
        // A colour terminal keeps ESC (the formatter's colours), and nothing else.
        let coloured = escaped("\x1b[2mtime\x1b[0m a\nb\n".as_bytes(), true);
        assert_eq!(&*coloured, "\x1b[2mtime\x1b[0m a\\nb\n".as_bytes());
        // A plain line is not copied.
        assert!(matches!(
            escaped(b"plain\tline\n", false),
            std::borrow::Cow::Borrowed(_)
        ));
    }
}

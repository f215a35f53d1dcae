//! zenoh's errors as an operator reads them.
//!
//! zenoh appends where in its own source an error was made (`... at
//! /root/.cargo/registry/src/.../zenoh-link-tcp-1.10.2/src/unicast.rs:338.`): a path of
//! the machine that built the binary, meaningless on a plant's host. [`describe`] keeps
//! the message and drops those locations.

/// The text of a zenoh error without its source locations.
pub fn describe(error: &dyn std::fmt::Display) -> String {
    without_source_locations(&error.to_string())
}

/// Removes every ` at /<path>.rs:<line>` (and the `.` after it) from `text`.
pub fn without_source_locations(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(at) = rest.find(" at /") {
        let after = &rest[at + " at ".len()..];
        let end = after
            .find(|c: char| c.is_whitespace() || c == ']')
            .unwrap_or(after.len());
        let location = &after[..end];
        let is_source = location
            .trim_end_matches('.')
            .rsplit_once(".rs:")
            .is_some_and(|(_, line)| !line.is_empty() && line.bytes().all(|b| b.is_ascii_digit()));
        if is_source {
            out.push_str(&rest[..at]);
        } else {
            out.push_str(&rest[..at + " at ".len()]);
            out.push_str(location);
        }
        rest = &after[end..];
    }
    out.push_str(rest);
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drops_the_build_machines_source_locations() {
        let zenoh = "Can not create a new TCP listener bound to tcp/1.2.3.4:5: [1.2.3.4:5: Cannot assign requested address (os error 99) at /root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/zenoh-link-commons-1.10.2/src/tcp.rs:61.] at /root/.cargo/registry/src/index.crates.io-1949cf8c6b5b557f/zenoh-link-tcp-1.10.2/src/unicast.rs:338.";
        assert_eq!(
            without_source_locations(zenoh),
            "Can not create a new TCP listener bound to tcp/1.2.3.4:5: [1.2.3.4:5: Cannot assign requested address (os error 99)]"
        );
        assert_eq!(
            without_source_locations("Unable to connect to any of [Single(tcp/127.0.0.1:1)]. Timeout! at /root/zenoh-1.10.2/src/net/runtime/orchestrator.rs:388."),
            "Unable to connect to any of [Single(tcp/127.0.0.1:1)]. Timeout!"
        );
        // Anything else that says "at /" stays.
        assert_eq!(
            without_source_locations("cannot write at /var/lib/holarchy: full"),
            "cannot write at /var/lib/holarchy: full"
        );
    }
}

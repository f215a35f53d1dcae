//! The `departed` outcome: a transporter's move has left its origin; the command goes
//! on, and still ends with its own reply.

use super::*;

/// `base` with a `departed` reply `text` expected by its only element.
fn with_departed(base: &str, expect: &str, text: &str) -> String {
    format!(
        "{}\n[[reply]]\nname = \"left\"\noutcome = \"departed\"\ntext = \"{text}\"\n",
        base.replace(
            expect,
            &expect.replace("expect = [", "expect = [\"left\", ")
        )
    )
}

#[test]
fn holarchy_xml_says_a_departure_with_the_command_id() {
    let dialect = Dialect::holarchy_xml();
    let departed = dialect.reply_index("departed").unwrap();
    assert_eq!(dialect.replies[departed].outcome, Outcome::Departed);
    // The command that moves (every action's one) accepts it.
    assert!(dialect.sequence[0].expect.contains(&departed));
    let mut values = Values::default();
    values.set("id", "7".into());
    let written = dialect
        .write(dialect.replies[departed].body.as_ref().unwrap(), &values)
        .unwrap();
    assert_eq!(written, b"<ROBOT_DEPARTED><ID>7</ID></ROBOT_DEPARTED>");
    let parsed = dialect.parse(&written).unwrap();
    let read = dialect.read_reply(departed, &parsed).unwrap().unwrap();
    assert_eq!(read.get("id"), Some("7"));
    // No other reply takes it: it is neither the result nor an error.
    for (i, _) in dialect
        .replies
        .iter()
        .enumerate()
        .filter(|&(i, _)| i != departed)
    {
        assert_eq!(dialect.read_reply(i, &parsed), Ok(None), "{i}");
    }
    // Nor is a result a departure.
    let result = dialect
        .parse(b"<ROBOT_REPLY><ID>7</ID><RESULT>arrived</RESULT></ROBOT_REPLY>")
        .unwrap();
    assert_eq!(dialect.read_reply(departed, &result), Ok(None));
    // A departure naming no command is a wrong value, as any reply's id.
    let bad = dialect
        .parse(b"<ROBOT_DEPARTED><ID>x</ID></ROBOT_DEPARTED>")
        .unwrap();
    assert!(dialect.read_reply(departed, &bad).is_err());
}

#[test]
fn a_departed_reply_compiles_beside_the_others() {
    let minimal = with_departed(MINIMAL, "expect = [\"ok\", \"no\"]", "LEFT");
    let dialect = Dialect::from_toml(&minimal, "left.toml").unwrap();
    let left = dialect.reply_index("left").unwrap();
    assert_eq!(dialect.replies[left].outcome, Outcome::Departed);
    assert_eq!(dialect.sequence[0].expect[0], left);
    // With ids, a departure that names its command.
    let example = job_ack_end();
    let expect = "expect = [\"ack\", \"end_ok\", \"end_fail\", \"nak\"]";
    let with_id = with_departed(&example, expect, "LEFT {id}");
    let dialect = Dialect::from_toml(&with_id, "left.toml").unwrap();
    assert!(dialect.reply_reads(dialect.reply_index("left").unwrap(), "id"));
}

#[test]
fn a_file_with_a_departed_reply_still_refuses_what_is_wrong() {
    let minimal = with_departed(MINIMAL, "expect = [\"ok\", \"no\"]", "LEFT");
    let cases: &[(&str, &str, &str)] = &[
        // What any reply is refused for.
        (
            "text = \"LEFT\"",
            "text = \"LEFT {idd}\"",
            "{idd} is not a value here",
        ),
        (
            "outcome = \"departed\"",
            "outcome = \"departd\"",
            "unknown variant",
        ),
        (
            "text = \"GO {action}\"",
            "text = \"GO {acton}\"",
            "{acton} is not a value here",
        ),
        // A departure ends nothing: it is not alone in an element's answers.
        (
            "expect = [\"left\", \"ok\", \"no\"]",
            "expect = [\"left\"]",
            "a `departed` reply does not end the element",
        ),
        // Nor is it the last element's end.
        (
            "expect = [\"left\", \"ok\", \"no\"]",
            "expect = [\"left\", \"no\"]",
            "the last element must expect a `done` reply",
        ),
    ];
    for (from, to, want) in cases {
        assert!(minimal.contains(from), "{from}");
        let err = error_of(&minimal.replace(from, to));
        assert!(err.contains(want), "{from} -> {to}: {err}");
    }
    // With ids, a departure that names no command could not be told apart.
    let example = job_ack_end();
    let expect = "expect = [\"ack\", \"end_ok\", \"end_fail\", \"nak\"]";
    let err = error_of(&with_departed(&example, expect, "LEFT"));
    assert!(
        err.contains("reply \"left\"") && err.contains("a `departed` reply carries {id}"),
        "{err}"
    );
    // An abort is not answered by a departure.
    let abort = with_departed(MINIMAL, "expect = [\"ok\", \"no\"]", "LEFT").replace(
        "[framing]",
        "abort = { send = \"stop\", expect = [\"left\"] }\n[framing]",
    ) + "[[command]]\nname = \"stop\"\ntext = \"STOP\"\n";
    let err = error_of(&abort);
    assert!(err.contains("abort.expect"), "{err}");
}

#[test]
fn a_poll_is_not_answered_by_a_departure() {
    // ur-dashboard polls programState until the program has stopped: a departure
    // among a poll's answers would leave the poll waiting for ever.
    let ur = SHIPPED
        .iter()
        .find(|(n, _)| *n == "ur-dashboard")
        .unwrap()
        .1;
    let expect = "expect = [\"running\", \"stopped\", \"paused\"]";
    assert!(ur.contains(expect));
    let err = error_of(&with_departed(ur, expect, "LEFT"));
    assert!(
        err.contains("a poll cannot expect a `departed` reply"),
        "{err}"
    );
    // On the element that sends the command it is taken.
    let expect = "expect = [\"playing\", \"play_failed\"]";
    assert!(ur.contains(expect));
    Dialect::from_toml(&with_departed(ur, expect, "LEFT"), "ur.toml").unwrap();
}

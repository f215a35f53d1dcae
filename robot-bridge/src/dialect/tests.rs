//! The dialect format: the shipped dialects, holarchy-xml against the codec byte for
//! byte, and the errors a bad file gets.

use super::*;
use crate::codec::{encode_abort, encode_message, parse_document};
use proptest::prelude::*;
use schemas::{Pose, RobotCommand, RobotMessage, RobotReply};

fn command(id: u64, action: &str, pos: Option<Pose>, program: Option<&str>) -> RobotCommand {
    RobotCommand {
        id,
        action: action.into(),
        pos,
        program: program.map(str::to_string),
        info: Default::default(),
    }
}

#[test]
fn every_shipped_dialect_is_valid_and_simulatable() {
    for (name, _) in SHIPPED {
        let dialect = Dialect::shipped(name).unwrap();
        assert_eq!(dialect.name, *name);
        dialect.check_simulatable().unwrap();
    }
    assert!(matches!(
        Dialect::shipped("fanuc"),
        Err(DialectError::Unknown(_))
    ));
}

#[test]
fn every_shipped_dialect_can_abort_and_writes_its_abort() {
    for (name, _) in SHIPPED {
        let dialect = Dialect::shipped(name).unwrap();
        assert!(dialect.can_abort(), "{name}");
        dialect.check_action("pick").unwrap();
        let abort = dialect.abort.as_ref().unwrap();
        let values = command_values(&command(7, "pick", None, None), &dialect.format);
        let written = dialect.write_command(abort.command, &values).unwrap();
        // robot-sim tells it from every other command.
        let parsed = dialect.parse(&written).unwrap();
        let first = (0..dialect.commands.len())
            .find(|&i| dialect.read_command(i, &parsed).unwrap().is_some());
        assert_eq!(first, Some(abort.command), "{name}");
    }
    let minimal = Dialect::from_toml(MINIMAL, "test.toml").unwrap();
    assert!(!minimal.can_abort());
}

#[test]
fn holarchy_xml_aborts_as_the_codec_writes_it() {
    let dialect = Dialect::holarchy_xml();
    let abort = dialect.abort.as_ref().unwrap();
    assert!(abort.expect.is_empty());
    for id in [1, 42, u64::MAX] {
        let values = command_values(&command(id, "pick", None, Some("b2")), &dialect.format);
        let written = dialect.write_command(abort.command, &values).unwrap();
        assert_eq!(String::from_utf8(written).unwrap(), encode_abort(id));
    }
}

#[test]
fn holarchy_xml_writes_what_the_codec_writes() {
    let dialect = Dialect::holarchy_xml();
    let pose = Pose {
        x: 100.0,
        y: -0.1,
        z: 1e16,
        a: 1e-5,
        b: 0.0,
        c: -180.0,
    };
    for cmd in [
        command(1, "pick", Some(pose), None),
        command(2, "place", None, Some("b2.1")),
        command(u64::MAX, "a&b", Some(pose), Some("x")),
        command(3, "inspect", None, None),
    ] {
        let values = command_values(&cmd, &dialect.format);
        let written = dialect.write_command(0, &values).unwrap();
        assert_eq!(
            String::from_utf8(written).unwrap(),
            encode_message(&RobotMessage::Command(cmd))
        );
    }
}

/// What the dialect makes of a reply document, as the codec's message.
fn read_as_codec(dialect: &Dialect, doc: &str) -> Result<RobotMessage, String> {
    let parsed = dialect.parse(doc.as_bytes()).map_err(|e| e.to_string())?;
    for i in 0..dialect.replies.len() {
        if let Some(values) = dialect.read_reply(i, &parsed)? {
            let reply = &dialect.replies[i];
            let id = values.get("id").map(|id| id.parse().unwrap());
            return Ok(match reply.outcome {
                Outcome::Status => RobotMessage::Status(dialect.state_of(i, &values)?),
                Outcome::Done => RobotMessage::Reply(RobotReply {
                    id: id.unwrap(),
                    result: dialect.evaluate(&reply.result, &values, &Values::default()),
                    message: None,
                }),
                _ => {
                    let message = dialect.evaluate(&reply.message, &values, &Values::default());
                    RobotMessage::Reply(RobotReply {
                        id: id.unwrap(),
                        result: "error".into(),
                        message: (!message.is_empty()).then_some(message),
                    })
                }
            });
        }
    }
    Err("no rule".into())
}

#[test]
fn holarchy_xml_reads_what_the_codec_reads() {
    let dialect = Dialect::holarchy_xml();
    for doc in [
        "<ROBOT_REPLY><ID>42</ID><RESULT>picking_done</RESULT></ROBOT_REPLY>",
        "<ROBOT_REPLY><ID>43</ID><RESULT>error</RESULT><MESSAGE>gripper &amp; empty</MESSAGE></ROBOT_REPLY>",
        "<ROBOT_REPLY><ID>43</ID><RESULT>error</RESULT></ROBOT_REPLY>",
        "<ROBOT_REPLY><ID> 7 </ID><RESULT> arrived </RESULT><EXTRA/></ROBOT_REPLY>",
        "<ROBOT_STATUS><STATE>estop</STATE></ROBOT_STATUS>",
        "<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>",
    ] {
        let codec = parse_document(doc.as_bytes()).unwrap();
        assert_eq!(read_as_codec(&dialect, doc), Ok(codec), "{doc}");
    }
    // What the codec refuses, the dialect refuses.
    for doc in [
        "<ROBOT_REPLY><ID>x</ID><RESULT>done</RESULT></ROBOT_REPLY>",
        "<ROBOT_REPLY><ID>1</ID></ROBOT_REPLY>",
        "<ROBOT_STATUS><STATE>sleepy</STATE></ROBOT_STATUS>",
        "<HELLO/>",
        "<ROBOT_CMD><ID>1</ID><ACTION>pick</ACTION></ROBOT_CMD>",
    ] {
        assert!(parse_document(doc.as_bytes()).is_err() || doc.starts_with("<ROBOT_CMD"));
        assert!(read_as_codec(&dialect, doc).is_err(), "{doc}");
    }
}

proptest! {
    #[test]
    fn holarchy_xml_matches_the_codec_for_any_command(
        id in any::<u64>(),
        action in "[a-z0-9_-]{1,12}",
        coords in proptest::collection::vec(-1e7f64..1e7, 6),
        program in proptest::option::of("[A-Za-z0-9_.-]{1,20}"),
        with_pose in any::<bool>(),
        material in proptest::collection::vec(proptest::option::of("[a-z0-9][a-z0-9_.-]{0,20}"), 3),
    ) {
        let dialect = Dialect::holarchy_xml();
        let pose = with_pose.then(|| Pose { x: coords[0], y: coords[1], z: coords[2], a: coords[3], b: coords[4], c: coords[5] });
        let mut cmd = command(id, &action, pose, program.as_deref());
        // The part and where it moves (material flow), each where the job names it.
        for ((_, key), value) in crate::codec::MATERIAL_FIELDS.iter().zip(&material) {
            if let Some(value) = value {
                cmd.info.insert(key.to_string(), serde_json::Value::from(value.as_str()));
            }
        }
        let values = command_values(&cmd, &dialect.format);
        let written = dialect.write_command(0, &values).unwrap();
        prop_assert_eq!(String::from_utf8(written.clone()).unwrap(), encode_message(&RobotMessage::Command(cmd.clone())));
        // And robot-sim reads back what the holon wrote.
        let back = dialect.read_command(0, &dialect.parse(&written).unwrap()).unwrap().unwrap();
        prop_assert_eq!(back, values);
        // And the codec reads the same command back.
        let RobotMessage::Command(read) = parse_document(&written).unwrap() else { panic!("a command") };
        prop_assert_eq!(read, cmd);
    }
}

const MINIMAL: &str = r#"
name = "tiny"
correlation = "one_in_flight"
sequence = [ { send = "go", expect = ["ok", "no"] } ]
[framing]
kind = "line"
[status]
source = "connection"
[[command]]
name = "go"
text = "GO {action}"
[[reply]]
name = "ok"
outcome = "done"
text = "OK"
result = "{action}_done"
[[reply]]
name = "no"
outcome = "failed"
text = "NO {message}"
"#;

fn error_of(text: &str) -> String {
    Dialect::from_toml(text, "test.toml")
        .unwrap_err()
        .to_string()
}

#[test]
fn a_minimal_dialect_loads() {
    let dialect = Dialect::from_toml(MINIMAL, "test.toml").unwrap();
    assert_eq!(dialect.status, Status::Connection);
    assert_eq!(
        dialect.framing,
        Framing::Line {
            terminator: b"\n".to_vec()
        }
    );
    assert!(dialect.sequence[0].starts);
}

#[test]
fn a_bad_dialect_names_the_field_and_the_problem() {
    let cases: &[(&str, &str, &str)] = &[
        (
            "text = \"GO {action}\"",
            "text = \"GO {acton}\"",
            "command[0] (go): {acton} is not a value here",
        ),
        (
            "text = \"GO {action}\"",
            "text = \"GO {action\"",
            "command[0] (go).text: unclosed placeholder",
        ),
        (
            "text = \"GO {action}\"",
            "text = \"GO {action:codes}\"",
            "names no [enums.codes]",
        ),
        (
            "text = \"GO {action}\"",
            "xml = \"<GO/>\"",
            "so the message is given as `text`",
        ),
        (
            "expect = [\"ok\", \"no\"]",
            "expect = [\"ok\", \"maybe\"]",
            "sequence[0].expect: no [[reply]] is named \"maybe\"",
        ),
        (
            "expect = [\"ok\", \"no\"]",
            "expect = [\"no\"]",
            "must expect a `done` reply",
        ),
        (
            "kind = \"line\"",
            "kind = \"line\"\nprefix_bytes = 2",
            "framing.prefix_bytes: only for kind = \"length_prefix\"",
        ),
        ("kind = \"line\"", "kind = \"lines\"", "not a dialect file"),
        (
            "source = \"connection\"",
            "source = \"polled\"",
            "status: source = \"polled\" needs poll",
        ),
        (
            "source = \"connection\"",
            "source = \"pushed\"",
            "needs a [[reply]] with outcome = \"status\"",
        ),
        (
            "result = \"{action}_done\"",
            "result = \"{result}\"",
            "reply[0] (ok).result: \"{result}\" uses a value the message does not carry",
        ),
        (
            "correlation = \"one_in_flight\"",
            "correlation = \"id\"",
            "every command of the sequence carries {id}",
        ),
        (
            "text = \"NO {message}\"",
            "text = \"NO {message}\"\nregex = \"(unclosed\"",
            "reply[1] (no).regex",
        ),
        (
            "text = \"NO {message}\"",
            "regex = \"^NO (?P<why>.*)$\"",
            "the group (?P<why>) is not a value a reply has",
        ),
        (
            "name = \"tiny\"",
            "name = \"tiny\"\nflavour = \"x\"",
            "unknown field `flavour`",
        ),
    ];
    for (from, to, expected) in cases {
        assert!(MINIMAL.contains(from), "{from}");
        let text = MINIMAL.replacen(from, to, 1);
        let error = error_of(&text);
        assert!(error.contains(expected), "{to:?}: {error}");
        assert!(error.starts_with("test.toml"), "{error}");
    }
}

/// MINIMAL with an abort: a command of its own and the replies to it.
fn with_abort(abort: &str) -> String {
    MINIMAL.replacen("[framing]", &format!("{abort}\n[framing]"), 1)
        + r#"
[[command]]
name = "halt"
text = "HALT {action}"
[[reply]]
name = "halted"
outcome = "accepted"
text = "HALTED"
[[reply]]
name = "idle"
outcome = "rejected"
text = "IDLE"
"#
}

#[test]
fn an_abort_loads_with_its_command_and_replies() {
    let dialect = Dialect::from_toml(
        &with_abort(r#"abort = { send = "halt", expect = ["halted", "idle"] }"#),
        "test.toml",
    )
    .unwrap();
    let abort = dialect.abort.as_ref().unwrap();
    assert_eq!(dialect.commands[abort.command].name, "halt");
    let names: Vec<&str> = abort
        .expect
        .iter()
        .map(|&r| dialect.replies[r].name.as_str())
        .collect();
    assert_eq!(names, ["halted", "idle"]);
    assert!(dialect.can_abort());
    // Without `expect`, the abort has no reply of its own.
    let bare =
        Dialect::from_toml(&with_abort(r#"abort = { send = "halt" }"#), "test.toml").unwrap();
    assert!(bare.abort.unwrap().expect.is_empty());
}

#[test]
fn a_bad_abort_names_the_field_and_the_problem() {
    let cases: &[(&str, &str)] = &[
        (
            r#"abort = { send = "stop" }"#,
            "test.toml: abort.send: no [[command]] is named \"stop\"",
        ),
        (
            r#"abort = { send = "halt", expect = ["halted", "stopped"] }"#,
            "test.toml: abort.expect: no [[reply]] is named \"stopped\"",
        ),
        (
            r#"abort = { send = "go" }"#,
            "test.toml: abort.send: \"go\" is also sent by sequence[0]",
        ),
        (
            r#"abort = { send = "halt", expect = ["ok"] }"#,
            "test.toml: abort.expect: \"ok\" is a done reply",
        ),
        (
            r#"abort = { send = "halt", expect = ["no"] }"#,
            "test.toml: abort.expect: \"no\" is a failed reply",
        ),
        (
            r#"abort = { send = "halt", expects = ["halted"] }"#,
            "unknown field `expects`",
        ),
        (r#"abort = { expect = ["halted"] }"#, "missing field `send`"),
    ];
    for (abort, expected) in cases {
        let error = error_of(&with_abort(abort));
        assert!(error.contains(expected), "{abort}: {error}");
    }
    // An abort's answer must be told apart from a step's.
    let text = with_abort(r#"abort = { send = "halt", expect = ["halted"] }"#).replace(
        r#"expect = ["ok", "no"]"#,
        r#"expect = ["halted", "ok", "no"]"#,
    );
    let error = error_of(&text);
    assert!(
        error.contains("abort.expect: \"halted\" also answers sequence[0]"),
        "{error}"
    );
    // The abort's message is checked like any other.
    let text = with_abort(r#"abort = { send = "halt" }"#).replace("HALT {action}", "HALT {acton}");
    assert!(error_of(&text).contains("command[1] (halt): {acton} is not a value here"));
}

#[test]
fn an_action_missing_from_an_enum_cannot_be_written() {
    let dialect = Dialect::shipped("kuka-eki").unwrap();
    let values = command_values(&command(1, "weld", None, None), &dialect.format);
    let why = dialect.write_command(0, &values).unwrap_err();
    assert!(
        why.contains("\"weld\" has no entry in [enums.eki_task]"),
        "{why}"
    );
}

/// Everything the holon and robot-sim do with bytes from the other end, in one dialect.
fn read_everything(dialect: &Dialect, bytes: &[u8]) {
    use bytes::BytesMut;
    use tokio_util::codec::Decoder;
    let mut codec = dialect.frame_codec();
    let mut buf = BytesMut::from(bytes);
    while let Ok(Some(frame)) = codec.decode(&mut buf) {
        let Ok(parsed) = dialect.parse(&frame) else {
            continue;
        };
        for i in 0..dialect.replies.len() {
            if let Ok(Some(values)) = dialect.read_reply(i, &parsed) {
                let reply = &dialect.replies[i];
                dialect.evaluate(&reply.result, &values, &Values::default());
                dialect.evaluate(&reply.message, &values, &Values::default());
                if reply.outcome == Outcome::Status {
                    let _ = dialect.state_of(i, &values);
                }
            }
        }
        for i in 0..dialect.commands.len() {
            let _ = dialect.read_command(i, &parsed);
        }
    }
}

proptest! {
    #[test]
    fn no_dialect_panics_on_arbitrary_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
        for (name, _) in SHIPPED {
            read_everything(&Dialect::shipped(name).unwrap(), &bytes);
        }
    }

    #[test]
    fn no_dialect_panics_on_mutated_messages(pos in 0usize..400, byte in any::<u8>(), cut in 0usize..400) {
        for (name, _) in SHIPPED {
            let dialect = Dialect::shipped(name).unwrap();
            let values = command_values(&command(7, "pick", Some(Pose::default()), Some("b2")), &dialect.format);
            for element in &dialect.sequence {
                let mut message = dialect.write_command(element.command, &values).unwrap();
                let mut framed = bytes::BytesMut::new();
                tokio_util::codec::Encoder::encode(&mut dialect.frame_codec(), message.as_slice(), &mut framed).unwrap();
                message = framed.to_vec();
                let i = pos % message.len();
                message[i] = byte;
                message.truncate(cut.max(1).min(message.len()));
                read_everything(&dialect, &message);
            }
        }
    }
}

#[test]
fn only_holarchy_xml_can_fence() {
    for (name, _) in SHIPPED {
        let dialect = Dialect::shipped(name).unwrap();
        assert_eq!(dialect.fencing_supported(), *name == DEFAULT, "{name}");
    }
}

#[test]
fn holarchy_xml_writes_the_epoch_and_step_only_when_given() {
    let dialect = Dialect::holarchy_xml();
    let mut values = command_values(&command(7, "pick", None, None), &dialect.format);
    let plain = dialect
        .write_command(dialect.sequence[0].command, &values)
        .unwrap();
    assert_eq!(
        String::from_utf8(plain).unwrap(),
        "<ROBOT_CMD><ID>7</ID><ACTION>pick</ACTION></ROBOT_CMD>"
    );
    values.set("epoch", "3".into());
    values.set("step", "orders1-3/2/1#0".into());
    let fenced = dialect
        .write_command(dialect.sequence[0].command, &values)
        .unwrap();
    assert_eq!(
        String::from_utf8(fenced.clone()).unwrap(),
        "<ROBOT_CMD><ID>7</ID><EPOCH>3</EPOCH><STEP>orders1-3/2/1#0</STEP><ACTION>pick</ACTION></ROBOT_CMD>"
    );
    let parsed = dialect.parse(&fenced).unwrap();
    let read = dialect
        .read_command(dialect.sequence[0].command, &parsed)
        .unwrap()
        .unwrap();
    assert_eq!(read.get("epoch"), Some("3"));
    assert_eq!(read.get("step"), Some("orders1-3/2/1#0"));
    // A stale refusal is read as such, not as a result.
    let fence = dialect.fence.unwrap();
    let stale = dialect
        .parse(b"<ROBOT_REPLY><ID>7</ID><RESULT>stale_epoch</RESULT><EPOCH>4</EPOCH></ROBOT_REPLY>")
        .unwrap();
    let first = dialect.sequence[0]
        .expect
        .iter()
        .copied()
        .find(|&r| dialect.read_reply(r, &stale).unwrap().is_some());
    assert_eq!(first, Some(fence.stale));
}

#[test]
fn a_bad_fence_names_the_field_and_the_problem() {
    let shipped = SHIPPED[0].1;
    let cases = [
        (
            shipped.replace("granted = \"claim_granted\"", "granted = \"nope\""),
            "fence.granted",
        ),
        (
            shipped.replace(
                "name = \"claim_granted\"\noutcome = \"fence\"",
                "name = \"claim_granted\"\noutcome = \"ignore\"",
            ),
            "fence.granted",
        ),
        (
            shipped.replace(
                "expect = [\"stale_epoch\", \"error\", \"departed\", \"result\"]",
                "expect = [\"error\", \"departed\", \"result\"]",
            ),
            "fence.stale",
        ),
        (
            shipped.replace("claim = \"claim\"", "claim = \"command\""),
            "fence",
        ),
    ];
    for (text, field) in cases {
        let e = Dialect::from_toml(&text, "t.toml").unwrap_err().to_string();
        assert!(e.contains(field), "{field}: {e}");
    }
    // A fence reply without [fence].
    let start = shipped.find("\n[fence]\n").unwrap();
    let end = start + shipped[start..].find("\n\n").unwrap();
    let without = format!("{}{}", &shipped[..start], &shipped[end..]);
    let e = Dialect::from_toml(&without, "t.toml")
        .unwrap_err()
        .to_string();
    assert!(e.contains("[fence]"), "{e}");
}

/// The worked example of docs/dialects.md 7.7 (replies with and without the id, one
/// status reply per state).
fn job_ack_end() -> String {
    std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../deploy/dialects/examples/job-ack-end.toml"
    ))
    .unwrap()
}

#[test]
fn a_regex_group_is_read_through_the_table_its_text_names() {
    // The trap: a regex whose group reads the wire form (`NORMAL`) where the text's
    // placeholder reads it through [enums.safety] (`ready`).
    let text = SHIPPED
        .iter()
        .find(|(n, _)| *n == "ur-dashboard")
        .unwrap()
        .1
        .replace(
            "text = \"Safetystatus: {state:safety}\"",
            "text = \"Safetystatus: {state:safety}\"\nregex = '^Safetystatus: (?P<state>\\w+)$'",
        );
    let dialect = Dialect::from_toml(&text, "ur.toml").unwrap();
    dialect.check_simulatable().unwrap();
    let parsed = dialect.parse(b"Safetystatus: REDUCED").unwrap();
    let (_, _, state) = dialect.read_unsolicited(&parsed).unwrap().unwrap();
    assert_eq!(state, Some(ControllerState::Ready));
    let parsed = dialect.parse(b"Safetystatus: HOMING").unwrap();
    let err = dialect.read_unsolicited(&parsed).unwrap_err();
    assert!(
        err.contains("\"HOMING\" is not a value of [enums.safety]"),
        "{err}"
    );
}

#[test]
fn status_replies_are_tried_in_order_a_miss_falling_through() {
    let dialect = Dialect::from_toml(&job_ack_end(), "job-ack-end.toml").unwrap();
    let read = |line: &[u8]| {
        let parsed = dialect.parse(line).unwrap();
        dialect
            .read_unsolicited(&parsed)
            .map(|r| r.map(|(i, v, s)| (dialect.replies[i].name.clone(), v, s)))
    };
    let (name, values, state) = read(b"STATE ERROR overtravel axis 3").unwrap().unwrap();
    assert_eq!(name, "state_error");
    assert_eq!(values.get("message"), Some("overtravel axis 3"));
    assert_eq!(state, Some(ControllerState::Fault));
    assert_eq!(
        read(b"STATE ESTOP").unwrap().unwrap().2,
        Some(ControllerState::Estop)
    );
    assert_eq!(
        read(b"STATE IDLE").unwrap().unwrap().2,
        Some(ControllerState::Ready)
    );
    assert!(read(b"STATE HOMING").unwrap().is_none());
    // A table's miss falls through to a later reply for the lines it does not list.
    let val3 = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../deploy/dialects/examples/staubli-val3-sio.toml"
    ))
    .unwrap()
        + "\n[[reply]]\nname = \"homing\"\noutcome = \"ignore\"\ntext = \"STATE HOMING\"\n";
    let dialect = Dialect::from_toml(&val3, "val3.toml").unwrap();
    let parsed = dialect.parse(b"STATE HOMING").unwrap();
    let (index, _, state) = dialect.read_unsolicited(&parsed).unwrap().unwrap();
    assert_eq!(
        (dialect.replies[index].name.as_str(), state),
        ("homing", None)
    );
    let parsed = dialect.parse(b"STATE BOGUS").unwrap();
    let err = dialect.read_unsolicited(&parsed).unwrap_err();
    assert!(
        err.contains("\"BOGUS\" is not a value of [enums.val3_state]"),
        "{err}"
    );
}

#[test]
fn robot_sim_check_finds_what_would_fail_on_the_first_line() {
    let example = job_ack_end();
    Dialect::from_toml(&example, "ok.toml")
        .unwrap()
        .check_simulatable()
        .unwrap();
    // A regex that does not match what the text writes.
    let bad = example.replace(
        "text = \"ACK {id}\"",
        "text = \"ACK {id}\"\nregex = '^ACK: (?P<id>\\d+)$'",
    );
    let err = Dialect::from_toml(&bad, "bad.toml")
        .unwrap()
        .check_simulatable()
        .unwrap_err();
    assert!(
        err.contains("reply ack") && err.contains("its regex does not match it"),
        "{err}"
    );
    // No status reply can say ready: the controller would never be used.
    let bad = example.replace("state = \"ready\"", "state = \"fault\"");
    let err = Dialect::from_toml(&bad, "bad.toml")
        .unwrap()
        .check_simulatable()
        .unwrap_err();
    assert!(err.contains("no status reply says ready"), "{err}");
    // No abort, no estop: warnings, not errors.
    let no_estop = example.replace(
        "text = \"STATE ESTOP\"\nstate = \"estop\"",
        "text = \"STATE ESTOP\"\nstate = \"fault\"",
    );
    let dialect = Dialect::from_toml(&no_estop, "w.toml").unwrap();
    dialect.check_simulatable().unwrap();
    let warnings = dialect.warnings();
    assert_eq!(warnings.len(), 2, "{warnings:?}");
    assert!(warnings[0].contains("has no `abort`"), "{warnings:?}");
    assert!(warnings[1].contains("says estop"), "{warnings:?}");
    for (name, _) in SHIPPED {
        assert!(
            Dialect::shipped(name).unwrap().warnings().is_empty(),
            "{name}"
        );
    }
}

#[test]
fn with_ids_an_element_needs_one_answer_with_the_id() {
    let example = job_ack_end();
    // The NAK carries no id: allowed beside replies that do.
    Dialect::from_toml(&example, "ok.toml").unwrap();
    let none = example
        .replace("text = \"ACK {id}\"", "text = \"ACK\"")
        .replace("text = \"END {id} OK\"", "text = \"END OK\"")
        .replace(
            "text = \"END {id} FAIL {message}\"",
            "text = \"END FAIL {message}\"",
        );
    let err = Dialect::from_toml(&none, "none.toml")
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("at least one answer of each element of the sequence carries {id}"),
        "{err}"
    );
}

mod departed;

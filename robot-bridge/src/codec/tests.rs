use super::*;
use proptest::prelude::*;

const REPLY: &str = "<ROBOT_REPLY><ID>42</ID><RESULT>picking_done</RESULT></ROBOT_REPLY>";

fn decode_all(chunks: &[&[u8]]) -> Vec<Result<RobotMessage, CodecError>> {
    let mut codec = RobotCodec;
    let mut buf = BytesMut::new();
    let mut out = Vec::new();
    for chunk in chunks {
        buf.extend_from_slice(chunk);
        loop {
            match codec.decode(&mut buf) {
                Ok(Some(m)) => out.push(Ok(m)),
                Ok(None) => break,
                Err(e) => {
                    out.push(Err(e));
                    return out;
                }
            }
        }
    }
    out
}

fn reply(id: u64, result: &str) -> RobotMessage {
    RobotMessage::Reply(RobotReply {
        id,
        result: result.into(),
        message: None,
    })
}

#[test]
fn decodes_the_contract_examples() {
    let cmd = parse_document(
        br#"<ROBOT_CMD><ID>42</ID><ACTION>pick</ACTION><POS X="100.0" Y="20.0" Z="5.0" A="0.0" B="0.0" C="0.0"></POS></ROBOT_CMD>"#,
    )
    .unwrap();
    assert_eq!(
        cmd,
        RobotMessage::Command(RobotCommand {
            id: 42,
            action: "pick".into(),
            pos: Some(Pose {
                x: 100.0,
                y: 20.0,
                z: 5.0,
                ..Pose::default()
            }),
            program: None,
            info: Default::default(),
        })
    );
    assert_eq!(
        parse_document(REPLY.as_bytes()).unwrap(),
        reply(42, "picking_done")
    );
    assert_eq!(
        parse_document(
            b"<ROBOT_REPLY><ID>43</ID><RESULT>error</RESULT><MESSAGE>gripper empty</MESSAGE></ROBOT_REPLY>"
        )
        .unwrap(),
        RobotMessage::Reply(RobotReply {
            id: 43,
            result: "error".into(),
                message: Some("gripper empty".into())
        })
    );
    assert_eq!(
        parse_document(b"<ROBOT_STATUS><STATE>estop</STATE></ROBOT_STATUS>").unwrap(),
        RobotMessage::Status(ControllerState::Estop)
    );
}

#[test]
fn a_command_names_its_program_or_none() {
    let cmd = parse_document(
        b"<ROBOT_CMD><ID>5</ID><ACTION>pick</ACTION><PROGRAM> b2 </PROGRAM></ROBOT_CMD>",
    )
    .unwrap();
    assert_eq!(
        cmd,
        RobotMessage::Command(RobotCommand {
            id: 5,
            action: "pick".into(),
            pos: None,
            program: Some("b2".into()),
            info: Default::default(),
        })
    );
    assert_eq!(
        parse_document(
            b"<ROBOT_CMD><ID>5</ID><ACTION>pick</ACTION><PROGRAM></PROGRAM></ROBOT_CMD>"
        ),
        Err(CodecError::InvalidField {
            root: "ROBOT_CMD",
            field: "PROGRAM",
            why: "it is empty".into()
        })
    );
}

#[test]
fn encodes_what_it_decodes() {
    let messages = [
        RobotMessage::Command(RobotCommand {
            id: 7,
            action: "place".into(),
            pos: Some(Pose {
                x: -1.5,
                y: 2.25,
                z: 1e3,
                a: 90.0,
                b: 0.0,
                c: -180.0,
            }),
            program: None,
            info: Default::default(),
        }),
        RobotMessage::Command(RobotCommand {
            id: 8,
            action: "inspect".into(),
            pos: None,
            program: Some("variant-b.2".into()),
            info: Default::default(),
        }),
        RobotMessage::Reply(RobotReply {
            id: 9,
            result: "error".into(),
            message: Some("a <b> & \"c\"".into()),
        }),
        RobotMessage::Status(ControllerState::Fault),
    ];
    for message in messages {
        let text = encode_message(&message);
        assert_eq!(parse_document(text.as_bytes()).unwrap(), message, "{text}");
    }
}

#[test]
fn reads_documents_split_across_reads() {
    let bytes = REPLY.as_bytes();
    for cut in 1..bytes.len() {
        let out = decode_all(&[&bytes[..cut], &bytes[cut..]]);
        assert_eq!(out, vec![Ok(reply(42, "picking_done"))], "cut at {cut}");
    }
    let one_by_one: Vec<&[u8]> = bytes.chunks(1).collect();
    assert_eq!(decode_all(&one_by_one), vec![Ok(reply(42, "picking_done"))]);
}

#[test]
fn reads_several_documents_in_one_read() {
    let text = format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>\r\n{REPLY}<ROBOT_REPLY><ID>43</ID><RESULT>placing_done</RESULT></ROBOT_REPLY>"
    );
    let out = decode_all(&[text.as_bytes()]);
    assert_eq!(
        out,
        vec![
            Ok(RobotMessage::Status(ControllerState::Ready)),
            Ok(reply(42, "picking_done")),
            Ok(reply(43, "placing_done")),
        ]
    );
}

#[test]
fn tolerates_declaration_comments_cdata_and_entities() {
    let doc = "\u{FEFF}<?xml version=\"1.0\"?><!-- hi > there --><ROBOT_REPLY><ID>1</ID><RESULT><![CDATA[arr]]>ived</RESULT><MESSAGE>a &amp; b &#x41; &lt;</MESSAGE></ROBOT_REPLY>";
    assert_eq!(
        decode_all(&[doc.as_bytes()]),
        vec![Ok(RobotMessage::Reply(RobotReply {
            id: 1,
            result: "arrived".into(),
            message: Some("a & b A <".into())
        }))]
    );
    // A quoted '>' inside an attribute does not end the tag.
    let doc = r#"<ROBOT_CMD><ID>1</ID><ACTION>pick</ACTION><POS X="1" Y='>' /></ROBOT_CMD>"#;
    assert!(matches!(
        decode_all(&[doc.as_bytes()])[..],
        [Err(CodecError::InvalidField { field: "POS", .. })]
    ));
}

#[test]
fn never_treats_a_truncated_document_as_complete() {
    let bytes = REPLY.as_bytes();
    for cut in 0..bytes.len() {
        let mut buf = BytesMut::from(&bytes[..cut]);
        assert_eq!(RobotCodec.decode(&mut buf), Ok(None), "cut at {cut}");
        let mut buf = BytesMut::from(&bytes[..cut]);
        let at_eof = RobotCodec.decode_eof(&mut buf);
        assert!(cut == 0 || at_eof.is_err(), "cut at {cut}: {at_eof:?}");
    }
}

#[test]
fn rejects_doctype() {
    let doc = b"<?xml version=\"1.0\"?><!DOCTYPE lol [<!ENTITY a \"aaaa\">]><ROBOT_STATUS><STATE>ready</STATE></ROBOT_STATUS>";
    assert_eq!(decode_all(&[doc]), vec![Err(CodecError::DoctypeRejected)]);
    // Even when the DOCTYPE arrives a byte at a time.
    let chunks: Vec<&[u8]> = doc.chunks(1).collect();
    assert_eq!(decode_all(&chunks), vec![Err(CodecError::DoctypeRejected)]);
}

#[test]
fn rejects_oversized_documents() {
    let big = format!(
        "<ROBOT_REPLY><ID>1</ID><RESULT>{}</RESULT></ROBOT_REPLY>",
        "x".repeat(MAX_DOCUMENT_BYTES)
    );
    assert_eq!(
        decode_all(&[big.as_bytes()]),
        vec![Err(CodecError::TooLarge)]
    );
    // Also when it never ends: the limit applies before the end is seen.
    let endless = format!("<ROBOT_REPLY><ID>{}", "1".repeat(MAX_DOCUMENT_BYTES + 10));
    assert_eq!(
        decode_all(&[endless.as_bytes()]),
        vec![Err(CodecError::TooLarge)]
    );
    let unclosed_tag = format!("<ROBOT_REPLY a=\"{}", "1".repeat(MAX_DOCUMENT_BYTES + 10));
    assert_eq!(
        decode_all(&[unclosed_tag.as_bytes()]),
        vec![Err(CodecError::TooLarge)]
    );
}

#[test]
fn rejects_excessive_depth() {
    let deep = format!(
        "<ROBOT_REPLY>{}{}</ROBOT_REPLY>",
        "<a>".repeat(MAX_DEPTH),
        "</a>".repeat(MAX_DEPTH)
    );
    assert_eq!(
        decode_all(&[deep.as_bytes()]),
        vec![Err(CodecError::TooDeep)]
    );
}

#[test]
fn rejects_malformed_documents() {
    let cases: &[&[u8]] = &[
        b"hello",
        b"<ROBOT_REPLY><ID>1</ID><RESULT>x</RESULT></ROBOT_REPL>",
        b"</ROBOT_REPLY>",
        b"<ROBOT_REPLY><ID>x</ID><RESULT>done</RESULT></ROBOT_REPLY>",
        b"<ROBOT_REPLY><ID>1</ID></ROBOT_REPLY>",
        b"<ROBOT_REPLY><ID>-1</ID><RESULT>a</RESULT></ROBOT_REPLY>",
        b"<ROBOT_STATUS><STATE>sleepy</STATE></ROBOT_STATUS>",
        b"<HELLO/>",
        b"<ROBOT_REPLY><ID>1</ID><RESULT>&bogus;</RESULT></ROBOT_REPLY>",
        b"<ROBOT_REPLY><ID>1</ID><RESULT>\xff\xfe</RESULT></ROBOT_REPLY>",
        b"<ROBOT_CMD><ID>1</ID><ACTION>pick</ACTION><POS X=\"NaN\"/></ROBOT_CMD>",
        b"<ROBOT_CMD><ID>1</ID><ACTION></ACTION></ROBOT_CMD>",
        b"<!ELEMENT x>",
    ];
    for case in cases {
        let out = decode_all(&[case]);
        assert!(
            matches!(out.last(), Some(Err(_))),
            "{:?} gave {out:?}",
            String::from_utf8_lossy(case)
        );
    }
}

proptest! {
    #[test]
    fn decoding_arbitrary_bytes_never_panics(chunks in proptest::collection::vec(proptest::collection::vec(any::<u8>(), 0..64), 0..8)) {
        let refs: Vec<&[u8]> = chunks.iter().map(|c| c.as_slice()).collect();
        let _ = decode_all(&refs);
    }

    #[test]
    fn any_split_of_a_stream_decodes_the_same(ids in proptest::collection::vec(any::<u64>(), 1..5), cuts in proptest::collection::vec(any::<usize>(), 0..6)) {
        let messages: Vec<RobotMessage> = ids.iter().map(|&id| reply(id, "arrived")).collect();
        let stream: String = messages.iter().map(encode_message).collect::<Vec<_>>().join("\n");
        let bytes = stream.as_bytes();
        let mut points: Vec<usize> = cuts.iter().map(|c| c % (bytes.len() + 1)).collect();
        points.sort();
        let mut chunks = Vec::new();
        let mut last = 0;
        for p in points { chunks.push(&bytes[last..p]); last = p; }
        chunks.push(&bytes[last..]);
        let out = decode_all(&chunks);
        prop_assert_eq!(out, messages.into_iter().map(Ok).collect::<Vec<_>>());
    }

    #[test]
    fn mutated_documents_never_panic(pos in 0usize..80, byte in any::<u8>()) {
        let mut doc = REPLY.as_bytes().to_vec();
        let i = pos % doc.len();
        doc[i] = byte;
        let _ = decode_all(&[&doc]);
    }
}

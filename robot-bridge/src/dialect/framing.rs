//! Where one message ends and the next begins: the end of an XML root element, a line
//! ended by given bytes, or a length prefix. [`FrameCodec`] cuts a byte stream into
//! messages (without looking inside them) and frames the messages written.
//!
//! Every framing bounds a message by the dialect's `max_message_bytes`, checked before
//! the message ends, so a peer that never ends one cannot make the bridge buffer without
//! limit. After any error the stream cannot be resynchronised: drop the connection.

use bytes::{Buf, BufMut, Bytes, BytesMut};
use tokio_util::codec::{Decoder, Encoder};

use crate::codec::{find_document_within, CodecError, Frame};

/// The byte order of a length prefix and of binary fields.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ByteOrder {
    Big,
    Little,
}

/// How messages are delimited.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Framing {
    /// One XML document after another, ended by the end of the root element (no DOCTYPE,
    /// at most 8 nested elements).
    Xml,
    /// Text lines ended by `terminator` (e.g. `\n`, `\r`, `\r\n`).
    Line { terminator: Vec<u8> },
    /// A length prefix of `bytes` (2 or 4) bytes, then the message.
    LengthPrefix {
        bytes: usize,
        order: ByteOrder,
        /// Whether the length counts the prefix itself.
        counts_itself: bool,
    },
}

/// Cuts a stream into messages of one framing, each at most `max` bytes.
#[derive(Debug, Clone)]
pub struct FrameCodec {
    pub framing: Framing,
    pub max: usize,
}

impl FrameCodec {
    fn prefix_value(&self, buf: &[u8], bytes: usize, order: ByteOrder) -> usize {
        let mut value = 0usize;
        for i in 0..bytes {
            let byte = match order {
                ByteOrder::Big => buf[i],
                ByteOrder::Little => buf[bytes - 1 - i],
            };
            value = (value << 8) | byte as usize;
        }
        value
    }
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    haystack.windows(needle.len()).position(|w| w == needle)
}

impl Decoder for FrameCodec {
    type Item = Bytes;
    type Error = CodecError;

    fn decode(&mut self, buf: &mut BytesMut) -> Result<Option<Bytes>, CodecError> {
        match &self.framing {
            Framing::Xml => match find_document_within(buf, self.max)? {
                Frame::Empty { skip } => {
                    buf.advance(skip);
                    Ok(None)
                }
                Frame::Incomplete { start } => {
                    buf.advance(start);
                    Ok(None)
                }
                Frame::Complete { start, end } => {
                    let doc = buf.split_to(end).freeze();
                    Ok(Some(doc.slice(start..)))
                }
            },
            Framing::Line { terminator } => match find(buf, terminator) {
                Some(at) if at > self.max => Err(CodecError::TooLargeFor(self.max)),
                Some(at) => {
                    let line = buf.split_to(at).freeze();
                    buf.advance(terminator.len());
                    Ok(Some(line))
                }
                // The terminator may be cut in two: allow for its first bytes.
                None if buf.len() >= self.max + terminator.len() => {
                    Err(CodecError::TooLargeFor(self.max))
                }
                None => Ok(None),
            },
            Framing::LengthPrefix {
                bytes,
                order,
                counts_itself,
            } => {
                let (bytes, order, counts_itself) = (*bytes, *order, *counts_itself);
                if buf.len() < bytes {
                    return Ok(None);
                }
                let length = self.prefix_value(buf, bytes, order);
                let body = if counts_itself {
                    length.checked_sub(bytes).ok_or_else(|| {
                        CodecError::BadMessage(format!(
                            "a length prefix of {length} cannot count its own {bytes} bytes"
                        ))
                    })?
                } else {
                    length
                };
                if body > self.max {
                    return Err(CodecError::TooLargeFor(self.max));
                }
                if buf.len() < bytes + body {
                    buf.reserve(bytes + body - buf.len());
                    return Ok(None);
                }
                buf.advance(bytes);
                Ok(Some(buf.split_to(body).freeze()))
            }
        }
    }

    fn decode_eof(&mut self, buf: &mut BytesMut) -> Result<Option<Bytes>, CodecError> {
        match self.decode(buf)? {
            Some(frame) => Ok(Some(frame)),
            None if buf.iter().all(u8::is_ascii_whitespace) => Ok(None),
            None => Err(CodecError::ClosedInsideDocument),
        }
    }
}

impl Encoder<&[u8]> for FrameCodec {
    type Error = CodecError;

    fn encode(&mut self, message: &[u8], buf: &mut BytesMut) -> Result<(), CodecError> {
        match &self.framing {
            Framing::Xml => buf.extend_from_slice(message),
            Framing::Line { terminator } => {
                buf.extend_from_slice(message);
                buf.extend_from_slice(terminator);
            }
            Framing::LengthPrefix {
                bytes,
                order,
                counts_itself,
            } => {
                let length = message.len() + if *counts_itself { *bytes } else { 0 };
                let max = if *bytes == 2 {
                    u16::MAX as usize
                } else {
                    u32::MAX as usize
                };
                if length > max {
                    return Err(CodecError::TooLargeFor(max));
                }
                match (bytes, order) {
                    (2, ByteOrder::Big) => buf.put_u16(length as u16),
                    (2, ByteOrder::Little) => buf.put_u16_le(length as u16),
                    (_, ByteOrder::Big) => buf.put_u32(length as u32),
                    (_, ByteOrder::Little) => buf.put_u32_le(length as u32),
                }
                buf.extend_from_slice(message);
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn decode_all(codec: &mut FrameCodec, chunks: &[&[u8]]) -> Vec<Result<Bytes, CodecError>> {
        let mut buf = BytesMut::new();
        let mut out = Vec::new();
        for chunk in chunks {
            buf.extend_from_slice(chunk);
            loop {
                match codec.decode(&mut buf) {
                    Ok(Some(frame)) => out.push(Ok(frame)),
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

    fn framed(codec: &mut FrameCodec, messages: &[&[u8]]) -> Vec<u8> {
        let mut buf = BytesMut::new();
        for m in messages {
            codec.encode(m, &mut buf).unwrap();
        }
        buf.to_vec()
    }

    fn codecs() -> Vec<FrameCodec> {
        let mut all = vec![
            FrameCodec {
                framing: Framing::Line {
                    terminator: b"\r\n".to_vec(),
                },
                max: 64,
            },
            FrameCodec {
                framing: Framing::Line {
                    terminator: b"\n".to_vec(),
                },
                max: 64,
            },
        ];
        for bytes in [2, 4] {
            for order in [ByteOrder::Big, ByteOrder::Little] {
                for counts_itself in [false, true] {
                    all.push(FrameCodec {
                        framing: Framing::LengthPrefix {
                            bytes,
                            order,
                            counts_itself,
                        },
                        max: 64,
                    });
                }
            }
        }
        all
    }

    #[test]
    fn any_split_gives_back_the_messages() {
        let messages: [&[u8]; 3] = [b"load pick.urp", b"", b"play"];
        for mut codec in codecs() {
            let stream = framed(&mut codec, &messages);
            for cut in 0..=stream.len() {
                for cut2 in cut..=stream.len() {
                    let out = decode_all(
                        &mut codec,
                        &[&stream[..cut], &stream[cut..cut2], &stream[cut2..]],
                    );
                    let out: Vec<Bytes> = out.into_iter().map(Result::unwrap).collect();
                    assert_eq!(out, messages.to_vec(), "{codec:?} cut at {cut}, {cut2}");
                }
            }
        }
    }

    #[test]
    fn refuses_a_message_over_the_limit_before_it_ends() {
        for mut codec in codecs() {
            let big = vec![b'x'; 70];
            let stream = framed(&mut codec, &[&big]);
            let prefix = match codec.framing {
                Framing::LengthPrefix { bytes, .. } => bytes,
                _ => 0,
            };
            // Never the end of the message: for a line, no terminator at all.
            let out = decode_all(&mut codec, &[&stream[..prefix + 70]]);
            assert_eq!(
                out.last(),
                Some(&Err(CodecError::TooLargeFor(64))),
                "{codec:?}"
            );
        }
    }

    #[test]
    fn a_length_that_cannot_count_itself_is_malformed() {
        let mut codec = FrameCodec {
            framing: Framing::LengthPrefix {
                bytes: 4,
                order: ByteOrder::Big,
                counts_itself: true,
            },
            max: 64,
        };
        assert!(matches!(
            decode_all(&mut codec, &[&[0, 0, 0, 2]])[..],
            [Err(CodecError::BadMessage(_))]
        ));
    }
}

//! The writing side of a simulated controller's connection: frames replies and writes
//! them, in pieces or held to go together as the faults say, and the hostile messages.

use std::time::Duration;

use bytes::BytesMut;
use schemas::ControllerState;
use tokio::io::AsyncWriteExt;
use tokio::net::tcp::OwnedWriteHalf;
use tokio_util::codec::Encoder;

use super::{SimConfig, SimError};
use crate::dialect::framing::{FrameCodec, Framing};
use crate::dialect::{Dialect, Status, Values};

/// The writing side of a connection: frames messages and writes them (in pieces, or held
/// to go together, as the faults say).
pub(super) struct Writer<'a> {
    pub(super) half: OwnedWriteHalf,
    pub(super) codec: FrameCodec,
    pub(super) dialect: &'a Dialect,
    pub(super) config: &'a SimConfig,
    /// Messages held to be written with the next one (`merge`).
    pub(super) held: BytesMut,
    /// The controller's state, as its status replies say it.
    pub(super) state: ControllerState,
    /// The controller's counts (whether its stop is in an undescribed state).
    pub(super) stats: &'a super::SimStats,
}

/// What the simulated controller says of its state in its own words, for a status
/// reply that carries a `{message}`.
fn said(state: ControllerState) -> &'static str {
    match state {
        ControllerState::Ready => "",
        ControllerState::Fault => "simulated fault (--fault-after)",
        ControllerState::Estop => "simulated emergency stop (--fault-after)",
    }
}

impl Writer<'_> {
    /// What the controller says first on a connection: its banner, then its state if
    /// it pushes it.
    pub(super) async fn greet(&mut self) -> Result<(), SimError> {
        if let Some(banner) = &self.dialect.banner {
            let mut framed = BytesMut::new();
            self.codec.clone().encode(banner.as_bytes(), &mut framed)?;
            self.raw(&framed).await?;
        }
        if self.dialect.status == Status::Pushed {
            self.status().await?;
        }
        Ok(())
    }

    /// Frames the reply `index` with `values`.
    fn frame(&mut self, index: usize, values: &Values) -> Result<BytesMut, SimError> {
        let reply = &self.dialect.replies[index];
        let body = reply
            .body
            .as_ref()
            .ok_or_else(|| SimError::Write(format!("reply {} has no text to write", reply.name)))?;
        let bytes = self
            .dialect
            .write(body, values)
            .map_err(|e| SimError::Write(format!("reply {}: {e}", reply.name)))?;
        let mut framed = BytesMut::new();
        self.codec.encode(bytes.as_slice(), &mut framed)?;
        Ok(framed)
    }

    /// Writes reply `index` (with anything held before it).
    pub(super) async fn reply(&mut self, index: usize, values: &Values) -> Result<(), SimError> {
        let mut framed = self.frame(index, values)?;
        if self.config.merge && self.dialect.status == Status::Pushed {
            // The state repeated in the same write as the reply (pushed only: a polled
            // controller says its state when asked, never unprompted).
            if let Some((status, state)) = self.status_reply(self.state) {
                let before = self.frame(status, &state)?;
                self.held.extend_from_slice(&before);
            }
        }
        self.held.extend_from_slice(&framed);
        framed.clear();
        let all = std::mem::take(&mut self.held);
        self.raw(&all).await
    }

    /// Holds reply `index` to go with the next write (`merge`), or writes it now.
    pub(super) async fn reply_or_hold(
        &mut self,
        index: usize,
        values: &Values,
    ) -> Result<(), SimError> {
        if self.config.merge {
            let framed = self.frame(index, values)?;
            self.held.extend_from_slice(&framed);
            return Ok(());
        }
        self.reply(index, values).await
    }

    /// The status reply that says `state` (in the simulated controller's words, where
    /// it carries a `{message}`), and its values ([`Dialect::status_reply_for`]).
    pub(super) fn status_reply(&self, state: ControllerState) -> Option<(usize, Values)> {
        self.dialect.status_reply_for(state, said(state))
    }

    /// Writes the state (`self.state`) in its status reply, if the dialect has one for it.
    pub(super) async fn status(&mut self) -> Result<(), SimError> {
        let state = self.state;
        if state != ControllerState::Ready && self.stats.undescribed() {
            return self.undescribed().await;
        }
        let Some((index, values)) = self.status_reply(state) else {
            tracing::warn!(%state, "the dialect has no status reply for this state: not said");
            return Ok(());
        };
        let framed = self.frame(index, &values)?;
        self.raw(&framed).await
    }

    /// The state in words the dialect does not describe (`unknown_state_every`): its
    /// `ready` status with [`super::UNDESCRIBED_STATE`] for the state's word.
    async fn undescribed(&mut self) -> Result<(), SimError> {
        let Some(message) = self.dialect.undescribed_status(super::UNDESCRIBED_STATE) else {
            tracing::warn!("the dialect's status cannot say an undescribed state: not said");
            return Ok(());
        };
        let mut framed = BytesMut::new();
        self.codec.encode(message.as_slice(), &mut framed)?;
        self.raw(&framed).await
    }

    /// Writes bytes as they are (in pieces with `fragment`).
    pub(super) async fn raw(&mut self, bytes: &[u8]) -> Result<(), SimError> {
        if !self.config.fragment {
            self.half.write_all(bytes).await?;
            return Ok(());
        }
        let mut at = 0;
        let mut size = 1;
        while at < bytes.len() {
            let end = (at + size).min(bytes.len());
            self.half.write_all(&bytes[at..end]).await?;
            self.half.flush().await?;
            tokio::time::sleep(Duration::from_micros(200)).await;
            at = end;
            size = size % 3 + 1;
        }
        Ok(())
    }

    /// Bytes no rule of the dialect describes, framed so they arrive whole.
    pub(super) async fn garbage(&mut self) -> Result<(), SimError> {
        let bytes: Vec<u8> = match &self.codec.framing {
            Framing::Xml => b"<ROBOT_REPLY><ID>oops</RESULT></ROBOT_REPLY>".to_vec(),
            Framing::Line { terminator } => {
                let mut line = b"\x01garbage \xff\xfe".to_vec();
                line.extend_from_slice(terminator);
                line
            }
            Framing::LengthPrefix { .. } => {
                let mut framed = BytesMut::new();
                self.codec
                    .encode(&b"\xde\xad\xbe\xef garbage"[..], &mut framed)?;
                framed.to_vec()
            }
        };
        self.raw(&bytes).await
    }

    /// A message one byte over the limit (its start: enough to be refused).
    pub(super) async fn oversize(&mut self) -> Result<(), SimError> {
        let over = self.codec.max + 1;
        let bytes: Vec<u8> = match &self.codec.framing {
            Framing::Xml => {
                let mut doc = b"<X>".to_vec();
                doc.resize(over + 3, b'x');
                doc.extend_from_slice(b"</X>");
                doc
            }
            Framing::Line { terminator } => {
                let mut line = vec![b'x'; over];
                line.extend_from_slice(terminator);
                line
            }
            Framing::LengthPrefix { bytes, .. } => {
                let mut framed = BytesMut::new();
                let codec = FrameCodec {
                    framing: self.codec.framing.clone(),
                    max: usize::MAX,
                };
                let mut codec = codec;
                codec.encode(vec![0u8; over].as_slice(), &mut framed)?;
                framed.truncate(bytes + 16);
                framed.to_vec()
            }
        };
        self.raw(&bytes).await
    }
}

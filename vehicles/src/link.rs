//! One MAVLink connection, signed or not: every end of ours (the bridge to an autopilot, the
//! simulated autopilot, the ground-station gateway) reads and writes frames through this, so a
//! link's signing is decided in one place. Frames are read raw, checked, then parsed, so a
//! refusal says why; what is sent is signed when the link is.

use crate::bridge::parse_frame;
use crate::signing::{LinkSigning, Refused};
use mavlink::dialects::common::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{Connection, MAVLinkMessageRaw, MavConnection, MavHeader};
use std::sync::atomic::{AtomicU8, Ordering};

/// What one read gave (a frame is moved once per read: its size is no cost worth a box).
#[derive(Debug)]
#[allow(clippy::large_enum_variant)]
pub enum Received {
    /// A frame that passed: its message and its bytes as they came.
    Frame(MavHeader, MavMessage, Vec<u8>),
    /// A readable frame the signing check refused.
    Refused(Refused),
    /// Bytes that are no frame of ours (bad CRC, unknown message, truncated).
    Unreadable(String),
    /// Nothing to read now (no peer yet, a refused datagram): try again later.
    Idle,
}

pub struct MavLink {
    conn: Connection<MavMessage>,
    signing: Option<LinkSigning>,
    /// Sequence numbers of signed frames (the crate numbers only what it serialises).
    sequence: AtomicU8,
}

impl MavLink {
    /// Open `address` (any `mavlink` connection string).
    pub fn open(address: &str, signing: Option<LinkSigning>) -> std::io::Result<Self> {
        Ok(Self {
            conn: mavlink::connect::<MavMessage>(address)?,
            signing,
            sequence: AtomicU8::new(0),
        })
    }

    pub fn signed(&self) -> bool {
        self.signing.is_some()
    }

    /// Block for the next frame.
    pub fn recv(&self) -> Received {
        let raw = match self.conn.recv_raw() {
            Ok(r) => r,
            Err(MessageReadError::Io(e))
                if !matches!(
                    e.kind(),
                    std::io::ErrorKind::InvalidData | std::io::ErrorKind::UnexpectedEof
                ) =>
            {
                return Received::Idle
            }
            Err(e) => return Received::Unreadable(e.to_string()),
        };
        let bytes = match &raw {
            MAVLinkMessageRaw::V1(r) => r.raw_bytes().to_vec(),
            MAVLinkMessageRaw::V2(r) => r.raw_bytes().to_vec(),
        };
        if let Some(s) = &self.signing {
            if let Err(r) = s.check(&bytes) {
                return Received::Refused(r);
            }
        }
        match parse_frame(&bytes) {
            Ok((h, m)) => Received::Frame(h, m, bytes),
            Err(e) => Received::Unreadable(e),
        }
    }

    /// Send a message (signed when the link is).
    pub fn send(&self, header: &MavHeader, msg: &MavMessage) -> Result<(), String> {
        let sent = match &self.signing {
            None => self.conn.send(header, msg),
            Some(s) => {
                let h = MavHeader {
                    sequence: self.sequence.fetch_add(1, Ordering::Relaxed),
                    ..*header
                };
                self.conn.send_raw(&MAVLinkMessageRaw::V2(s.frame(h, msg)))
            }
        };
        sent.map(|_| ()).map_err(|e| e.to_string())
    }
}

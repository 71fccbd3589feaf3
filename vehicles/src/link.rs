//! One MAVLink connection, signed or not, and the frame codec: every end of ours (the bridge to
//! an autopilot, the simulated autopilot, the ground-station gateway) reads and writes frames
//! through this, so a link's signing and what counts as a frame are decided in one place.
//! Frames are read raw, checked, then parsed, so a refusal says why; what is sent is signed
//! when the link is.
//!
//! Reading is one thread per link ([`MavLink::reader`]) that blocks on the socket and hands
//! each read to a channel: the actor that owns the link's state (the bridge, the gateway)
//! wakes on what arrives, never on a timer. (The `mavlink` crate's async UDP connection retries
//! every read error inside `recv_raw`, so a garbled frame would never be seen, let alone
//! counted; its blocking connection reports each one.)

use crate::signing::{LinkSigning, Refused};
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::error::MessageReadError;
use mavlink::{Connection, MAVLinkMessageRaw, MavConnection, MavHeader, MavlinkVersion};
use std::sync::atomic::{AtomicU8, Ordering};
use std::sync::Arc;
use tokio::sync::mpsc;

/// Longest MAVLink 2 frame.
pub const MAX_FRAME: usize = 280;

/// A MAVLink 2 frame of a message.
pub fn frame_bytes(header: MavHeader, msg: &MavMessage) -> Vec<u8> {
    let mut buf = Vec::with_capacity(64);
    // Writing to a Vec cannot fail.
    let _ = mavlink::write_versioned_msg(&mut buf, MavlinkVersion::V2, header, msg);
    buf
}

/// The message of one MAVLink frame (v1 or v2), checked (CRC, known id, length).
pub fn parse_frame(bytes: &[u8]) -> Result<(MavHeader, MavMessage), String> {
    if bytes.len() > MAX_FRAME {
        return Err(format!("{} bytes: longer than a MAVLink frame", bytes.len()));
    }
    mavlink::MavlinkReader::new(bytes)
        .read_any_message::<MavMessage>()
        .map_err(|e| format!("not a MAVLink frame: {e}"))
}

/// The frames of a bundle (frames written one after another, as a vehicle's pipe to the
/// gateway puts them), cut by their own lengths (MAVLink 1: 8 bytes around the payload;
/// MAVLink 2: 12, and 13 more when the signed flag is set). Each piece still goes through
/// [`parse_frame`]; bytes that do not start a frame, or a frame cut short, end the bundle with
/// an error after the frames before them.
pub fn split_frames(bundle: &[u8]) -> (Vec<&[u8]>, Option<String>) {
    let (mut frames, mut at) = (vec![], 0);
    while at < bundle.len() {
        let rest = &bundle[at..];
        let len = match rest {
            [0xFE, n, ..] => 8 + *n as usize,
            [0xFD, n, flags, ..] => 12 + *n as usize + if flags & 0x01 != 0 { 13 } else { 0 },
            [0xFE | 0xFD, ..] => usize::MAX,
            _ => {
                return (
                    frames,
                    Some(format!("byte {at} of {}: not the start of a frame", bundle.len())),
                )
            }
        };
        if len > rest.len() {
            return (
                frames,
                Some(format!("byte {at} of {}: a frame cut short", bundle.len())),
            );
        }
        frames.push(&rest[..len]);
        at += len;
    }
    (frames, None)
}

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
    /// Nothing read (a socket's read timeout, an ICMP refusal of what we sent): read again.
    Idle,
    /// The other end closed a stream link (TCP, serial): nothing more will come.
    Closed,
}

pub struct MavLink {
    conn: Connection<MavMessage>,
    signing: Option<LinkSigning>,
    /// Sequence numbers of signed frames (the crate numbers only what it serialises).
    sequence: AtomicU8,
    /// A stream (TCP, serial), where end of file is the end of the link; on UDP it is an empty
    /// datagram.
    stream: bool,
}

impl MavLink {
    /// Open `address` (any `mavlink` connection string).
    pub fn open(address: &str, signing: Option<LinkSigning>) -> std::io::Result<Self> {
        Ok(Self {
            conn: mavlink::connect::<MavMessage>(address)?,
            signing,
            sequence: AtomicU8::new(0),
            stream: !address.starts_with("udp"),
        })
    }

    pub fn signed(&self) -> bool {
        self.signing.is_some()
    }

    /// Block for the next frame.
    pub fn recv(&self) -> Received {
        let raw = match self.conn.recv_raw() {
            Ok(r) => r,
            Err(MessageReadError::Io(e)) if e.kind() == std::io::ErrorKind::UnexpectedEof && self.stream => {
                return Received::Closed
            }
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

    /// A thread (named `name`) that blocks on the link and hands every read but [`Received::Idle`]
    /// to the returned channel, until the link closes or the receiver is dropped (then at its
    /// next read).
    pub fn reader(self: &Arc<Self>, name: &str) -> std::io::Result<mpsc::UnboundedReceiver<Received>> {
        let (tx, rx) = mpsc::unbounded_channel();
        let link = self.clone();
        std::thread::Builder::new().name(name.into()).spawn(move || loop {
            let got = link.recv();
            let closed = matches!(got, Received::Closed);
            if !matches!(got, Received::Idle) && tx.send(got).is_err() || closed {
                return;
            }
            if tx.is_closed() {
                return;
            }
        })?;
        Ok(rx)
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

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{GLOBAL_POSITION_INT_DATA, HEARTBEAT_DATA};

    #[test]
    fn a_bundle_splits_into_its_frames_and_a_bad_tail_is_named() {
        let header = MavHeader {
            system_id: 3,
            component_id: 1,
            sequence: 7,
        };
        let hb = frame_bytes(header, &MavMessage::HEARTBEAT(HEARTBEAT_DATA::default()));
        let pos = frame_bytes(
            header,
            &MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA::default()),
        );
        let mut v1 = vec![];
        let msg = MavMessage::HEARTBEAT(HEARTBEAT_DATA::default());
        mavlink::write_versioned_msg(&mut v1, MavlinkVersion::V1, header, &msg).unwrap();
        // A signed MAVLink 2 frame is 13 bytes longer, flagged in its incompatibility byte.
        let mut signed = hb.clone();
        signed[2] |= 0x01;
        signed.extend_from_slice(&[0xAA; 13]);
        let bundle: Vec<u8> = [&hb[..], &v1, &signed, &pos].concat();
        let (frames, err) = split_frames(&bundle);
        assert_eq!(err, None);
        assert_eq!(frames, vec![&hb[..], &v1[..], &signed[..], &pos[..]]);
        assert!(parse_frame(frames[0]).is_ok() && parse_frame(frames[1]).is_ok() && parse_frame(frames[3]).is_ok());
        // Cut short, or garbage after good frames: the good ones, and the error.
        let (frames, err) = split_frames(&bundle[..bundle.len() - 1]);
        assert_eq!(frames.len(), 3);
        assert!(err.unwrap().contains("cut short"));
        let junk: Vec<u8> = [&hb[..], b"junk"].concat();
        let (frames, err) = split_frames(&junk);
        assert_eq!(frames, vec![&hb[..]]);
        assert!(err.unwrap().contains("not the start of a frame"));
        assert_eq!(
            split_frames(&[0xFD]),
            (vec![], Some("byte 0 of 1: a frame cut short".into()))
        );
    }
}

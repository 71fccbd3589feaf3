//! MAVLink 2 signing of one link, as the signing specification defines it: a SHA-256 signature
//! over the frame and a shared secret, a 48-bit timestamp in 10 µs units since 2015 that must
//! grow on every stream (link id, system, component), so a recorded frame sent again is
//! refused. The crate's `SigningData` keeps the timestamps; this adds why a frame is refused,
//! since each reason is counted apart (a stranger without the key, a key that does not match,
//! a replay).

use fleet_mission::signing_key::SigningKey;
use mavlink::dialects::ardupilotmega::MavMessage;
use mavlink::{MAVLinkV2MessageRaw, MavHeader, SigningConfig, SigningData};

use mavlink::consts::{v2::IFLAG_SIGNED, MAX_FRAME_SIZE};

/// Where a MAVLink 2 frame's incompatibility flags sit, and its start marker.
const FLAGS_AT: usize = 2;
const STX_V2: u8 = 0xFD;

/// Link ids our ends sign with (each end of a link has its own streams).
pub const LINK_AUTOPILOT: u8 = 0;
pub const LINK_BRIDGE: u8 = 1;
pub const LINK_GATEWAY: u8 = 2;

/// Why a frame was refused.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Refused {
    /// No signature (or MAVLink 1, which cannot carry one).
    Unsigned,
    /// Signed, but not with our key (or altered on the way).
    BadSignature,
    /// Signed with our key, but its timestamp is not newer than the last on its stream (or a
    /// new stream more than a minute behind): a frame sent again.
    Replay,
}

impl Refused {
    /// The counter's name.
    pub fn reason(self) -> &'static str {
        match self {
            Refused::Unsigned => "unsigned",
            Refused::BadSignature => "bad_signature",
            Refused::Replay => "replay",
        }
    }
}

/// One end of a signed link: signs what it sends, checks what it receives.
pub struct LinkSigning {
    key: SigningKey,
    data: SigningData,
    accept_unsigned: bool,
}

impl LinkSigning {
    /// Sign with `key` as link `link_id`; `accept_unsigned` takes unsigned frames (an
    /// autopilot that cannot sign), never wrongly signed or replayed ones.
    pub fn new(key: SigningKey, link_id: u8, accept_unsigned: bool) -> Self {
        let data = SigningData::from_config(SigningConfig::new(key.0, link_id, true, accept_unsigned));
        Self {
            key,
            data,
            accept_unsigned,
        }
    }

    /// Check one received frame (whole, as it came off the link).
    pub fn check(&self, frame: &[u8]) -> Result<(), Refused> {
        let signed = frame.first() == Some(&STX_V2) && frame.get(FLAGS_AT).is_some_and(|f| f & IFLAG_SIGNED != 0);
        if !signed {
            return if self.accept_unsigned {
                Ok(())
            } else {
                Err(Refused::Unsigned)
            };
        }
        // Any other incompatibility flag is one we do not know: the specification says drop.
        if frame[FLAGS_AT] & !IFLAG_SIGNED != 0 || frame.len() > MAX_FRAME_SIZE {
            return Err(Refused::BadSignature);
        }
        let mut buf = [0u8; MAX_FRAME_SIZE];
        let n = frame.len().min(buf.len());
        buf[..n].copy_from_slice(&frame[..n]);
        let raw = MAVLinkV2MessageRaw::from_bytes_unparsed(buf);
        if raw.raw_bytes().len() != n {
            // Shorter than its header says: no signature to check.
            return Err(Refused::BadSignature);
        }
        let mut want = [0u8; 6];
        raw.calculate_signature(&self.key.0, &mut want);
        if want != raw.signature_value() {
            return Err(Refused::BadSignature);
        }
        // The signature is ours: the crate's check now fails only on the timestamp.
        if self.data.verify_signature(&raw) {
            Ok(())
        } else {
            Err(Refused::Replay)
        }
    }

    /// A signed MAVLink 2 frame of a message.
    pub fn frame(&self, header: MavHeader, msg: &MavMessage) -> MAVLinkV2MessageRaw {
        let mut raw = MAVLinkV2MessageRaw::new();
        raw.serialize_message_for_signing(header, msg);
        self.data.sign_message(&mut raw);
        raw
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::link::{frame_bytes, parse_frame};
    use mavlink::dialects::ardupilotmega::*;

    fn hb() -> MavMessage {
        MavMessage::HEARTBEAT(HEARTBEAT_DATA::default())
    }

    const GCS: MavHeader = MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 7,
    };

    #[test]
    fn signed_frames_pass_and_unsigned_foreign_altered_and_replayed_ones_are_refused_each_by_name() {
        let key = SigningKey::from_passphrase("field");
        let (gcs, gateway) = (
            LinkSigning::new(key.clone(), 0, false),
            LinkSigning::new(key, LINK_GATEWAY, false),
        );
        let f = gcs.frame(GCS, &hb());
        let bytes = f.raw_bytes().to_vec();
        // Still a readable frame, the message intact, 13 bytes of signature more.
        assert_eq!(parse_frame(&bytes).unwrap(), (GCS, hb()));
        assert_eq!(bytes.len(), frame_bytes(GCS, &hb()).len() + 13);
        assert_eq!(gateway.check(&bytes), Ok(()));
        assert_eq!(gateway.check(&bytes), Err(Refused::Replay), "the same frame again");
        assert_eq!(gateway.check(gcs.frame(GCS, &hb()).raw_bytes()), Ok(()), "a later one");
        assert_eq!(gateway.check(&frame_bytes(GCS, &hb())), Err(Refused::Unsigned));
        let stranger = LinkSigning::new(SigningKey::from_passphrase("guess"), 0, false);
        assert_eq!(
            gateway.check(stranger.frame(GCS, &hb()).raw_bytes()),
            Err(Refused::BadSignature)
        );
        let mut altered = gcs.frame(GCS, &hb()).raw_bytes().to_vec();
        altered[12] ^= 1;
        assert_eq!(
            gateway.check(&altered),
            Err(Refused::BadSignature),
            "a payload byte changed"
        );
        assert_eq!(
            gateway.check(&bytes[..bytes.len() - 3]),
            Err(Refused::BadSignature),
            "cut short"
        );
        // An autopilot that cannot sign: unsigned taken, wrong signatures still not.
        let lenient = LinkSigning::new(SigningKey::from_passphrase("field"), LINK_BRIDGE, true);
        assert_eq!(lenient.check(&frame_bytes(GCS, &hb())), Ok(()));
        assert_eq!(
            lenient.check(stranger.frame(GCS, &hb()).raw_bytes()),
            Err(Refused::BadSignature)
        );
    }

    #[test]
    fn any_bytes_claiming_a_signature_are_refused_without_a_panic() {
        use rand::{RngExt, SeedableRng};
        let check = LinkSigning::new(SigningKey::from_passphrase("field"), 0, false);
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for i in 0..50_000 {
            let n = rng.random_range(1..400);
            let mut f: Vec<u8> = (0..n).map(|_| rng.random()).collect();
            f[0] = 0xfd;
            if n > 2 {
                f[2] |= IFLAG_SIGNED;
                if i % 2 == 0 {
                    f[2] = IFLAG_SIGNED;
                }
            }
            assert!(check.check(&f).is_err(), "{f:?}");
        }
    }
}

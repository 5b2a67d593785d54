//! A channel packet as bytes on a network (docs/TELEOP.md §9): a fixed 120-byte little-endian
//! frame, so two daemons on two PCs (zenoh) exchange exactly what two arms of one daemon do.
//! What arrives is checked before it can move an arm: its size, its magic and version, that
//! the sender runs the same architecture and passivity setting, and that every number is
//! finite and within what an Omni can do. A frame that fails names why.
//!
//! Between two daemons a frame travels sealed (docs/TELEOP.md §9): followed by the sending
//! session's own counter and an HMAC-SHA256, with the pair's pre-shared key, over the frame,
//! the counter and the key expression it was put on. The receiver checks the code before
//! anything else and keeps a replay window on the counter, so a frame is taken once, only
//! from a holder of the key, and only on the key it was sealed for.

use super::channel::{packet_flags, Packet};
use super::{Architecture, DelayControl, TeleopConfig};
use hmac::{Hmac, Mac};
use sha2::Sha256;
use thiserror::Error;

/// Bytes of a frame.
pub const FRAME_BYTES: usize = 120;
/// The frame's first four bytes.
pub const MAGIC: [u8; 4] = *b"OMTP";
/// The frame layout's version.
pub const VERSION: u8 = 1;

/// Largest position a frame may carry (motion since engaging, scaled), mm: ten times an
/// Omni's reach.
pub const MAX_POS_MM: f64 = 3000.0;
/// Largest velocity, mm/s.
pub const MAX_VEL_MM_S: f64 = 20_000.0;
/// Largest force estimate, N (an Omni's motors give about 3.3 N at the tip).
pub const MAX_FORCE_N: f64 = 100.0;

/// What the two sides of a pair must agree on: the architecture and whether passivity runs
/// on both ports (the other settings are each side's own: the leader scales its motion
/// before sending, and scales the force it feels itself).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Agreement {
    /// pp or pf.
    pub architecture: Architecture,
    /// Time-domain passivity on both ports.
    pub passivity: bool,
    /// Delay-aware gains or wave variables (byte 7).
    pub delay_control: DelayControl,
}

impl Agreement {
    /// The agreement a side's settings ask for.
    pub fn of(cfg: &TeleopConfig) -> Agreement {
        Agreement {
            architecture: cfg.architecture,
            passivity: cfg.passivity,
            delay_control: cfg.delay_control,
        }
    }

    fn describe(self) -> String {
        format!(
            "{}, passivity {}, delay control {}",
            self.architecture.as_str(),
            if self.passivity { "on" } else { "off" },
            self.delay_control.as_str()
        )
    }
}

/// Why a frame was refused.
#[derive(Debug, Error, PartialEq)]
pub enum WireError {
    /// Not 120 bytes.
    #[error("a frame is {FRAME_BYTES} bytes; this one is {0}")]
    Size(usize),
    /// Bytes 0..4 are not `OMTP`.
    #[error("bytes 0..4 are not the frame's magic `OMTP`")]
    Magic,
    /// Byte 4, the version, is not one this build reads.
    #[error("byte 4: frame version {0}; this omnid reads version {VERSION}")]
    Version(u8),
    /// Byte 5 is not an architecture.
    #[error("byte 5: {0} is not an architecture (0 pp, 1 pf)")]
    Architecture(u8),
    /// Byte 7 is not a delay control.
    #[error("byte 7: {0} is not a delay control (0 gains, 1 wave)")]
    DelayControl(u8),
    /// The sender's pair settings differ from this side's.
    #[error(
        "the peer runs {theirs}; this side runs {ours}: start both sides with the same settings"
    )]
    Disagrees {
        /// The peer's.
        theirs: String,
        /// This side's.
        ours: String,
    },
    /// A number that is not finite, or beyond what an Omni can do.
    #[error("bytes {at}..{}: {field} = {value} is not a finite number within ±{max}", at + 8)]
    Value {
        /// Its byte offset.
        at: usize,
        /// The packet field.
        field: &'static str,
        /// The value read.
        value: f64,
        /// The largest magnitude allowed.
        max: f64,
    },
    /// Flag bits this build does not know.
    #[error("bytes 28..32: flags {0:#x} has bits this omnid does not know")]
    Flags(u32),
    /// A bare frame where a sealed one is due: the sender has no key for the pair.
    #[error(
        "a frame without an authentication code (the sender has no key for this pair: \
         `[zenoh.teleop_keys]` on both daemons)"
    )]
    Unsealed,
    /// Neither a bare nor a sealed frame.
    #[error("a sealed frame is {SEALED_BYTES} bytes; this one is {0}")]
    SealedSize(usize),
    /// The authentication code does not match: another key, another key expression, or a
    /// changed byte.
    #[error(
        "the authentication code does not match (a sender without this pair's key, or a frame \
         sealed for another key expression)"
    )]
    Mac,
    /// A counter already taken, or too far behind the newest to tell.
    #[error("counter {seq} was already taken or is older than the replay window (newest {top})")]
    Replay {
        /// The frame's counter.
        seq: u64,
        /// The newest counter taken from its sender.
        top: u64,
    },
    /// A pre-shared key too short to be one.
    #[error("a pair's key is {0} bytes; at least {MIN_KEY_BYTES} are needed (32 from `head -c32 /dev/urandom | base64`)")]
    ShortKey(usize),
}

/// The frame for `p`, sent by a side that runs `agreement`.
pub fn encode(p: &Packet, agreement: Agreement) -> [u8; FRAME_BYTES] {
    let mut b = [0u8; FRAME_BYTES];
    b[0..4].copy_from_slice(&MAGIC);
    b[4] = VERSION;
    b[5] = match agreement.architecture {
        Architecture::Pp => 0,
        Architecture::Pf => 1,
    };
    b[6] = u8::from(agreement.passivity);
    b[7] = match agreement.delay_control {
        // An unresolved `auto` runs the gains (docs/TELEOP.md §5).
        DelayControl::Gains | DelayControl::Auto => 0,
        DelayControl::Wave => 1,
    };
    let mut at = 8;
    let mut put = |bytes: &[u8]| {
        b[at..at + bytes.len()].copy_from_slice(bytes);
        at += bytes.len();
    };
    put(&p.seq.to_le_bytes());
    put(&p.t.to_le_bytes());
    put(&p.engage.to_le_bytes());
    put(&p.flags.to_le_bytes());
    for v in p.pos_mm.iter().chain(&p.vel_mm_s).chain(&p.force_n) {
        put(&v.to_le_bytes());
    }
    put(&p.energy_in_j.to_le_bytes());
    put(&p.echo_t.to_le_bytes());
    b
}

/// The packet in `b`, if it is a well-formed frame from a side that agrees with `ours`.
pub fn decode(b: &[u8], ours: Agreement) -> Result<Packet, WireError> {
    if b.len() != FRAME_BYTES {
        return Err(WireError::Size(b.len()));
    }
    if b[0..4] != MAGIC {
        return Err(WireError::Magic);
    }
    if b[4] != VERSION {
        return Err(WireError::Version(b[4]));
    }
    let architecture = match b[5] {
        0 => Architecture::Pp,
        1 => Architecture::Pf,
        x => return Err(WireError::Architecture(x)),
    };
    let delay_control = match b[7] {
        0 => DelayControl::Gains,
        1 => DelayControl::Wave,
        x => return Err(WireError::DelayControl(x)),
    };
    let theirs = Agreement {
        architecture,
        passivity: b[6] != 0,
        delay_control,
    };
    if theirs != ours {
        return Err(WireError::Disagrees {
            theirs: theirs.describe(),
            ours: ours.describe(),
        });
    }
    let u64_at = |at: usize| {
        let mut x = [0u8; 8];
        x.copy_from_slice(&b[at..at + 8]);
        u64::from_le_bytes(x)
    };
    let u32_at = |at: usize| {
        let mut x = [0u8; 4];
        x.copy_from_slice(&b[at..at + 4]);
        u32::from_le_bytes(x)
    };
    let f64_at = |at: usize, field: &'static str, max: f64| {
        let value = f64::from_bits(u64_at(at));
        if value.is_finite() && value.abs() <= max {
            Ok(value)
        } else {
            Err(WireError::Value {
                at,
                field,
                value,
                max,
            })
        }
    };
    let v3 = |at: usize, field: &'static str, max: f64| -> Result<[f64; 3], WireError> {
        Ok([
            f64_at(at, field, max)?,
            f64_at(at + 8, field, max)?,
            f64_at(at + 16, field, max)?,
        ])
    };
    let flags = u32_at(28);
    if flags & !(packet_flags::CLUTCH | packet_flags::DOWN) != 0 {
        return Err(WireError::Flags(flags));
    }
    // Times are device clocks (seconds since a daemon started); a day's run is far inside.
    const MAX_T: f64 = 1e9;
    Ok(Packet {
        seq: u64_at(8),
        t: f64_at(16, "t", MAX_T)?,
        engage: u32_at(24),
        flags,
        pos_mm: v3(32, "pos_mm", MAX_POS_MM)?,
        vel_mm_s: v3(56, "vel_mm_s", MAX_VEL_MM_S)?,
        force_n: v3(80, "force_n", MAX_FORCE_N)?,
        energy_in_j: f64_at(104, "energy_in_j", MAX_T)?,
        echo_t: f64_at(112, "echo_t", MAX_T)?,
    })
}

/// Bytes after a frame when sealed: the sender's counter (u64, little-endian) and the code.
pub const TRAILER_BYTES: usize = 8 + 32;
/// Bytes of a sealed frame.
pub const SEALED_BYTES: usize = FRAME_BYTES + TRAILER_BYTES;
/// The shortest pre-shared key taken, bytes (32 recommended).
pub const MIN_KEY_BYTES: usize = 16;
/// Counters this far behind the newest taken are still taken once (a reordered frame).
pub const REPLAY_WINDOW: u64 = 64;

/// A pair's pre-shared key, ready to seal and check frames.
#[derive(Clone)]
pub struct PairKey(Hmac<Sha256>);

impl std::fmt::Debug for PairKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the key.
        f.write_str("PairKey(..)")
    }
}

impl PairKey {
    /// The key from its bytes (at least [`MIN_KEY_BYTES`]).
    pub fn new(secret: &[u8]) -> Result<PairKey, WireError> {
        if secret.len() < MIN_KEY_BYTES {
            return Err(WireError::ShortKey(secret.len()));
        }
        Hmac::<Sha256>::new_from_slice(secret)
            .map(PairKey)
            .map_err(|_| WireError::ShortKey(secret.len()))
    }

    /// The code's state over what a sealed frame binds: a label, the key expression, the
    /// frame and its counter.
    fn mac(&self, key_expr: &str, body: &[u8]) -> Hmac<Sha256> {
        let mut m = self.0.clone();
        m.update(b"omnid teleop frame 1\0");
        m.update(key_expr.as_bytes());
        m.update(&[0]);
        m.update(body);
        m
    }
}

/// `frame` sealed with `key` for the key expression it is put on, carrying the sending
/// session's counter `seq` (from 1, never reused while the session lives).
pub fn seal(
    frame: &[u8; FRAME_BYTES],
    seq: u64,
    key_expr: &str,
    key: &PairKey,
) -> [u8; SEALED_BYTES] {
    let mut b = [0u8; SEALED_BYTES];
    b[..FRAME_BYTES].copy_from_slice(frame);
    b[FRAME_BYTES..FRAME_BYTES + 8].copy_from_slice(&seq.to_le_bytes());
    let tag = key
        .mac(key_expr, &b[..FRAME_BYTES + 8])
        .finalize()
        .into_bytes();
    b[FRAME_BYTES + 8..].copy_from_slice(&tag);
    b
}

/// The frame and its counter in `b`, if `b` was sealed with `key` for `key_expr` (the code
/// compared in constant time). The frame itself is checked next by [`decode`].
pub fn unseal(
    b: &[u8],
    key_expr: &str,
    key: &PairKey,
) -> Result<(u64, [u8; FRAME_BYTES]), WireError> {
    if b.len() == FRAME_BYTES {
        return Err(WireError::Unsealed);
    }
    if b.len() != SEALED_BYTES {
        return Err(WireError::SealedSize(b.len()));
    }
    let (body, tag) = b.split_at(FRAME_BYTES + 8);
    key.mac(key_expr, body)
        .verify_slice(tag)
        .map_err(|_| WireError::Mac)?;
    let mut frame = [0u8; FRAME_BYTES];
    frame.copy_from_slice(&body[..FRAME_BYTES]);
    let mut seq = [0u8; 8];
    seq.copy_from_slice(&body[FRAME_BYTES..]);
    Ok((u64::from_le_bytes(seq), frame))
}

/// Which counters of one sender have been taken: the newest, and a bit for each of the
/// [`REPLAY_WINDOW`] before it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplayWindow {
    top: u64,
    seen: u64,
}

impl ReplayWindow {
    /// Take counter `seq` if it is new (call only for a frame whose code matched).
    pub fn accept(&mut self, seq: u64) -> Result<(), WireError> {
        let refuse = |top| Err(WireError::Replay { seq, top });
        if seq == 0 {
            // Counters start at 1.
            return refuse(self.top);
        }
        if seq > self.top {
            let shift = seq - self.top;
            self.seen = if shift >= REPLAY_WINDOW {
                0
            } else {
                self.seen << shift
            };
            self.seen |= 1;
            self.top = seq;
            return Ok(());
        }
        let behind = self.top - seq;
        if behind >= REPLAY_WINDOW || self.seen & (1 << behind) != 0 {
            return refuse(self.top);
        }
        self.seen |= 1 << behind;
        Ok(())
    }

    /// The newest counter taken (0: none).
    pub fn newest(&self) -> u64 {
        self.top
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PP: Agreement = Agreement {
        architecture: Architecture::Pp,
        passivity: true,
        delay_control: DelayControl::Gains,
    };

    fn sample() -> Packet {
        Packet {
            seq: 0x0102_0304_0506_0708,
            t: 12.345,
            engage: 3,
            flags: packet_flags::CLUTCH,
            pos_mm: [1.5, -2.25, 40.0],
            vel_mm_s: [-100.0, 0.5, 7.0],
            force_n: [0.25, -1.0, 3.0],
            energy_in_j: 0.125,
            echo_t: 12.340,
        }
    }

    #[test]
    fn a_packet_comes_back_as_it_went() {
        let p = sample();
        assert_eq!(decode(&encode(&p, PP), PP), Ok(p));
        let d = Packet::default();
        assert_eq!(decode(&encode(&d, PP), PP), Ok(d));
    }

    #[test]
    fn the_layout_is_the_documented_one() {
        // Offsets as docs/TELEOP.md §9 lists them, read back independently of `decode`.
        let b = encode(&sample(), PP);
        assert_eq!(&b[0..8], b"OMTP\x01\x00\x01\x00");
        assert_eq!(
            u64::from_le_bytes(b[8..16].try_into().unwrap()),
            0x0102_0304_0506_0708
        );
        assert_eq!(f64::from_le_bytes(b[16..24].try_into().unwrap()), 12.345);
        assert_eq!(u32::from_le_bytes(b[24..28].try_into().unwrap()), 3);
        assert_eq!(u32::from_le_bytes(b[28..32].try_into().unwrap()), 1);
        assert_eq!(f64::from_le_bytes(b[40..48].try_into().unwrap()), -2.25);
        assert_eq!(f64::from_le_bytes(b[56..64].try_into().unwrap()), -100.0);
        assert_eq!(f64::from_le_bytes(b[96..104].try_into().unwrap()), 3.0);
        assert_eq!(f64::from_le_bytes(b[112..120].try_into().unwrap()), 12.340);
    }

    #[test]
    fn a_bad_frame_is_refused_naming_what_is_wrong() {
        let good = encode(&sample(), PP);
        assert_eq!(decode(&good[..100], PP), Err(WireError::Size(100)));
        let mut b = good;
        b[0] = b'X';
        assert_eq!(decode(&b, PP), Err(WireError::Magic));
        let mut b = good;
        b[4] = 9;
        assert_eq!(decode(&b, PP), Err(WireError::Version(9)));
        let mut b = good;
        b[5] = 7;
        assert_eq!(decode(&b, PP), Err(WireError::Architecture(7)));
        let pf = Agreement {
            architecture: Architecture::Pf,
            passivity: true,
            delay_control: DelayControl::Gains,
        };
        let e = decode(&good, pf).unwrap_err();
        assert_eq!(
            e.to_string(),
            "the peer runs pp, passivity on, delay control gains; this side runs pf, passivity \
             on, delay control gains: start both sides with the same settings"
        );
        let mut b = good;
        b[28] = 0x80;
        assert_eq!(decode(&b, PP), Err(WireError::Flags(0x80)));
        for (at, v) in [(40, f64::NAN), (64, 1e9), (88, f64::INFINITY), (16, -1e12)] {
            let mut b = good;
            b[at..at + 8].copy_from_slice(&f64::to_le_bytes(v));
            let e = decode(&b, PP).unwrap_err();
            assert!(
                matches!(e, WireError::Value { at: a, .. } if a == at),
                "{at}: {e}"
            );
        }
        let mut b = good;
        b[80..88].copy_from_slice(&f64::to_le_bytes(f64::NAN));
        assert!(decode(&b, PP)
            .unwrap_err()
            .to_string()
            .starts_with("bytes 80..88: force_n = NaN"));
    }

    #[test]
    fn no_byte_pattern_panics() {
        // Every single-byte change of a good frame, and every truncation.
        let good = encode(&sample(), PP);
        for i in 0..FRAME_BYTES {
            for x in [0u8, 0x7f, 0x80, 0xff] {
                let mut b = good;
                b[i] = x;
                let _ = decode(&b, PP);
            }
            let _ = decode(&good[..i], PP);
        }
    }

    const KEY: &[u8] = b"0123456789abcdef0123456789abcdef";
    const AT: &str = "omnid/teleop/l/f/to_follower/0123";

    #[test]
    fn a_sealed_frame_opens_only_with_its_key_on_its_key_expression() {
        let key = PairKey::new(KEY).unwrap();
        let frame = encode(&sample(), PP);
        let sealed = seal(&frame, 7, AT, &key);
        assert_eq!(unseal(&sealed, AT, &key), Ok((7, frame)));
        // Another key, another key expression (the other direction, another sender).
        let other = PairKey::new(b"another key of sixteen+ bytes").unwrap();
        assert_eq!(unseal(&sealed, AT, &other), Err(WireError::Mac));
        assert_eq!(
            unseal(&sealed, "omnid/teleop/l/f/to_leader/0123", &key),
            Err(WireError::Mac)
        );
        assert_eq!(
            unseal(&sealed, "omnid/teleop/l/f/to_follower/4567", &key),
            Err(WireError::Mac)
        );
        // Any changed byte: the frame, the counter, the code.
        for i in [0, 9, 40, FRAME_BYTES, FRAME_BYTES + 7, SEALED_BYTES - 1] {
            let mut b = sealed;
            b[i] ^= 1;
            assert_eq!(unseal(&b, AT, &key), Err(WireError::Mac), "byte {i}");
        }
        // A bare frame, and other sizes, name what they are.
        assert_eq!(unseal(&frame, AT, &key), Err(WireError::Unsealed));
        assert!(unseal(&frame, AT, &key)
            .unwrap_err()
            .to_string()
            .contains("[zenoh.teleop_keys]"));
        assert_eq!(
            unseal(&sealed[..100], AT, &key),
            Err(WireError::SealedSize(100))
        );
        assert!(matches!(
            PairKey::new(b"short"),
            Err(WireError::ShortKey(5))
        ));
        assert!(PairKey::new(b"short")
            .unwrap_err()
            .to_string()
            .contains("head -c32 /dev/urandom | base64"));
        assert_eq!(format!("{key:?}"), "PairKey(..)");
    }

    #[test]
    fn the_replay_window_takes_each_counter_once() {
        let mut w = ReplayWindow::default();
        assert!(w.accept(0).is_err());
        for s in [1, 2, 5, 4, 3] {
            assert_eq!(w.accept(s), Ok(()), "{s}");
        }
        for s in [1, 2, 3, 4, 5] {
            assert_eq!(
                w.accept(s),
                Err(WireError::Replay { seq: s, top: 5 }),
                "{s}"
            );
        }
        assert_eq!(w.accept(5 + REPLAY_WINDOW), Ok(()));
        // Just inside the window and not yet taken; just outside.
        assert_eq!(w.accept(6), Ok(()));
        assert!(w.accept(5).is_err());
        assert_eq!(w.newest(), 5 + REPLAY_WINDOW);
        // A jump far ahead forgets the old bits but still refuses what is behind.
        assert_eq!(w.accept(1_000_000), Ok(()));
        assert!(w.accept(6 + REPLAY_WINDOW).is_err());
        assert_eq!(w.accept(999_999), Ok(()));
        assert!(w.accept(999_999).is_err());
        assert_eq!(w.accept(u64::MAX), Ok(()));
        assert!(w.accept(u64::MAX).is_err());
    }

    #[test]
    fn no_sealed_byte_pattern_panics() {
        let key = PairKey::new(KEY).unwrap();
        let sealed = seal(&encode(&sample(), PP), 1, AT, &key);
        for i in 0..SEALED_BYTES {
            let mut b = sealed;
            b[i] = b[i].wrapping_add(1);
            let _ = unseal(&b, AT, &key);
            let _ = unseal(&sealed[..i], AT, &key);
        }
    }
}

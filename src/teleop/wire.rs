//! A channel packet as bytes on a network (docs/TELEOP.md §9): a fixed 120-byte little-endian
//! frame, so two daemons on two PCs (zenoh) exchange exactly what two arms of one daemon do.
//! What arrives is checked before it can move an arm: its size, its magic and version, that
//! the sender runs the same architecture and passivity setting, and that every number is
//! finite and within what an Omni can do. A frame that fails names why.

use super::channel::{packet_flags, Packet};
use super::{Architecture, TeleopConfig};
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
}

impl Agreement {
    /// The agreement a side's settings ask for.
    pub fn of(cfg: &TeleopConfig) -> Agreement {
        Agreement {
            architecture: cfg.architecture,
            passivity: cfg.passivity,
        }
    }

    fn describe(self) -> String {
        format!(
            "{}, passivity {}",
            self.architecture.as_str(),
            if self.passivity { "on" } else { "off" }
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
    let theirs = Agreement {
        architecture,
        passivity: b[6] != 0,
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

#[cfg(test)]
mod tests {
    use super::*;

    const PP: Agreement = Agreement {
        architecture: Architecture::Pp,
        passivity: true,
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
        };
        let e = decode(&good, pf).unwrap_err();
        assert_eq!(
            e.to_string(),
            "the peer runs pp, passivity on; this side runs pf, passivity on: start both sides \
             with the same settings"
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
}

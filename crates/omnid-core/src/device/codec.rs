//! The Omni packet codec. Every byte position lives in the two layout tables below, so a
//! correction to the (reverse-engineered) layout is one edit. Each position is a fact of
//! docs/FIREWIRE.md, which names the driver file and line it comes from; the tests in
//! `firewire/tests.rs` check these tables against a byte table written independently from the
//! same sources.

use thiserror::Error;

/// Host → device packet length, bytes (docs/FIREWIRE.md §3).
pub const COMMAND_LEN: usize = 16;
/// Device → host packet length, bytes (docs/FIREWIRE.md §4).
pub const STATE_LEN: usize = 44;
/// DAC word for zero torque (12-bit offset binary).
pub(crate) const DAC_ZERO: u16 = 0x07FF;
/// Largest DAC word (12 bits).
pub(crate) const DAC_MAX: u16 = 0x0FFF;
/// Byte 7 of every command both open drivers send: a constant, not a counter
/// (docs/FIREWIRE.md §3).
pub const DRIVERS_BYTE7: u8 = 0x53;

/// Byte layout of the host → device command packet (little-endian).
pub(crate) struct CommandLayout {
    /// Offsets of the three u16 motor words.
    pub motor: [usize; 3],
    /// Offset of the misc-out byte.
    pub misc: usize,
    /// Bits of the misc-out byte both drivers always set (0xC0).
    pub misc_fixed: u8,
    /// Misc-out bit that switches the amplifiers on.
    pub amps_bit: u8,
    /// Misc-out mask of the dock lamp bits.
    pub lamp_mask: u8,
    /// Offset of byte 7 (the drivers send [`DRIVERS_BYTE7`]; see [`MotorCommand::watchdog`]).
    pub watchdog: usize,
}

/// Byte layout of the device → host state packet (little-endian).
pub(crate) struct StateLayout {
    /// Offsets of the three u16 encoder counts.
    pub encoder: [usize; 3],
    /// Offsets of the three u16 gimbal potentiometer words.
    pub gimbal: [usize; 3],
    /// Offset of the switch byte (all active-low).
    pub status: usize,
    /// Status bits of stylus buttons 1 and 2.
    pub button_bits: [u8; 2],
    /// Status bit of the inkwell switch (low = stylus docked).
    pub inkwell_bit: u8,
    /// Offset of the u32 per-packet counter.
    pub counter: usize,
}

/// docs/FIREWIRE.md §3: omnifirewire.h:60-90 (ROS) and PhantomSpec.h:93-123 (Twente).
pub(crate) const COMMAND_LAYOUT: CommandLayout = CommandLayout {
    // force_x/y/z: omnifirewire.h:62-64; PhantomSpec.h:95-97.
    motor: [0, 2, 4],
    // The low byte of the u16 status word: omnifirewire.h:66-86; PhantomSpec.h:98-120.
    misc: 6,
    // 0x53C0 with lamp and motors off: omnifirewire.cpp:213; omni.c:281; opensource.c:42.
    misc_fixed: 0xC0,
    // force_enabled / motors_on: omnifirewire.h:72; PhantomSpec.h:106.
    amps_bit: 3,
    // dock_led0/1 / dl_flash, dl_fflash: omnifirewire.h:69-70; PhantomSpec.h:103-104.
    lamp_mask: 0b11,
    // The high byte of the same word, 0x53 (as misc_fixed).
    watchdog: 7,
};

/// docs/FIREWIRE.md §4: omnifirewire.h:92-136 (ROS) and PhantomSpec.h:53-88 (Twente); the
/// switch byte is 19 in both (omnifirewire.h:105-119, PhantomSpec.h:62-77).
pub(crate) const STATE_LAYOUT: StateLayout = StateLayout {
    // encoder_x/y/z: omnifirewire.h:96-98; PhantomSpec.h:57-59.
    encoder: [4, 6, 8],
    // gimbal_a_x/y/z: omnifirewire.h:100-102; PhantomSpec.h:60.
    gimbal: [10, 12, 14],
    // status: omnifirewire.h:107-119 (after tx_packet_num at 18, :105); PhantomSpec.h:63-77.
    status: 19,
    // button1, button2 (0 = pressed): omnifirewire.h:110-111; PhantomSpec.h:68-69.
    button_bits: [0, 1],
    // undocked / docked (0 = in the inkwell): omnifirewire.h:112; PhantomSpec.h:70.
    inkwell_bit: 2,
    // count0, "+1 every message": PhantomSpec.h:82 (ROS `time`, omnifirewire.h:130).
    counter: 32,
};

/// Bits 3..7 of the switch byte as the Twente trace expects them on an idle device
/// (libraw1394-2.0.5-trace.patch:1580-1588: bit 4 and bit 7 set), so that encoded packets
/// look like the device's.
pub(crate) const STATUS_IDLE_HIGH_BITS: u8 = 0x90;

/// A malformed packet. Never a panic: every decoder returns one of these.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum CodecError {
    /// A packet of the wrong size.
    #[error("{what} packet has {got} bytes, expected {expected}")]
    Length {
        /// Which packet: `state` or `command`.
        what: &'static str,
        /// Its length, bytes.
        got: usize,
        /// The length it must have, bytes.
        expected: usize,
    },
    /// A motor word above 0x0FFF.
    #[error("command packet byte {byte}: motor word {word:#06x} exceeds the 12-bit DAC range")]
    DacRange {
        /// Offset of the word in the packet.
        byte: usize,
        /// The word.
        word: u16,
    },
    /// A reserved byte that is not zero.
    #[error("command packet byte {byte}: reserved byte is {value:#04x}, expected 0")]
    Reserved {
        /// Offset of the byte in the packet.
        byte: usize,
        /// Its value.
        value: u8,
    },
}

/// Decoded host → device command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct MotorCommand {
    /// Motor DAC words, 0..=0x0FFF, 0x07FF = zero torque.
    pub dac: [u16; 3],
    /// Motor amplifiers enabled.
    pub amps_on: bool,
    /// Dock lamp bits (0..=3).
    pub lamp: u8,
    /// Byte 7. The open drivers send the constant [`DRIVERS_BYTE7`] there, and the real
    /// backends put that on the wire (docs/FIREWIRE.md §3). The simulator reads it as a
    /// watchdog that drops its amplifiers when the byte stops changing: a modelling choice of
    /// omnid's, not a documented behaviour of the device.
    pub watchdog: u8,
}

impl MotorCommand {
    /// Zero torque with the amplifiers off: what every stop path sends.
    pub fn safe(watchdog: u8) -> Self {
        MotorCommand {
            dac: [DAC_ZERO; 3],
            amps_on: false,
            lamp: 0,
            watchdog,
        }
    }

    /// True when this command carries zero torque and the amplifiers are off.
    pub fn is_safe(&self) -> bool {
        self.dac == [DAC_ZERO; 3] && !self.amps_on
    }
}

/// Decoded device → host state.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StatePacket {
    /// Raw 16-bit encoder counts (wrapping; see [`EncoderUnwrap`]).
    pub encoder: [u16; 3],
    /// Gimbal potentiometer words (upper 11 bits useful).
    pub gimbal: [u16; 3],
    /// Stylus buttons pressed.
    pub buttons: [bool; 2],
    /// Stylus in the inkwell.
    pub inkwell: bool,
    /// Per-packet counter.
    pub counter: u32,
}

fn put_u16(buf: &mut [u8], at: usize, v: u16) {
    buf[at..at + 2].copy_from_slice(&v.to_le_bytes());
}

fn get_u16(buf: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([buf[at], buf[at + 1]])
}

/// Encode a command into its 16-byte packet. DAC words above 12 bits are clamped.
pub fn encode_command(cmd: &MotorCommand) -> [u8; COMMAND_LEN] {
    let l = &COMMAND_LAYOUT;
    let mut b = [0u8; COMMAND_LEN];
    for (j, &at) in l.motor.iter().enumerate() {
        put_u16(&mut b, at, cmd.dac[j].min(DAC_MAX));
    }
    b[l.misc] =
        l.misc_fixed | (cmd.lamp & l.lamp_mask) | if cmd.amps_on { 1 << l.amps_bit } else { 0 };
    b[l.watchdog] = cmd.watchdog;
    b
}

/// Decode a command packet (the device side: simulator and fake buses use it).
pub fn decode_command(b: &[u8]) -> Result<MotorCommand, CodecError> {
    let l = &COMMAND_LAYOUT;
    if b.len() != COMMAND_LEN {
        return Err(CodecError::Length {
            what: "command",
            got: b.len(),
            expected: COMMAND_LEN,
        });
    }
    let mut dac = [0u16; 3];
    for (j, &at) in l.motor.iter().enumerate() {
        let word = get_u16(b, at);
        if word > DAC_MAX {
            return Err(CodecError::DacRange { byte: at, word });
        }
        dac[j] = word;
    }
    if let Some(byte) = (8..COMMAND_LEN).find(|&i| b[i] != 0) {
        return Err(CodecError::Reserved {
            byte,
            value: b[byte],
        });
    }
    Ok(MotorCommand {
        dac,
        amps_on: b[l.misc] & (1 << l.amps_bit) != 0,
        lamp: b[l.misc] & l.lamp_mask,
        watchdog: b[l.watchdog],
    })
}

/// Encode a state packet (the device side).
pub fn encode_state(s: &StatePacket) -> [u8; STATE_LEN] {
    let l = &STATE_LAYOUT;
    let mut b = [0u8; STATE_LEN];
    for j in 0..3 {
        put_u16(&mut b, l.encoder[j], s.encoder[j]);
        put_u16(&mut b, l.gimbal[j], s.gimbal[j]);
    }
    // Switches are active-low: a released button reads 1.
    let mut status = STATUS_IDLE_HIGH_BITS | 0b111;
    for (k, &bit) in l.button_bits.iter().enumerate() {
        if s.buttons[k] {
            status &= !(1 << bit);
        }
    }
    if s.inkwell {
        status &= !(1 << l.inkwell_bit);
    }
    b[l.status] = status;
    b[l.counter..l.counter + 4].copy_from_slice(&s.counter.to_le_bytes());
    b
}

/// Decode a state packet from the device.
pub fn decode_state(b: &[u8]) -> Result<StatePacket, CodecError> {
    let l = &STATE_LAYOUT;
    if b.len() != STATE_LEN {
        return Err(CodecError::Length {
            what: "state",
            got: b.len(),
            expected: STATE_LEN,
        });
    }
    let status = b[l.status];
    let low = |bit: u8| status & (1 << bit) == 0;
    Ok(StatePacket {
        encoder: [
            get_u16(b, l.encoder[0]),
            get_u16(b, l.encoder[1]),
            get_u16(b, l.encoder[2]),
        ],
        gimbal: [
            get_u16(b, l.gimbal[0]),
            get_u16(b, l.gimbal[1]),
            get_u16(b, l.gimbal[2]),
        ],
        buttons: [low(l.button_bits[0]), low(l.button_bits[1])],
        inkwell: low(l.inkwell_bit),
        counter: u32::from_le_bytes([
            b[l.counter],
            b[l.counter + 1],
            b[l.counter + 2],
            b[l.counter + 3],
        ]),
    })
}

/// Turns 16-bit wrapping encoder counts into continuous counts, assuming less than half a
/// turn of the 16-bit counter (32768 counts, ≈ 2.2 rev) between two packets.
#[derive(Debug, Clone, Copy, Default)]
pub struct EncoderUnwrap {
    last: Option<[u16; 3]>,
    total: [i64; 3],
}

impl EncoderUnwrap {
    /// Start from a known continuous count for the first packet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Feed one packet's raw counts; returns the continuous counts. The first packet's raw
    /// value is taken as a signed 16-bit count.
    pub fn update(&mut self, raw: [u16; 3]) -> [i64; 3] {
        match self.last {
            None => {
                for (t, r) in self.total.iter_mut().zip(raw) {
                    *t = r as i16 as i64;
                }
            }
            Some(last) => {
                for j in 0..3 {
                    self.total[j] += raw[j].wrapping_sub(last[j]) as i16 as i64;
                }
            }
        }
        self.last = Some(raw);
        self.total
    }
}

/// Torque → DAC word (rounded, saturated to 12 bits) and back.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DacScale {
    /// N·m per DAC count, per joint.
    pub nm_per_count: [f64; 3],
}

impl DacScale {
    /// Joint torques, N·m, as DAC words (rounded, saturated at the 12-bit range; a
    /// non-finite torque gives zero torque).
    pub fn to_words(&self, tau: &[f64; 3]) -> [u16; 3] {
        let mut w = [DAC_ZERO; 3];
        for j in 0..3 {
            let counts = (tau[j] / self.nm_per_count[j]).round();
            // NaN maps to zero torque; the safety layer has already refused it.
            let counts = if counts.is_finite() { counts } else { 0.0 };
            let word = (DAC_ZERO as f64 + counts).clamp(0.0, DAC_MAX as f64);
            w[j] = word as u16;
        }
        w
    }

    /// DAC words as the joint torques they command, N·m.
    pub fn to_torque(&self, words: &[u16; 3]) -> [f64; 3] {
        let mut t = [0.0; 3];
        for j in 0..3 {
            t[j] = (words[j] as f64 - DAC_ZERO as f64) * self.nm_per_count[j];
        }
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn command_round_trip_every_field() {
        for amps in [false, true] {
            for lamp in 0..4 {
                let c = MotorCommand {
                    dac: [0, DAC_ZERO, DAC_MAX],
                    amps_on: amps,
                    lamp,
                    watchdog: 0xA5,
                };
                assert_eq!(decode_command(&encode_command(&c)).unwrap(), c);
            }
        }
    }

    #[test]
    fn safe_command_bytes() {
        let b = encode_command(&MotorCommand::safe(7));
        assert_eq!(&b[0..6], &[0xFF, 0x07, 0xFF, 0x07, 0xFF, 0x07]);
        assert_eq!(b[6], 0xC0);
        assert_eq!(b[7], 7);
        assert!(b[8..].iter().all(|&x| x == 0));
    }

    #[test]
    fn amps_bit_is_bit_three_of_byte_six() {
        let mut c = MotorCommand::safe(0);
        c.amps_on = true;
        assert_eq!(encode_command(&c)[6], 0xC8);
    }

    #[test]
    fn state_round_trip_every_field() {
        for (b1, b2, ink) in [
            (false, false, false),
            (true, false, true),
            (false, true, false),
        ] {
            let s = StatePacket {
                encoder: [0, 0x7FFF, 0xFFFF],
                gimbal: [0x0123, 0xFFE0, 0x8000],
                buttons: [b1, b2],
                inkwell: ink,
                counter: 0xDEAD_BEEF,
            };
            assert_eq!(decode_state(&encode_state(&s)).unwrap(), s);
        }
    }

    #[test]
    fn switches_are_active_low() {
        let mut b = [0u8; STATE_LEN];
        b[STATE_LAYOUT.status] = 0xFF;
        let s = decode_state(&b).unwrap();
        assert_eq!((s.buttons, s.inkwell), ([false, false], false));
        b[STATE_LAYOUT.status] = !(1 << 2);
        assert!(decode_state(&b).unwrap().inkwell);
    }

    #[test]
    fn encoder_unwrap_across_rollover() {
        let mut u = EncoderUnwrap::new();
        assert_eq!(u.update([0xFFF0, 10, 0x0005]), [-16, 10, 5]);
        // Forward across 0xFFFF → 0x0000 on joint 1, backward across 0 on joint 3.
        assert_eq!(u.update([0x0010, 20, 0xFFFB]), [16, 20, -5]);
        // Many small steps forward keep accumulating past 16 bits.
        let mut raw = 0x0010u16;
        let mut last = [0; 3];
        for _ in 0..10_000 {
            raw = raw.wrapping_add(13);
            last = u.update([raw, 20, 0xFFFB]);
        }
        assert_eq!(last[0], 16 + 130_000);
    }

    #[test]
    fn short_and_long_packets_are_typed_errors() {
        assert_eq!(
            decode_state(&[0u8; 43]),
            Err(CodecError::Length {
                what: "state",
                got: 43,
                expected: 44
            })
        );
        assert!(matches!(
            decode_command(&[0u8; 17]),
            Err(CodecError::Length { got: 17, .. })
        ));
        let mut b = encode_command(&MotorCommand::safe(0));
        b[1] = 0x10;
        assert!(matches!(
            decode_command(&b),
            Err(CodecError::DacRange { byte: 0, .. })
        ));
        let mut b = encode_command(&MotorCommand::safe(0));
        b[12] = 1;
        assert_eq!(
            decode_command(&b),
            Err(CodecError::Reserved { byte: 12, value: 1 })
        );
    }

    #[test]
    fn dac_scale_rounds_saturates_and_inverts() {
        let s = DacScale {
            nm_per_count: [1e-3; 3],
        };
        assert_eq!(
            s.to_words(&[0.0, 0.0104, -0.0106]),
            [DAC_ZERO, DAC_ZERO + 10, DAC_ZERO - 11]
        );
        assert_eq!(s.to_words(&[10.0, -10.0, f64::NAN]), [DAC_MAX, 0, DAC_ZERO]);
        let t = s.to_torque(&[DAC_ZERO + 10, DAC_ZERO, DAC_ZERO - 11]);
        assert!((t[0] - 0.010).abs() < 1e-15 && t[1] == 0.0 && (t[2] + 0.011).abs() < 1e-15);
    }

    proptest! {
        #[test]
        fn decoders_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = decode_state(&bytes);
            let _ = decode_command(&bytes);
        }

        #[test]
        fn any_valid_state_round_trips(enc in any::<[u16; 3]>(), gim in any::<[u16; 3]>(),
                                       b in any::<[bool; 2]>(), ink in any::<bool>(), n in any::<u32>()) {
            let s = StatePacket { encoder: enc, gimbal: gim, buttons: b, inkwell: ink, counter: n };
            prop_assert_eq!(decode_state(&encode_state(&s)).unwrap(), s);
        }

        #[test]
        fn unwrap_tracks_any_small_steps(start in any::<i16>(), steps in proptest::collection::vec(-30000i32..30000, 1..50)) {
            let mut u = EncoderUnwrap::new();
            let mut truth = start as i64;
            u.update([start as u16; 3]);
            for s in steps {
                truth += s as i64;
                let raw = truth as u16;
                prop_assert_eq!(u.update([raw; 3])[0], truth);
            }
        }
    }
}

//! Stream logic shared by the real backends (USB bridge, FireWire): what goes on the wire and
//! what comes off it, independent of how the bytes travel.
//!
//! - [`CommandGate`] turns the servo's command into the packet actually sent: the amplifiers
//!   stay off until the backend has delivered a sample (after open and after every restart),
//!   byte 7 and the DAC signs follow the [`WireFormat`] (by default the open drivers' constant
//!   0x53, docs/FIREWIRE.md §3), and a malformed command is never sent (the safe packet goes
//!   instead).
//! - [`CounterTracker`] checks the device's per-packet counter: fresh packets, gaps (packets the
//!   device sent that never arrived), duplicates and stale packets; device time comes from the
//!   counter, so a gap shows up as a longer step in time.
//! - [`Framer`] cuts a byte stream (USB transfers may split or merge packets) into 44-byte
//!   packets, resynchronising on the counter when bytes are lost.
//!
//! Nothing here allocates: every buffer is fixed.

use super::codec::{
    decode_command, encode_command, CodecError, MotorCommand, COMMAND_LEN, DAC_MAX, DAC_ZERO,
    DRIVERS_BYTE7, STATE_LAYOUT, STATE_LEN,
};
use super::MissReason;

/// A forward jump of the per-packet counter up to this many counts is taken as packets lost on
/// the way; a bigger jump (or a bigger step back) means the bytes are not a packet.
pub const MAX_COUNTER_JUMP: u32 = 4096;

/// The per-packet counter of a state packet (`p` holds at least [`STATE_LEN`] bytes).
pub fn packet_counter(p: &[u8]) -> u32 {
    let at = STATE_LAYOUT.counter;
    u32::from_le_bytes([p[at], p[at + 1], p[at + 2], p[at + 3]])
}

/// Counters of everything unusual the stream has seen since open.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StreamStats {
    /// Samples handed to the servo.
    pub delivered: u64,
    /// Packets the device counted that never arrived (sum of all counter gaps).
    pub lost: u64,
    /// Number of counter gaps (each of one or more lost packets).
    pub gaps: u64,
    /// Packets whose counter equals the last delivered one.
    pub duplicates: u64,
    /// Packets older than the last delivered one (arrived out of order).
    pub stale: u64,
    /// Fresh packets that arrived in the same read as a newer one; the newer was delivered.
    pub superseded: u64,
    /// Bytes dropped while looking for packet boundaries.
    pub resync_bytes: u64,
    /// Packets of the wrong length (FireWire) or transfers too big for the buffer (USB).
    pub malformed: u64,
    /// Exchanges that returned `Missed`.
    pub misses: u64,
    /// Streaming restarts (FireWire bus resets).
    pub restarts: u64,
    /// Why the last miss happened.
    pub last_miss: Option<MissReason>,
}

/// What the counter of a newly arrived packet means.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Verdict {
    /// The next packet, after `lost` packets that never arrived.
    Fresh { lost: u32 },
    /// Same counter as the last delivered packet.
    Duplicate,
    /// Older than the last delivered packet.
    Stale,
    /// Too far from the last counter to be this device's next packet.
    Implausible,
    /// No packet accepted yet (or since a restart): any counter can start the stream.
    Unanchored,
}

/// Per-packet counter bookkeeping and device time.
#[derive(Debug, Clone, Copy)]
pub struct CounterTracker {
    period_s: f64,
    /// Counter of the last accepted packet.
    last: Option<u32>,
    /// False before the first packet and while resynchronising: any counter may (re)start the
    /// stream.
    trusted: bool,
    /// Packets (by counter) since the anchor.
    steps: u64,
    /// Device time of the anchor packet.
    anchor_time: f64,
    /// Device time of the last accepted packet.
    last_time: Option<f64>,
}

impl CounterTracker {
    /// `period_s`: the device's packet period (1 / rate).
    pub fn new(period_s: f64) -> Self {
        CounterTracker {
            period_s,
            last: None,
            trusted: false,
            steps: 0,
            anchor_time: 0.0,
            last_time: None,
        }
    }

    pub fn classify(&self, counter: u32) -> Verdict {
        if self.trusted {
            self.relate(counter)
        } else {
            Verdict::Unanchored
        }
    }

    /// How `counter` relates to the last accepted packet, trusted or not (`Unanchored` only
    /// before the first packet).
    pub fn relate(&self, counter: u32) -> Verdict {
        let Some(last) = self.last else {
            return Verdict::Unanchored;
        };
        let ahead = counter.wrapping_sub(last);
        if ahead == 0 {
            Verdict::Duplicate
        } else if ahead <= MAX_COUNTER_JUMP {
            Verdict::Fresh { lost: ahead - 1 }
        } else if last.wrapping_sub(counter) <= MAX_COUNTER_JUMP {
            Verdict::Stale
        } else {
            Verdict::Implausible
        }
    }

    /// Accept a packet classified `Fresh` or `Unanchored`; returns its device time (seconds)
    /// and how many packets were lost before it. A packet that does not follow the last one
    /// (first packet, restarted counter) anchors a new time base one period after the last
    /// accepted packet, so time never runs backwards.
    pub fn accept(&mut self, counter: u32) -> (f64, u32) {
        let ahead = self.last.map(|last| counter.wrapping_sub(last));
        let lost = match ahead {
            Some(d) if (1..=MAX_COUNTER_JUMP).contains(&d) => {
                self.steps += u64::from(d);
                d - 1
            }
            _ => {
                self.anchor_time = self.last_time.map_or(0.0, |t| t + self.period_s);
                self.steps = 0;
                0
            }
        };
        self.last = Some(counter);
        self.trusted = true;
        let t = self.anchor_time + self.steps as f64 * self.period_s;
        self.last_time = Some(t);
        (t, lost)
    }

    /// Stop trusting the counter (the stream restarted or lost its boundaries); the next
    /// accepted packet re-anchors, time stays continuous, a gap is still counted when the new
    /// counter follows the old one.
    pub fn reanchor(&mut self) {
        self.trusted = false;
    }

    /// Whether the counter is trusted (an accepted packet anchored it since the last reset).
    #[cfg(test)]
    pub fn is_anchored(&self) -> bool {
        self.trusted
    }
}

/// What goes in byte 7 of every command on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Byte7 {
    /// The same value on every packet (both open drivers: 0x53, docs/FIREWIRE.md §3).
    Constant(u8),
    /// A counter advancing by one per packet (omnid's guess before issue 19; no source sends
    /// one).
    Counter,
}

/// How the servo's command becomes the bytes on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireFormat {
    pub byte7: Byte7,
    /// Per motor: `1` the DAC word as the servo computed it, `-1` mirrored about zero torque,
    /// `0` zero torque always (the sign of that axis has not been measured).
    pub dac_sign: [i8; 3],
}

impl WireFormat {
    /// The open drivers' byte 7, DAC words as computed.
    pub const DRIVERS: WireFormat = WireFormat {
        byte7: Byte7::Constant(DRIVERS_BYTE7),
        dac_sign: [1; 3],
    };

    /// A DAC word with this axis's sign applied.
    pub fn signed_dac(&self, axis: usize, word: u16) -> u16 {
        match self.dac_sign[axis] {
            1 => word,
            -1 => (2 * i32::from(DAC_ZERO) - i32::from(word)).clamp(0, i32::from(DAC_MAX)) as u16,
            _ => DAC_ZERO,
        }
    }
}

impl Default for WireFormat {
    fn default() -> Self {
        WireFormat::DRIVERS
    }
}

/// Builds the packets that actually go on the wire.
#[derive(Debug, Clone, Copy)]
pub struct CommandGate {
    format: WireFormat,
    counter: u8,
    sample_delivered: bool,
}

impl Default for CommandGate {
    fn default() -> Self {
        CommandGate::with_format(WireFormat::DRIVERS)
    }
}

impl CommandGate {
    /// The open drivers' wire format.
    pub fn new() -> Self {
        Self::default()
    }

    pub fn with_format(format: WireFormat) -> Self {
        CommandGate {
            format,
            counter: 0,
            sample_delivered: false,
        }
    }

    fn stamp(&mut self, mut cmd: MotorCommand) -> [u8; COMMAND_LEN] {
        self.counter = self.counter.wrapping_add(1);
        cmd.watchdog = match self.format.byte7 {
            Byte7::Constant(v) => v,
            Byte7::Counter => self.counter,
        };
        encode_command(&cmd)
    }

    /// The packet to send for the servo's `command`. Amplifiers off (and zero torque) until a
    /// sample has been delivered; a malformed command is replaced by the safe packet and the
    /// error is returned beside it.
    pub fn wire(&mut self, command: &[u8; COMMAND_LEN]) -> ([u8; COMMAND_LEN], Option<CodecError>) {
        match decode_command(command) {
            Ok(mut cmd) => {
                for j in 0..3 {
                    cmd.dac[j] = self.format.signed_dac(j, cmd.dac[j]);
                }
                (self.raw(cmd), None)
            }
            Err(e) => (self.safe(), Some(e)),
        }
    }

    /// `cmd` as it is (no DAC signs: for the guided sign check of `omnid probe --outputs`),
    /// still with the amplifiers off until a sample has been delivered.
    pub fn raw(&mut self, mut cmd: MotorCommand) -> [u8; COMMAND_LEN] {
        if !self.sample_delivered {
            cmd.amps_on = false;
            cmd.dac = [DAC_ZERO; 3];
        }
        self.stamp(cmd)
    }

    /// Zero torque, amplifiers off, lamp off.
    pub fn safe(&mut self) -> [u8; COMMAND_LEN] {
        self.stamp(MotorCommand::safe(0))
    }

    /// A sample went to the servo: from now on its commands pass as they are.
    pub fn sample_delivered(&mut self) {
        self.sample_delivered = true;
    }

    /// Streaming restarted: amplifiers off again until the next sample.
    pub fn require_new_sample(&mut self) {
        self.sample_delivered = false;
    }
}

/// Room for unconsumed bytes between reads.
pub const FRAMER_CAPACITY: usize = 4096;

/// Consecutive frames with counters stepping by exactly one that (re)establish the packet
/// boundaries of a byte stream.
pub const ANCHOR_CHAIN: usize = 4;

/// Cuts a byte stream into state packets by length, checking the counter.
pub struct Framer {
    buf: [u8; FRAMER_CAPACITY],
    len: usize,
    /// A duplicate or stale frame was taken at face value and no fresh one has come since.
    suspicious: bool,
}

impl Default for Framer {
    fn default() -> Self {
        Self::new()
    }
}

impl Framer {
    pub fn new() -> Self {
        Framer {
            buf: [0; FRAMER_CAPACITY],
            len: 0,
            suspicious: false,
        }
    }

    /// Bytes waiting for the rest of their packet (or for boundaries to be confirmed).
    #[cfg(test)]
    pub fn pending(&self) -> usize {
        self.len
    }

    /// Append one transfer. If it does not fit, the oldest bytes are dropped (counted).
    pub fn push(&mut self, data: &[u8], stats: &mut StreamStats) {
        let data = if data.len() > FRAMER_CAPACITY {
            let cut = data.len() - FRAMER_CAPACITY;
            stats.resync_bytes += cut as u64;
            &data[cut..]
        } else {
            data
        };
        let free = FRAMER_CAPACITY - self.len;
        if data.len() > free {
            let drop = data.len() - free;
            self.buf.copy_within(drop..self.len, 0);
            self.len -= drop;
            stats.resync_bytes += drop as u64;
        }
        self.buf[self.len..self.len + data.len()].copy_from_slice(data);
        self.len += data.len();
    }

    /// True when `ANCHOR_CHAIN` frames from `pos` have counters stepping by exactly one.
    fn chain_at(&self, pos: usize) -> bool {
        let mut prev = packet_counter(&self.buf[pos..pos + STATE_LEN]);
        for k in 1..ANCHOR_CHAIN {
            let at = pos + k * STATE_LEN;
            let c = packet_counter(&self.buf[at..at + STATE_LEN]);
            if c.wrapping_sub(prev) != 1 {
                return false;
            }
            prev = c;
        }
        true
    }

    /// Cut every complete packet out of the buffer and keep the newest fresh one in `out`;
    /// returns its device time, or `None` when no fresh packet is complete yet. Bytes of an
    /// incomplete packet stay for the next read.
    ///
    /// Boundaries: once anchored, packets follow each other every 44 bytes. A duplicate or
    /// stale frame is dropped when the frame after it is fresh (or, once, when there is none
    /// yet); otherwise, and on any frame whose counter makes no sense, the boundaries are
    /// searched again byte by byte for `ANCHOR_CHAIN` frames whose counters step by exactly
    /// one.
    pub fn drain_newest(
        &mut self,
        tracker: &mut CounterTracker,
        stats: &mut StreamStats,
        out: &mut [u8; STATE_LEN],
    ) -> Option<f64> {
        let mut pos = 0;
        let mut newest = None;
        while self.len - pos >= STATE_LEN {
            let counter = packet_counter(&self.buf[pos..pos + STATE_LEN]);
            let take = match tracker.classify(counter) {
                Verdict::Fresh { .. } => true,
                verdict @ (Verdict::Duplicate | Verdict::Stale) => {
                    let next_fresh = (self.len - pos >= 2 * STATE_LEN).then(|| {
                        let next = &self.buf[pos + STATE_LEN..pos + 2 * STATE_LEN];
                        matches!(
                            tracker.classify(packet_counter(next)),
                            Verdict::Fresh { .. }
                        )
                    });
                    if next_fresh.unwrap_or(!self.suspicious) {
                        count_old(verdict, stats);
                        self.suspicious = true;
                        pos += STATE_LEN;
                    } else {
                        tracker.reanchor();
                    }
                    false
                }
                Verdict::Implausible => {
                    // Lost bytes or a restarted device: search the boundaries again.
                    tracker.reanchor();
                    false
                }
                Verdict::Unanchored => {
                    if self.len - pos < ANCHOR_CHAIN * STATE_LEN {
                        break;
                    }
                    if !self.chain_at(pos) {
                        stats.resync_bytes += 1;
                        pos += 1;
                        false
                    } else {
                        match tracker.relate(counter) {
                            verdict @ (Verdict::Duplicate | Verdict::Stale) => {
                                count_old(verdict, stats);
                                pos += STATE_LEN;
                                false
                            }
                            _ => true,
                        }
                    }
                }
            };
            if take {
                let (t, lost) = tracker.accept(counter);
                if lost > 0 {
                    stats.lost += u64::from(lost);
                    stats.gaps += 1;
                }
                if newest.is_some() {
                    stats.superseded += 1;
                }
                out.copy_from_slice(&self.buf[pos..pos + STATE_LEN]);
                newest = Some(t);
                pos += STATE_LEN;
                self.suspicious = false;
            }
        }
        self.buf.copy_within(pos..self.len, 0);
        self.len -= pos;
        newest
    }
}

fn count_old(verdict: Verdict, stats: &mut StreamStats) {
    if verdict == Verdict::Duplicate {
        stats.duplicates += 1;
    } else {
        stats.stale += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::codec::{decode_command, encode_state, StatePacket};
    use proptest::prelude::*;

    /// A state packet whose other fields do not look like a counter.
    fn packet(counter: u32) -> [u8; STATE_LEN] {
        encode_state(&StatePacket {
            encoder: [0x1234, 0x8001, 0x0F0F],
            gimbal: [0x4000, 0x5000, 0x6000],
            counter,
            ..Default::default()
        })
    }

    fn stream(counters: &[u32]) -> Vec<u8> {
        counters.iter().flat_map(|&c| packet(c)).collect()
    }

    struct Rig {
        f: Framer,
        t: CounterTracker,
        s: StreamStats,
        out: [u8; STATE_LEN],
    }

    impl Rig {
        fn new() -> Self {
            Rig {
                f: Framer::new(),
                t: CounterTracker::new(1e-3),
                s: StreamStats::default(),
                out: [0; STATE_LEN],
            }
        }
        /// Push one transfer; the counter of the delivered packet, if any.
        fn feed(&mut self, bytes: &[u8]) -> Option<u32> {
            self.f.push(bytes, &mut self.s);
            self.f
                .drain_newest(&mut self.t, &mut self.s, &mut self.out)
                .map(|_| packet_counter(&self.out))
        }
    }

    #[test]
    fn tracker_classifies_and_times_by_counter() {
        let mut t = CounterTracker::new(1e-3);
        assert_eq!(t.classify(7), Verdict::Unanchored);
        assert_eq!(t.accept(7), (0.0, 0));
        assert_eq!(t.classify(8), Verdict::Fresh { lost: 0 });
        assert_eq!(t.classify(11), Verdict::Fresh { lost: 3 });
        assert_eq!(t.classify(7), Verdict::Duplicate);
        assert_eq!(t.classify(3), Verdict::Stale);
        assert_eq!(t.classify(7 + MAX_COUNTER_JUMP + 1), Verdict::Implausible);
        let (time, lost) = t.accept(11);
        assert!((time - 4e-3).abs() < 1e-12 && lost == 3);
        // Wrap-around of the 32-bit counter is an ordinary step.
        let mut w = CounterTracker::new(1e-3);
        w.accept(u32::MAX);
        assert_eq!(w.classify(1), Verdict::Fresh { lost: 1 });
        assert!((w.accept(1).0 - 2e-3).abs() < 1e-12);
    }

    #[test]
    fn reanchor_keeps_time_monotonic_and_still_counts_gaps() {
        let mut t = CounterTracker::new(1e-3);
        t.accept(100);
        t.accept(101);
        t.reanchor();
        assert_eq!(t.classify(105), Verdict::Unanchored);
        // The stream came back where it would have been: three packets lost.
        let (time, lost) = t.accept(105);
        assert!((time - 5e-3).abs() < 1e-12 && lost == 3);
        // The device's counter restarted at 5: time continues one period later.
        t.reanchor();
        let (time, lost) = t.accept(5);
        assert!((time - 6e-3).abs() < 1e-12 && lost == 0);
        assert!((t.accept(6).0 - 7e-3).abs() < 1e-12);
    }

    #[test]
    fn gate_keeps_amps_off_until_a_sample_and_sends_the_drivers_byte7() {
        let mut g = CommandGate::new();
        let mut cmd = MotorCommand::safe(42);
        cmd.amps_on = true;
        cmd.dac = [100, 200, 300];
        let bytes = encode_command(&cmd);
        let (w1, e) = g.wire(&bytes);
        assert!(e.is_none());
        let d1 = decode_command(&w1).unwrap();
        assert!(d1.is_safe(), "amps before a sample: {d1:?}");
        g.sample_delivered();
        // Whatever the servo put in byte 7, the wire carries the drivers' constant.
        let (w2, _) = g.wire(&bytes);
        let d2 = decode_command(&w2).unwrap();
        assert!(d2.amps_on && d2.dac == [100, 200, 300]);
        assert_eq!((w1[7], w2[7]), (0x53, 0x53));
        g.require_new_sample();
        assert!(decode_command(&g.wire(&bytes).0).unwrap().is_safe());
        // The counter format advances one per packet.
        let mut c = CommandGate::with_format(WireFormat {
            byte7: Byte7::Counter,
            dac_sign: [1; 3],
        });
        let a = c.safe()[7];
        assert_eq!(c.wire(&bytes).0[7], a.wrapping_add(1));
    }

    #[test]
    fn gate_applies_dac_signs_and_zeroes_unmeasured_axes() {
        let mut g = CommandGate::with_format(WireFormat {
            byte7: Byte7::Constant(0x53),
            dac_sign: [1, -1, 0],
        });
        g.sample_delivered();
        let mut cmd = MotorCommand::safe(0);
        cmd.amps_on = true;
        cmd.dac = [DAC_ZERO + 100, DAC_ZERO + 100, DAC_ZERO + 100];
        let d = decode_command(&g.wire(&encode_command(&cmd)).0).unwrap();
        assert_eq!(d.dac, [DAC_ZERO + 100, DAC_ZERO - 100, DAC_ZERO]);
        // Mirroring saturates inside 12 bits: 0x0FFF (+2048) mirrors to 0 (-2047).
        cmd.dac = [0, DAC_MAX, 0];
        let d = decode_command(&g.wire(&encode_command(&cmd)).0).unwrap();
        assert_eq!(d.dac, [0, 0, DAC_ZERO]);
        cmd.dac = [0, 0, 0];
        let d = decode_command(&g.wire(&encode_command(&cmd)).0).unwrap();
        assert_eq!(d.dac[1], 0x0FFE);
        // The raw path (the probe's sign check) leaves the words alone.
        cmd.dac = [DAC_ZERO, DAC_ZERO + 7, DAC_ZERO - 7];
        let d = decode_command(&g.raw(cmd)).unwrap();
        assert_eq!(d.dac, [DAC_ZERO, DAC_ZERO + 7, DAC_ZERO - 7]);
    }

    #[test]
    fn gate_never_sends_a_malformed_command() {
        let mut g = CommandGate::new();
        g.sample_delivered();
        let mut bad = encode_command(&MotorCommand::safe(0));
        bad[1] = 0xF0; // DAC word beyond 12 bits
        let (w, e) = g.wire(&bad);
        assert!(matches!(e, Some(CodecError::DacRange { .. })));
        assert!(decode_command(&w).unwrap().is_safe());
    }

    #[test]
    fn framer_reassembles_split_packets() {
        let mut r = Rig::new();
        let bytes = stream(&[10, 11, 12, 13, 14, 15]);
        // Boundaries are trusted after four consecutive counters.
        assert_eq!(r.feed(&bytes[..30]), None);
        assert_eq!(r.feed(&bytes[30..100]), None);
        assert_eq!(r.feed(&bytes[100..175]), None);
        assert_eq!(r.feed(&bytes[175..200]), Some(13));
        assert_eq!(r.s.superseded, 3);
        // Packet 14 (bytes 176..220) split over three transfers.
        assert_eq!(r.feed(&bytes[200..201]), None);
        assert_eq!(r.feed(&bytes[201..215]), None);
        assert_eq!(r.feed(&bytes[215..220]), Some(14));
        assert_eq!(r.out, packet(14));
        assert_eq!(r.f.pending(), 0);
        // Device time follows the counter.
        r.f.push(&bytes[220..], &mut r.s);
        let t = r.f.drain_newest(&mut r.t, &mut r.s, &mut r.out).unwrap();
        assert!((t - 5e-3).abs() < 1e-12, "{t}");
    }

    #[test]
    fn framer_takes_the_newest_of_merged_packets() {
        let mut r = Rig::new();
        assert_eq!(r.feed(&stream(&[1, 2, 3, 4])), Some(4));
        assert_eq!(r.feed(&stream(&[5, 6])), Some(6));
        assert_eq!(r.s.superseded, 3 + 1);
        // One and a half packets: the whole one now, the half with its rest.
        let b = stream(&[7, 8]);
        assert_eq!(r.feed(&b[..66]), Some(7));
        assert_eq!(r.feed(&b[66..]), Some(8));
        assert_eq!(r.s.lost, 0);
    }

    #[test]
    fn framer_counts_gaps_and_drops_duplicates_and_stale() {
        let mut r = Rig::new();
        assert_eq!(r.feed(&stream(&[1, 2, 3, 4])), Some(4));
        assert_eq!(r.feed(&stream(&[7])), Some(7));
        assert_eq!((r.s.lost, r.s.gaps), (2, 1));
        // A duplicate followed by a fresh packet, and a stale one: dropped and counted.
        assert_eq!(r.feed(&stream(&[7, 8])), Some(8));
        assert_eq!(r.feed(&stream(&[5])), None);
        assert_eq!((r.s.duplicates, r.s.stale), (1, 1));
        assert_eq!(r.feed(&stream(&[9, 20])), Some(20));
        assert_eq!((r.s.lost, r.s.gaps), (2 + 10, 2));
    }

    #[test]
    fn framer_skips_garbage_before_the_first_packet() {
        let mut r = Rig::new();
        let mut bytes = vec![0xAB; 17];
        bytes.extend(stream(&[500, 501, 502, 503]));
        assert_eq!(r.feed(&bytes), Some(503));
        assert_eq!(r.s.resync_bytes, 17);
    }

    #[test]
    fn framer_resyncs_after_lost_bytes() {
        let mut r = Rig::new();
        assert_eq!(r.feed(&stream(&[1, 2, 3, 4])), Some(4));
        // 10 bytes of packet 5 lost in transit, then 6..=9 intact.
        let rest = stream(&[5, 6, 7, 8, 9]);
        assert_eq!(r.feed(&rest[10..]), Some(9));
        assert_eq!(r.out, packet(9));
        assert_eq!((r.s.lost, r.s.gaps), (1, 1));
        assert_eq!(r.s.resync_bytes, 34);
    }

    #[test]
    fn framer_follows_a_device_whose_counter_restarted() {
        let mut r = Rig::new();
        assert_eq!(
            r.feed(&stream(&[90_000, 90_001, 90_002, 90_003])),
            Some(90_003)
        );
        // A frame far from the last counter is not delivered, and the boundaries are
        // searched again; a chain of the new counters re-anchors the stream.
        assert_eq!(r.feed(&stream(&[0])), None);
        assert_eq!(r.feed(&stream(&[1, 2, 3])), Some(3));
        assert!(r.t.is_anchored());
    }

    proptest! {
        /// However a stream of packets is cut into transfers (and whatever garbage precedes
        /// it), the framer delivers increasing counters, the last packet in the end, and
        /// every delivered packet byte-exact.
        #[test]
        fn any_chunking_delivers_the_stream(
            garbage in proptest::collection::vec(any::<u8>(), 0..60),
            start in any::<u32>(),
            n in 4usize..40,
            cuts in proptest::collection::vec(1usize..120, 1..60),
        ) {
            let counters: Vec<u32> = (0..n as u32).map(|k| start.wrapping_add(k)).collect();
            let mut bytes = garbage.clone();
            bytes.extend(stream(&counters));
            let mut r = Rig::new();
            let mut delivered: Vec<u32> = Vec::new();
            let mut at = 0;
            let mut k = 0;
            while at < bytes.len() {
                let len = cuts[k % cuts.len()].min(bytes.len() - at);
                k += 1;
                if let Some(c) = r.feed(&bytes[at..at + len]) {
                    prop_assert_eq!(r.out, packet(c));
                    delivered.push(c);
                }
                at += len;
            }
            prop_assert!(!delivered.is_empty());
            prop_assert_eq!(*delivered.last().unwrap(), *counters.last().unwrap());
            for w in delivered.windows(2) {
                let step = w[1].wrapping_sub(w[0]);
                prop_assert!(step >= 1 && step < n as u32, "{:?}", delivered);
            }
            prop_assert_eq!(r.s.lost, 0);
        }

        #[test]
        fn framer_never_panics_on_noise(chunks in proptest::collection::vec(
            proptest::collection::vec(any::<u8>(), 0..300), 0..30)) {
            let mut r = Rig::new();
            for c in &chunks {
                let _ = r.feed(c);
                prop_assert!(r.f.pending() < ANCHOR_CHAIN * STATE_LEN);
            }
        }
    }
}

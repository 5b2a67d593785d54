//! A fake FireWire Omni for tests: it models the device's registers and stream, records every
//! bus operation, and builds and checks packets from its own byte table ([`wire`]), written
//! from the open drivers independently of `codec.rs`, so that a wrong byte in the codec makes
//! a test fail.

use super::{reg, BusError, BusEvent, FireWireBus, PacketInfo, ISO_PAYLOAD_MAX};
use crate::device::codec::MotorCommand;
use crate::device::COMMAND_LEN;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// The Omni's packets byte by byte, from the sources named beside each field: ROS =
/// jdrew1303/ros_geomagic_touch_phantom_omni `omni_driver/include/omnifirewire.h` (and
/// `src/omnifirewire.cpp`), Twente = scottsharris/phantom-drivers `lib/src/PhantomSpec.h`
/// (and `rev-eng/omni.c`, `minimal-test/opensource.c`). Both declare the same 44 and 16
/// bytes.
pub mod wire {
    /// Device → host: ROS RxIsoBuffer omnifirewire.h:92-136; Twente PhantomDataRead
    /// PhantomSpec.h:53-88.
    pub const STATE_LEN: usize = 44;
    /// Twente PhantomSpec.h:56 `unknown1`, "always 0x001e" (u16 at byte 2; bytes 0..2 are
    /// PhantomSpec.h:55 `unknown0` = 0; ROS calls bytes 0..4 `magic`, omnifirewire.h:94).
    pub const UNKNOWN1: usize = 2;
    pub const UNKNOWN1_VALUE: u16 = 0x001E;
    /// Encoders x, y, z: ROS omnifirewire.h:96-98 (int16); Twente PhantomSpec.h:57-59.
    pub const ENCODER: [usize; 3] = [4, 6, 8];
    /// Gimbal pots: ROS omnifirewire.h:100-102 `gimbal_a_*`; Twente PhantomSpec.h:60 (upper
    /// 11 bits used, PhantomSpec.h:36-48).
    pub const GIMBAL: [usize; 3] = [10, 12, 14];
    /// ROS omnifirewire.h:105 `tx_packet_num` (u8 after `v0` at 16, omnifirewire.h:104);
    /// Twente PhantomSpec.h:62 `unknown9a`.
    pub const TX_PACKET_NUM: usize = 18;
    /// The switch byte: ROS omnifirewire.h:107-119 (after the u8 at 18); Twente
    /// PhantomSpec.h:63-77.
    pub const SWITCHES: usize = 19;
    /// ROS omnifirewire.h:110 `button1`; Twente PhantomSpec.h:68 "When 0 the button is
    /// pressed" (ROS omnifirewire.cpp:124 negates it too).
    pub const BUTTON1: u8 = 1 << 0;
    /// ROS omnifirewire.h:111; Twente PhantomSpec.h:69.
    pub const BUTTON2: u8 = 1 << 1;
    /// ROS omnifirewire.h:112 `undocked` (omnifirewire.cpp:45 calibrates when it is 0);
    /// Twente PhantomSpec.h:70 "When 0 the gimbal is docked".
    pub const UNDOCKED: u8 = 1 << 2;
    /// Bits 3..7 of an idle device: the Twente trace warns unless bit 4 and bit 7 are set and
    /// 3, 5, 6 clear (libraw1394-2.0.5-trace.patch:1580-1588).
    pub const SWITCHES_IDLE: u8 = 0x90;
    /// Twente PhantomSpec.h:78 `unknown10`, "always 0x1007" (ROS `s0`, omnifirewire.h:121).
    pub const UNKNOWN10: usize = 20;
    pub const UNKNOWN10_VALUE: u16 = 0x1007;
    /// The complementary gimbal copy: ROS omnifirewire.h:123-125 `gimbal_b_*`; Twente
    /// PhantomSpec.h:79 "seems to be the inverse of gimbal".
    pub const GIMBAL_INVERSE: [usize; 3] = [22, 24, 26];
    /// Twente PhantomSpec.h:80 `unknown14`, "always 0x5746" (ROS `v1`, omnifirewire.h:127).
    pub const UNKNOWN14: usize = 28;
    pub const UNKNOWN14_VALUE: u16 = 0x5746;
    /// u32 counter: Twente PhantomSpec.h:82 `count0`, "increased by one every time a message
    /// is received"; ROS omnifirewire.h:130 `time`.
    pub const COUNT0: usize = 32;
    /// Twente PhantomSpec.h:85 `count1`, "slower than count0 (half the speed?)" (ROS
    /// `wall_time`, omnifirewire.h:135).
    pub const COUNT1: usize = 40;

    /// Host → device: ROS TxIsoBuffer omnifirewire.h:60-90; Twente PhantomDataWrite
    /// PhantomSpec.h:93-123.
    pub const COMMAND_LEN: usize = 16;
    /// Motor words x, y, z: ROS omnifirewire.h:62-64; Twente PhantomSpec.h:95-97.
    pub const FORCE: [usize; 3] = [0, 2, 4];
    /// Zero torque: ROS omnifirewire.cpp:210-212; Twente minimal-test/opensource.c:42
    /// (`0x07ff07ff`), lib/src/PhantomIsoChannel.cpp:196-198.
    pub const FORCE_ZERO: u16 = 0x07FF;
    /// The u16 status word at byte 6: ROS omnifirewire.h:66-86; Twente PhantomSpec.h:98-120.
    pub const STATUS: usize = 6;
    /// Its value with lamp and motors off, in both drivers: ROS omnifirewire.cpp:213
    /// (`0x53c0`), Twente rev-eng/omni.c:281 and minimal-test/opensource.c:42.
    pub const STATUS_BASE: u16 = 0x53C0;
    /// Dock lamp: ROS omnifirewire.h:69-70 `dock_led0/1`; Twente PhantomSpec.h:103-104
    /// (`dl_flash`, `dl_fflash`; both set = lamp on).
    pub const LAMP0: u16 = 1 << 0;
    pub const LAMP1: u16 = 1 << 1;
    /// Amplifiers: ROS omnifirewire.h:72 `force_enabled`; Twente PhantomSpec.h:106
    /// `motors_on`.
    pub const MOTORS_ON: u16 = 1 << 3;
    /// Bytes 8..16: ROS omnifirewire.h:88-89 `padding1/2` (zeroed, omnifirewire.cpp:214-215);
    /// Twente PhantomSpec.h:121-122 "Must be zero".
    pub const PADDING: std::ops::Range<usize> = 8..16;
}

/// The arm as the fake device reports it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ArmState {
    /// Encoder counts as the device counts them (before any sign).
    pub encoder: [u16; 3],
    pub gimbal: [u16; 3],
    pub buttons: [bool; 2],
    pub docked: bool,
}

impl Default for ArmState {
    fn default() -> Self {
        ArmState {
            encoder: [1, 2, 3],
            gimbal: [0x8000; 3],
            buttons: [false; 2],
            docked: false,
        }
    }
}

/// A device → host packet built from the [`wire`] table.
pub fn device_packet(arm: &ArmState, count0: u32, tx_packet_num: u8) -> [u8; wire::STATE_LEN] {
    let mut b = [0u8; wire::STATE_LEN];
    let put = |b: &mut [u8; wire::STATE_LEN], at: usize, v: u16| {
        b[at..at + 2].copy_from_slice(&v.to_le_bytes())
    };
    put(&mut b, wire::UNKNOWN1, wire::UNKNOWN1_VALUE);
    for j in 0..3 {
        put(&mut b, wire::ENCODER[j], arm.encoder[j]);
        put(&mut b, wire::GIMBAL[j], arm.gimbal[j]);
        put(&mut b, wire::GIMBAL_INVERSE[j], !arm.gimbal[j]);
    }
    b[wire::TX_PACKET_NUM] = tx_packet_num;
    let mut sw = wire::SWITCHES_IDLE;
    if !arm.buttons[0] {
        sw |= wire::BUTTON1;
    }
    if !arm.buttons[1] {
        sw |= wire::BUTTON2;
    }
    if !arm.docked {
        sw |= wire::UNDOCKED;
    }
    b[wire::SWITCHES] = sw;
    put(&mut b, wire::UNKNOWN10, wire::UNKNOWN10_VALUE);
    put(&mut b, wire::UNKNOWN14, wire::UNKNOWN14_VALUE);
    b[wire::COUNT0..wire::COUNT0 + 4].copy_from_slice(&count0.to_le_bytes());
    put(&mut b, wire::COUNT1, (count0 / 2) as u16);
    b
}

/// A host → device packet as the [`wire`] table reads it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WireCommand {
    pub force: [u16; 3],
    pub lamp: u8,
    pub motors_on: bool,
}

impl WireCommand {
    pub fn is_safe(&self) -> bool {
        self.force == [wire::FORCE_ZERO; 3] && !self.motors_on
    }
}

/// Read a command with the [`wire`] table; anything the drivers would not send is an error
/// naming the byte.
pub fn read_command(b: &[u8]) -> Result<WireCommand, String> {
    if b.len() != wire::COMMAND_LEN {
        return Err(format!("command of {} bytes, the drivers send 16", b.len()));
    }
    let word = |at: usize| u16::from_le_bytes([b[at], b[at + 1]]);
    let mut force = [0u16; 3];
    for j in 0..3 {
        force[j] = word(wire::FORCE[j]);
        if force[j] > 0x0FFF {
            return Err(format!(
                "byte {}: motor word {:#06x} beyond 12 bits",
                wire::FORCE[j],
                force[j]
            ));
        }
    }
    let status = word(wire::STATUS);
    let known = wire::LAMP0 | wire::LAMP1 | wire::MOTORS_ON;
    if status & !known != wire::STATUS_BASE {
        return Err(format!(
            "bytes 6-7: status word {status:#06x}, the drivers send {:#06x} plus lamp and \
             motor bits",
            wire::STATUS_BASE
        ));
    }
    if let Some(i) = wire::PADDING.clone().find(|&i| b[i] != 0) {
        return Err(format!("byte {i}: {:#04x} in the padding", b[i]));
    }
    Ok(WireCommand {
        force,
        lamp: (status & (wire::LAMP0 | wire::LAMP1)) as u8,
        motors_on: status & wire::MOTORS_ON != 0,
    })
}

/// One bus operation, as the fake saw it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Op {
    ReadQuadlet(u64),
    WriteQuadlet(u64, u32),
    ReadByte(u64),
    WriteByte(u64, u8),
    Allocate(u8),
    Free(u8),
    StartIso { rx: u8, tx: u8 },
    StopIso,
    Send([u8; 16]),
}

/// What `next_packet` does when asked, in order; when empty, the device streams normally
/// (or stays silent with `silent`).
pub enum Next {
    Packet(u32),
    Raw(Vec<u8>),
    Timeout,
    BusReset,
    Gone,
}

pub struct FakeNode {
    pub regs: HashMap<u64, u8>,
    pub vendor_quadlet: u32,
    pub serial: u32,
    /// Quadlets written (0x20010).
    pub quadlets: HashMap<u64, u32>,
    pub ops: Vec<Op>,
    pub script: VecDeque<Next>,
    pub next_counter: u32,
    pub free_channels: Vec<u8>,
    pub iso: bool,
    pub silent: bool,
    pub gone: bool,
    /// The arm; `arm_at` changes it when that many packets have been delivered.
    pub arm: ArmState,
    pub arm_at: VecDeque<(usize, ArmState)>,
    /// Packets per second the device sends (receive timestamps follow it).
    pub rate_hz: f64,
    /// Cycle (of the 8 s cycle clock) of the first packet.
    pub first_cycle: u32,
    /// Packets handed out so far (for stop/unplug/silence triggers).
    pub delivered: usize,
    pub stop_after: Option<(usize, Arc<AtomicBool>)>,
    pub silent_after: Option<usize>,
    pub gone_after: Option<usize>,
    pub reset_after: Option<usize>,
    /// Register writes so far, and the write (1-based) at which a bus reset happens.
    pub writes: usize,
    pub reset_at_write: Option<usize>,
    /// Busy answers still to give, per register offset.
    pub busy: HashMap<u64, u32>,
    /// 0x1001 keeps only channel numbers (the scratch test then fails).
    pub scratch_broken: bool,
    /// The last command, as the wire table reads it.
    pub last_command: Option<WireCommand>,
    /// How the motors move the arm: per packet with the amplifiers on, encoder `j` moves by
    /// (motor word − 0x7FF) × `motor_gain[j]` / 8 counts (the sign is the fake's "DAC sign").
    pub motor_gain: [i32; 3],
    /// Take real host-wide unit locks under this prefix (unique per test, so tests running
    /// beside each other or beside a real daemon never meet); None: hold nothing.
    pub unit_lock_prefix: Option<String>,
}

impl Default for FakeNode {
    fn default() -> Self {
        let regs = HashMap::from([
            (reg::CHANNEL_TO_DEVICE, 0),
            (reg::CHANNEL_FROM_DEVICE, 0),
            (reg::RATE, 0x00),
            (reg::CHECK_A, 0xC0),
            (reg::CHECK_B, 0x00),
            (reg::CONTROL, 0x00),
        ]);
        FakeNode {
            regs,
            vendor_quadlet: 0x000B_9900,
            serial: SERIAL_QUADLET,
            quadlets: HashMap::new(),
            ops: Vec::new(),
            script: VecDeque::new(),
            next_counter: 1000,
            free_channels: vec![5, 9, 12, 14, 20, 21],
            iso: false,
            silent: false,
            gone: false,
            arm: ArmState::default(),
            arm_at: VecDeque::new(),
            rate_hz: 1000.0,
            first_cycle: 63_900,
            delivered: 0,
            stop_after: None,
            silent_after: None,
            gone_after: None,
            reset_after: None,
            writes: 0,
            reset_at_write: None,
            busy: HashMap::new(),
            scratch_broken: false,
            last_command: None,
            motor_gain: [0; 3],
            unit_lock_prefix: None,
        }
    }
}

/// The fake's serial quadlet: label 10203400567 packed as omnifirewire.cpp:335-359 does.
pub const SERIAL_QUADLET: u32 =
    0x8000_0001 | (1 << 23) | (2 << 19) | (3 << 14) | (4 << 11) | (567 << 1);
pub const SERIAL_LABEL: &str = "10203400567";

impl FakeNode {
    pub fn streaming(&self) -> bool {
        self.iso && self.regs[&reg::CONTROL] & reg::CONTROL_STREAM != 0
    }

    /// A bus reset: the device forgets its channels and stops streaming; the IRM forgets
    /// the allocations (the fake hands out fresh ones).
    fn reset(&mut self) {
        self.regs.insert(reg::CONTROL, 0);
        self.regs.insert(reg::CHANNEL_TO_DEVICE, 0);
        self.regs.insert(reg::CHANNEL_FROM_DEVICE, 0);
        self.iso = false;
    }

    /// Every command sent, read with the independent table; a packet the drivers would not
    /// send fails the test, naming the byte.
    pub fn sent_wire(&self) -> Vec<WireCommand> {
        self.ops
            .iter()
            .filter_map(|op| match op {
                Op::Send(b) => {
                    Some(read_command(b).unwrap_or_else(|e| panic!("bad command on the wire: {e}")))
                }
                _ => None,
            })
            .collect()
    }

    /// [`sent_wire`](Self::sent_wire) as `MotorCommand`s (byte 7 in `watchdog`).
    pub fn sent(&self) -> Vec<MotorCommand> {
        let sevens = self.ops.iter().filter_map(|op| match op {
            Op::Send(b) => Some(b[7]),
            _ => None,
        });
        self.sent_wire()
            .into_iter()
            .zip(sevens)
            .map(|(c, b7)| MotorCommand {
                dac: c.force,
                amps_on: c.motors_on,
                lamp: c.lamp,
                watchdog: b7,
            })
            .collect()
    }

    fn busy(&mut self, offset: u64) -> Result<(), BusError> {
        if let Some(n) = self.busy.get_mut(&offset) {
            if *n > 0 {
                *n -= 1;
                return Err(BusError::Busy(0x12));
            }
        }
        Ok(())
    }

    /// Receive timestamp of the `k`-th packet (3 bits seconds, 13 bits cycle count).
    fn timestamp(&self, k: usize) -> u16 {
        let c =
            (self.first_cycle as u64 + (k as f64 * 8000.0 / self.rate_hz).round() as u64) % 64_000;
        ((c / 8000) << 13 | (c % 8000)) as u16
    }
}

#[derive(Clone, Default)]
pub struct FakeBus(pub Arc<Mutex<FakeNode>>);

impl FakeBus {
    pub fn with(f: impl FnOnce(&mut FakeNode)) -> Self {
        let bus = FakeBus::default();
        f(&mut bus.0.lock().unwrap());
        bus
    }
    pub fn node(&self) -> std::sync::MutexGuard<'_, FakeNode> {
        self.0.lock().unwrap()
    }
}

/// The packet the fake sends with counter `c` while the arm is at its default state.
pub fn state(counter: u32) -> [u8; wire::STATE_LEN] {
    device_packet(&ArmState::default(), counter, counter as u8)
}

impl FireWireBus for FakeBus {
    fn hold_unit(&mut self, id: &str) -> Result<Option<std::os::fd::OwnedFd>, String> {
        match self.node().unit_lock_prefix.clone() {
            Some(prefix) => crate::arm::lock::hold(&format!("{prefix}{id}")).map(Some),
            None => Ok(None),
        }
    }

    fn read_quadlet(&mut self, offset: u64) -> Result<u32, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::ReadQuadlet(offset));
        n.busy(offset)?;
        match offset {
            reg::VENDOR => Ok(n.vendor_quadlet),
            reg::SERIAL => Ok(n.serial),
            _ => Err(BusError::Rcode(0x07)),
        }
    }

    fn write_quadlet(&mut self, offset: u64, value: u32) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.writes += 1;
        if n.reset_at_write == Some(n.writes) {
            n.reset();
            return Err(BusError::BusReset);
        }
        n.ops.push(Op::WriteQuadlet(offset, value));
        n.busy(offset)?;
        if offset != reg::VENDOR_INIT {
            return Err(BusError::Rcode(0x07));
        }
        n.quadlets.insert(offset, value);
        Ok(())
    }

    fn read_byte(&mut self, offset: u64) -> Result<u8, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::ReadByte(offset));
        n.busy(offset)?;
        n.regs.get(&offset).copied().ok_or(BusError::Rcode(0x07))
    }

    fn write_byte(&mut self, offset: u64, value: u8) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.writes += 1;
        if n.reset_at_write == Some(n.writes) {
            n.reset();
            return Err(BusError::BusReset);
        }
        n.ops.push(Op::WriteByte(offset, value));
        n.busy(offset)?;
        if !n.regs.contains_key(&offset) || offset == reg::RATE {
            return Err(BusError::Rcode(0x07));
        }
        let keep = if offset == reg::CHANNEL_FROM_DEVICE && n.scratch_broken {
            value & 0x3F
        } else {
            value
        };
        n.regs.insert(offset, keep);
        Ok(())
    }

    fn allocate_channel(&mut self) -> Result<u8, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        if n.free_channels.is_empty() {
            return Err(BusError::NoChannel);
        }
        let ch = n.free_channels.remove(0);
        n.ops.push(Op::Allocate(ch));
        Ok(ch)
    }

    fn free_channel(&mut self, channel: u8) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::Free(channel));
        n.free_channels.push(channel);
        Ok(())
    }

    fn start_iso(&mut self, rx: u8, tx: u8) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::StartIso { rx, tx });
        n.iso = true;
        Ok(())
    }

    fn stop_iso(&mut self) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::StopIso);
        n.iso = false;
        Ok(())
    }

    fn send_packet(&mut self, packet: &[u8; COMMAND_LEN]) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        if !n.iso {
            return Err(BusError::NotStreaming);
        }
        n.ops.push(Op::Send(*packet));
        n.last_command = read_command(packet).ok();
        Ok(())
    }

    fn next_packet(
        &mut self,
        buf: &mut [u8; ISO_PAYLOAD_MAX],
        timeout: Duration,
    ) -> Result<BusEvent, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        // Draining (zero wait) after a packet: one packet per exchange, like the device.
        if timeout.is_zero() {
            return Ok(BusEvent::Timeout);
        }
        let d = n.delivered;
        if let Some((k, flag)) = &n.stop_after {
            if d >= *k {
                flag.store(true, Ordering::SeqCst);
            }
        }
        if n.silent_after.is_some_and(|k| d >= k) {
            n.silent = true;
        }
        if n.gone_after.is_some_and(|k| d >= k) {
            n.gone = true;
            return Err(BusError::Gone);
        }
        if n.reset_after.is_some_and(|k| d >= k) {
            n.reset_after = None;
            n.script.push_front(Next::BusReset);
        }
        while n.arm_at.front().is_some_and(|(k, _)| *k <= d) {
            if let Some((_, arm)) = n.arm_at.pop_front() {
                n.arm = arm;
            }
        }
        if let Some(cmd) = n.last_command.filter(|c| c.motors_on) {
            for j in 0..3 {
                let step =
                    (i32::from(cmd.force[j]) - i32::from(wire::FORCE_ZERO)) * n.motor_gain[j] / 8;
                n.arm.encoder[j] = n.arm.encoder[j].wrapping_add(step as i16 as u16);
            }
        }
        let next = match n.script.pop_front() {
            Some(x) => x,
            None if n.silent || !n.streaming() => Next::Timeout,
            None => {
                let c = n.next_counter;
                n.next_counter = c.wrapping_add(1);
                Next::Packet(c)
            }
        };
        let channel = u32::from(n.regs[&reg::CHANNEL_FROM_DEVICE] & 0x3F);
        // data_length, tag 0, channel, tcode 0xA (iso data block), sy 0.
        let header = |len: usize| ((len as u32) << 16) | (channel << 8) | (0xA << 4);
        match next {
            Next::Packet(c) => {
                let p = device_packet(&n.arm, c, c as u8);
                buf[..p.len()].copy_from_slice(&p);
                let info = PacketInfo {
                    len: p.len(),
                    iso_header: header(p.len()),
                    timestamp: n.timestamp(d),
                };
                n.delivered += 1;
                Ok(BusEvent::Packet(info))
            }
            Next::Raw(b) => {
                buf[..b.len()].copy_from_slice(&b);
                Ok(BusEvent::Packet(PacketInfo {
                    len: b.len(),
                    iso_header: header(b.len()),
                    timestamp: n.timestamp(d),
                }))
            }
            Next::Timeout => Ok(BusEvent::Timeout),
            Next::BusReset => {
                n.reset();
                Ok(BusEvent::BusReset)
            }
            Next::Gone => {
                n.gone = true;
                Err(BusError::Gone)
            }
        }
    }
}

//! The FireWire Omni (IEEE-1394a) over Linux firewire-cdev (`/dev/fw*`). Every fact this
//! backend relies on is in docs/FIREWIRE.md with the line of the open driver it comes from.
//!
//! Split in two:
//! - [`FireWireOmni`] holds the protocol: identify the node (vendor and serial registers),
//!   the start sequence of the vendor library's trace (docs/FIREWIRE.md §2), the packet-rate
//!   check at open (§5), the counter check on every packet, the encoder signs (§6), a full
//!   restart after every bus reset, and the stop sequence on close (safe packet, clear bit 3
//!   of 0x1087, stop iso, free channels).
//! - [`FireWireBus`] does the bus work: asynchronous register reads and writes, channel
//!   allocation, iso contexts, packets and bus-reset events. `cdev::CdevBus` is the real
//!   one (ioctls on `/dev/fwN`); tests drive the protocol over a fake bus.
//!
//! The registers at 0x1000..0x1087 are single bytes at byte addresses (0x1087 is not
//! quadlet-aligned), so the bus has byte access (1-byte block transactions, as libraw1394 makes
//! of the drivers' 1-byte `raw1394_write`) beside quadlet access (0x1006000C, 0x10060010,
//! 0x20010).

pub(crate) mod cdev;
#[cfg(test)]
pub(crate) mod fake;
pub(crate) mod rate;
pub(crate) mod serial;

use super::codec::{MotorCommand, STATE_LAYOUT};
use super::stream::{
    packet_counter, Byte7, CommandGate, CounterTracker, StreamStats, Verdict, WireFormat,
};
use super::{Device, DeviceError, MissReason, RawSample, COMMAND_LEN, STATE_LEN};
use crate::config_check::{self as check, ConfigError};
use rate::RateMeasurement;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use thiserror::Error;

/// SensAble's IEEE OUI, in the config ROM and in the device's vendor register.
pub(crate) const SENSABLE_VENDOR_ID: u32 = 0x000B99;

/// Largest iso payload the bus hands over (the Omni's are 44 bytes).
pub(crate) const ISO_PAYLOAD_MAX: usize = 256;

/// Start attempts after a bus reset before giving up (each further reset during the start
/// costs one).
pub(crate) const RESTART_ATTEMPTS: u32 = 3;

/// Packets read per exchange at most (the newest is delivered).
pub(crate) const MAX_PACKETS_PER_EXCHANGE: usize = 64;

/// Device registers (offsets in the node's address space), docs/FIREWIRE.md §2.
pub(crate) mod reg {
    /// Quadlet: vendor id << 8 (reads 0x000B9900 on an Omni).
    pub(crate) const VENDOR: u64 = 0x1006_000C;
    /// Quadlet: serial number, packed label digits (see `serial`).
    pub(crate) const SERIAL: u64 = 0x1006_0010;
    /// Byte: isochronous channel host → device.
    pub(crate) const CHANNEL_TO_DEVICE: u64 = 0x1000;
    /// Byte: isochronous channel device → host; also the scratch test's register.
    pub(crate) const CHANNEL_FROM_DEVICE: u64 = 0x1001;
    /// Byte: the packet rate per the vendor library's symbol names. No open source reads or
    /// writes it; `omnid probe` only reads it (docs/FIREWIRE.md §5).
    pub(crate) const RATE: u64 = 0x1002;
    /// Byte read during the start; expected [`CHECK_A_VALUE`].
    pub(crate) const CHECK_A: u64 = 0x1083;
    pub(crate) const CHECK_A_VALUE: u8 = 0xC0;
    /// Byte read during the start; expected [`CHECK_B_VALUE`].
    pub(crate) const CHECK_B: u64 = 0x1082;
    pub(crate) const CHECK_B_VALUE: u8 = 0x00;
    /// Byte: control; bit 3 starts and stops streaming.
    pub(crate) const CONTROL: u64 = 0x1087;
    pub(crate) const CONTROL_STREAM: u8 = 1 << 3;
    /// Quadlet the vendor library writes before the start (purpose unknown).
    pub(crate) const VENDOR_INIT: u64 = 0x2_0010;
    /// The quadlet as it goes on the wire: bytes 00 00 0F F8. The drivers write the x86
    /// integer 0xf80f0000 from memory, which the bus carries as these bytes
    /// (docs/FIREWIRE.md §2).
    pub(crate) const VENDOR_INIT_VALUE: u32 = 0x0000_0FF8;
    /// The scratch test's value, written to and read back from 0x1001.
    pub(crate) const SCRATCH_VALUE: u8 = 0x40;
}

/// `[firewire]`: which node, how long to wait, and the start sequence's options.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct FirewireConfig {
    /// Device node to use (`/dev/fw1`); empty = search every `/dev/fw*` for vendor 0x000B99.
    pub device: String,
    /// Serial number of the Omni to use when several are on the bus (the 11 digits of its
    /// label); empty = the only one.
    pub serial: String,
    /// How long one exchange may wait for the next state packet, ms.
    pub timeout_ms: u32,
    /// How long a register read or write, or a channel allocation, may take, ms.
    pub register_timeout_ms: u32,
    /// Write the vendor library's quadlet to 0x20010 before starting.
    pub vendor_init: bool,
    /// The vendor library's scratch test of register 0x1001 (write 0x40, read it back).
    pub scratch_test: bool,
    /// Retries of a register transaction the node answers busy.
    pub busy_retries: u32,
    /// Pause before each such retry, ms.
    pub busy_retry_ms: u32,
    /// Sign per joint that turns encoder counts into the OpenHaptics joint directions.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub encoder_sign: [i8; 3],
    /// Sign per motor of the DAC word; 0 = not measured yet (`omnid probe --outputs`): no
    /// torque on that motor, and `run`/`serve` refuse to start.
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub dac_sign: [i8; 3],
    /// Byte 7 of every command: "0x53" (the open drivers) or another "0xNN", or "counter".
    pub command_byte7: String,
}

impl Default for FirewireConfig {
    fn default() -> Self {
        FirewireConfig {
            device: String::new(),
            serial: String::new(),
            timeout_ms: 10,
            register_timeout_ms: 100,
            vendor_init: true,
            scratch_test: true,
            busy_retries: 5,
            busy_retry_ms: 100,
            encoder_sign: OPENHAPTICS_ENCODER_SIGN,
            dac_sign: [0; 3],
            command_byte7: "0x53".into(),
        }
    }
}

/// Encoder count direction → OpenHaptics joint direction, per joint (docs/FIREWIRE.md §6).
pub(crate) const OPENHAPTICS_ENCODER_SIGN: [i8; 3] = [-1, -1, 1];

impl FirewireConfig {
    /// Check every value; the first problem names its field (`firewire.timeout_ms`, ...).
    pub(crate) fn validate(&self) -> Result<(), ConfigError> {
        let node_ok = self
            .device
            .strip_prefix("/dev/fw")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if !self.device.is_empty() && !node_ok {
            return Err(check::invalid(
                "firewire.device",
                format!("{:?}", self.device),
                "empty (search) or a node like \"/dev/fw1\"",
            ));
        }
        if !self.serial.is_empty() {
            if let Err(e) = serial::parse(&self.serial) {
                return Err(check::invalid(
                    "firewire.serial",
                    format!("{:?}", self.serial),
                    format!("empty, or {}", e.0),
                ));
            }
        }
        if !(1..=1000).contains(&self.timeout_ms) {
            return Err(check::invalid(
                "firewire.timeout_ms",
                self.timeout_ms.to_string(),
                "1 ..= 1000 ms",
            ));
        }
        if !(1..=5000).contains(&self.register_timeout_ms) {
            return Err(check::invalid(
                "firewire.register_timeout_ms",
                self.register_timeout_ms.to_string(),
                "1 ..= 5000 ms",
            ));
        }
        if self.busy_retries > 50 {
            return Err(check::invalid(
                "firewire.busy_retries",
                self.busy_retries.to_string(),
                "0 ..= 50",
            ));
        }
        if !(1..=1000).contains(&self.busy_retry_ms) {
            return Err(check::invalid(
                "firewire.busy_retry_ms",
                self.busy_retry_ms.to_string(),
                "1 ..= 1000 ms",
            ));
        }
        for (j, s) in self.encoder_sign.iter().enumerate() {
            if !matches!(s, -1 | 1) {
                return Err(check::invalid(
                    format!("firewire.encoder_sign[{j}]"),
                    s.to_string(),
                    "1 or -1",
                ));
            }
        }
        for (j, s) in self.dac_sign.iter().enumerate() {
            if !matches!(s, -1..=1) {
                return Err(check::invalid(
                    format!("firewire.dac_sign[{j}]"),
                    s.to_string(),
                    "1 or -1, or 0 (not measured yet)",
                ));
            }
        }
        if self.byte7().is_none() {
            return Err(check::invalid(
                "firewire.command_byte7",
                format!("{:?}", self.command_byte7),
                "\"0x53\" (the open drivers), another \"0xNN\", or \"counter\"",
            ));
        }
        Ok(())
    }

    /// `command_byte7` parsed (`None` when it is not valid).
    pub(crate) fn byte7(&self) -> Option<Byte7> {
        if self.command_byte7 == "counter" {
            return Some(Byte7::Counter);
        }
        let hex = self.command_byte7.strip_prefix("0x")?;
        (hex.len() == 2)
            .then(|| u8::from_str_radix(hex, 16).ok())
            .flatten()
            .map(Byte7::Constant)
    }

    /// Motors whose DAC sign has not been measured (0-based).
    pub(crate) fn unmeasured_dac_signs(&self) -> Vec<usize> {
        (0..3).filter(|&j| self.dac_sign[j] == 0).collect()
    }

    /// The protocol options of this configuration at packet rate `rate_hz`.
    pub(crate) fn options(&self, rate_hz: f64) -> FireWireOptions {
        FireWireOptions {
            timeout: Duration::from_millis(u64::from(self.timeout_ms)),
            rate_hz,
            vendor_init: self.vendor_init,
            scratch_test: self.scratch_test,
            busy_retries: self.busy_retries,
            busy_retry: Duration::from_millis(u64::from(self.busy_retry_ms)),
            encoder_sign: self.encoder_sign,
            format: WireFormat {
                byte7: self.byte7().unwrap_or(WireFormat::DRIVERS.byte7),
                dac_sign: self.dac_sign,
            },
        }
    }

    /// What [`find_firewire`] looks for, in words.
    pub(crate) fn looked_for(&self) -> String {
        let what = if self.device.is_empty() {
            "a FireWire Omni (config-ROM vendor 0x000B99) on /dev/fw*".to_string()
        } else {
            format!("a FireWire Omni (vendor 0x000B99) at {}", self.device)
        };
        if self.serial.is_empty() {
            what
        } else {
            format!("{what} with serial {}", self.serial)
        }
    }

    /// Whether the unit with serial quadlet `quadlet` is the configured one.
    pub(crate) fn wants_serial(&self, quadlet: u32) -> bool {
        self.serial.is_empty() || serial::parse(&self.serial) == Ok(quadlet)
    }
}

/// How [`FireWireOmni`] runs the protocol.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FireWireOptions {
    /// How long one exchange waits for the next packet.
    pub(crate) timeout: Duration,
    /// The configured packet rate (device time is counter / rate; checked at open).
    pub(crate) rate_hz: f64,
    pub(crate) vendor_init: bool,
    pub(crate) scratch_test: bool,
    pub(crate) busy_retries: u32,
    pub(crate) busy_retry: Duration,
    pub(crate) encoder_sign: [i8; 3],
    pub(crate) format: WireFormat,
}

impl FireWireOptions {
    /// The defaults of `[firewire]` at `rate_hz`, with `timeout`.
    pub(crate) fn new(timeout: Duration, rate_hz: f64) -> Self {
        FireWireOptions {
            timeout,
            ..FirewireConfig::default().options(rate_hz)
        }
    }
}

/// The udev rule of docs/FIREWIRE.md §7.
pub(crate) const FIREWIRE_UDEV_RULE: &str =
    "SUBSYSTEM==\"firewire\", ATTR{vendor}==\"0x000b99\", MODE=\"0660\", GROUP=\"plugdev\"";

/// How to fix "permission denied" on `/dev/fwN`.
pub(crate) fn firewire_permission_hint() -> String {
    format!(
        "Install the udev rule (udev/99-omnid-firewire.rules, or put this line in \
         /etc/udev/rules.d/99-omnid-firewire.rules: {FIREWIRE_UDEV_RULE}), run `sudo udevadm \
         control --reload-rules && sudo udevadm trigger`, add yourself to plugdev (`sudo usermod \
         -aG plugdev $USER`), log in again and replug the Omni. See udev/README.md."
    )
}

fn os_text(errno: &i32) -> String {
    std::io::Error::from_raw_os_error(*errno).to_string()
}

/// What the bus reports. Copy and allocation-free: it travels through the 1 kHz path.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub enum BusError {
    /// The bus was reset (a node joined or left): node ids and channels must be set up again.
    #[error("bus reset")]
    BusReset,
    /// The node disappeared.
    #[error("the node is gone (unplugged or powered off)")]
    Gone,
    /// No answer or packet within the wait.
    #[error("timed out")]
    Timeout,
    /// The node's device file may not be opened by this user (the udev rule is missing).
    #[error("permission denied")]
    Permission,
    /// Every isochronous channel is taken.
    #[error("no free isochronous channel at the isochronous resource manager")]
    NoChannel,
    /// Our transmit context stopped taking packets.
    #[error("the isochronous transmit queue is full (the controller stopped sending)")]
    TxStalled,
    /// The node answered busy (RCODE_BUSY) or conflict (RCODE_CONFLICT_ERROR): try again, as
    /// the Twente driver does on EAGAIN (rev-eng/easy-com.c:34-37).
    #[error("the node answered busy (response code {0:#04x})")]
    Busy(u32),
    /// Any other IEEE 1394 response code (address or type error, …).
    #[error("the node answered with response code {0:#04x}")]
    Rcode(u32),
    /// A packet was sent or awaited before the stream was started.
    #[error("isochronous streaming is not running")]
    NotStreaming,
    /// A system call failed.
    #[error("{op}: {}", os_text(.errno))]
    Os {
        /// The call (`FW_CDEV_IOC_QUEUE_ISO`, …).
        op: &'static str,
        /// Its `errno`.
        errno: i32,
    },
}

/// One received iso packet: its length and what the kernel reports beside it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PacketInfo {
    /// Payload bytes in the buffer.
    pub(crate) len: usize,
    /// The 1394 iso packet header (data_length, tag, channel, tcode, sy), as a number.
    pub(crate) iso_header: u32,
    /// Receive timestamp: 3 bits cycleSeconds, 13 bits cycleCount.
    pub(crate) timestamp: u16,
}

/// What waiting for the next packet brought.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusEvent {
    /// A packet is in the buffer.
    Packet(PacketInfo),
    /// The bus was reset: channels and device state are void, the start must be redone.
    BusReset,
    /// Nothing arrived in time.
    Timeout,
}

/// The bus operations the protocol needs, on one node.
pub trait FireWireBus: Send {
    /// Read a quadlet (big-endian on the wire, returned as a number).
    fn read_quadlet(&mut self, offset: u64) -> Result<u32, BusError>;
    /// Write a quadlet (the number goes on the wire big-endian).
    fn write_quadlet(&mut self, offset: u64, value: u32) -> Result<(), BusError>;
    /// Read one byte (a 1-byte block read).
    fn read_byte(&mut self, offset: u64) -> Result<u8, BusError>;
    /// Write one byte (a 1-byte block write).
    fn write_byte(&mut self, offset: u64, value: u8) -> Result<(), BusError>;
    /// Allocate an isochronous channel at the bus's IRM (for this bus generation).
    fn allocate_channel(&mut self) -> Result<u8, BusError>;
    /// Give a channel back to the IRM.
    fn free_channel(&mut self, channel: u8) -> Result<(), BusError>;
    /// Start receiving on `receive_channel` and transmitting (S100) on `transmit_channel`.
    fn start_iso(&mut self, receive_channel: u8, transmit_channel: u8) -> Result<(), BusError>;
    /// Stop both iso contexts (after the last queued packet has gone out, when possible).
    fn stop_iso(&mut self) -> Result<(), BusError>;
    /// Queue one command packet for transmission.
    fn send_packet(&mut self, packet: &[u8; COMMAND_LEN]) -> Result<(), BusError>;
    /// Wait up to `timeout` (zero: only what is already there) for the next received packet.
    fn next_packet(
        &mut self,
        buf: &mut [u8; ISO_PAYLOAD_MAX],
        timeout: Duration,
    ) -> Result<BusEvent, BusError>;
}

/// Which step of the start sequence an error happened in (named in the message).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Step {
    ReadByte(u64),
    WriteByte(u64, u8),
    WriteQuadlet(u64, u32),
    AllocateChannel,
    StartIso,
    SendSafePacket,
}

impl std::fmt::Display for Step {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Step::ReadByte(r) => write!(f, "reading register {r:#x}"),
            Step::WriteByte(r, v) => write!(f, "writing {v:#04x} to register {r:#x}"),
            Step::WriteQuadlet(r, v) => write!(f, "writing quadlet {v:#010x} to {r:#x}"),
            Step::AllocateChannel => f.write_str("allocating an isochronous channel"),
            Step::StartIso => f.write_str("starting the isochronous contexts"),
            Step::SendSafePacket => f.write_str("sending the first zero-torque packet"),
        }
    }
}

/// Why the start sequence failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StartError {
    Bus(Step, BusError),
    Register {
        reg: u64,
        got: u8,
        expected: u8,
        what: &'static str,
    },
}

impl StartError {
    fn bus(&self) -> Option<BusError> {
        match self {
            StartError::Bus(_, e) => Some(*e),
            StartError::Register { .. } => None,
        }
    }
}

/// One received or sent packet as `omnid probe` captures it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Tapped {
    /// Host monotonic time, ns.
    pub(crate) host_ns: u64,
    /// `None` for a command the host sent.
    pub(crate) received: Option<PacketInfo>,
    pub(crate) bytes: Vec<u8>,
}

/// One register as `omnid probe` reads it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct RegisterReading {
    pub(crate) offset: u64,
    /// 1 (byte register) or 4 (quadlet).
    pub(crate) width: u8,
    pub(crate) name: &'static str,
    pub(crate) value: Result<u32, BusError>,
}

/// The registers `omnid probe` reads (reads only: nothing here is written).
pub(crate) const PROBE_REGISTERS: &[(u64, u8, &str)] = &[
    (reg::VENDOR, 4, "vendor quadlet (expect 0x000b9900)"),
    (reg::SERIAL, 4, "serial quadlet (label digits packed)"),
    (reg::CHANNEL_TO_DEVICE, 1, "iso channel host -> device"),
    (reg::CHANNEL_FROM_DEVICE, 1, "iso channel device -> host"),
    (reg::RATE, 1, "rate? (vendor symbol name only; unverified)"),
    (reg::CHECK_B, 1, "start check (expect 0x00)"),
    (reg::CHECK_A, 1, "start check (expect 0xc0)"),
    (reg::CONTROL, 1, "control (bit 3 = streaming)"),
];

/// The FireWire Omni. Generic over the bus so tests can script the node.
pub struct FireWireOmni<B: FireWireBus> {
    bus: B,
    name: String,
    serial: Option<String>,
    serial_quadlet: Option<u32>,
    opts: FireWireOptions,
    gate: CommandGate,
    tracker: CounterTracker,
    stats: StreamStats,
    buf: Box<[u8; ISO_PAYLOAD_MAX]>,
    to_device: Option<u8>,
    from_device: Option<u8>,
    iso_running: bool,
    streaming: bool,
    /// The start sequence has written to the device (so close must undo it).
    touched: bool,
    gone: bool,
    closed: bool,
    /// The stream bit was found set at a start (a run that crashed) and cleared.
    stale_stream_cleared: bool,
    /// `omnid probe`: every packet received and sent, when on.
    tap: Option<Vec<Tapped>>,
}

impl<B: FireWireBus> FireWireOmni<B> {
    /// No bus traffic yet; default `[firewire]` options with this timeout and rate. See
    /// [`identify`](Self::identify) and [`start`](Self::start).
    pub(crate) fn new(bus: B, name: String, timeout: Duration, rate_hz: f64) -> Self {
        Self::with_options(bus, name, FireWireOptions::new(timeout, rate_hz))
    }

    /// No bus traffic yet.
    pub(crate) fn with_options(bus: B, name: String, opts: FireWireOptions) -> Self {
        FireWireOmni {
            bus,
            name,
            serial: None,
            serial_quadlet: None,
            opts,
            gate: CommandGate::with_format(opts.format),
            tracker: CounterTracker::new(1.0 / opts.rate_hz),
            stats: StreamStats::default(),
            buf: Box::new([0; ISO_PAYLOAD_MAX]),
            to_device: None,
            from_device: None,
            iso_running: false,
            streaming: false,
            touched: false,
            gone: false,
            closed: false,
            stale_stream_cleared: false,
            tap: None,
        }
    }

    /// Identify, then start streaming (no rate check: see [`check_rate`](Self::check_rate)).
    #[cfg(test)]
    pub(crate) fn open(
        bus: B,
        name: String,
        timeout: Duration,
        rate_hz: f64,
    ) -> Result<Self, DeviceError> {
        Self::open_with(bus, name, FireWireOptions::new(timeout, rate_hz))
    }

    /// Identify, then start streaming with these options.
    #[cfg(test)]
    pub(crate) fn open_with(
        bus: B,
        name: String,
        opts: FireWireOptions,
    ) -> Result<Self, DeviceError> {
        let mut omni = Self::with_options(bus, name, opts);
        omni.identify()?;
        omni.start()?;
        Ok(omni)
    }

    /// The name messages use (`/dev/fw1`).
    pub(crate) fn name(&self) -> &str {
        &self.name
    }

    /// The serial quadlet as read by [`identify`](Self::identify).
    pub(crate) fn serial_quadlet(&self) -> Option<u32> {
        self.serial_quadlet
    }

    /// Whether a start found the stream bit set (left by a run that did not stop) and cleared
    /// it.
    pub(crate) fn stale_stream_cleared(&self) -> bool {
        self.stale_stream_cleared
    }

    /// Check the vendor register says SensAble and read the serial number (no writes).
    /// Returns the serial in the 11-digit form of the unit's label.
    pub(crate) fn identify(&mut self) -> Result<String, DeviceError> {
        let vendor = self
            .read_quadlet(reg::VENDOR)
            .map_err(|e| self.bus_failure("reading the vendor register 0x1006000c", e))?;
        if vendor >> 8 != SENSABLE_VENDOR_ID {
            return Err(DeviceError::NotFound {
                looked_for: format!(
                    "a SensAble Omni (vendor {SENSABLE_VENDOR_ID:#08x}) at {}",
                    self.name
                ),
                hint: format!(
                    "its vendor register {:#x} reads {:#08x}: this node is not an Omni. Leave \
                     firewire.device empty to search, or name the Omni's node.",
                    reg::VENDOR,
                    vendor >> 8
                ),
            });
        }
        let quadlet = self
            .read_quadlet(reg::SERIAL)
            .map_err(|e| self.bus_failure("reading the serial register 0x10060010", e))?;
        let serial = serial::name(quadlet);
        self.serial = Some(serial.clone());
        self.serial_quadlet = Some(quadlet);
        Ok(serial)
    }

    /// Read the registers of [`PROBE_REGISTERS`] (reads only).
    pub(crate) fn read_registers(&mut self) -> Vec<RegisterReading> {
        PROBE_REGISTERS
            .iter()
            .map(|&(offset, width, name)| RegisterReading {
                offset,
                width,
                name,
                value: if width == 4 {
                    self.read_quadlet(offset)
                } else {
                    self.read_byte(offset).map(u32::from)
                },
            })
            .collect()
    }

    /// The start sequence (docs/FIREWIRE.md §2), redone after every bus reset.
    pub(crate) fn start(&mut self) -> Result<(), DeviceError> {
        match self.start_sequence() {
            Ok(()) => Ok(()),
            Err(e) => {
                self.undo_failed_start(e);
                Err(self.start_failure(e))
            }
        }
    }

    /// Measure the packet rate over [`rate::MEASURE_PACKETS`] packets (zero torque, amplifiers
    /// off) and refuse a device that does not run at the configured rate. The amplifiers stay
    /// off until the next sample after this.
    pub(crate) fn check_rate(&mut self) -> Result<RateMeasurement, DeviceError> {
        let m = self.measure_rate(rate::MEASURE_PACKETS)?;
        match m.mismatch(self.opts.rate_hz) {
            None => Ok(m),
            Some(why) => Err(DeviceError::Unsupported(format!(
                "FireWire Omni {}: {why}",
                self.name
            ))),
        }
    }

    /// Exchange `packets` safe packets and measure the stream from what arrived.
    pub(crate) fn measure_rate(&mut self, packets: usize) -> Result<RateMeasurement, DeviceError> {
        let tapping = self.tap.is_some();
        let mut seen: Vec<(u32, u16)> = Vec::with_capacity(packets);
        let mut misses = 0usize;
        while seen.len() < packets {
            let safe = crate::device::codec::encode_command(&MotorCommand::safe(0));
            match self.exchange_observed(&safe, &mut seen) {
                Ok(()) => {}
                Err(DeviceError::Missed(_)) => {
                    misses += 1;
                    if misses > packets {
                        break;
                    }
                }
                Err(e) => return Err(e),
            }
        }
        if !tapping {
            self.tap = None;
        }
        self.gate.require_new_sample();
        Ok(RateMeasurement::from_packets(&seen))
    }

    /// One exchange that also notes every packet's `(counter, timestamp)` (all of them, not
    /// only the delivered one).
    fn exchange_observed(
        &mut self,
        command: &[u8; COMMAND_LEN],
        seen: &mut Vec<(u32, u16)>,
    ) -> Result<(), DeviceError> {
        let mut tap = self.tap.take().unwrap_or_default();
        let before = tap.len();
        self.tap = Some(tap);
        let r = self.exchange(command).map(|_| ());
        tap = self.tap.take().unwrap_or_default();
        for t in &tap[before..] {
            if let Some(info) = t.received {
                if t.bytes.len() >= STATE_LEN {
                    seen.push((packet_counter(&t.bytes), info.timestamp));
                }
            }
        }
        self.tap = Some(tap);
        r
    }

    /// Start or stop recording every packet received and sent ([`take_tapped`]). Off in the
    /// servo: recording allocates.
    ///
    /// [`take_tapped`]: Self::take_tapped
    pub(crate) fn set_tap(&mut self, on: bool) {
        self.tap = on.then(|| self.tap.take().unwrap_or_default());
    }

    /// The packets recorded since the last call.
    pub(crate) fn take_tapped(&mut self) -> Vec<Tapped> {
        match self.tap.as_mut() {
            Some(t) => std::mem::take(t),
            None => Vec::new(),
        }
    }

    /// One exchange with `cmd` as it is: no DAC signs applied (the probe's sign check). The
    /// amplifiers still stay off until a sample has been delivered.
    pub(crate) fn exchange_raw(&mut self, cmd: MotorCommand) -> Result<RawSample, DeviceError> {
        let wire = self.gate.raw(cmd);
        self.exchange_wire(wire, None)
    }

    /// Everything unusual seen on the stream so far.
    pub(crate) fn stats(&self) -> StreamStats {
        self.stats
    }

    /// A register transaction, retried while the node answers busy.
    fn retry<T>(
        &mut self,
        mut op: impl FnMut(&mut B) -> Result<T, BusError>,
    ) -> Result<T, BusError> {
        let mut left = self.opts.busy_retries;
        loop {
            match op(&mut self.bus) {
                Err(BusError::Busy(_)) if left > 0 => {
                    left -= 1;
                    std::thread::sleep(self.opts.busy_retry);
                }
                r => return r,
            }
        }
    }

    fn read_byte(&mut self, r: u64) -> Result<u8, BusError> {
        self.retry(|b| b.read_byte(r))
    }

    fn read_quadlet(&mut self, r: u64) -> Result<u32, BusError> {
        self.retry(|b| b.read_quadlet(r))
    }

    fn write_byte(&mut self, r: u64, v: u8) -> Result<(), StartError> {
        self.retry(|b| b.write_byte(r, v))
            .map_err(|e| StartError::Bus(Step::WriteByte(r, v), e))
    }

    fn read_step(&mut self, r: u64) -> Result<u8, StartError> {
        self.read_byte(r)
            .map_err(|e| StartError::Bus(Step::ReadByte(r), e))
    }

    fn expect(&mut self, r: u64, expected: u8, what: &'static str) -> Result<(), StartError> {
        let got = self.read_step(r)?;
        if got != expected {
            return Err(StartError::Register {
                reg: r,
                got,
                expected,
                what,
            });
        }
        Ok(())
    }

    fn start_sequence(&mut self) -> Result<(), StartError> {
        self.touched = true;
        // A run that crashed leaves the device streaming on channels nobody owns: stop it
        // first (the drivers only ever set this bit; PhantomIsoChannel.cpp:115-121 would
        // leave it as it is).
        let control = self.read_step(reg::CONTROL)?;
        if control & reg::CONTROL_STREAM != 0 {
            self.write_byte(reg::CONTROL, control & !reg::CONTROL_STREAM)?;
            self.stale_stream_cleared = true;
        }
        let to_device = self.allocate()?;
        self.to_device = Some(to_device);
        let from_device = self.allocate()?;
        self.from_device = Some(from_device);
        // The vendor trace's order (minimal-test/opensource.c:194-224): host → device channel
        // (:194; PhantomSpec.h:25), device → host channel (:197; PhantomSpec.h:26), the
        // 0x20010 quadlet (:200; omnifirewire.cpp:391-392), the scratch test (:203-212;
        // PhantomIsoChannel.cpp:71-93), 0x1083 and 0x1082 (:217-221; omni.c:429-439).
        self.write_byte(reg::CHANNEL_TO_DEVICE, to_device)?;
        self.write_byte(reg::CHANNEL_FROM_DEVICE, from_device)?;
        if self.opts.vendor_init {
            let v = reg::VENDOR_INIT_VALUE;
            self.retry(|b| b.write_quadlet(reg::VENDOR_INIT, v))
                .map_err(|e| StartError::Bus(Step::WriteQuadlet(reg::VENDOR_INIT, v), e))?;
        }
        if self.opts.scratch_test {
            self.expect(
                reg::CHANNEL_FROM_DEVICE,
                from_device,
                "the channel just written",
            )?;
            self.write_byte(reg::CHANNEL_FROM_DEVICE, reg::SCRATCH_VALUE)?;
            self.expect(
                reg::CHANNEL_FROM_DEVICE,
                reg::SCRATCH_VALUE,
                "the scratch value just written",
            )?;
            self.write_byte(reg::CHANNEL_FROM_DEVICE, from_device)?;
        }
        self.expect(reg::CHECK_A, reg::CHECK_A_VALUE, "the start check")?;
        self.expect(reg::CHECK_B, reg::CHECK_B_VALUE, "the start check")?;
        // omnid starts its own contexts before the device streams (the drivers do it after
        // writing 0x1087), so that the first packet on the wire is the safe one.
        self.bus
            .start_iso(from_device, to_device)
            .map_err(|e| StartError::Bus(Step::StartIso, e))?;
        self.iso_running = true;
        self.gate.require_new_sample();
        let safe = self.gate.safe();
        self.bus
            .send_packet(&safe)
            .map_err(|e| StartError::Bus(Step::SendSafePacket, e))?;
        self.tap_sent(&safe);
        // Bit 3 of 0x1087 starts the stream (opensource.c:223; omni.c:443-453).
        let control = self.read_step(reg::CONTROL)?;
        self.write_byte(reg::CONTROL, control | reg::CONTROL_STREAM)?;
        self.streaming = true;
        self.tracker.reanchor();
        Ok(())
    }

    fn allocate(&mut self) -> Result<u8, StartError> {
        self.bus
            .allocate_channel()
            .map_err(|e| StartError::Bus(Step::AllocateChannel, e))
    }

    /// After a failed start: stop iso and give the channels back, unless a bus reset already
    /// voided them (then someone else may own them now) or the node is gone.
    fn undo_failed_start(&mut self, e: StartError) {
        // The stream bit is the start's last write: a failed start leaves nothing to clear.
        self.streaming = false;
        self.touched = false;
        if e.bus() == Some(BusError::Gone) {
            self.gone = true;
            return;
        }
        if self.iso_running {
            let _ = self.bus.stop_iso();
            self.iso_running = false;
        }
        let reset = e.bus() == Some(BusError::BusReset);
        for ch in [self.to_device.take(), self.from_device.take()]
            .into_iter()
            .flatten()
        {
            if !reset {
                let _ = self.bus.free_channel(ch);
            }
        }
    }

    fn bus_failure(&mut self, what: &str, e: BusError) -> DeviceError {
        match e {
            BusError::Gone => {
                self.gone = true;
                DeviceError::Disconnected(format!("FireWire Omni {}: {e}", self.name))
            }
            BusError::Permission => DeviceError::Permission {
                what: self.name.clone(),
                hint: firewire_permission_hint(),
            },
            e => DeviceError::Io(format!("FireWire Omni {}: {what}: {e}", self.name)),
        }
    }

    fn start_failure(&mut self, e: StartError) -> DeviceError {
        match e {
            StartError::Bus(_, BusError::NoChannel) => DeviceError::Io(format!(
                "FireWire Omni {}: no free isochronous channel at the bus's resource manager \
                 (another program streaming? unplug other FireWire devices)",
                self.name
            )),
            StartError::Bus(step, BusError::Busy(rcode)) => DeviceError::Io(format!(
                "FireWire Omni {}: {step}: the node still answered busy (response code \
                 {rcode:#04x}) after {} retries {} ms apart",
                self.name,
                self.opts.busy_retries,
                self.opts.busy_retry.as_millis()
            )),
            StartError::Bus(step, b) => self.bus_failure(&format!("start sequence: {step}"), b),
            StartError::Register {
                reg,
                got,
                expected,
                what,
            } => DeviceError::Io(format!(
                "FireWire Omni {}: register {reg:#x} reads {got:#04x}, expected {expected:#04x} \
                 ({what}): the device is not in the state the start sequence expects; \
                 power-cycle it",
                self.name
            )),
        }
    }

    fn miss(&mut self, reason: MissReason) -> DeviceError {
        self.stats.misses += 1;
        self.stats.last_miss = Some(reason);
        DeviceError::Missed(reason)
    }

    /// A bus reset: forget the void channels, redo the start, and report this tick missed.
    fn restart(&mut self) -> DeviceError {
        self.stats.restarts += 1;
        for _ in 0..RESTART_ATTEMPTS {
            self.undo_failed_start(StartError::Bus(Step::StartIso, BusError::BusReset));
            match self.start_sequence() {
                Ok(()) => return self.miss(MissReason::BusReset),
                Err(e) if e.bus() == Some(BusError::BusReset) => continue,
                Err(e) => {
                    self.undo_failed_start(e);
                    return self.start_failure(e);
                }
            }
        }
        self.undo_failed_start(StartError::Bus(Step::StartIso, BusError::BusReset));
        DeviceError::Io(format!(
            "FireWire Omni {}: the bus kept resetting; streaming could not be restarted",
            self.name
        ))
    }

    /// One step of the stop sequence: false when the node is gone (nothing more to do); a bus
    /// reset already stopped the device and voided the channels; other errors are kept (the
    /// first one is returned) and the sequence goes on.
    fn stop_step(
        &mut self,
        what: &str,
        r: Result<(), BusError>,
        first: &mut Option<DeviceError>,
        reset: &mut bool,
    ) -> bool {
        match r {
            Ok(()) => true,
            Err(BusError::Gone) => {
                self.gone = true;
                false
            }
            Err(BusError::BusReset) => {
                *reset = true;
                true
            }
            Err(e) => {
                first.get_or_insert_with(|| {
                    DeviceError::Io(format!("FireWire Omni {}: {what}: {e}", self.name))
                });
                true
            }
        }
    }

    /// The delivered packet: encoder words turned to the OpenHaptics directions.
    fn deliver(&mut self, mut out: [u8; STATE_LEN], t: f64) -> RawSample {
        for (j, &at) in STATE_LAYOUT.encoder.iter().enumerate() {
            if self.opts.encoder_sign[j] < 0 {
                let raw = u16::from_le_bytes([out[at], out[at + 1]]);
                out[at..at + 2].copy_from_slice(&raw.wrapping_neg().to_le_bytes());
            }
        }
        self.stats.delivered += 1;
        self.gate.sample_delivered();
        RawSample::new(out, t)
    }

    fn tap_sent(&mut self, wire: &[u8; COMMAND_LEN]) {
        if let Some(tap) = self.tap.as_mut() {
            tap.push(Tapped {
                host_ns: crate::clock::now_ns(),
                received: None,
                bytes: wire.to_vec(),
            });
        }
    }

    fn tap_received(&mut self, info: PacketInfo) {
        if let Some(tap) = self.tap.as_mut() {
            let n = info.len.min(ISO_PAYLOAD_MAX);
            tap.push(Tapped {
                host_ns: crate::clock::now_ns(),
                received: Some(info),
                bytes: self.buf[..n].to_vec(),
            });
        }
    }

    fn exchange_wire(
        &mut self,
        wire: [u8; COMMAND_LEN],
        malformed: Option<super::CodecError>,
    ) -> Result<RawSample, DeviceError> {
        if self.gone {
            return Err(DeviceError::Disconnected(format!(
                "FireWire Omni {}: {}",
                self.name,
                BusError::Gone
            )));
        }
        if self.closed {
            return Err(DeviceError::Io(format!(
                "FireWire Omni {}: already closed",
                self.name
            )));
        }
        if !self.streaming {
            return Err(self.restart());
        }
        match self.bus.send_packet(&wire) {
            Ok(()) => self.tap_sent(&wire),
            Err(BusError::BusReset) => return Err(self.restart()),
            Err(BusError::TxStalled) | Err(BusError::Timeout) => {
                return Err(self.miss(MissReason::WriteStalled))
            }
            Err(e) => return Err(self.bus_failure("sending a command", e)),
        }
        if let Some(e) = malformed {
            self.stats.misses += 1;
            self.stats.last_miss = Some(MissReason::MalformedCommand);
            return Err(DeviceError::Malformed(e));
        }
        let start = Instant::now();
        let mut out = [0u8; STATE_LEN];
        let mut newest: Option<f64> = None;
        for _ in 0..MAX_PACKETS_PER_EXCHANGE {
            // Once a fresh packet is in hand, only take what is already there.
            let wait = match newest {
                Some(_) => Duration::ZERO,
                None => match self.opts.timeout.checked_sub(start.elapsed()) {
                    Some(w) if !w.is_zero() => w,
                    _ => return Err(self.miss(MissReason::ReadTimeout)),
                },
            };
            match self.bus.next_packet(&mut self.buf, wait) {
                Ok(BusEvent::Packet(info)) => {
                    self.tap_received(info);
                    if info.len < STATE_LEN {
                        self.stats.malformed += 1;
                        continue;
                    }
                    let packet = &self.buf[..STATE_LEN];
                    let counter = packet_counter(packet);
                    match self.tracker.classify(counter) {
                        Verdict::Duplicate => self.stats.duplicates += 1,
                        Verdict::Stale => self.stats.stale += 1,
                        // Iso packets carry their own boundaries: any other counter is this
                        // device's (a jump means it restarted counting; time stays monotonic).
                        Verdict::Fresh { .. } | Verdict::Unanchored | Verdict::Implausible => {
                            let (t, lost) = self.tracker.accept(counter);
                            if lost > 0 {
                                self.stats.lost += u64::from(lost);
                                self.stats.gaps += 1;
                            }
                            if newest.is_some() {
                                self.stats.superseded += 1;
                            }
                            out.copy_from_slice(packet);
                            newest = Some(t);
                        }
                    }
                }
                Ok(BusEvent::BusReset) | Err(BusError::BusReset) => return Err(self.restart()),
                Ok(BusEvent::Timeout) | Err(BusError::Timeout) => match newest {
                    Some(t) => return Ok(self.deliver(out, t)),
                    None => return Err(self.miss(MissReason::ReadTimeout)),
                },
                Err(e) => return Err(self.bus_failure("receiving", e)),
            }
        }
        match newest {
            Some(t) => Ok(self.deliver(out, t)),
            None => Err(self.miss(MissReason::NoFreshPacket)),
        }
    }
}

impl<B: FireWireBus> Device for FireWireOmni<B> {
    fn kind(&self) -> &'static str {
        "firewire"
    }

    fn serial(&self) -> Option<&str> {
        self.serial.as_deref()
    }

    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        let (wire, malformed) = self.gate.wire(command);
        self.exchange_wire(wire, malformed)
    }

    /// The stop sequence: one more safe packet, clear bit 3 of 0x1087, stop iso, free the
    /// channels. A node that is gone needs none of it.
    fn close(&mut self) -> Result<(), DeviceError> {
        if self.closed {
            return Ok(());
        }
        self.closed = true;
        if self.gone || !self.touched {
            return Ok(());
        }
        let mut first: Option<DeviceError> = None;
        let mut reset = false;
        if self.iso_running {
            let safe = self.gate.safe();
            let r = self.bus.send_packet(&safe);
            if r.is_ok() {
                self.tap_sent(&safe);
            }
            if !self.stop_step(
                "sending the final zero-torque packet",
                r,
                &mut first,
                &mut reset,
            ) {
                return Ok(());
            }
        }
        let r = self
            .read_byte(reg::CONTROL)
            .and_then(|c| self.retry(|b| b.write_byte(reg::CONTROL, c & !reg::CONTROL_STREAM)));
        if !self.stop_step(
            "clearing the stream bit of register 0x1087",
            r,
            &mut first,
            &mut reset,
        ) {
            return Ok(());
        }
        self.streaming = false;
        if self.iso_running {
            let r = self.bus.stop_iso();
            self.iso_running = false;
            if !self.stop_step("stopping isochronous streaming", r, &mut first, &mut reset) {
                return Ok(());
            }
        }
        for ch in [self.to_device.take(), self.from_device.take()]
            .into_iter()
            .flatten()
        {
            if reset {
                continue;
            }
            let r = self.bus.free_channel(ch);
            if !self.stop_step("freeing an isochronous channel", r, &mut first, &mut reset) {
                return Ok(());
            }
        }
        first.map_or(Ok(()), Err)
    }
}

impl<B: FireWireBus> Drop for FireWireOmni<B> {
    /// Dropped without `close` (early return, unwinding): still stop the device safely.
    fn drop(&mut self) {
        let _ = self.close();
    }
}

// ------------------------------------------------------------------------------------------
// Opening the real thing.

/// A `/dev/fw*` node as found on this machine.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeInfo {
    /// `/dev/fw1`.
    pub(crate) path: PathBuf,
    /// Config-ROM vendor id (from sysfs, else from the ROM through the node), when known.
    pub(crate) vendor: Option<u32>,
    /// GUID from sysfs, when known.
    pub(crate) guid: Option<String>,
    /// Vendor and model names from sysfs, when known.
    pub(crate) vendor_name: Option<String>,
    pub(crate) model_name: Option<String>,
    /// Whether this user may open the node.
    pub(crate) access: NodeAccess,
}

/// Whether a node can be opened read-write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum NodeAccess {
    /// It opens read-write.
    Ok,
    /// Permission denied (the udev rule is missing or the user is not in its group).
    Denied,
    /// Another error, its message.
    Error(String),
}

impl NodeInfo {
    pub(crate) fn is_omni(&self) -> bool {
        self.vendor == Some(SENSABLE_VENDOR_ID)
    }
}

/// The hint when there is no Omni among `nodes`.
pub(crate) fn no_omni_hint(nodes: &[NodeInfo]) -> String {
    if nodes.is_empty() {
        return "There are no /dev/fw* nodes at all: this machine has no IEEE-1394 (FireWire) \
                controller, or its driver is not loaded (`sudo modprobe firewire-ohci`). Check \
                the controller, the cable and the Omni's power."
            .to_string();
    }
    let seen: Vec<String> = nodes
        .iter()
        .map(|n| match (n.vendor, &n.access) {
            (Some(v), _) => format!("{} vendor {v:#08x}", n.path.display()),
            (None, NodeAccess::Denied) => {
                format!("{} (vendor unknown: permission denied)", n.path.display())
            }
            (None, _) => format!("{} (vendor unknown)", n.path.display()),
        })
        .collect();
    format!(
        "found {}; none has vendor 0x000b99. The Omni shows up as its own node beside the \
         controller's: check the cable and the Omni's power (the inkwell lamp).",
        seen.join(", ")
    )
}

/// Nodes to try, in order, for this configuration; errors say what was found instead.
pub(crate) fn candidate_nodes(
    nodes: &[NodeInfo],
    cfg: &FirewireConfig,
) -> Result<Vec<PathBuf>, DeviceError> {
    let not_found = |hint: String| DeviceError::NotFound {
        looked_for: cfg.looked_for(),
        hint,
    };
    if !cfg.device.is_empty() {
        let Some(node) = nodes.iter().find(|n| n.path == Path::new(&cfg.device)) else {
            return Err(not_found(format!(
                "{} does not exist. {}",
                cfg.device,
                if nodes.is_empty() {
                    no_omni_hint(nodes)
                } else {
                    "Leave firewire.device empty to search.".to_string()
                }
            )));
        };
        if node.access == NodeAccess::Denied {
            return Err(DeviceError::Permission {
                what: cfg.device.clone(),
                hint: firewire_permission_hint(),
            });
        }
        // The vendor register check after opening refuses anything that is not an Omni.
        return Ok(vec![node.path.clone()]);
    }
    let omnis: Vec<&NodeInfo> = nodes.iter().filter(|n| n.is_omni()).collect();
    let openable: Vec<PathBuf> = omnis
        .iter()
        .filter(|n| n.access != NodeAccess::Denied)
        .map(|n| n.path.clone())
        .collect();
    if openable.is_empty() {
        if let Some(n) = omnis.first() {
            return Err(DeviceError::Permission {
                what: format!("the FireWire Omni at {}", n.path.display()),
                hint: firewire_permission_hint(),
            });
        }
        // Nodes whose vendor could not be read because of permissions may hide the Omni.
        if let Some(n) = nodes
            .iter()
            .find(|n| n.vendor.is_none() && n.access == NodeAccess::Denied)
        {
            return Err(DeviceError::Permission {
                what: format!("{} (to read its vendor id)", n.path.display()),
                hint: firewire_permission_hint(),
            });
        }
        return Err(not_found(no_omni_hint(nodes)));
    }
    Ok(openable)
}

/// Find and identify the configured Omni (reads only: nothing is written to it yet).
pub(crate) fn find_firewire(
    cfg: &FirewireConfig,
    rate_hz: f64,
) -> Result<FireWireOmni<cdev::CdevBus>, DeviceError> {
    cfg.validate()
        .map_err(|e| DeviceError::Unsupported(e.to_string()))?;
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(DeviceError::Unsupported(format!(
            "packet rate {rate_hz} Hz is out of range: allowed a finite rate > 0"
        )));
    }
    let nodes = cdev::scan_nodes(Path::new("/dev"), Path::new(cdev::SYSFS_FIREWIRE_DEVICES));
    let candidates = candidate_nodes(&nodes, cfg)?;
    let register_timeout = Duration::from_millis(u64::from(cfg.register_timeout_ms));
    let mut serials = Vec::new();
    let mut chosen = Vec::new();
    for path in &candidates {
        let bus = match cdev::CdevBus::open(path, register_timeout) {
            Ok(b) => b,
            Err(BusError::Permission) => {
                return Err(DeviceError::Permission {
                    what: path.display().to_string(),
                    hint: firewire_permission_hint(),
                })
            }
            Err(BusError::Gone) => continue,
            Err(e) => return Err(DeviceError::Io(format!("opening {}: {e}", path.display()))),
        };
        let mut omni =
            FireWireOmni::with_options(bus, path.display().to_string(), cfg.options(rate_hz));
        let serial = omni.identify()?;
        serials.push(format!("{serial} at {}", path.display()));
        if omni.serial_quadlet().is_some_and(|q| cfg.wants_serial(q)) {
            chosen.push(omni);
        }
    }
    if chosen.len() > 1 {
        return Err(DeviceError::NotFound {
            looked_for: "exactly one FireWire Omni".into(),
            hint: format!(
                "found {} ({}); set firewire.serial to choose one.",
                chosen.len(),
                serials.join(", ")
            ),
        });
    }
    chosen.pop().ok_or_else(|| DeviceError::NotFound {
        looked_for: cfg.looked_for(),
        hint: if serials.is_empty() {
            no_omni_hint(&nodes)
        } else {
            format!(
                "Omnis found: {}; set firewire.serial to one of them.",
                serials.join(", ")
            )
        },
    })
}

#[cfg(test)]
mod tests;

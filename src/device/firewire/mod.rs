//! The FireWire Omni (IEEE-1394a, DESIGN §4.5) over Linux firewire-cdev (`/dev/fw*`).
//!
//! Split in two:
//! - [`FireWireOmni`] holds the protocol: identify the node (vendor register), the start
//!   sequence (two isochronous channels at the IRM, channel registers 0x1000/0x1001, checks of
//!   0x1083 = 0xC0 and 0x1082 = 0x00, iso contexts, bit 3 of 0x1087 to stream), the counter
//!   check on every packet, a full restart after every bus reset, and the stop sequence on
//!   close (safe packet, clear bit 3 of 0x1087, stop iso, free channels).
//! - [`FireWireBus`] does the bus work: asynchronous register reads and writes, channel
//!   allocation, iso contexts, packets and bus-reset events. [`cdev::CdevBus`] is the real
//!   one (ioctls on `/dev/fwN`); tests drive the protocol over a fake bus.
//!
//! The §4.5 registers at 0x1000..0x1087 are single bytes at byte addresses (0x1087 is not
//! quadlet-aligned), so the bus has byte access (1-byte block transactions) beside quadlet
//! access (the vendor and serial quadlets at 0x1006000C/0x10060010).

pub mod cdev;

use super::stream::{
    packet_counter, CommandGate, CounterTracker, MissReason, StreamStats, Verdict,
};
use super::{Device, DeviceError, RawSample, COMMAND_LEN, STATE_LEN};
use crate::config::ConfigError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use thiserror::Error;

/// SensAble's IEEE OUI, in the config ROM and in the device's vendor register.
pub const SENSABLE_VENDOR_ID: u32 = 0x000B99;

/// Packet rate assumed by [`open_firewire`] (the servo rate of the default config).
pub const DEFAULT_RATE_HZ: f64 = 1000.0;

/// Largest iso payload the bus hands over (the Omni's are about 44 bytes).
pub const ISO_PAYLOAD_MAX: usize = 256;

/// Start attempts after a bus reset before giving up (each further reset during the start
/// costs one).
pub const RESTART_ATTEMPTS: u32 = 3;

/// Packets read per exchange at most (the newest is delivered).
pub const MAX_PACKETS_PER_EXCHANGE: usize = 64;

/// Device registers (offsets in the node's address space), DESIGN §4.5.
pub mod reg {
    /// Quadlet: vendor id << 8 (reads 0x000B99xx on an Omni).
    pub const VENDOR: u64 = 0x1006_000C;
    /// Quadlet: serial number.
    pub const SERIAL: u64 = 0x1006_0010;
    /// Byte: isochronous channel host → device.
    pub const CHANNEL_TO_DEVICE: u64 = 0x1000;
    /// Byte: isochronous channel device → host.
    pub const CHANNEL_FROM_DEVICE: u64 = 0x1001;
    /// Byte read during the start; expected [`CHECK_A_VALUE`].
    pub const CHECK_A: u64 = 0x1083;
    pub const CHECK_A_VALUE: u8 = 0xC0;
    /// Byte read during the start; expected [`CHECK_B_VALUE`].
    pub const CHECK_B: u64 = 0x1082;
    pub const CHECK_B_VALUE: u8 = 0x00;
    /// Byte: control; bit 3 starts and stops streaming.
    pub const CONTROL: u64 = 0x1087;
    pub const CONTROL_STREAM: u8 = 1 << 3;
}

/// `[firewire]`: which node and how long to wait.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct FirewireConfig {
    /// Device node to use (`/dev/fw1`); empty = search every `/dev/fw*` for vendor 0x000B99.
    pub device: String,
    /// Serial number of the Omni to use when several are on the bus; empty = the only one.
    pub serial: String,
    /// How long one exchange may wait for the next state packet, ms.
    pub timeout_ms: u32,
    /// How long a register read or write, or a channel allocation, may take, ms.
    pub register_timeout_ms: u32,
}

impl Default for FirewireConfig {
    fn default() -> Self {
        FirewireConfig {
            device: String::new(),
            serial: String::new(),
            timeout_ms: 10,
            register_timeout_ms: 100,
        }
    }
}

/// One-line explanations of every `[firewire]` key, for `omnid config --print-default`.
pub const FIREWIRE_FIELD_DOCS: &[(&str, &str)] = &[
    (
        "firewire",
        "FireWire Omni (DESIGN §4.5) on Linux firewire-cdev (/dev/fw*).",
    ),
    (
        "firewire.device",
        "device node to use, e.g. \"/dev/fw1\"; empty = search for vendor 0x000B99",
    ),
    (
        "firewire.serial",
        "serial number of the Omni to use when several are connected; empty = the only one",
    ),
    (
        "firewire.timeout_ms",
        "wait for the next state packet, ms (1..=1000); a timeout is a missed tick",
    ),
    (
        "firewire.register_timeout_ms",
        "wait for a register transaction or channel allocation, ms (1..=5000)",
    ),
];

impl FirewireConfig {
    /// Check every value; the first problem names its field (`firewire.timeout_ms`, ...).
    pub fn validate(&self) -> Result<(), ConfigError> {
        let invalid = |field: &str, value: String, allowed: &str| ConfigError::Invalid {
            field: field.to_string(),
            value,
            allowed: allowed.to_string(),
        };
        let node_ok = self
            .device
            .strip_prefix("/dev/fw")
            .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()));
        if !self.device.is_empty() && !node_ok {
            return Err(invalid(
                "firewire.device",
                format!("{:?}", self.device),
                "empty (search) or a node like \"/dev/fw1\"",
            ));
        }
        if self.serial.len() > 64 || !self.serial.chars().all(|c| c.is_ascii_graphic()) {
            return Err(invalid(
                "firewire.serial",
                format!("{:?}", self.serial),
                "empty, or up to 64 printable ASCII characters without spaces",
            ));
        }
        if !(1..=1000).contains(&self.timeout_ms) {
            return Err(invalid(
                "firewire.timeout_ms",
                self.timeout_ms.to_string(),
                "1 ..= 1000 ms",
            ));
        }
        if !(1..=5000).contains(&self.register_timeout_ms) {
            return Err(invalid(
                "firewire.register_timeout_ms",
                self.register_timeout_ms.to_string(),
                "1 ..= 5000 ms",
            ));
        }
        Ok(())
    }

    /// What `open_firewire` looks for, in words.
    pub fn looked_for(&self) -> String {
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
}

/// The udev rule of DESIGN §4.5.
pub const FIREWIRE_UDEV_RULE: &str =
    "SUBSYSTEM==\"firewire\", ATTR{vendor}==\"0x000b99\", MODE=\"0660\", GROUP=\"plugdev\"";

/// How to fix "permission denied" on `/dev/fwN`.
pub fn firewire_permission_hint() -> String {
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
    #[error("bus reset")]
    BusReset,
    #[error("the node is gone (unplugged or powered off)")]
    Gone,
    #[error("timed out")]
    Timeout,
    #[error("permission denied")]
    Permission,
    #[error("no free isochronous channel at the isochronous resource manager")]
    NoChannel,
    #[error("the isochronous transmit queue is full (the controller stopped sending)")]
    TxStalled,
    #[error("the node answered with response code {0:#04x}")]
    Rcode(u32),
    #[error("isochronous streaming is not running")]
    NotStreaming,
    #[error("{op}: {}", os_text(.errno))]
    Os { op: &'static str, errno: i32 },
}

/// What waiting for the next packet brought.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BusEvent {
    /// A packet of this many bytes is in the buffer.
    Packet(usize),
    /// The bus was reset: channels and device state are void, the start must be redone.
    BusReset,
    /// Nothing arrived in time.
    Timeout,
}

/// The bus operations the protocol needs, on one node.
pub trait FireWireBus: Send {
    /// Read a quadlet (big-endian on the wire, returned as a number).
    fn read_quadlet(&mut self, offset: u64) -> Result<u32, BusError>;
    /// Write a quadlet.
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

/// Why the start sequence failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum StartError {
    Bus(BusError),
    Register { reg: u64, got: u8, expected: u8 },
}

impl From<BusError> for StartError {
    fn from(e: BusError) -> Self {
        StartError::Bus(e)
    }
}

/// The FireWire Omni. Generic over the bus so tests can script the node.
pub struct FireWireOmni<B: FireWireBus> {
    bus: B,
    name: String,
    serial: Option<String>,
    timeout: Duration,
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
}

impl<B: FireWireBus> FireWireOmni<B> {
    /// No bus traffic yet: see [`identify`](Self::identify) and [`start`](Self::start).
    pub fn new(bus: B, name: String, timeout: Duration, rate_hz: f64) -> Self {
        FireWireOmni {
            bus,
            name,
            serial: None,
            timeout,
            gate: CommandGate::new(),
            tracker: CounterTracker::new(1.0 / rate_hz),
            stats: StreamStats::default(),
            buf: Box::new([0; ISO_PAYLOAD_MAX]),
            to_device: None,
            from_device: None,
            iso_running: false,
            streaming: false,
            touched: false,
            gone: false,
            closed: false,
        }
    }

    /// Identify, then start streaming.
    pub fn open(
        bus: B,
        name: String,
        timeout: Duration,
        rate_hz: f64,
    ) -> Result<Self, DeviceError> {
        let mut omni = Self::new(bus, name, timeout, rate_hz);
        omni.identify()?;
        omni.start()?;
        Ok(omni)
    }

    /// Check the vendor register says SensAble and read the serial number (no writes).
    pub fn identify(&mut self) -> Result<String, DeviceError> {
        let vendor = self
            .bus
            .read_quadlet(reg::VENDOR)
            .map_err(|e| self.bus_failure("reading the vendor register", e))?;
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
        let serial = self
            .bus
            .read_quadlet(reg::SERIAL)
            .map_err(|e| self.bus_failure("reading the serial register", e))?;
        let serial = serial.to_string();
        self.serial = Some(serial.clone());
        Ok(serial)
    }

    /// The start sequence of DESIGN §4.5, redone after every bus reset.
    pub fn start(&mut self) -> Result<(), DeviceError> {
        match self.start_sequence() {
            Ok(()) => Ok(()),
            Err(e) => {
                self.undo_failed_start(e);
                Err(self.start_failure(e))
            }
        }
    }

    /// Everything unusual seen on the stream so far.
    pub fn stats(&self) -> StreamStats {
        self.stats
    }

    fn start_sequence(&mut self) -> Result<(), StartError> {
        self.touched = true;
        let to_device = self.bus.allocate_channel()?;
        self.to_device = Some(to_device);
        let from_device = self.bus.allocate_channel()?;
        self.from_device = Some(from_device);
        self.bus.write_byte(reg::CHANNEL_TO_DEVICE, to_device)?;
        self.bus.write_byte(reg::CHANNEL_FROM_DEVICE, from_device)?;
        for (r, expected) in [
            (reg::CHECK_A, reg::CHECK_A_VALUE),
            (reg::CHECK_B, reg::CHECK_B_VALUE),
        ] {
            let got = self.bus.read_byte(r)?;
            if got != expected {
                return Err(StartError::Register {
                    reg: r,
                    got,
                    expected,
                });
            }
        }
        self.bus.start_iso(from_device, to_device)?;
        self.iso_running = true;
        // The first packet on the wire is the safe one.
        self.gate.require_new_sample();
        let safe = self.gate.safe();
        self.bus.send_packet(&safe)?;
        let control = self.bus.read_byte(reg::CONTROL)?;
        self.bus
            .write_byte(reg::CONTROL, control | reg::CONTROL_STREAM)?;
        self.streaming = true;
        self.tracker.reanchor();
        Ok(())
    }

    /// After a failed start: stop iso and give the channels back, unless a bus reset already
    /// voided them (then someone else may own them now) or the node is gone.
    fn undo_failed_start(&mut self, e: StartError) {
        // The stream bit is the start's last write: a failed start leaves nothing to clear.
        self.streaming = false;
        self.touched = false;
        if e == StartError::Bus(BusError::Gone) {
            self.gone = true;
            return;
        }
        if self.iso_running {
            let _ = self.bus.stop_iso();
            self.iso_running = false;
        }
        let reset = e == StartError::Bus(BusError::BusReset);
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
            StartError::Bus(BusError::NoChannel) => DeviceError::Io(format!(
                "FireWire Omni {}: no free isochronous channel at the bus's resource manager \
                 (another program streaming? unplug other FireWire devices)",
                self.name
            )),
            StartError::Bus(b) => self.bus_failure("starting the stream", b),
            StartError::Register { reg, got, expected } => DeviceError::Io(format!(
                "FireWire Omni {}: register {reg:#x} reads {got:#04x}, expected {expected:#04x}: \
                 the device is not in the state the start sequence expects; power-cycle it",
                self.name
            )),
        }
    }

    fn miss(&mut self, reason: MissReason) -> DeviceError {
        self.stats.misses += 1;
        self.stats.last_miss = reason;
        // No text: a miss must not allocate (the reason is in `stats().last_miss`).
        DeviceError::Missed(String::new())
    }

    /// A bus reset: forget the void channels, redo the start, and report this tick missed.
    fn restart(&mut self) -> DeviceError {
        self.stats.restarts += 1;
        for _ in 0..RESTART_ATTEMPTS {
            self.undo_failed_start(StartError::Bus(BusError::BusReset));
            match self.start_sequence() {
                Ok(()) => return self.miss(MissReason::BusReset),
                Err(StartError::Bus(BusError::BusReset)) => continue,
                Err(e) => {
                    self.undo_failed_start(e);
                    return self.start_failure(e);
                }
            }
        }
        self.undo_failed_start(StartError::Bus(BusError::BusReset));
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

    fn deliver(&mut self, out: [u8; STATE_LEN], t: f64) -> RawSample {
        self.stats.delivered += 1;
        self.gate.sample_delivered();
        RawSample::new(out, t)
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
        let (wire, malformed) = self.gate.wire(command);
        match self.bus.send_packet(&wire) {
            Ok(()) => {}
            Err(BusError::BusReset) => return Err(self.restart()),
            Err(BusError::TxStalled) | Err(BusError::Timeout) => {
                return Err(self.miss(MissReason::WriteStalled))
            }
            Err(e) => return Err(self.bus_failure("sending a command", e)),
        }
        if let Some(e) = malformed {
            self.stats.misses += 1;
            self.stats.last_miss = MissReason::MalformedCommand;
            return Err(DeviceError::Malformed(e));
        }
        let start = Instant::now();
        let mut out = [0u8; STATE_LEN];
        let mut newest: Option<f64> = None;
        for _ in 0..MAX_PACKETS_PER_EXCHANGE {
            // Once a fresh packet is in hand, only take what is already there.
            let wait = match newest {
                Some(_) => Duration::ZERO,
                None => match self.timeout.checked_sub(start.elapsed()) {
                    Some(w) if !w.is_zero() => w,
                    _ => return Err(self.miss(MissReason::ReadTimeout)),
                },
            };
            match self.bus.next_packet(&mut self.buf, wait) {
                Ok(BusEvent::Packet(len)) => {
                    if len < STATE_LEN {
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
            .bus
            .read_byte(reg::CONTROL)
            .and_then(|c| self.bus.write_byte(reg::CONTROL, c & !reg::CONTROL_STREAM));
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
    pub path: PathBuf,
    /// Config-ROM vendor id (from sysfs, else from the ROM through the node), when known.
    pub vendor: Option<u32>,
    /// GUID from sysfs, when known.
    pub guid: Option<String>,
    /// Vendor and model names from sysfs, when known.
    pub vendor_name: Option<String>,
    pub model_name: Option<String>,
    /// Whether this user may open the node.
    pub access: NodeAccess,
}

/// Whether a node can be opened read-write.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NodeAccess {
    Ok,
    Denied,
    Error(String),
}

impl NodeInfo {
    pub fn is_omni(&self) -> bool {
        self.vendor == Some(SENSABLE_VENDOR_ID)
    }
}

/// The hint when there is no Omni among `nodes`.
pub fn no_omni_hint(nodes: &[NodeInfo]) -> String {
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
pub fn candidate_nodes(
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

/// Open the FireWire Omni at the default rate (1 kHz).
pub fn open_firewire(cfg: &FirewireConfig) -> Result<Box<dyn Device>, DeviceError> {
    open_firewire_with_rate(cfg, DEFAULT_RATE_HZ)
}

/// Open the FireWire Omni; `rate_hz` is the packet rate the device is set to (device time
/// comes from the packet counter). Fails fast with `NotFound` when there is no FireWire or no
/// Omni, and with `Permission` (and the udev fix) when the node cannot be opened.
pub fn open_firewire_with_rate(
    cfg: &FirewireConfig,
    rate_hz: f64,
) -> Result<Box<dyn Device>, DeviceError> {
    cfg.validate()
        .map_err(|e| DeviceError::Unsupported(e.to_string()))?;
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(DeviceError::Unsupported(format!(
            "packet rate {rate_hz} Hz is out of range: allowed a finite rate > 0"
        )));
    }
    let nodes = cdev::scan_nodes(Path::new("/dev"), Path::new(cdev::SYSFS_FIREWIRE_DEVICES));
    let candidates = candidate_nodes(&nodes, cfg)?;
    let timeout = Duration::from_millis(u64::from(cfg.timeout_ms));
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
        let mut omni = FireWireOmni::new(bus, path.display().to_string(), timeout, rate_hz);
        let serial = omni.identify()?;
        serials.push(format!("{serial} at {}", path.display()));
        if cfg.serial.is_empty() || cfg.serial == serial {
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
    let Some(mut omni) = chosen.pop() else {
        return Err(DeviceError::NotFound {
            looked_for: cfg.looked_for(),
            hint: if serials.is_empty() {
                no_omni_hint(&nodes)
            } else {
                format!(
                    "Omnis found: {}; set firewire.serial to one of them.",
                    serials.join(", ")
                )
            },
        });
    };
    omni.start()?;
    Ok(Box::new(omni))
}

#[cfg(test)]
mod tests;

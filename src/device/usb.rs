//! The USB bridge backend (docs/DESIGN.md §4.6): a device that forwards the Omni's packets over
//! USB, one 16-byte command out and one 44-byte state packet in per millisecond, on configured
//! endpoints (bulk or interrupt).
//!
//! Split in two:
//! - `UsbOmni` holds the protocol: it frames the incoming byte stream by length (a transfer
//!   may carry part of a packet or several), checks the per-packet counter (gaps, duplicates,
//!   stale packets), keeps the amplifiers off until it has delivered a sample, sends the open
//!   drivers' byte 7 (0x53, docs/FIREWIRE.md §3: the bridge forwards the Omni's packets) on
//!   every packet, maps timeouts to `Missed` and unplugging to `Disconnected`, and ends with
//!   the safe packet on close (or drop).
//! - `UsbTransport` moves bytes. `RusbTransport` is the real one (libusb through `rusb`);
//!   tests drive `UsbOmni` over a scriptable fake.
//!
//! `exchange` allocates nothing: its buffers are made at open. (libusb's synchronous
//! transfers allocate their transfer structure inside libusb on every call; that is outside
//! this crate.)

use super::stream::{CommandGate, CounterTracker, Framer, StreamStats};
use super::{Device, DeviceError, MissReason, RawSample, COMMAND_LEN, STATE_LEN};
use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};
use std::fmt;
use std::time::{Duration, Instant};
use thiserror::Error;

/// Size of one read; a transfer may carry several packets.
pub(crate) const READ_BUF_LEN: usize = 1024;

/// Reads tried per exchange before it counts as missed (a bound for a device that trickles
/// bytes that never make a packet).
pub(crate) const MAX_READS_PER_EXCHANGE: usize = 64;

/// USB transfer type of the bridge's endpoints.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum UsbTransfer {
    /// Bulk endpoints (most bridges).
    Bulk,
    /// Interrupt endpoints (polled by the host every frame).
    Interrupt,
}

impl fmt::Display for UsbTransfer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            UsbTransfer::Bulk => "bulk",
            UsbTransfer::Interrupt => "interrupt",
        })
    }
}

/// `[usb]`: which bridge and how to talk to it. Nothing public fixes these, so the defaults
/// are placeholders (the pid.codes test id 1209:0001) to be set for the bridge at hand.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct UsbConfig {
    /// USB vendor id of the bridge.
    pub vendor_id: u16,
    /// USB product id of the bridge.
    pub product_id: u16,
    /// Interface number carrying the two endpoints.
    pub interface: u8,
    /// OUT endpoint address for commands (0x01..=0x0F).
    pub endpoint_out: u8,
    /// IN endpoint address for state packets (0x81..=0x8F).
    pub endpoint_in: u8,
    /// Transfer type of both endpoints.
    pub transfer: UsbTransfer,
    /// How long one exchange may wait for the next state packet, ms (≥ 1: libusb takes 0 as
    /// "wait forever").
    pub timeout_ms: u32,
    /// Serial number of the bridge to use; empty = the only one present.
    pub serial: String,
}

impl Default for UsbConfig {
    fn default() -> Self {
        UsbConfig {
            vendor_id: 0x1209,
            product_id: 0x0001,
            interface: 0,
            endpoint_out: 0x01,
            endpoint_in: 0x81,
            transfer: UsbTransfer::Bulk,
            timeout_ms: 10,
            serial: String::new(),
        }
    }
}

/// USB vendor id of 3D Systems, maker of the USB Geomagic/3D Systems Touch.
pub(crate) const TOUCH_VENDOR_ID: u16 = 0x2988;

/// Whether these ids are a USB Touch: vendor 0x2988 (the Touch reports 2988:0302), or
/// 0301:2988, the pair 3D Systems' own instructions give (both seen in
/// bharatm11/Geomagic_Touch_ROS_Drivers issue #2). docs/FIREWIRE.md §8.
pub(crate) fn is_usb_touch(vendor_id: u16, product_id: u16) -> bool {
    vendor_id == TOUCH_VENDOR_ID || (vendor_id == 0x0301 && product_id == TOUCH_VENDOR_ID)
}

/// What a USB Touch is, for refusals.
pub(crate) const TOUCH_IS_NOT_A_BRIDGE: &str =
    "a 3D Systems (Geomagic) Touch: a USB CDC-ACM serial \
     device with an undocumented protocol, not a bridge forwarding a FireWire Omni's packets; \
     omnid cannot drive it (docs/FIREWIRE.md §8)";

impl UsbConfig {
    /// Check every value; the first problem names its field (`usb.timeout_ms`, ...).
    pub fn validate(&self) -> Result<(), ConfigError> {
        if self.vendor_id == 0 {
            return Err(check::invalid(
                "usb.vendor_id",
                "0x0000",
                "0x0001 ..= 0xFFFF",
            ));
        }
        if is_usb_touch(self.vendor_id, self.product_id) {
            return Err(check::invalid(
                "usb.vendor_id",
                format!(
                    "{:#06x} (with usb.product_id {:#06x})",
                    self.vendor_id, self.product_id
                ),
                format!(
                    "the ids of a USB bridge to an Omni; {} is {TOUCH_IS_NOT_A_BRIDGE}",
                    self.ids()
                ),
            ));
        }
        let ep_ok = |ep: u8, dir: u8| ep & 0xF0 == dir && (1..=15).contains(&(ep & 0x0F));
        if !ep_ok(self.endpoint_out, 0x00) {
            return Err(check::invalid(
                "usb.endpoint_out",
                format!("{:#04x}", self.endpoint_out),
                "an OUT endpoint address, 0x01 ..= 0x0F",
            ));
        }
        if !ep_ok(self.endpoint_in, 0x80) {
            return Err(check::invalid(
                "usb.endpoint_in",
                format!("{:#04x}", self.endpoint_in),
                "an IN endpoint address, 0x81 ..= 0x8F",
            ));
        }
        if !(1..=1000).contains(&self.timeout_ms) {
            return Err(check::invalid(
                "usb.timeout_ms",
                self.timeout_ms.to_string(),
                "1 ..= 1000 ms (0 would mean \"wait forever\" to libusb)",
            ));
        }
        if self.serial.len() > 126 || !self.serial.chars().all(|c| c.is_ascii_graphic()) {
            return Err(check::invalid(
                "usb.serial",
                format!("{:?}", self.serial),
                "empty, or up to 126 printable ASCII characters without spaces",
            ));
        }
        Ok(())
    }

    /// Whether a device with these ids is the configured bridge.
    pub(crate) fn matches(&self, vendor_id: u16, product_id: u16) -> bool {
        vendor_id == self.vendor_id && product_id == self.product_id
    }

    /// `1209:0001` style.
    pub(crate) fn ids(&self) -> String {
        format!("{:04x}:{:04x}", self.vendor_id, self.product_id)
    }

    /// What `open_usb_with_rate` looks for, in words.
    pub(crate) fn looked_for(&self) -> String {
        if self.serial.is_empty() {
            format!("a USB bridge with id {}", self.ids())
        } else {
            format!(
                "a USB bridge with id {} and serial {:?}",
                self.ids(),
                self.serial
            )
        }
    }

    /// The udev rule that lets the plugdev group open this bridge.
    pub(crate) fn udev_rule(&self) -> String {
        format!(
            "SUBSYSTEM==\"usb\", ATTRS{{idVendor}}==\"{:04x}\", ATTRS{{idProduct}}==\"{:04x}\", MODE=\"0660\", GROUP=\"plugdev\"",
            self.vendor_id, self.product_id
        )
    }

    /// How to fix "permission denied" on the bridge.
    pub(crate) fn permission_hint(&self) -> String {
        format!(
            "Install the udev rule (udev/99-omnid-usb.rules, or put this line in \
             /etc/udev/rules.d/99-omnid-usb.rules: {}), run `sudo udevadm control --reload-rules \
             && sudo udevadm trigger`, add yourself to plugdev (`sudo usermod -aG plugdev $USER`), \
             log in again and replug the bridge. See udev/README.md.",
            self.udev_rule()
        )
    }
}

/// What a transport reports. Copy and allocation-free: it travels through the 1 kHz path.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Error)]
pub(crate) enum TransportError {
    #[error("timed out")]
    Timeout,
    #[error("the device is gone (unplugged or reset)")]
    Disconnected,
    #[error("the device sent more than the read buffer holds")]
    Overflow,
    #[error("{0}")]
    Io(&'static str),
}

/// Moves bytes to and from the bridge's endpoints.
pub(crate) trait UsbTransport: Send {
    /// Write one command packet to the OUT endpoint; returns the bytes written.
    fn write_out(&mut self, data: &[u8], timeout: Duration) -> Result<usize, TransportError>;
    /// Read one transfer from the IN endpoint (any length up to `buf.len()`).
    fn read_in(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError>;
    /// Give the interface back (and the kernel driver, if one was detached).
    fn release(&mut self) -> Result<(), TransportError>;
}

/// The Omni behind a USB bridge. Generic over the transport so tests can script the bridge.
pub(crate) struct UsbOmni<T: UsbTransport> {
    transport: T,
    name: String,
    serial: Option<String>,
    timeout: Duration,
    gate: CommandGate,
    tracker: CounterTracker,
    framer: Box<Framer>,
    read_buf: Box<[u8]>,
    stats: StreamStats,
    gone: bool,
    closed: bool,
}

impl<T: UsbTransport> UsbOmni<T> {
    /// `name` says which bridge this is in messages; `rate_hz` is the device's packet rate
    /// (device time comes from the packet counter).
    pub fn new(
        transport: T,
        cfg: &UsbConfig,
        rate_hz: f64,
        name: String,
        serial: Option<String>,
    ) -> Self {
        UsbOmni {
            transport,
            name,
            serial,
            timeout: Duration::from_millis(u64::from(cfg.timeout_ms.max(1))),
            gate: CommandGate::new(),
            tracker: CounterTracker::new(1.0 / rate_hz),
            framer: Box::new(Framer::new()),
            read_buf: vec![0u8; READ_BUF_LEN].into_boxed_slice(),
            stats: StreamStats::default(),
            gone: false,
            closed: false,
        }
    }

    /// Everything unusual seen on the stream so far (the tests' view; the servo sees each
    /// miss as it happens).
    #[cfg(test)]
    fn stats(&self) -> StreamStats {
        self.stats
    }

    fn miss(&mut self, reason: MissReason) -> DeviceError {
        self.stats.misses += 1;
        self.stats.last_miss = Some(reason);
        DeviceError::Missed(reason)
    }

    fn fail(&mut self, e: TransportError) -> DeviceError {
        match e {
            TransportError::Disconnected => {
                self.gone = true;
                DeviceError::Disconnected(format!("USB bridge {}: {e}", self.name))
            }
            _ => DeviceError::Io(format!("USB bridge {}: {e}", self.name)),
        }
    }
}

impl<T: UsbTransport> Device for UsbOmni<T> {
    fn kind(&self) -> &'static str {
        "usb"
    }

    fn serial(&self) -> Option<&str> {
        self.serial.as_deref()
    }

    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        if self.gone {
            return Err(self.fail(TransportError::Disconnected));
        }
        if self.closed {
            return Err(DeviceError::Io(format!(
                "USB bridge {}: already closed",
                self.name
            )));
        }
        let start = Instant::now();
        let (wire, malformed) = self.gate.wire(command);
        match self.transport.write_out(&wire, self.timeout) {
            Ok(n) if n == COMMAND_LEN => {}
            Ok(_) | Err(TransportError::Timeout) => return Err(self.miss(MissReason::WriteStalled)),
            Err(e) => return Err(self.fail(e)),
        }
        if let Some(e) = malformed {
            self.stats.misses += 1;
            self.stats.last_miss = Some(MissReason::MalformedCommand);
            return Err(DeviceError::Malformed(e));
        }
        let mut out = [0u8; STATE_LEN];
        for _ in 0..MAX_READS_PER_EXCHANGE {
            if let Some(t) = self
                .framer
                .drain_newest(&mut self.tracker, &mut self.stats, &mut out)
            {
                self.stats.delivered += 1;
                self.gate.sample_delivered();
                return Ok(RawSample::new(out, t));
            }
            let elapsed = start.elapsed();
            if elapsed >= self.timeout {
                return Err(self.miss(MissReason::ReadTimeout));
            }
            // Under 1 ms libusb would wait forever.
            let wait = (self.timeout - elapsed).max(Duration::from_millis(1));
            match self.transport.read_in(&mut self.read_buf, wait) {
                Ok(n) => {
                    let n = n.min(self.read_buf.len());
                    self.framer.push(&self.read_buf[..n], &mut self.stats);
                }
                Err(TransportError::Timeout) => return Err(self.miss(MissReason::ReadTimeout)),
                Err(TransportError::Overflow) => self.stats.malformed += 1,
                Err(e) => return Err(self.fail(e)),
            }
        }
        Err(self.miss(MissReason::NoFreshPacket))
    }

    /// Sends one more safe packet (zero torque, amplifiers off), then releases the interface.
    fn close(&mut self) -> Result<(), DeviceError> {
        if self.closed {
            return Ok(());
        }
        self.closed = true;
        if self.gone {
            // Nothing to stop: the bridge is gone, and with it the amplifiers' power.
            let _ = self.transport.release();
            return Ok(());
        }
        let safe = self.gate.safe();
        let sent = self.transport.write_out(&safe, self.timeout);
        let released = self.transport.release();
        match (sent, released) {
            (Err(TransportError::Disconnected), _) => Ok(()),
            (Err(e), _) => Err(DeviceError::Io(format!(
                "USB bridge {}: sending the final zero-torque packet: {e}",
                self.name
            ))),
            (Ok(_), Err(e)) if e != TransportError::Disconnected => Err(DeviceError::Io(format!(
                "USB bridge {}: releasing the interface: {e}",
                self.name
            ))),
            _ => Ok(()),
        }
    }
}

impl<T: UsbTransport> Drop for UsbOmni<T> {
    /// A bridge dropped without `close` (an early return, a panic unwinding) still gets the
    /// safe packet.
    fn drop(&mut self) {
        let _ = self.close();
    }
}

// ------------------------------------------------------------------------------------------
// The real transport: libusb through rusb.

/// Endpoint transfer kinds as the descriptors state them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum EndpointKind {
    Bulk,
    Interrupt,
    Other,
}

impl EndpointKind {
    fn name(self) -> &'static str {
        match self {
            EndpointKind::Bulk => "bulk",
            EndpointKind::Interrupt => "interrupt",
            EndpointKind::Other => "isochronous/control",
        }
    }
}

/// Check the configured endpoints against the interface's endpoint list
/// `(address, kind)`; the error says what the bridge has and which key to change.
pub(crate) fn check_endpoints(cfg: &UsbConfig, found: &[(u8, EndpointKind)]) -> Result<(), String> {
    let want = match cfg.transfer {
        UsbTransfer::Bulk => EndpointKind::Bulk,
        UsbTransfer::Interrupt => EndpointKind::Interrupt,
    };
    let list = || {
        let v: Vec<String> = found
            .iter()
            .map(|(a, k)| {
                let dir = if a & 0x80 != 0 { "in" } else { "out" };
                format!("{a:#04x} {} {dir}", k.name())
            })
            .collect();
        if v.is_empty() {
            "no endpoints".to_string()
        } else {
            v.join(", ")
        }
    };
    for (key, addr) in [
        ("usb.endpoint_out", cfg.endpoint_out),
        ("usb.endpoint_in", cfg.endpoint_in),
    ] {
        match found.iter().find(|(a, _)| *a == addr) {
            None => {
                return Err(format!(
                    "interface {} has no endpoint {addr:#04x} ({key}); it has: {}",
                    cfg.interface,
                    list()
                ))
            }
            Some((_, kind)) if *kind != want => {
                return Err(format!(
                    "endpoint {addr:#04x} is {} but usb.transfer = \"{}\"; it has: {}",
                    kind.name(),
                    cfg.transfer,
                    list()
                ))
            }
            Some(_) => {}
        }
    }
    Ok(())
}

fn map_rusb(e: rusb::Error) -> TransportError {
    match e {
        rusb::Error::Timeout => TransportError::Timeout,
        rusb::Error::NoDevice => TransportError::Disconnected,
        rusb::Error::Overflow => TransportError::Overflow,
        rusb::Error::Pipe => TransportError::Io("endpoint stalled (pipe error)"),
        rusb::Error::Io => TransportError::Io("USB I/O error"),
        rusb::Error::Interrupted => TransportError::Io("transfer interrupted"),
        rusb::Error::Access => TransportError::Io("access denied"),
        rusb::Error::Busy => TransportError::Io("resource busy"),
        rusb::Error::NoMem => TransportError::Io("libusb out of memory"),
        rusb::Error::NotFound => TransportError::Io("entity not found"),
        rusb::Error::InvalidParam => TransportError::Io("invalid parameter"),
        rusb::Error::NotSupported => TransportError::Io("operation not supported"),
        _ => TransportError::Io("libusb error"),
    }
}

/// The bridge's claimed interface, through libusb.
pub(crate) struct RusbTransport {
    handle: rusb::DeviceHandle<rusb::Context>,
    interface: u8,
    endpoint_out: u8,
    endpoint_in: u8,
    transfer: UsbTransfer,
    reattach_kernel_driver: bool,
    released: bool,
}

impl UsbTransport for RusbTransport {
    fn write_out(&mut self, data: &[u8], timeout: Duration) -> Result<usize, TransportError> {
        let timeout = timeout.max(Duration::from_millis(1));
        match self.transfer {
            UsbTransfer::Bulk => self.handle.write_bulk(self.endpoint_out, data, timeout),
            UsbTransfer::Interrupt => self
                .handle
                .write_interrupt(self.endpoint_out, data, timeout),
        }
        .map_err(map_rusb)
    }

    fn read_in(&mut self, buf: &mut [u8], timeout: Duration) -> Result<usize, TransportError> {
        let timeout = timeout.max(Duration::from_millis(1));
        match self.transfer {
            UsbTransfer::Bulk => self.handle.read_bulk(self.endpoint_in, buf, timeout),
            UsbTransfer::Interrupt => self.handle.read_interrupt(self.endpoint_in, buf, timeout),
        }
        .map_err(map_rusb)
    }

    fn release(&mut self) -> Result<(), TransportError> {
        if self.released {
            return Ok(());
        }
        self.released = true;
        let r = self
            .handle
            .release_interface(self.interface)
            .map_err(map_rusb);
        if self.reattach_kernel_driver {
            let _ = self.handle.attach_kernel_driver(self.interface);
        }
        r
    }
}

impl Drop for RusbTransport {
    fn drop(&mut self) {
        let _ = self.release();
    }
}

/// Why libusb cannot start, with what to check.
pub(crate) fn no_usb_hint(e: rusb::Error) -> String {
    let usbfs = std::path::Path::new("/dev/bus/usb").exists();
    format!(
        "libusb cannot start here ({e}){}. Run on a machine with USB and the bridge plugged in \
         (in a container, pass the bus through, e.g. --device /dev/bus/usb).",
        if usbfs {
            ""
        } else {
            ": this machine has no USB subsystem (no /dev/bus/usb)"
        }
    )
}

/// One USB device whose ids match the configuration.
pub(crate) struct Matched {
    pub device: rusb::Device<rusb::Context>,
    pub descriptor: rusb::DeviceDescriptor,
    pub location: String,
}

/// USB Touches on the bus, as `2988:0302 at bus 001 device 004`.
pub(crate) fn touches(context: &rusb::Context) -> Vec<String> {
    use rusb::UsbContext;
    let Ok(list) = context.devices() else {
        return Vec::new();
    };
    list.iter()
        .filter_map(|device| {
            let d = device.device_descriptor().ok()?;
            is_usb_touch(d.vendor_id(), d.product_id()).then(|| {
                format!(
                    "{:04x}:{:04x} at bus {:03} device {:03}",
                    d.vendor_id(),
                    d.product_id(),
                    device.bus_number(),
                    device.address()
                )
            })
        })
        .collect()
}

/// The hint when no bridge is there but a USB Touch is.
pub(crate) fn touch_hint(touches: &[String]) -> String {
    if touches.is_empty() {
        String::new()
    } else {
        format!(
            " The USB device {} is {TOUCH_IS_NOT_A_BRIDGE}.",
            touches.join(", ")
        )
    }
}

/// All devices on the bus and those matching the configured ids.
pub(crate) fn enumerate(
    context: &rusb::Context,
    cfg: &UsbConfig,
) -> Result<(usize, Vec<Matched>), rusb::Error> {
    use rusb::UsbContext;
    let list = context.devices()?;
    let total = list.len();
    let mut matched = Vec::new();
    for device in list.iter() {
        let Ok(descriptor) = device.device_descriptor() else {
            continue;
        };
        if cfg.matches(descriptor.vendor_id(), descriptor.product_id()) {
            let location = format!(
                "bus {:03} device {:03} (/dev/bus/usb/{:03}/{:03})",
                device.bus_number(),
                device.address(),
                device.bus_number(),
                device.address()
            );
            matched.push(Matched {
                device,
                descriptor,
                location,
            });
        }
    }
    Ok((total, matched))
}

/// The hint when no device has the configured ids.
pub(crate) fn no_match_hint(cfg: &UsbConfig, total: usize) -> String {
    if total == 0 {
        "libusb sees no USB devices at all: is the bridge plugged in, and is /dev/bus/usb \
         visible here?"
            .to_string()
    } else {
        format!(
            "{total} USB device(s) present, none with id {}. Check that the bridge is plugged \
             in and powered, and that usb.vendor_id / usb.product_id match what `lsusb` shows.",
            cfg.ids()
        )
    }
}

/// Read the serial string of an opened device (None when it has none or it cannot be read).
pub(crate) fn read_serial(
    handle: &rusb::DeviceHandle<rusb::Context>,
    descriptor: &rusb::DeviceDescriptor,
) -> Option<String> {
    descriptor.serial_number_string_index()?;
    handle
        .read_serial_number_string_ascii(descriptor)
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
}

/// Endpoints of interface `cfg.interface` (alternate setting 0) in the active configuration.
pub(crate) fn interface_endpoints(
    device: &rusb::Device<rusb::Context>,
    cfg: &UsbConfig,
) -> Result<Vec<(u8, EndpointKind)>, String> {
    let config = device
        .active_config_descriptor()
        .map_err(|e| format!("cannot read the configuration descriptor: {e}"))?;
    let mut numbers = Vec::new();
    for interface in config.interfaces() {
        numbers.push(interface.number());
        if interface.number() != cfg.interface {
            continue;
        }
        if let Some(alt) = interface.descriptors().next() {
            return Ok(alt
                .endpoint_descriptors()
                .map(|ep| {
                    let kind = match ep.transfer_type() {
                        rusb::TransferType::Bulk => EndpointKind::Bulk,
                        rusb::TransferType::Interrupt => EndpointKind::Interrupt,
                        _ => EndpointKind::Other,
                    };
                    (ep.address(), kind)
                })
                .collect());
        }
    }
    Err(format!(
        "the bridge has no interface {} (usb.interface); it has {:?}",
        cfg.interface, numbers
    ))
}

/// Open the configured USB bridge; `rate_hz` is the device's packet rate (device time comes
/// from the packet counter). Fails fast with `NotFound` when there is no USB or no bridge,
/// and with `Permission` (and the udev fix) when the bridge cannot be opened.
pub(crate) fn open_usb_with_rate(
    cfg: &UsbConfig,
    rate_hz: f64,
) -> Result<Box<dyn Device>, DeviceError> {
    cfg.validate()
        .map_err(|e| DeviceError::Unsupported(e.to_string()))?;
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(DeviceError::Unsupported(format!(
            "packet rate {rate_hz} Hz is out of range: allowed a finite rate > 0"
        )));
    }
    let (m, handle, serial) = find_bridge(cfg)?;
    check_bridge_endpoints(cfg, &m)?;
    let reattach = claim_interface(cfg, &handle, &m.location)?;
    let name = match &serial {
        Some(s) => format!("{} serial {s} at {}", cfg.ids(), m.location),
        None => format!("{} at {}", cfg.ids(), m.location),
    };
    let transport = RusbTransport {
        handle,
        interface: cfg.interface,
        endpoint_out: cfg.endpoint_out,
        endpoint_in: cfg.endpoint_in,
        transfer: cfg.transfer,
        reattach_kernel_driver: reattach,
        released: false,
    };
    Ok(Box::new(UsbOmni::new(
        transport, cfg, rate_hz, name, serial,
    )))
}

/// A bridge opened by [`open_matches`]: where it is, its handle, its serial.
type OpenedBridge = (Matched, rusb::DeviceHandle<rusb::Context>, Option<String>);

/// The one bridge with the configured ids (and serial, when set), opened. No USB, no match,
/// no permission, or several matches without a serial to choose: each its own error.
fn find_bridge(cfg: &UsbConfig) -> Result<OpenedBridge, DeviceError> {
    let not_found = |hint: String| DeviceError::NotFound {
        looked_for: cfg.looked_for(),
        hint,
    };
    let context = rusb::Context::new().map_err(|e| not_found(no_usb_hint(e)))?;
    let (total, matched) =
        enumerate(&context, cfg).map_err(|e| not_found(format!("cannot list USB devices: {e}")))?;
    if matched.is_empty() {
        return Err(not_found(format!(
            "{}{}",
            no_match_hint(cfg, total),
            touch_hint(&touches(&context))
        )));
    }
    let (mut opened, serials_seen) = open_matches(cfg, matched)?;
    if opened.len() > 1 {
        return Err(DeviceError::NotFound {
            looked_for: format!("exactly one USB bridge with id {}", cfg.ids()),
            hint: format!(
                "found {} (serials {}); set usb.serial to choose one.",
                opened.len(),
                serials_seen.join(", ")
            ),
        });
    }
    opened
        .pop()
        .ok_or_else(|| not_found(no_match_hint(cfg, total)))
}

/// Open every match (permission problems show here) and keep those with the wanted serial;
/// also every serial seen, for the message when none or several are kept. None kept: a
/// permission error when one was denied, else a hint naming the serials present.
fn open_matches(
    cfg: &UsbConfig,
    matched: Vec<Matched>,
) -> Result<(Vec<OpenedBridge>, Vec<String>), DeviceError> {
    let mut opened = Vec::new();
    let mut denied = None;
    let mut serials_seen = Vec::new();
    for m in matched {
        match m.device.open() {
            Ok(handle) => {
                let serial = read_serial(&handle, &m.descriptor);
                serials_seen.push(serial.clone().unwrap_or_else(|| "(none)".into()));
                if cfg.serial.is_empty() || serial.as_deref() == Some(cfg.serial.as_str()) {
                    opened.push((m, handle, serial));
                }
            }
            Err(rusb::Error::Access) => {
                denied.get_or_insert(m.location.clone());
            }
            Err(rusb::Error::NoDevice) => {}
            Err(e) => {
                return Err(DeviceError::Io(format!(
                    "opening the USB bridge at {}: {e}",
                    m.location
                )))
            }
        }
    }
    if opened.is_empty() {
        if let Some(location) = denied {
            return Err(DeviceError::Permission {
                what: format!("the USB bridge {} at {location}", cfg.ids()),
                hint: cfg.permission_hint(),
            });
        }
        return Err(DeviceError::NotFound {
            looked_for: cfg.looked_for(),
            hint: format!(
                "bridges with id {} have serials {}; set usb.serial to one of them.",
                cfg.ids(),
                serials_seen.join(", ")
            ),
        });
    }
    Ok((opened, serials_seen))
}

/// The bridge's interface must exist and have the configured endpoints and transfer type.
fn check_bridge_endpoints(cfg: &UsbConfig, m: &Matched) -> Result<(), DeviceError> {
    let endpoints = interface_endpoints(&m.device, cfg).map_err(|e| DeviceError::NotFound {
        looked_for: format!(
            "interface {} of the bridge at {}",
            cfg.interface, m.location
        ),
        hint: e,
    })?;
    check_endpoints(cfg, &endpoints).map_err(|e| DeviceError::NotFound {
        looked_for: format!(
            "endpoints {:#04x}/{:#04x} ({}) on the bridge at {}",
            cfg.endpoint_out, cfg.endpoint_in, cfg.transfer, m.location
        ),
        hint: e,
    })
}

/// Detach a kernel driver from the interface (if one holds it) and claim it; whether a
/// driver was detached (to reattach it on release). A failed claim reattaches it at once.
fn claim_interface(
    cfg: &UsbConfig,
    handle: &rusb::DeviceHandle<rusb::Context>,
    location: &str,
) -> Result<bool, DeviceError> {
    let iface = cfg.interface;
    let mut reattach = false;
    if let Ok(true) = handle.kernel_driver_active(iface) {
        handle.detach_kernel_driver(iface).map_err(|e| match e {
            rusb::Error::Access => DeviceError::Permission {
                what: format!("detaching the kernel driver from {location}"),
                hint: cfg.permission_hint(),
            },
            e => DeviceError::Io(format!(
                "detaching the kernel driver from interface {iface} at {location}: {e}"
            )),
        })?;
        reattach = true;
    }
    if let Err(e) = handle.claim_interface(iface) {
        if reattach {
            let _ = handle.attach_kernel_driver(iface);
        }
        return Err(match e {
            rusb::Error::Busy => DeviceError::Io(format!(
                "interface {iface} of the bridge at {location} is in use by another program (another omnid?)"
            )),
            rusb::Error::Access => DeviceError::Permission {
                what: format!("claiming interface {iface} of the bridge at {location}"),
                hint: cfg.permission_hint(),
            },
            rusb::Error::NoDevice => DeviceError::NotFound {
                looked_for: cfg.looked_for(),
                hint: "the bridge vanished while opening it".into(),
            },
            e => DeviceError::Io(format!("claiming interface {iface} at {location}: {e}")),
        });
    }
    Ok(reattach)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::device::codec::{encode_command, encode_state, MotorCommand, StatePacket};
    use crate::device::testkit::{assert_wire_discipline, decode_all, run_servo};
    use crate::servo::EndReason;
    use std::collections::VecDeque;
    use std::sync::atomic::{AtomicBool, Ordering};
    use std::sync::{Arc, Mutex};

    /// What the fake bridge answers to one read.
    enum In {
        Bytes(Vec<u8>),
        Timeout,
        Unplug,
    }

    #[derive(Default)]
    struct FakeState {
        /// Scripted answers, consumed one per read.
        script: VecDeque<In>,
        /// When the script is empty: the next counter of a packet made on the spot, or None
        /// for silence (every read times out).
        auto: Option<u32>,
        /// Every packet the backend tried to write, and whether the write went through.
        writes: Vec<([u8; 16], bool)>,
        reads: usize,
        unplugged: bool,
        released: bool,
        /// Raise this flag (the servo's stop) after this many reads.
        stop_after: Option<(usize, Arc<AtomicBool>)>,
        /// Unplug after this many reads.
        unplug_after: Option<usize>,
        /// Go silent after this many reads.
        silent_after: Option<usize>,
    }

    #[derive(Clone, Default)]
    struct FakeUsb(Arc<Mutex<FakeState>>);

    impl FakeUsb {
        fn with(f: impl FnOnce(&mut FakeState)) -> Self {
            let fake = FakeUsb::default();
            f(&mut fake.0.lock().unwrap());
            fake
        }
        fn state(&self) -> std::sync::MutexGuard<'_, FakeState> {
            self.0.lock().unwrap()
        }
        fn sent(&self) -> Vec<MotorCommand> {
            let s = self.state();
            let ok: Vec<[u8; 16]> = s.writes.iter().map(|(b, _)| *b).collect();
            decode_all(&ok)
        }
    }

    impl UsbTransport for FakeUsb {
        fn write_out(&mut self, data: &[u8], _: Duration) -> Result<usize, TransportError> {
            let mut s = self.state();
            let mut b = [0u8; 16];
            b.copy_from_slice(data);
            let ok = !s.unplugged;
            s.writes.push((b, ok));
            if ok {
                Ok(data.len())
            } else {
                Err(TransportError::Disconnected)
            }
        }

        fn read_in(&mut self, buf: &mut [u8], _: Duration) -> Result<usize, TransportError> {
            let mut s = self.state();
            s.reads += 1;
            let reads = s.reads;
            if let Some((n, flag)) = &s.stop_after {
                if reads > *n {
                    flag.store(true, Ordering::SeqCst);
                }
            }
            if s.unplug_after.is_some_and(|n| reads > n) {
                s.unplugged = true;
            }
            if s.silent_after.is_some_and(|n| reads > n) {
                s.auto = None;
            }
            if s.unplugged {
                return Err(TransportError::Disconnected);
            }
            let next = match s.script.pop_front() {
                Some(x) => x,
                None => match s.auto {
                    Some(c) => {
                        s.auto = Some(c.wrapping_add(1));
                        In::Bytes(packet(c).to_vec())
                    }
                    None => In::Timeout,
                },
            };
            match next {
                In::Bytes(b) if b.len() > buf.len() => Err(TransportError::Overflow),
                In::Bytes(b) => {
                    buf[..b.len()].copy_from_slice(&b);
                    Ok(b.len())
                }
                In::Timeout => Err(TransportError::Timeout),
                In::Unplug => {
                    s.unplugged = true;
                    Err(TransportError::Disconnected)
                }
            }
        }

        fn release(&mut self) -> Result<(), TransportError> {
            self.state().released = true;
            Ok(())
        }
    }

    fn packet(counter: u32) -> [u8; STATE_LEN] {
        encode_state(&StatePacket {
            encoder: [10, 2000, 0xFF00],
            gimbal: [0x8000; 3],
            counter,
            ..Default::default()
        })
    }

    fn packets(counters: &[u32]) -> Vec<u8> {
        counters.iter().flat_map(|&c| packet(c)).collect()
    }

    fn omni(fake: &FakeUsb) -> UsbOmni<FakeUsb> {
        UsbOmni::new(
            fake.clone(),
            &UsbConfig::default(),
            1000.0,
            "fake".into(),
            Some("SN1".into()),
        )
    }

    fn amps_on(watchdog: u8) -> [u8; 16] {
        let mut c = MotorCommand::safe(watchdog);
        c.amps_on = true;
        c.dac = [0x0900, 0x0700, 0x07FF];
        encode_command(&c)
    }

    #[test]
    fn config_defaults_round_trip_and_validate() {
        let cfg = UsbConfig::default();
        cfg.validate().unwrap();
        let text = toml::to_string(&cfg).unwrap();
        assert_eq!(toml::from_str::<UsbConfig>(&text).unwrap(), cfg);
        let hex: UsbConfig =
            toml::from_str("vendor_id = 0x0B99\ntransfer = \"interrupt\"\n").unwrap();
        assert_eq!(
            (hex.vendor_id, hex.transfer),
            (0x0B99, UsbTransfer::Interrupt)
        );
        assert!(toml::from_str::<UsbConfig>("vendorid = 1\n").is_err());
    }

    #[test]
    fn usb_touch_ids_are_refused_saying_what_the_device_is() {
        for (vid, pid) in [(0x2988, 0x0302), (0x2988, 0x0301), (0x0301, 0x2988)] {
            let cfg = UsbConfig {
                vendor_id: vid,
                product_id: pid,
                ..Default::default()
            };
            let e = cfg.validate().unwrap_err().to_string();
            assert!(
                e.contains("usb.vendor_id") && e.contains("Touch") && e.contains("CDC-ACM"),
                "{vid:04x}:{pid:04x}: {e}"
            );
            assert!(e.contains(&format!("{vid:04x}:{pid:04x}")), "{e}");
        }
        assert!(!is_usb_touch(0x1209, 0x0001));
        assert!(!is_usb_touch(0x0301, 0x0001));
        assert_eq!(touch_hint(&[]), "");
        let h = touch_hint(&["2988:0302 at bus 001 device 004".into()]);
        assert!(h.contains("2988:0302") && h.contains("not a bridge"), "{h}");
    }

    #[test]
    fn config_errors_name_the_field() {
        let cases: Vec<(UsbConfig, &str)> = vec![
            (
                UsbConfig {
                    timeout_ms: 0,
                    ..Default::default()
                },
                "usb.timeout_ms",
            ),
            (
                UsbConfig {
                    endpoint_in: 0x01,
                    ..Default::default()
                },
                "usb.endpoint_in",
            ),
            (
                UsbConfig {
                    endpoint_out: 0x82,
                    ..Default::default()
                },
                "usb.endpoint_out",
            ),
            (
                UsbConfig {
                    vendor_id: 0,
                    ..Default::default()
                },
                "usb.vendor_id",
            ),
            (
                UsbConfig {
                    serial: "a b".into(),
                    ..Default::default()
                },
                "usb.serial",
            ),
        ];
        for (cfg, field) in cases {
            let e = cfg.validate().unwrap_err().to_string();
            assert!(e.contains(field), "{e}");
        }
    }

    #[test]
    fn udev_rule_uses_the_configured_ids() {
        let cfg = UsbConfig {
            vendor_id: 0xABCD,
            product_id: 0x0042,
            ..Default::default()
        };
        let rule = cfg.udev_rule();
        assert!(rule.contains("ATTRS{idVendor}==\"abcd\""), "{rule}");
        assert!(rule.contains("ATTRS{idProduct}==\"0042\""), "{rule}");
        assert!(rule.contains("MODE=\"0660\"") && rule.contains("GROUP=\"plugdev\""));
        assert!(cfg.permission_hint().contains("usermod -aG plugdev"));
    }

    #[test]
    fn only_the_configured_ids_match() {
        let cfg = UsbConfig::default();
        assert!(cfg.matches(0x1209, 0x0001));
        assert!(!cfg.matches(0x1209, 0x0002), "wrong product id accepted");
        assert!(!cfg.matches(0x0B99, 0x0001), "wrong vendor id accepted");
    }

    #[test]
    fn shipped_udev_rule_matches_the_default_ids() {
        let file = include_str!("../../udev/99-omnid-usb.rules");
        let rules: Vec<&str> = file
            .lines()
            .filter(|l| !l.trim_start().starts_with('#') && !l.trim().is_empty())
            .collect();
        assert_eq!(rules, [UsbConfig::default().udev_rule().as_str()]);
    }

    #[test]
    fn endpoint_check_names_what_is_wrong() {
        let cfg = UsbConfig::default();
        let good = [(0x01, EndpointKind::Bulk), (0x81, EndpointKind::Bulk)];
        check_endpoints(&cfg, &good).unwrap();
        let e = check_endpoints(
            &cfg,
            &[(0x02, EndpointKind::Bulk), (0x81, EndpointKind::Bulk)],
        )
        .unwrap_err();
        assert!(e.contains("0x01") && e.contains("usb.endpoint_out") && e.contains("0x02"));
        let e = check_endpoints(
            &cfg,
            &[(0x01, EndpointKind::Bulk), (0x81, EndpointKind::Interrupt)],
        )
        .unwrap_err();
        assert!(e.contains("usb.transfer") && e.contains("interrupt"), "{e}");
    }

    #[test]
    fn split_transfers_are_reassembled() {
        let bytes = packets(&[100, 101, 102, 103, 104]);
        let fake = FakeUsb::with(|s| {
            // The first four packets in odd pieces, then packet 104 in three.
            for chunk in bytes[..176].chunks(30) {
                s.script.push_back(In::Bytes(chunk.to_vec()));
            }
            s.script.push_back(In::Bytes(bytes[176..180].to_vec()));
            s.script.push_back(In::Bytes(bytes[180..200].to_vec()));
            s.script.push_back(In::Bytes(bytes[200..].to_vec()));
        });
        let mut dev = omni(&fake);
        let first = dev.exchange(&amps_on(1)).unwrap();
        assert_eq!(first.packet(), &packet(103)[..]);
        let second = dev.exchange(&amps_on(2)).unwrap();
        assert_eq!(second.packet(), &packet(104)[..]);
        assert!((second.device_time_s - first.device_time_s - 1e-3).abs() < 1e-12);
        assert_eq!(fake.state().reads, 6 + 3);
    }

    #[test]
    fn merged_transfers_deliver_the_newest_packet() {
        let fake = FakeUsb::with(|s| {
            s.script.push_back(In::Bytes(packets(&[1, 2, 3, 4])));
            // Two and a half packets, then the rest of the half.
            let b = packets(&[5, 6, 7]);
            s.script.push_back(In::Bytes(b[..110].to_vec()));
            s.script.push_back(In::Bytes(b[110..].to_vec()));
        });
        let mut dev = omni(&fake);
        assert_eq!(dev.exchange(&amps_on(1)).unwrap().packet(), &packet(4)[..]);
        assert_eq!(dev.exchange(&amps_on(2)).unwrap().packet(), &packet(6)[..]);
        assert_eq!(dev.exchange(&amps_on(3)).unwrap().packet(), &packet(7)[..]);
        let st = dev.stats();
        assert_eq!((st.delivered, st.superseded, st.lost), (3, 3 + 1, 0));
    }

    #[test]
    fn counter_gaps_are_counted_and_advance_device_time() {
        let fake = FakeUsb::with(|s| {
            s.script.push_back(In::Bytes(packets(&[10, 11, 12, 13])));
            s.script.push_back(In::Bytes(packets(&[14])));
            s.script.push_back(In::Bytes(packets(&[18])));
            s.script.push_back(In::Bytes(packets(&[19])));
            s.script.push_back(In::Bytes(packets(&[25])));
        });
        let mut dev = omni(&fake);
        let t0 = dev.exchange(&amps_on(1)).unwrap().device_time_s;
        dev.exchange(&amps_on(2)).unwrap();
        let t = dev.exchange(&amps_on(3)).unwrap().device_time_s;
        assert!((t - t0 - 5e-3).abs() < 1e-12, "{t} {t0}");
        dev.exchange(&amps_on(4)).unwrap();
        dev.exchange(&amps_on(5)).unwrap();
        let st = dev.stats();
        assert_eq!((st.gaps, st.lost), (2, 3 + 5));
    }

    #[test]
    fn amps_stay_off_until_a_sample_is_delivered() {
        let fake = FakeUsb::with(|s| {
            s.script.push_back(In::Timeout);
            s.script.push_back(In::Timeout);
            s.auto = Some(0);
        });
        let mut dev = omni(&fake);
        assert!(matches!(
            dev.exchange(&amps_on(1)),
            Err(DeviceError::Missed(_))
        ));
        assert!(matches!(
            dev.exchange(&amps_on(2)),
            Err(DeviceError::Missed(_))
        ));
        dev.exchange(&amps_on(3)).unwrap();
        dev.exchange(&amps_on(4)).unwrap();
        let sent = fake.sent();
        assert_eq!(sent.len(), 4);
        assert!(sent[..3].iter().all(|c| c.is_safe()), "{sent:?}");
        assert!(sent[3].amps_on && sent[3].dac == [0x0900, 0x0700, 0x07FF]);
        // The caller's byte 7 does not matter: the wire carries the drivers' constant.
        assert_wire_discipline(&sent[..3], 3);
        assert_eq!(dev.stats().last_miss, Some(MissReason::ReadTimeout));
    }

    #[test]
    fn a_malformed_command_is_replaced_by_the_safe_packet() {
        let fake = FakeUsb::with(|s| s.auto = Some(0));
        let mut dev = omni(&fake);
        dev.exchange(&amps_on(1)).unwrap();
        let mut bad = amps_on(2);
        bad[9] = 1; // reserved byte
        assert!(matches!(dev.exchange(&bad), Err(DeviceError::Malformed(_))));
        assert!(fake.sent().last().unwrap().is_safe());
    }

    #[test]
    fn unplug_is_disconnected_and_stays_so() {
        let fake = FakeUsb::with(|s| {
            s.script.push_back(In::Bytes(packets(&[0, 1, 2, 3])));
            s.script.push_back(In::Bytes(packets(&[4])));
            s.script.push_back(In::Bytes(packets(&[5])));
            s.script.push_back(In::Unplug);
        });
        let mut dev = omni(&fake);
        for k in 0..3 {
            dev.exchange(&amps_on(k)).unwrap();
        }
        let e = dev.exchange(&amps_on(9)).unwrap_err();
        assert!(matches!(e, DeviceError::Disconnected(_)), "{e}");
        // Once gone, it stays gone without touching the bus.
        let writes = fake.state().writes.len();
        assert!(matches!(
            dev.exchange(&amps_on(10)),
            Err(DeviceError::Disconnected(_))
        ));
        assert_eq!(fake.state().writes.len(), writes);
        dev.close().unwrap();
        assert!(fake.state().released);
    }

    #[test]
    fn close_and_drop_send_the_safe_packet() {
        let fake = FakeUsb::with(|s| s.auto = Some(0));
        let mut dev = omni(&fake);
        dev.exchange(&amps_on(1)).unwrap();
        dev.exchange(&amps_on(2)).unwrap();
        assert!(fake.sent().last().unwrap().amps_on);
        dev.close().unwrap();
        assert!(fake.sent().last().unwrap().is_safe());
        assert!(fake.state().released);
        let n = fake.state().writes.len();
        dev.close().unwrap();
        assert_eq!(fake.state().writes.len(), n, "close is idempotent");

        let fake = FakeUsb::with(|s| s.auto = Some(0));
        {
            let mut dev = omni(&fake);
            dev.exchange(&amps_on(1)).unwrap();
            dev.exchange(&amps_on(2)).unwrap();
        }
        assert!(fake.sent().last().unwrap().is_safe());
        assert!(fake.state().released);
    }

    /// The servo loop over the USB backend: every stop path ends with zero torque and the
    /// amplifiers off on the wire.
    mod servo_stop_paths {
        use super::*;

        fn first_amps_on(sent: &[MotorCommand]) -> usize {
            sent.iter().position(|c| c.amps_on).unwrap_or(sent.len())
        }

        #[test]
        fn end_of_run() {
            let cfg = Config::default();
            let fake = FakeUsb::with(|s| s.auto = Some(7));
            let report = run_servo(
                &cfg,
                Box::new(omni(&fake)),
                200,
                Arc::new(AtomicBool::new(false)),
            );
            assert_eq!(report.end, EndReason::Completed);
            assert!(
                report.shutdown_error.is_none(),
                "{:?}",
                report.shutdown_error
            );
            let sent = fake.sent();
            // The servo asked for torque from its second tick; the wire followed.
            let on = first_amps_on(&sent);
            assert!((1..10).contains(&on), "amps first on at packet {on}");
            assert_wire_discipline(&sent, 1);
            // The loop's own safe packet, then the one close sends.
            assert!(sent[sent.len() - 2].is_safe());
            assert!(fake.state().released);
        }

        #[test]
        fn device_stops_answering_then_fault() {
            let cfg = Config::default();
            let fake = FakeUsb::with(|s| {
                s.auto = Some(0);
                s.silent_after = Some(50);
            });
            let report = run_servo(
                &cfg,
                Box::new(omni(&fake)),
                100_000,
                Arc::new(AtomicBool::new(false)),
            );
            let EndReason::DeviceFault(msg) = &report.end else {
                panic!("expected a device fault, got {:?}", report.end);
            };
            // The loop's own policy (consecutive misses, link-quality floor) decides when;
            // it must be from the misses, within the configured count.
            assert!(msg.contains("packets"), "{msg}");
            let n = report.missed_packets;
            assert!(n >= 1 && n <= u64::from(cfg.safety.max_missed_ticks), "{n}");
            let sent = fake.sent();
            assert!(sent.iter().any(|c| c.amps_on));
            assert_wire_discipline(&sent, 1);
            assert!(report.last_command.is_safe());
        }

        #[test]
        fn operator_stop() {
            let cfg = Config::default();
            let stop = Arc::new(AtomicBool::new(false));
            let fake = FakeUsb::with(|s| {
                s.auto = Some(0);
                s.stop_after = Some((30, stop.clone()));
            });
            let report = run_servo(&cfg, Box::new(omni(&fake)), 100_000, stop);
            assert_eq!(report.end, EndReason::OperatorStop);
            let sent = fake.sent();
            assert!(sent.iter().any(|c| c.amps_on));
            assert_wire_discipline(&sent, 1);
        }

        #[test]
        fn unplug() {
            let cfg = Config::default();
            let fake = FakeUsb::with(|s| {
                s.auto = Some(0);
                s.unplug_after = Some(40);
            });
            let report = run_servo(
                &cfg,
                Box::new(omni(&fake)),
                100_000,
                Arc::new(AtomicBool::new(false)),
            );
            let EndReason::DeviceFault(msg) = &report.end else {
                panic!("expected a device fault, got {:?}", report.end);
            };
            assert!(msg.contains("disconnected"), "{msg}");
            // Once the bridge was known to be gone, no write was even tried (every recorded
            // write went through), and the loop reports that its safe packet could not go.
            assert!(fake.state().writes.iter().all(|(_, ok)| *ok));
            let sent = fake.sent();
            assert!(sent.iter().any(|c| c.amps_on));
            let e = report.shutdown_error.as_deref().unwrap_or("");
            assert!(e.contains("final zero-torque packet"), "{e}");
            assert!(fake.state().released);
        }
    }

    #[test]
    fn no_usb_here_is_not_found_quickly() {
        // This test documents the behaviour on any machine: with no bridge attached (the CI
        // and development machines have none), opening fails with NotFound, saying what was
        // looked for and what to check.
        let cfg = UsbConfig {
            vendor_id: 0xFFFE,
            product_id: 0xFFFD,
            ..Default::default()
        };
        let t = Instant::now();
        let e = match open_usb_with_rate(&cfg, 1000.0) {
            Ok(_) => panic!("a bridge with the unassigned id fffe:fffd opened"),
            Err(e) => e,
        };
        assert!(t.elapsed() < Duration::from_secs(1), "{:?}", t.elapsed());
        let DeviceError::NotFound { looked_for, hint } = &e else {
            panic!("expected NotFound, got {e}");
        };
        assert!(looked_for.contains("fffe:fffd"), "{looked_for}");
        assert!(!hint.is_empty());
    }
}

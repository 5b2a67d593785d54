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
//!
//! Files: `config` (`[firewire]` and the protocol's options), `bus` (the `FireWireBus` trait),
//! `cdev` (the real bus), `protocol` (`FireWireOmni`), `discovery` (finding the node and what
//! to say when it is not there), and the bring-up tools of a first device: `probe` (a guided
//! first contact) and `capture` (recording and reading raw packets).

mod bus;
pub mod capture;
pub(crate) mod cdev;
mod config;
mod discovery;
#[cfg(test)]
pub(crate) mod fake;
pub mod probe;
mod protocol;
pub(crate) mod rate;
pub(crate) mod serial;

pub use bus::*;
pub use config::*;
pub use discovery::*;
pub use protocol::*;

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

#[cfg(test)]
mod tests;

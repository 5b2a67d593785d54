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
//!
//! Files: `config` (`[usb]` and its checks), `protocol` (`UsbOmni` over any `UsbTransport`),
//! `transport` (`RusbTransport`, libusb), `discovery` (finding, checking and opening the
//! bridge, and what to say when it is not there).

mod config;
mod discovery;
mod protocol;
#[cfg(test)]
mod tests;
mod transport;

pub use config::*;
pub(crate) use discovery::*;
pub(crate) use protocol::*;
pub(crate) use transport::*;

//! What the protocol needs of the bus, as a trait: the real one is `cdev::CdevBus`, tests
//! use a fake.

use super::*;
use crate::device::COMMAND_LEN;
use std::os::fd::OwnedFd;
use std::time::Duration;
use thiserror::Error;

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
    /// Hold the unit named `id` for this process, host-wide, for as long as the returned
    /// descriptor lives; refused, naming the holder, while another process holds it. The
    /// kernel lets any number of processes open a FireWire node, so this is what keeps two
    /// arms (of any names) off one Omni (docs/FIREWIRE.md, One process per Omni). A bus that
    /// reaches no real unit holds nothing.
    fn hold_unit(&mut self, id: &str) -> Result<Option<OwnedFd>, String> {
        let _ = id;
        Ok(None)
    }
}

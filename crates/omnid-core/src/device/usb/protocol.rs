//! The bridge's protocol, over any transport: framing, counter checks, the command gate and
//! the safe packet on close.

use super::*;
use crate::device::stream::{CommandGate, CounterTracker, Framer, StreamStats};
use crate::device::{Device, DeviceError, MissReason, RawSample, COMMAND_LEN, STATE_LEN};
use std::time::{Duration, Instant};
use thiserror::Error;

/// Size of one read; a transfer may carry several packets.
pub(crate) const READ_BUF_LEN: usize = 1024;

/// Reads tried per exchange before it counts as missed (a bound for a device that trickles
/// bytes that never make a packet).
pub(crate) const MAX_READS_PER_EXCHANGE: usize = 64;

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
    pub(super) fn stats(&self) -> StreamStats {
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

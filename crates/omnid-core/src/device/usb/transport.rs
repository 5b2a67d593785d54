//! The real transport: libusb through rusb.

use super::*;
use std::time::Duration;

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
    pub(super) handle: rusb::DeviceHandle<rusb::Context>,
    pub(super) interface: u8,
    pub(super) endpoint_out: u8,
    pub(super) endpoint_in: u8,
    pub(super) transfer: UsbTransfer,
    pub(super) reattach_kernel_driver: bool,
    pub(super) released: bool,
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

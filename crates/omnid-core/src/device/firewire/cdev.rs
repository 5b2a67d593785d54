//! Linux firewire-cdev: the ABI of `<linux/firewire-cdev.h>` (structures, ioctl numbers,
//! constants) and [`CdevBus`], the real [`FireWireBus`] on a `/dev/fwN` node.
//!
//! Every `#[repr(C)]` structure and ioctl number here is checked against the installed kernel
//! header by a test that compiles a C program printing `sizeof`/`offsetof` and the `_IOW`/
//! `_IOR`/`_IOWR` values (see the tests at the end).
//!
//! Three file descriptors on the node: one for register transactions, channel allocation and
//! bus-reset events, one per iso context (the kernel allows one context per descriptor). The
//! receive context fills a ring of 32 slots of an mmap()ed buffer, one packet per slot, with an
//! interrupt per packet; the transmit context sends one queued 16-byte packet per command.
//! Nothing in `send_packet`/`next_packet` allocates.

#![allow(non_camel_case_types)]

use super::{BusError, BusEvent, FireWireBus, NodeAccess, NodeInfo, PacketInfo, ISO_PAYLOAD_MAX};
use crate::device::COMMAND_LEN;
use std::ffi::CString;
use std::mem::{offset_of, size_of};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd, RawFd};
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Where sysfs lists FireWire nodes (`fw1/vendor`, `fw1/guid`, ...).
pub const SYSFS_FIREWIRE_DEVICES: &str = "/sys/bus/firewire/devices";

// ---- Constants of <linux/firewire-cdev.h> and <linux/firewire-constants.h>.

pub const FW_CDEV_EVENT_BUS_RESET: u32 = 0x00;
pub const FW_CDEV_EVENT_RESPONSE: u32 = 0x01;
pub const FW_CDEV_EVENT_ISO_INTERRUPT: u32 = 0x03;
pub const FW_CDEV_EVENT_ISO_RESOURCE_ALLOCATED: u32 = 0x04;
pub const FW_CDEV_EVENT_ISO_RESOURCE_DEALLOCATED: u32 = 0x05;

pub const FW_CDEV_ISO_CONTEXT_TRANSMIT: u32 = 0;
pub const FW_CDEV_ISO_CONTEXT_RECEIVE: u32 = 1;
pub const FW_CDEV_ISO_INTERRUPT: u32 = 1 << 16;
pub const FW_CDEV_ISO_CONTEXT_MATCH_ALL_TAGS: u32 = 15;

pub const fn fw_cdev_iso_payload_length(v: u32) -> u32 {
    v
}
pub const fn fw_cdev_iso_tag(v: u32) -> u32 {
    v << 18
}
pub const fn fw_cdev_iso_sy(v: u32) -> u32 {
    v << 20
}
pub const fn fw_cdev_iso_header_length(v: u32) -> u32 {
    v << 24
}

pub const TCODE_WRITE_QUADLET_REQUEST: u32 = 0x0;
pub const TCODE_WRITE_BLOCK_REQUEST: u32 = 0x1;
pub const TCODE_READ_QUADLET_REQUEST: u32 = 0x4;
pub const TCODE_READ_BLOCK_REQUEST: u32 = 0x5;
pub const RCODE_COMPLETE: u32 = 0x0;
pub const RCODE_CONFLICT_ERROR: u32 = 0x4;
pub const RCODE_BUSY: u32 = 0x12;
pub const RCODE_GENERATION: u32 = 0x13;
pub const SCODE_100: u32 = 0x0;

/// The ABI version this client is written for (told to the kernel in GET_INFO).
pub const CLIENT_ABI_VERSION: u32 = 5;

// ---- Structures.

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_get_info {
    pub version: u32,
    pub rom_length: u32,
    pub rom: u64,
    pub bus_reset: u64,
    pub bus_reset_closure: u64,
    pub card: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_send_request {
    pub tcode: u32,
    pub length: u32,
    pub offset: u64,
    pub closure: u64,
    pub data: u64,
    pub generation: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_event_common {
    pub closure: u64,
    pub type_: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_event_bus_reset {
    pub closure: u64,
    pub type_: u32,
    pub node_id: u32,
    pub local_node_id: u32,
    pub bm_node_id: u32,
    pub irm_node_id: u32,
    pub root_node_id: u32,
    pub generation: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_event_response {
    pub closure: u64,
    pub type_: u32,
    pub rcode: u32,
    pub length: u32,
    pub data: [u32; 0],
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_event_iso_interrupt {
    pub closure: u64,
    pub type_: u32,
    pub cycle: u32,
    pub header_length: u32,
    pub header: [u32; 0],
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_event_iso_resource {
    pub closure: u64,
    pub type_: u32,
    pub handle: u32,
    pub channel: i32,
    pub bandwidth: i32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_create_iso_context {
    pub type_: u32,
    pub header_size: u32,
    pub channel: u32,
    pub speed: u32,
    pub closure: u64,
    pub handle: u32,
}

/// Kept for the layout test only: the iso queue writes these descriptors (header-less,
/// so one control word each) straight into a `u32` slice.
#[cfg(test)]
#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_iso_packet {
    pub control: u32,
    pub header: [u32; 0],
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_queue_iso {
    pub packets: u64,
    pub data: u64,
    pub size: u32,
    pub handle: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_start_iso {
    pub cycle: i32,
    pub sync: u32,
    pub tags: u32,
    pub handle: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_stop_iso {
    pub handle: u32,
}

#[repr(C)]
#[derive(Debug, Default, Clone, Copy)]
pub struct fw_cdev_allocate_iso_resource {
    pub closure: u64,
    pub channels: u64,
    pub bandwidth: u32,
    pub handle: u32,
}

// ---- ioctl numbers: _IOC(dir, type, nr, size) as <asm-generic/ioctl.h> (and the arches with
// their own layout).

#[cfg(any(
    target_arch = "powerpc",
    target_arch = "powerpc64",
    target_arch = "mips",
    target_arch = "mips64",
    target_arch = "sparc",
    target_arch = "sparc64"
))]
mod ioc {
    pub const SIZEBITS: u32 = 13;
    pub const WRITE: u32 = 4;
    pub const READ: u32 = 2;
}
#[cfg(not(any(
    target_arch = "powerpc",
    target_arch = "powerpc64",
    target_arch = "mips",
    target_arch = "mips64",
    target_arch = "sparc",
    target_arch = "sparc64"
)))]
mod ioc {
    pub const SIZEBITS: u32 = 14;
    pub const WRITE: u32 = 1;
    pub const READ: u32 = 2;
}

const fn ioc(dir: u32, nr: u32, size: usize) -> u32 {
    const TYPE: u32 = b'#' as u32;
    (dir << (16 + ioc::SIZEBITS)) | ((size as u32) << 16) | (TYPE << 8) | nr
}
const fn iow<T>(nr: u32) -> u32 {
    ioc(ioc::WRITE, nr, size_of::<T>())
}
const fn iowr<T>(nr: u32) -> u32 {
    ioc(ioc::READ | ioc::WRITE, nr, size_of::<T>())
}

pub const FW_CDEV_IOC_GET_INFO: u32 = iowr::<fw_cdev_get_info>(0x00);
pub const FW_CDEV_IOC_SEND_REQUEST: u32 = iow::<fw_cdev_send_request>(0x01);
pub const FW_CDEV_IOC_CREATE_ISO_CONTEXT: u32 = iowr::<fw_cdev_create_iso_context>(0x08);
pub const FW_CDEV_IOC_QUEUE_ISO: u32 = iowr::<fw_cdev_queue_iso>(0x09);
pub const FW_CDEV_IOC_START_ISO: u32 = iow::<fw_cdev_start_iso>(0x0a);
pub const FW_CDEV_IOC_STOP_ISO: u32 = iow::<fw_cdev_stop_iso>(0x0b);
pub const FW_CDEV_IOC_ALLOCATE_ISO_RESOURCE_ONCE: u32 = iow::<fw_cdev_allocate_iso_resource>(0x0f);
pub const FW_CDEV_IOC_DEALLOCATE_ISO_RESOURCE_ONCE: u32 =
    iow::<fw_cdev_allocate_iso_resource>(0x10);

// ---- Helpers.

/// Channels the IRM may give us: 0..=62 except 31 (the usual broadcast channel); 63 is
/// reserved.
pub const CHANNEL_CANDIDATES: u64 = ((1u64 << 63) - 1) & !(1u64 << 31);

/// Receive ring: slots of this many bytes (≥ one Omni packet, ≤ ISO_PAYLOAD_MAX).
pub const RX_SLOT: usize = 128;
pub const RX_SLOTS: usize = 32;
/// Bytes per received packet returned beside the payload: iso header + timestamp.
pub const RX_HEADER_SIZE: usize = 8;
pub const TX_SLOTS: usize = 256;
/// Bytes of iso buffer the contexts use; the mapping is this rounded up to whole pages.
const RX_BYTES: usize = RX_SLOT * RX_SLOTS;
const TX_BYTES: usize = COMMAND_LEN * TX_SLOTS;
const _: () = assert!(RX_SLOT <= ISO_PAYLOAD_MAX);

/// The mmap length for `bytes` of iso buffer: the kernel maps whole pages, and a length that
/// is not a multiple of the page size (16 KiB and 64 KiB on some arm64 kernels) is refused.
pub fn map_len(bytes: usize, page: usize) -> usize {
    let page = page.max(1);
    bytes.max(1).div_ceil(page) * page
}

/// The kernel's page size (4096 if it cannot be asked).
fn page_size() -> usize {
    // SAFETY: sysconf has no preconditions.
    let p = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    if p > 0 {
        p as usize
    } else {
        4096
    }
}

const EVENT_BUF_WORDS: usize = 1024;

fn errno() -> i32 {
    std::io::Error::last_os_error().raw_os_error().unwrap_or(0)
}

fn os_error(op: &'static str, errno: i32) -> BusError {
    match errno {
        libc::ENODEV => BusError::Gone,
        libc::EACCES | libc::EPERM => BusError::Permission,
        _ => BusError::Os { op, errno },
    }
}

/// ioctl with a pointer argument; `Err(errno)` on failure.
///
/// # Safety
/// `arg` must be the structure the request expects, valid for reads and writes.
unsafe fn ioctl_ptr<T>(fd: RawFd, request: u32, arg: *mut T) -> Result<(), i32> {
    // The request type is c_ulong on glibc and c_int on musl: the cast keeps the bits.
    let r = libc::ioctl(fd, request as libc::Ioctl, arg);
    if r < 0 {
        Err(errno())
    } else {
        Ok(())
    }
}

fn open_node(path: &Path) -> Result<OwnedFd, BusError> {
    let c = CString::new(path.as_os_str().as_bytes()).map_err(|_| BusError::Os {
        op: "open",
        errno: libc::EINVAL,
    })?;
    // SAFETY: a valid NUL-terminated path; the descriptor is owned from here on.
    let fd = unsafe { libc::open(c.as_ptr(), libc::O_RDWR | libc::O_CLOEXEC) };
    if fd < 0 {
        let e = errno();
        return Err(match e {
            libc::ENOENT | libc::ENXIO => BusError::Gone,
            e => os_error("open", e),
        });
    }
    // SAFETY: fd was just returned by open and is not owned elsewhere.
    Ok(unsafe { OwnedFd::from_raw_fd(fd) })
}

/// GET_INFO: starts bus-reset events on `fd`; fills the config ROM (host-endian quadlets, as
/// the kernel keeps it) and returns the current bus-reset state and the ROM length in bytes.
fn get_info(
    fd: RawFd,
    rom: Option<&mut [u32]>,
) -> Result<(fw_cdev_event_bus_reset, usize), BusError> {
    let mut reset = fw_cdev_event_bus_reset::default();
    let (rom_ptr, rom_len) = match rom {
        Some(r) => (r.as_mut_ptr() as u64, (r.len() * 4) as u32),
        None => (0, 0),
    };
    let mut info = fw_cdev_get_info {
        version: CLIENT_ABI_VERSION,
        rom_length: rom_len,
        rom: rom_ptr,
        bus_reset: &mut reset as *mut _ as u64,
        bus_reset_closure: 0,
        card: 0,
    };
    // SAFETY: info points to a live fw_cdev_get_info; rom and reset outlive the call.
    unsafe { ioctl_ptr(fd, FW_CDEV_IOC_GET_INFO, &mut info) }
        .map_err(|e| os_error("FW_CDEV_IOC_GET_INFO", e))?;
    Ok((reset, info.rom_length as usize))
}

/// The vendor id in a config ROM (bus info block, quadlet 3 bits 31..8), or the 24-bit
/// vendor of a minimal ROM.
pub fn rom_vendor(rom: &[u32]) -> Option<u32> {
    let first = *rom.first()?;
    match first >> 24 {
        1 => Some(first & 0x00FF_FFFF),
        n if n >= 4 && rom.len() >= 4 && rom[1] == 0x3133_3934 => Some(rom[3] >> 8),
        _ => None,
    }
}

/// Read the config-ROM vendor of a node through the node itself.
pub fn read_rom_vendor(path: &Path) -> Result<Option<u32>, BusError> {
    Ok(rom_vendor(&read_rom(path)?))
}

/// The first quadlets (up to 16) of a node's config ROM, as the kernel keeps them.
pub fn read_rom(path: &Path) -> Result<Vec<u32>, BusError> {
    let fd = open_node(path)?;
    let mut rom = [0u32; 16];
    let (_, len) = get_info(fd.as_raw_fd(), Some(&mut rom))?;
    Ok(rom[..(len / 4).min(rom.len())].to_vec())
}

/// A page of mmap()ed iso buffer.
struct Mapping {
    ptr: *mut u8,
    len: usize,
}

// SAFETY: the mapping is owned by one CdevBus and only touched through &mut self.
unsafe impl Send for Mapping {}

impl Mapping {
    fn new(fd: RawFd, len: usize, writable: bool) -> Result<Self, BusError> {
        // Read-only maps make the kernel map the buffer for reception, writable ones for
        // transmission.
        let prot = if writable {
            libc::PROT_READ | libc::PROT_WRITE
        } else {
            libc::PROT_READ
        };
        // SAFETY: mapping a fresh region of the descriptor; checked below.
        let ptr = unsafe { libc::mmap(std::ptr::null_mut(), len, prot, libc::MAP_SHARED, fd, 0) };
        if ptr == libc::MAP_FAILED {
            return Err(os_error("mmap", errno()));
        }
        Ok(Mapping {
            ptr: ptr as *mut u8,
            len,
        })
    }

    fn addr(&self, offset: usize) -> u64 {
        self.ptr as u64 + offset as u64
    }
}

impl Drop for Mapping {
    fn drop(&mut self) {
        // SAFETY: ptr/len are exactly what mmap returned.
        unsafe {
            libc::munmap(self.ptr as *mut libc::c_void, self.len);
        }
    }
}

/// Event buffer, 8-byte aligned for the u64 closures.
struct EventBuf {
    words: [u64; EVENT_BUF_WORDS],
}

impl EventBuf {
    fn bytes(&self) -> &[u8] {
        // SAFETY: viewing initialised u64s as bytes.
        unsafe { std::slice::from_raw_parts(self.words.as_ptr() as *const u8, EVENT_BUF_WORDS * 8) }
    }
    fn bytes_mut(&mut self) -> &mut [u8] {
        // SAFETY: as above; any byte pattern is a valid u64.
        unsafe {
            std::slice::from_raw_parts_mut(self.words.as_mut_ptr() as *mut u8, EVENT_BUF_WORDS * 8)
        }
    }
    fn u32_at(&self, at: usize) -> u32 {
        let b = self.bytes();
        u32::from_ne_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
    }
    fn u64_at(&self, at: usize) -> u64 {
        let b = self.bytes();
        let mut x = [0u8; 8];
        x.copy_from_slice(&b[at..at + 8]);
        u64::from_ne_bytes(x)
    }
}

/// Read one event from `fd` into `buf`; returns its length. Call only when `fd` is readable
/// (the kernel's read blocks until an event is there).
fn read_event(fd: RawFd, buf: &mut EventBuf) -> Result<usize, BusError> {
    let bytes = buf.bytes_mut();
    // SAFETY: reading into our own buffer of the given length.
    let n = unsafe { libc::read(fd, bytes.as_mut_ptr() as *mut libc::c_void, bytes.len()) };
    if n < 0 {
        return Err(os_error("read", errno()));
    }
    Ok(n as usize)
}

/// Wait until one of `fds` is readable; returns which (bit mask), 0 on timeout.
fn wait_readable(fds: &[RawFd], timeout: Duration) -> Result<u32, BusError> {
    let mut p = [libc::pollfd {
        fd: -1,
        events: 0,
        revents: 0,
    }; 2];
    for (slot, &fd) in p.iter_mut().zip(fds) {
        slot.fd = fd;
        slot.events = libc::POLLIN;
    }
    let ts = libc::timespec {
        tv_sec: timeout.as_secs() as libc::time_t,
        tv_nsec: timeout.subsec_nanos() as libc::c_long,
    };
    loop {
        // SAFETY: p holds fds.len() ≤ 2 initialised entries; ts is a valid timespec.
        let r = unsafe {
            libc::ppoll(
                p.as_mut_ptr(),
                fds.len() as libc::nfds_t,
                &ts,
                std::ptr::null(),
            )
        };
        if r < 0 {
            let e = errno();
            if e == libc::EINTR {
                continue;
            }
            return Err(os_error("ppoll", e));
        }
        let mut mask = 0;
        for (i, slot) in p.iter().take(fds.len()).enumerate() {
            if slot.revents & (libc::POLLHUP | libc::POLLERR) != 0 {
                return Err(BusError::Gone);
            }
            if slot.revents & libc::POLLIN != 0 {
                mask |= 1 << i;
            }
        }
        return Ok(mask);
    }
}

struct IsoRx {
    fd: OwnedFd,
    map: Mapping,
    handle: u32,
    /// Slot of the next completed packet.
    next_slot: usize,
    /// Completed packets not yet handed out (in slot order): iso header and timestamp.
    pending: [(u32, u16); RX_SLOTS],
    pending_head: usize,
    pending_count: usize,
}

struct IsoTx {
    fd: OwnedFd,
    map: Mapping,
    handle: u32,
    next_slot: usize,
    outstanding: usize,
    started: bool,
}

/// The real bus: firewire-cdev ioctls on one node.
pub struct CdevBus {
    path: PathBuf,
    ctl: OwnedFd,
    generation: u32,
    register_timeout: Duration,
    closure_seq: u64,
    events: Box<EventBuf>,
    rx: Option<IsoRx>,
    tx: Option<IsoTx>,
}

impl CdevBus {
    /// Open the node and learn the bus generation.
    pub fn open(path: &Path, register_timeout: Duration) -> Result<Self, BusError> {
        let ctl = open_node(path)?;
        let (reset, _) = get_info(ctl.as_raw_fd(), None)?;
        Ok(CdevBus {
            path: path.to_path_buf(),
            ctl,
            generation: reset.generation,
            register_timeout,
            closure_seq: 0,
            events: Box::new(EventBuf {
                words: [0; EVENT_BUF_WORDS],
            }),
            rx: None,
            tx: None,
        })
    }

    fn next_closure(&mut self) -> u64 {
        // Closures start at 1 so that 0 (the iso contexts') never matches a request.
        self.closure_seq += 1;
        self.closure_seq
    }

    /// Read events from the control descriptor until `want` accepts one, a bus reset comes
    /// (reported as `BusReset`), or the register timeout passes.
    fn wait_ctl<R>(
        &mut self,
        mut want: impl FnMut(&EventBuf, usize) -> Option<R>,
    ) -> Result<R, BusError> {
        let deadline = Instant::now() + self.register_timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(BusError::Timeout);
            }
            if wait_readable(&[self.ctl.as_raw_fd()], left)? == 0 {
                return Err(BusError::Timeout);
            }
            let n = read_event(self.ctl.as_raw_fd(), &mut self.events)?;
            if n < size_of::<fw_cdev_event_common>() {
                continue;
            }
            let kind = self.events.u32_at(offset_of!(fw_cdev_event_common, type_));
            if kind == FW_CDEV_EVENT_BUS_RESET {
                self.generation = self
                    .events
                    .u32_at(offset_of!(fw_cdev_event_bus_reset, generation));
                return Err(BusError::BusReset);
            }
            if let Some(r) = want(&self.events, n) {
                return Ok(r);
            }
        }
    }

    /// One asynchronous transaction; read data lands in `data`.
    fn transact(&mut self, tcode: u32, offset: u64, data: &mut [u8]) -> Result<(), BusError> {
        let closure = self.next_closure();
        let mut req = fw_cdev_send_request {
            tcode,
            length: data.len() as u32,
            offset,
            closure,
            data: data.as_mut_ptr() as u64,
            generation: self.generation,
        };
        // SAFETY: req is a live fw_cdev_send_request; the kernel copies the payload during
        // the call.
        unsafe { ioctl_ptr(self.ctl.as_raw_fd(), FW_CDEV_IOC_SEND_REQUEST, &mut req) }
            .map_err(|e| os_error("FW_CDEV_IOC_SEND_REQUEST", e))?;
        let (rcode, len) = self.wait_ctl(|ev, n| {
            let kind = ev.u32_at(offset_of!(fw_cdev_event_common, type_));
            let ours = ev.u64_at(offset_of!(fw_cdev_event_common, closure)) == closure;
            (kind == FW_CDEV_EVENT_RESPONSE && ours && n >= size_of::<fw_cdev_event_response>())
                .then(|| {
                    (
                        ev.u32_at(offset_of!(fw_cdev_event_response, rcode)),
                        ev.u32_at(offset_of!(fw_cdev_event_response, length)) as usize,
                    )
                })
        })?;
        match rcode {
            RCODE_COMPLETE => {
                if tcode == TCODE_READ_QUADLET_REQUEST || tcode == TCODE_READ_BLOCK_REQUEST {
                    let at = offset_of!(fw_cdev_event_response, data);
                    let n = len.min(data.len());
                    data[..n].copy_from_slice(&self.events.bytes()[at..at + n]);
                }
                Ok(())
            }
            RCODE_GENERATION => Err(BusError::BusReset),
            RCODE_BUSY | RCODE_CONFLICT_ERROR => Err(BusError::Busy(rcode)),
            r => Err(BusError::Rcode(r)),
        }
    }

    fn iso_resource(
        &mut self,
        request: u32,
        channels: u64,
        want_kind: u32,
    ) -> Result<i32, BusError> {
        let closure = self.next_closure();
        let mut a = fw_cdev_allocate_iso_resource {
            closure,
            channels,
            bandwidth: 0,
            handle: 0,
        };
        // SAFETY: a is a live fw_cdev_allocate_iso_resource.
        unsafe { ioctl_ptr(self.ctl.as_raw_fd(), request, &mut a) }
            .map_err(|e| os_error("FW_CDEV_IOC_(DE)ALLOCATE_ISO_RESOURCE_ONCE", e))?;
        self.wait_ctl(|ev, n| {
            let kind = ev.u32_at(offset_of!(fw_cdev_event_common, type_));
            let ours = ev.u64_at(offset_of!(fw_cdev_event_common, closure)) == closure;
            (kind == want_kind && ours && n >= size_of::<fw_cdev_event_iso_resource>())
                .then(|| ev.u32_at(offset_of!(fw_cdev_event_iso_resource, channel)) as i32)
        })
    }

    fn create_context(
        fd: RawFd,
        kind: u32,
        channel: u8,
        header_size: u32,
    ) -> Result<u32, BusError> {
        let mut c = fw_cdev_create_iso_context {
            type_: kind,
            header_size,
            channel: u32::from(channel),
            speed: SCODE_100,
            closure: 0,
            handle: 0,
        };
        // SAFETY: c is a live fw_cdev_create_iso_context.
        unsafe { ioctl_ptr(fd, FW_CDEV_IOC_CREATE_ISO_CONTEXT, &mut c) }
            .map_err(|e| os_error("FW_CDEV_IOC_CREATE_ISO_CONTEXT", e))?;
        Ok(c.handle)
    }

    fn queue(fd: RawFd, handle: u32, controls: &mut [u32], data: u64) -> Result<(), BusError> {
        let mut q = fw_cdev_queue_iso {
            packets: controls.as_mut_ptr() as u64,
            data,
            size: std::mem::size_of_val(controls) as u32,
            handle,
        };
        // SAFETY: q points at `controls` (header-less iso packet descriptors) and into our
        // own mapping; both outlive the call.
        unsafe { ioctl_ptr(fd, FW_CDEV_IOC_QUEUE_ISO, &mut q) }
            .map_err(|e| os_error("FW_CDEV_IOC_QUEUE_ISO", e))?;
        if q.size != 0 {
            // The kernel did not take every descriptor.
            return Err(BusError::Os {
                op: "FW_CDEV_IOC_QUEUE_ISO (queue full)",
                errno: libc::ENOSPC,
            });
        }
        Ok(())
    }

    fn start_context(fd: RawFd, handle: u32, tags: u32) -> Result<(), BusError> {
        let mut s = fw_cdev_start_iso {
            cycle: -1,
            sync: 0,
            tags,
            handle,
        };
        // SAFETY: s is a live fw_cdev_start_iso.
        unsafe { ioctl_ptr(fd, FW_CDEV_IOC_START_ISO, &mut s) }
            .map_err(|e| os_error("FW_CDEV_IOC_START_ISO", e))
    }

    fn stop_context(fd: RawFd, handle: u32) -> Result<(), BusError> {
        let mut s = fw_cdev_stop_iso { handle };
        // SAFETY: s is a live fw_cdev_stop_iso.
        unsafe { ioctl_ptr(fd, FW_CDEV_IOC_STOP_ISO, &mut s) }
            .map_err(|e| os_error("FW_CDEV_IOC_STOP_ISO", e))
    }

    fn open_rx(&self, channel: u8) -> Result<IsoRx, BusError> {
        let fd = open_node(&self.path)?;
        get_info(fd.as_raw_fd(), None)?;
        let handle = Self::create_context(
            fd.as_raw_fd(),
            FW_CDEV_ISO_CONTEXT_RECEIVE,
            channel,
            RX_HEADER_SIZE as u32,
        )?;
        let map = Mapping::new(fd.as_raw_fd(), map_len(RX_BYTES, page_size()), false)?;
        let mut controls = [0u32; RX_SLOTS];
        for c in controls.iter_mut() {
            *c = rx_control();
        }
        Self::queue(fd.as_raw_fd(), handle, &mut controls, map.addr(0))?;
        Self::start_context(fd.as_raw_fd(), handle, FW_CDEV_ISO_CONTEXT_MATCH_ALL_TAGS)?;
        Ok(IsoRx {
            fd,
            map,
            handle,
            next_slot: 0,
            pending: [(0, 0); RX_SLOTS],
            pending_head: 0,
            pending_count: 0,
        })
    }

    fn open_tx(&self, channel: u8) -> Result<IsoTx, BusError> {
        let fd = open_node(&self.path)?;
        get_info(fd.as_raw_fd(), None)?;
        let handle =
            Self::create_context(fd.as_raw_fd(), FW_CDEV_ISO_CONTEXT_TRANSMIT, channel, 0)?;
        let map = Mapping::new(fd.as_raw_fd(), map_len(TX_BYTES, page_size()), true)?;
        Ok(IsoTx {
            fd,
            map,
            handle,
            next_slot: 0,
            outstanding: 0,
            started: false,
        })
    }

    /// Count transmitted packets from the transmit context's interrupt events.
    fn drain_tx(tx: &mut IsoTx, events: &mut EventBuf, wait: Duration) -> Result<(), BusError> {
        let mut wait = wait;
        while wait_readable(&[tx.fd.as_raw_fd()], wait)? != 0 {
            let n = read_event(tx.fd.as_raw_fd(), events)?;
            wait = Duration::ZERO;
            if n < size_of::<fw_cdev_event_iso_interrupt>() {
                continue;
            }
            if events.u32_at(offset_of!(fw_cdev_event_common, type_)) == FW_CDEV_EVENT_ISO_INTERRUPT
            {
                // ABI ≥ 3: one timestamp quadlet per completed packet; each packet interrupts.
                let done = (events.u32_at(offset_of!(fw_cdev_event_iso_interrupt, header_length))
                    / 4)
                .max(1) as usize;
                tx.outstanding = tx.outstanding.saturating_sub(done);
            }
        }
        Ok(())
    }
}

fn rx_control() -> u32 {
    fw_cdev_iso_payload_length(RX_SLOT as u32)
        | FW_CDEV_ISO_INTERRUPT
        | fw_cdev_iso_header_length(RX_HEADER_SIZE as u32)
}

impl FireWireBus for CdevBus {
    fn hold_unit(&mut self, id: &str) -> Result<Option<OwnedFd>, String> {
        crate::arm::lock::hold(id).map(Some)
    }

    fn read_quadlet(&mut self, offset: u64) -> Result<u32, BusError> {
        let mut b = [0u8; 4];
        self.transact(TCODE_READ_QUADLET_REQUEST, offset, &mut b)?;
        Ok(u32::from_be_bytes(b))
    }

    fn write_quadlet(&mut self, offset: u64, value: u32) -> Result<(), BusError> {
        let mut b = value.to_be_bytes();
        self.transact(TCODE_WRITE_QUADLET_REQUEST, offset, &mut b)
    }

    fn read_byte(&mut self, offset: u64) -> Result<u8, BusError> {
        let mut b = [0u8; 1];
        self.transact(TCODE_READ_BLOCK_REQUEST, offset, &mut b)?;
        Ok(b[0])
    }

    fn write_byte(&mut self, offset: u64, value: u8) -> Result<(), BusError> {
        let mut b = [value];
        self.transact(TCODE_WRITE_BLOCK_REQUEST, offset, &mut b)
    }

    fn allocate_channel(&mut self) -> Result<u8, BusError> {
        let ch = self.iso_resource(
            FW_CDEV_IOC_ALLOCATE_ISO_RESOURCE_ONCE,
            CHANNEL_CANDIDATES,
            FW_CDEV_EVENT_ISO_RESOURCE_ALLOCATED,
        )?;
        u8::try_from(ch).map_err(|_| BusError::NoChannel)
    }

    fn free_channel(&mut self, channel: u8) -> Result<(), BusError> {
        self.iso_resource(
            FW_CDEV_IOC_DEALLOCATE_ISO_RESOURCE_ONCE,
            1u64 << (channel & 63),
            FW_CDEV_EVENT_ISO_RESOURCE_DEALLOCATED,
        )
        .map(|_| ())
    }

    fn start_iso(&mut self, receive_channel: u8, transmit_channel: u8) -> Result<(), BusError> {
        self.rx = None;
        self.tx = None;
        self.rx = Some(self.open_rx(receive_channel)?);
        self.tx = Some(self.open_tx(transmit_channel)?);
        Ok(())
    }

    fn stop_iso(&mut self) -> Result<(), BusError> {
        let mut result = Ok(());
        if let Some(mut tx) = self.tx.take() {
            // Let the last queued packet (the safe one) go out first.
            let deadline = Instant::now() + Duration::from_millis(10);
            while tx.outstanding > 0 {
                let left = deadline.saturating_duration_since(Instant::now());
                if left.is_zero() || Self::drain_tx(&mut tx, &mut self.events, left).is_err() {
                    break;
                }
            }
            if tx.started {
                result = Self::stop_context(tx.fd.as_raw_fd(), tx.handle);
            }
        }
        if let Some(rx) = self.rx.take() {
            let r = Self::stop_context(rx.fd.as_raw_fd(), rx.handle);
            if result.is_ok() {
                result = r;
            }
        }
        result
    }

    fn send_packet(&mut self, packet: &[u8; COMMAND_LEN]) -> Result<(), BusError> {
        let Some(tx) = self.tx.as_mut() else {
            return Err(BusError::NotStreaming);
        };
        Self::drain_tx(tx, &mut self.events, Duration::ZERO)?;
        if tx.outstanding >= TX_SLOTS - 1 {
            return Err(BusError::TxStalled);
        }
        let at = tx.next_slot * COMMAND_LEN;
        // SAFETY: the slot lies inside our writable mapping (checked by the const assert).
        unsafe {
            std::ptr::copy_nonoverlapping(packet.as_ptr(), tx.map.ptr.add(at), COMMAND_LEN);
        }
        let mut control = [fw_cdev_iso_payload_length(COMMAND_LEN as u32)
            | FW_CDEV_ISO_INTERRUPT
            | fw_cdev_iso_tag(0)
            | fw_cdev_iso_sy(0)
            | fw_cdev_iso_header_length(0)];
        Self::queue(tx.fd.as_raw_fd(), tx.handle, &mut control, tx.map.addr(at))?;
        tx.outstanding += 1;
        tx.next_slot = (tx.next_slot + 1) % TX_SLOTS;
        if !tx.started {
            Self::start_context(tx.fd.as_raw_fd(), tx.handle, 0)?;
            tx.started = true;
        }
        Ok(())
    }

    fn next_packet(
        &mut self,
        buf: &mut [u8; ISO_PAYLOAD_MAX],
        timeout: Duration,
    ) -> Result<BusEvent, BusError> {
        let deadline = Instant::now() + timeout;
        loop {
            let Some(rx) = self.rx.as_mut() else {
                return Err(BusError::NotStreaming);
            };
            if rx.pending_count > 0 {
                let (iso_header, timestamp) = rx.pending[rx.pending_head];
                let len = ((iso_header >> 16) as usize).min(RX_SLOT);
                let at = rx.next_slot * RX_SLOT;
                // SAFETY: the slot lies inside our mapping; the kernel has completed it.
                let slot = unsafe { std::slice::from_raw_parts(rx.map.ptr.add(at), RX_SLOT) };
                buf[..len].copy_from_slice(&slot[..len]);
                rx.pending_head = (rx.pending_head + 1) % RX_SLOTS;
                rx.pending_count -= 1;
                // Give the slot back to the controller.
                let mut control = [rx_control()];
                Self::queue(rx.fd.as_raw_fd(), rx.handle, &mut control, rx.map.addr(at))?;
                rx.next_slot = (rx.next_slot + 1) % RX_SLOTS;
                return Ok(BusEvent::Packet(PacketInfo {
                    len,
                    iso_header,
                    timestamp,
                }));
            }
            let rx_fd = rx.fd.as_raw_fd();
            let left = deadline.saturating_duration_since(Instant::now());
            let ready = wait_readable(&[self.ctl.as_raw_fd(), rx_fd], left)?;
            if ready == 0 {
                return Ok(BusEvent::Timeout);
            }
            if ready & 1 != 0 {
                let n = read_event(self.ctl.as_raw_fd(), &mut self.events)?;
                if n >= size_of::<fw_cdev_event_bus_reset>()
                    && self.events.u32_at(offset_of!(fw_cdev_event_common, type_))
                        == FW_CDEV_EVENT_BUS_RESET
                {
                    self.generation = self
                        .events
                        .u32_at(offset_of!(fw_cdev_event_bus_reset, generation));
                    return Ok(BusEvent::BusReset);
                }
                // Anything else on the control descriptor is a late answer: drop it.
            }
            if ready & 2 != 0 {
                let n = read_event(rx_fd, &mut self.events)?;
                let Some(rx) = self.rx.as_mut() else {
                    return Err(BusError::NotStreaming);
                };
                if n >= size_of::<fw_cdev_event_iso_interrupt>()
                    && self.events.u32_at(offset_of!(fw_cdev_event_common, type_))
                        == FW_CDEV_EVENT_ISO_INTERRUPT
                {
                    let hl = self
                        .events
                        .u32_at(offset_of!(fw_cdev_event_iso_interrupt, header_length))
                        as usize;
                    let base = offset_of!(fw_cdev_event_iso_interrupt, header);
                    let count = (hl / RX_HEADER_SIZE).min(RX_SLOTS - rx.pending_count);
                    for k in 0..count {
                        let h = &self.events.bytes()[base + k * RX_HEADER_SIZE..];
                        // Iso packet header, big-endian (data_length in the upper 16 bits),
                        // then the timestamp quadlet: 16 bits invalid, 3 bits cycleSeconds,
                        // 13 bits cycleCount, big-endian (<linux/firewire-cdev.h>).
                        let iso_header = u32::from_be_bytes([h[0], h[1], h[2], h[3]]);
                        let timestamp = u16::from_be_bytes([h[6], h[7]]);
                        let at = (rx.pending_head + rx.pending_count) % RX_SLOTS;
                        rx.pending[at] = (iso_header, timestamp);
                        rx.pending_count += 1;
                    }
                }
                // Bus-reset events on this descriptor are reported by the control one.
            }
        }
    }
}

impl Drop for CdevBus {
    fn drop(&mut self) {
        let _ = self.stop_iso();
    }
}

// ---- Finding nodes.

fn read_trimmed(path: &Path) -> Option<String> {
    std::fs::read_to_string(path)
        .ok()
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
}

fn parse_hex(s: &str) -> Option<u32> {
    u32::from_str_radix(s.trim().trim_start_matches("0x"), 16).ok()
}

/// Whether this user may open `path` read-write.
pub fn node_access(path: &Path) -> NodeAccess {
    let Ok(c) = CString::new(path.as_os_str().as_bytes()) else {
        return NodeAccess::Error("path contains NUL".into());
    };
    // SAFETY: a valid NUL-terminated path.
    if unsafe { libc::access(c.as_ptr(), libc::R_OK | libc::W_OK) } == 0 {
        NodeAccess::Ok
    } else {
        match errno() {
            libc::EACCES | libc::EPERM => NodeAccess::Denied,
            e => NodeAccess::Error(std::io::Error::from_raw_os_error(e).to_string()),
        }
    }
}

/// `/dev/fw*` nodes with what sysfs (or, failing that, the node's config ROM) says about them.
pub fn scan_nodes(dev_dir: &Path, sysfs_dir: &Path) -> Vec<NodeInfo> {
    scan_nodes_with(dev_dir, sysfs_dir, &node_access, &|p| {
        read_rom_vendor(p).ok().flatten()
    })
}

/// [`scan_nodes`] with the access check and the ROM reader given (tests fake both).
pub fn scan_nodes_with(
    dev_dir: &Path,
    sysfs_dir: &Path,
    access: &dyn Fn(&Path) -> NodeAccess,
    rom_vendor_of: &dyn Fn(&Path) -> Option<u32>,
) -> Vec<NodeInfo> {
    let Ok(entries) = std::fs::read_dir(dev_dir) else {
        return Vec::new();
    };
    let mut names: Vec<(u32, String)> = entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let n: u32 = name.strip_prefix("fw")?.parse().ok()?;
            Some((n, name))
        })
        .collect();
    names.sort();
    names
        .into_iter()
        .map(|(_, name)| {
            let path = dev_dir.join(&name);
            let sys = sysfs_dir.join(&name);
            let access = access(&path);
            let mut vendor = read_trimmed(&sys.join("vendor")).and_then(|v| parse_hex(&v));
            if vendor.is_none() && access == NodeAccess::Ok {
                vendor = rom_vendor_of(&path);
            }
            NodeInfo {
                vendor,
                guid: read_trimmed(&sys.join("guid")),
                vendor_name: read_trimmed(&sys.join("vendor_name")),
                model_name: read_trimmed(&sys.join("model_name")),
                access,
                path,
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;
    use std::process::Command;

    /// The header the structures above mirror.
    const HEADER: &str = "/usr/include/linux/firewire-cdev.h";

    /// Every (struct, field) whose offset we rely on, and the Rust value.
    fn rust_layout() -> Vec<(String, usize)> {
        let mut v: Vec<(String, usize)> = Vec::new();
        macro_rules! layout {
            ($t:ident { $($f:ident $(as $c:tt)?),* }) => {
                v.push((format!("sizeof {}", stringify!($t)), size_of::<$t>()));
                $(
                    let cname = layout!(@name $f $($c)?);
                    v.push((format!("offsetof {}.{}", stringify!($t), cname), offset_of!($t, $f)));
                )*
            };
            (@name $f:ident $c:tt) => { stringify!($c) };
            (@name $f:ident) => { stringify!($f) };
        }
        layout!(fw_cdev_get_info {
            version,
            rom_length,
            rom,
            bus_reset,
            bus_reset_closure,
            card
        });
        layout!(fw_cdev_send_request {
            tcode,
            length,
            offset,
            closure,
            data,
            generation
        });
        layout!(fw_cdev_event_common { closure, type_ as type });
        layout!(fw_cdev_event_bus_reset {
            closure, type_ as type, node_id, local_node_id, bm_node_id, irm_node_id,
            root_node_id, generation
        });
        layout!(fw_cdev_event_response { closure, type_ as type, rcode, length, data });
        layout!(fw_cdev_event_iso_interrupt { closure, type_ as type, cycle, header_length, header });
        layout!(fw_cdev_event_iso_resource { closure, type_ as type, handle, channel, bandwidth });
        layout!(fw_cdev_create_iso_context { type_ as type, header_size, channel, speed, closure, handle });
        layout!(fw_cdev_iso_packet { control, header });
        layout!(fw_cdev_queue_iso {
            packets,
            data,
            size,
            handle
        });
        layout!(fw_cdev_start_iso {
            cycle,
            sync,
            tags,
            handle
        });
        layout!(fw_cdev_stop_iso { handle });
        layout!(fw_cdev_allocate_iso_resource {
            closure,
            channels,
            bandwidth,
            handle
        });
        for (name, value) in [
            ("FW_CDEV_IOC_GET_INFO", FW_CDEV_IOC_GET_INFO),
            ("FW_CDEV_IOC_SEND_REQUEST", FW_CDEV_IOC_SEND_REQUEST),
            (
                "FW_CDEV_IOC_CREATE_ISO_CONTEXT",
                FW_CDEV_IOC_CREATE_ISO_CONTEXT,
            ),
            ("FW_CDEV_IOC_QUEUE_ISO", FW_CDEV_IOC_QUEUE_ISO),
            ("FW_CDEV_IOC_START_ISO", FW_CDEV_IOC_START_ISO),
            ("FW_CDEV_IOC_STOP_ISO", FW_CDEV_IOC_STOP_ISO),
            (
                "FW_CDEV_IOC_ALLOCATE_ISO_RESOURCE_ONCE",
                FW_CDEV_IOC_ALLOCATE_ISO_RESOURCE_ONCE,
            ),
            (
                "FW_CDEV_IOC_DEALLOCATE_ISO_RESOURCE_ONCE",
                FW_CDEV_IOC_DEALLOCATE_ISO_RESOURCE_ONCE,
            ),
            ("FW_CDEV_EVENT_BUS_RESET", FW_CDEV_EVENT_BUS_RESET),
            ("FW_CDEV_EVENT_RESPONSE", FW_CDEV_EVENT_RESPONSE),
            ("FW_CDEV_EVENT_ISO_INTERRUPT", FW_CDEV_EVENT_ISO_INTERRUPT),
            (
                "FW_CDEV_EVENT_ISO_RESOURCE_ALLOCATED",
                FW_CDEV_EVENT_ISO_RESOURCE_ALLOCATED,
            ),
            (
                "FW_CDEV_EVENT_ISO_RESOURCE_DEALLOCATED",
                FW_CDEV_EVENT_ISO_RESOURCE_DEALLOCATED,
            ),
            ("FW_CDEV_ISO_CONTEXT_TRANSMIT", FW_CDEV_ISO_CONTEXT_TRANSMIT),
            ("FW_CDEV_ISO_CONTEXT_RECEIVE", FW_CDEV_ISO_CONTEXT_RECEIVE),
            ("FW_CDEV_ISO_INTERRUPT", FW_CDEV_ISO_INTERRUPT),
            (
                "FW_CDEV_ISO_CONTEXT_MATCH_ALL_TAGS",
                FW_CDEV_ISO_CONTEXT_MATCH_ALL_TAGS,
            ),
            ("FW_CDEV_ISO_TAG(3)", fw_cdev_iso_tag(3)),
            ("FW_CDEV_ISO_SY(9)", fw_cdev_iso_sy(9)),
            ("FW_CDEV_ISO_HEADER_LENGTH(8)", fw_cdev_iso_header_length(8)),
            (
                "FW_CDEV_ISO_PAYLOAD_LENGTH(128)",
                fw_cdev_iso_payload_length(128),
            ),
            ("TCODE_WRITE_QUADLET_REQUEST", TCODE_WRITE_QUADLET_REQUEST),
            ("TCODE_WRITE_BLOCK_REQUEST", TCODE_WRITE_BLOCK_REQUEST),
            ("TCODE_READ_QUADLET_REQUEST", TCODE_READ_QUADLET_REQUEST),
            ("TCODE_READ_BLOCK_REQUEST", TCODE_READ_BLOCK_REQUEST),
            ("RCODE_COMPLETE", RCODE_COMPLETE),
            ("RCODE_CONFLICT_ERROR", RCODE_CONFLICT_ERROR),
            ("RCODE_BUSY", RCODE_BUSY),
            ("RCODE_GENERATION", RCODE_GENERATION),
            ("SCODE_100", SCODE_100),
        ] {
            v.push((format!("value {name}"), value as usize));
        }
        v
    }

    /// The same table from the C compiler, as a C program.
    fn c_program(table: &[(String, usize)]) -> String {
        let mut c = String::from(
            "#include <stdio.h>\n#include <stddef.h>\n#include <linux/firewire-cdev.h>\n\
             #include <linux/firewire-constants.h>\nint main(void) {\n",
        );
        for (key, _) in table {
            let (kind, what) = key.split_once(' ').unwrap();
            let expr = match kind {
                "sizeof" => format!("sizeof(struct {what})"),
                "offsetof" => {
                    let (s, f) = what.split_once('.').unwrap();
                    format!("offsetof(struct {s}, {f})")
                }
                _ => format!("(unsigned long)({what})"),
            };
            c.push_str(&format!(
                "  printf(\"%s=%lu\\n\", \"{key}\", (unsigned long)({expr}));\n"
            ));
        }
        c.push_str("  return 0;\n}\n");
        c
    }

    #[test]
    fn abi_matches_the_kernel_header() {
        if !Path::new(HEADER).exists() {
            let must = std::env::var_os("OMNID_REQUIRE_FIREWIRE_HEADER").is_some();
            assert!(
                !must,
                "{HEADER} is missing and OMNID_REQUIRE_FIREWIRE_HEADER is set: install linux-libc-dev"
            );
            eprintln!(
                "SKIPPED abi_matches_the_kernel_header: {HEADER} is not installed \
                 (install linux-libc-dev to run this check)"
            );
            return;
        }
        let table = rust_layout();
        let dir = tempfile::tempdir().unwrap();
        let src = dir.path().join("layout.c");
        let exe = dir.path().join("layout");
        std::fs::write(&src, c_program(&table)).unwrap();
        let cc = std::env::var("CC").unwrap_or_else(|_| "cc".into());
        let out = Command::new(&cc)
            .arg(&src)
            .arg("-o")
            .arg(&exe)
            .output()
            .unwrap_or_else(|e| panic!("cannot run the C compiler `{cc}`: {e}"));
        assert!(
            out.status.success(),
            "compiling the layout check failed:\n{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let run = Command::new(&exe).output().unwrap();
        assert!(run.status.success());
        let c: HashMap<String, usize> = String::from_utf8(run.stdout)
            .unwrap()
            .lines()
            .map(|l| {
                let (k, v) = l.rsplit_once('=').unwrap();
                (k.to_string(), v.parse().unwrap())
            })
            .collect();
        let mut bad = Vec::new();
        for (key, rust) in &table {
            match c.get(key) {
                Some(cv) if cv == rust => {}
                Some(cv) => bad.push(format!("{key}: C {cv}, Rust {rust}")),
                None => bad.push(format!("{key}: missing from the C output")),
            }
        }
        assert!(bad.is_empty(), "ABI mismatches:\n{}", bad.join("\n"));
        assert_eq!(c.len(), table.len());
    }

    #[test]
    fn rom_vendor_reads_the_bus_info_block() {
        // General ROM: info length 4, "1394", capabilities, vendor 0x000B99 + chip id high.
        let rom = [
            0x0404_1234,
            0x3133_3934,
            0xE000_A002,
            0x000B_9912,
            0x3456_7890,
        ];
        assert_eq!(rom_vendor(&rom), Some(0x000B99));
        // Minimal ROM: just a vendor id.
        assert_eq!(rom_vendor(&[0x0100_0B99]), Some(0x000B99));
        assert_eq!(rom_vendor(&[0x0404_0000, 0xDEAD_BEEF, 0, 0]), None);
        assert_eq!(rom_vendor(&[]), None);
    }

    #[test]
    fn iso_mappings_are_whole_pages() {
        for page in [4096, 16384, 65536] {
            for bytes in [RX_BYTES, TX_BYTES] {
                let len = map_len(bytes, page);
                assert_eq!(len % page, 0, "{bytes} bytes on {page}-byte pages: {len}");
                assert!(len >= bytes && len < bytes + page);
            }
        }
        assert_eq!(map_len(4096, 4096), 4096);
        assert_eq!(map_len(4097, 4096), 8192);
        assert_eq!(map_len(4096, 65536), 65536);
        assert_eq!(map_len(RX_BYTES, page_size()) % page_size(), 0);
    }

    #[test]
    fn channel_candidates_exclude_broadcast_and_63() {
        assert_eq!(CHANNEL_CANDIDATES & (1 << 31), 0);
        assert_eq!(CHANNEL_CANDIDATES & (1 << 63), 0);
        assert_eq!(CHANNEL_CANDIDATES.count_ones(), 62);
    }

    #[test]
    fn scan_reads_sysfs_and_falls_back_to_the_rom() {
        let root = tempfile::tempdir().unwrap();
        let dev = root.path().join("dev");
        let sys = root.path().join("sys");
        std::fs::create_dir_all(&dev).unwrap();
        for (name, vendor) in [
            ("fw0", Some("0x001b8c")),
            ("fw1", Some("0x000b99")),
            ("fw2", None),
        ] {
            std::fs::write(dev.join(name), "").unwrap();
            std::fs::create_dir_all(sys.join(name)).unwrap();
            if let Some(v) = vendor {
                std::fs::write(sys.join(name).join("vendor"), format!("{v}\n")).unwrap();
            }
        }
        std::fs::write(sys.join("fw1").join("guid"), "0x000b990012345678\n").unwrap();
        std::fs::write(dev.join("fw1.0"), "").unwrap(); // unit directories are not nodes
        std::fs::write(dev.join("full"), "").unwrap();
        let nodes = scan_nodes_with(&dev, &sys, &|_| NodeAccess::Ok, &|p| {
            (p.file_name().unwrap() == "fw2").then_some(0x000B99)
        });
        let names: Vec<_> = nodes
            .iter()
            .map(|n| n.path.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names, ["fw0", "fw1", "fw2"]);
        assert_eq!(nodes[0].vendor, Some(0x001B8C));
        assert!(nodes[1].is_omni() && nodes[2].is_omni());
        assert_eq!(nodes[1].guid.as_deref(), Some("0x000b990012345678"));
        // No access: the ROM cannot be read, so the vendor of fw2 stays unknown.
        let nodes = scan_nodes_with(&dev, &sys, &|_| NodeAccess::Denied, &|_| Some(0x000B99));
        assert_eq!(nodes[2].vendor, None);
        assert!(scan_nodes(&root.path().join("nothing"), &sys).is_empty());
    }
}

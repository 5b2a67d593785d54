//! The Omni's protocol over any `FireWireBus`: identify, start, check every packet, restart
//! after a bus reset, stop safely.

use super::rate::RateMeasurement;
use super::*;
use crate::device::codec::{MotorCommand, STATE_LAYOUT};
use crate::device::stream::{packet_counter, CommandGate, CounterTracker, StreamStats, Verdict};
use crate::device::{Device, DeviceError, MissReason, RawSample, COMMAND_LEN, STATE_LEN};
use std::time::{Duration, Instant};

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
    /// This process's hold on the unit, host-wide, from the first start to the close.
    unit: Option<std::os::fd::OwnedFd>,
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
            unit: None,
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

    /// The lock id of this unit: by its serial once identified (whatever node it is on), else
    /// by its node.
    pub(crate) fn unit_id(&self) -> String {
        format!(
            "omnid-dev-firewire-{}",
            self.serial.as_deref().unwrap_or(&self.name)
        )
    }

    /// The start sequence (docs/FIREWIRE.md §2), redone after every bus reset. The first
    /// start takes the unit for this process before anything is written (another process's
    /// arm on the same Omni, under any name, is refused here: docs/FIREWIRE.md, One process
    /// per Omni).
    pub(crate) fn start(&mut self) -> Result<(), DeviceError> {
        if self.unit.is_none() {
            let id = self.unit_id();
            self.unit = self
                .bus
                .hold_unit(&id)
                .map_err(|holder| DeviceError::InUse {
                    what: format!(
                        "FireWire Omni {} (at {})",
                        self.serial.as_deref().unwrap_or("of unknown serial"),
                        self.name
                    ),
                    holder,
                })?;
        }
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
        malformed: Option<crate::device::CodecError>,
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
        // Held to the end of the stop sequence (whichever way it returns), then let go.
        let _unit = self.unit.take();
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

//! The FireWire protocol over a fake bus that models the Omni's registers and stream and
//! records every operation.

use super::*;
use crate::config::Config;
use crate::device::codec::{
    decode_command, encode_command, encode_state, MotorCommand, StatePacket,
};
use crate::device::testkit::{assert_wire_discipline, run_servo};
use crate::servo::EndReason;
use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// One bus operation, as the fake saw it.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Op {
    ReadQuadlet(u64),
    ReadByte(u64),
    WriteByte(u64, u8),
    Allocate(u8),
    Free(u8),
    StartIso { rx: u8, tx: u8 },
    StopIso,
    Send([u8; 16]),
}

/// What `next_packet` does when asked, in order; when empty, the device streams normally
/// (or stays silent with `silent`).
enum Next {
    Packet(u32),
    Raw(Vec<u8>),
    Timeout,
    BusReset,
    Gone,
}

struct FakeNode {
    regs: HashMap<u64, u8>,
    vendor_quadlet: u32,
    serial: u32,
    ops: Vec<Op>,
    script: VecDeque<Next>,
    next_counter: u32,
    free_channels: Vec<u8>,
    iso: bool,
    silent: bool,
    gone: bool,
    /// Packets handed out so far (for stop/unplug/silence triggers).
    delivered: usize,
    stop_after: Option<(usize, Arc<AtomicBool>)>,
    silent_after: Option<usize>,
    gone_after: Option<usize>,
    reset_after: Option<usize>,
    /// Register writes so far, and the write (1-based) at which a bus reset happens.
    writes: usize,
    reset_at_write: Option<usize>,
}

impl Default for FakeNode {
    fn default() -> Self {
        let regs = HashMap::from([
            (reg::CHANNEL_TO_DEVICE, 0),
            (reg::CHANNEL_FROM_DEVICE, 0),
            (reg::CHECK_A, 0xC0),
            (reg::CHECK_B, 0x00),
            (reg::CONTROL, 0x00),
        ]);
        FakeNode {
            regs,
            vendor_quadlet: 0x000B_9900,
            serial: 31337,
            ops: Vec::new(),
            script: VecDeque::new(),
            next_counter: 1000,
            free_channels: vec![5, 9, 12, 14, 20, 21],
            iso: false,
            silent: false,
            gone: false,
            delivered: 0,
            stop_after: None,
            silent_after: None,
            gone_after: None,
            reset_after: None,
            writes: 0,
            reset_at_write: None,
        }
    }
}

impl FakeNode {
    fn streaming(&self) -> bool {
        self.iso && self.regs[&reg::CONTROL] & reg::CONTROL_STREAM != 0
    }

    /// A bus reset: the device forgets its channels and stops streaming; the IRM forgets
    /// the allocations (the fake hands out fresh ones).
    fn reset(&mut self) {
        self.regs.insert(reg::CONTROL, 0);
        self.regs.insert(reg::CHANNEL_TO_DEVICE, 0);
        self.regs.insert(reg::CHANNEL_FROM_DEVICE, 0);
        self.iso = false;
    }

    fn sent(&self) -> Vec<MotorCommand> {
        self.ops
            .iter()
            .filter_map(|op| match op {
                Op::Send(b) => Some(decode_command(b).expect("malformed command on the wire")),
                _ => None,
            })
            .collect()
    }
}

#[derive(Clone, Default)]
struct FakeBus(Arc<Mutex<FakeNode>>);

impl FakeBus {
    fn with(f: impl FnOnce(&mut FakeNode)) -> Self {
        let bus = FakeBus::default();
        f(&mut bus.0.lock().unwrap());
        bus
    }
    fn node(&self) -> std::sync::MutexGuard<'_, FakeNode> {
        self.0.lock().unwrap()
    }
}

fn state(counter: u32) -> [u8; STATE_LEN] {
    encode_state(&StatePacket {
        encoder: [1, 2, 3],
        gimbal: [0x8000; 3],
        counter,
        ..Default::default()
    })
}

impl FireWireBus for FakeBus {
    fn read_quadlet(&mut self, offset: u64) -> Result<u32, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::ReadQuadlet(offset));
        match offset {
            reg::VENDOR => Ok(n.vendor_quadlet),
            reg::SERIAL => Ok(n.serial),
            _ => Err(BusError::Rcode(0x07)),
        }
    }

    fn write_quadlet(&mut self, _: u64, _: u32) -> Result<(), BusError> {
        Err(BusError::Rcode(0x07))
    }

    fn read_byte(&mut self, offset: u64) -> Result<u8, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::ReadByte(offset));
        n.regs.get(&offset).copied().ok_or(BusError::Rcode(0x07))
    }

    fn write_byte(&mut self, offset: u64, value: u8) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.writes += 1;
        if n.reset_at_write == Some(n.writes) {
            n.reset();
            return Err(BusError::BusReset);
        }
        n.ops.push(Op::WriteByte(offset, value));
        if !n.regs.contains_key(&offset) {
            return Err(BusError::Rcode(0x07));
        }
        n.regs.insert(offset, value);
        Ok(())
    }

    fn allocate_channel(&mut self) -> Result<u8, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        if n.free_channels.is_empty() {
            return Err(BusError::NoChannel);
        }
        let ch = n.free_channels.remove(0);
        n.ops.push(Op::Allocate(ch));
        Ok(ch)
    }

    fn free_channel(&mut self, channel: u8) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::Free(channel));
        n.free_channels.push(channel);
        Ok(())
    }

    fn start_iso(&mut self, rx: u8, tx: u8) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::StartIso { rx, tx });
        n.iso = true;
        Ok(())
    }

    fn stop_iso(&mut self) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        n.ops.push(Op::StopIso);
        n.iso = false;
        Ok(())
    }

    fn send_packet(&mut self, packet: &[u8; COMMAND_LEN]) -> Result<(), BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        if !n.iso {
            return Err(BusError::NotStreaming);
        }
        n.ops.push(Op::Send(*packet));
        Ok(())
    }

    fn next_packet(
        &mut self,
        buf: &mut [u8; ISO_PAYLOAD_MAX],
        timeout: Duration,
    ) -> Result<BusEvent, BusError> {
        let mut n = self.node();
        if n.gone {
            return Err(BusError::Gone);
        }
        // Draining (zero wait) after a packet: one packet per exchange, like the device.
        if timeout.is_zero() {
            return Ok(BusEvent::Timeout);
        }
        let d = n.delivered;
        if let Some((k, flag)) = &n.stop_after {
            if d >= *k {
                flag.store(true, Ordering::SeqCst);
            }
        }
        if n.silent_after.is_some_and(|k| d >= k) {
            n.silent = true;
        }
        if n.gone_after.is_some_and(|k| d >= k) {
            n.gone = true;
            return Err(BusError::Gone);
        }
        if n.reset_after.is_some_and(|k| d >= k) {
            n.reset_after = None;
            n.script.push_front(Next::BusReset);
        }
        let next = match n.script.pop_front() {
            Some(x) => x,
            None if n.silent || !n.streaming() => Next::Timeout,
            None => {
                let c = n.next_counter;
                n.next_counter = c.wrapping_add(1);
                Next::Packet(c)
            }
        };
        match next {
            Next::Packet(c) => {
                buf[..STATE_LEN].copy_from_slice(&state(c));
                n.delivered += 1;
                Ok(BusEvent::Packet(STATE_LEN))
            }
            Next::Raw(b) => {
                buf[..b.len()].copy_from_slice(&b);
                Ok(BusEvent::Packet(b.len()))
            }
            Next::Timeout => Ok(BusEvent::Timeout),
            Next::BusReset => {
                n.reset();
                Ok(BusEvent::BusReset)
            }
            Next::Gone => {
                n.gone = true;
                Err(BusError::Gone)
            }
        }
    }
}

fn open(bus: &FakeBus) -> FireWireOmni<FakeBus> {
    FireWireOmni::open(
        bus.clone(),
        "fake-fw1".into(),
        Duration::from_millis(10),
        1000.0,
    )
    .expect("open")
}

fn amps_on(watchdog: u8) -> [u8; 16] {
    let mut c = MotorCommand::safe(watchdog);
    c.amps_on = true;
    c.dac = [0x0A00, 0x0600, 0x07FF];
    encode_command(&c)
}

/// The start sequence as the fake sees it, with the channels it hands out.
fn start_ops(to_device: u8, from_device: u8) -> Vec<Op> {
    vec![
        Op::Allocate(to_device),
        Op::Allocate(from_device),
        Op::WriteByte(0x1000, to_device),
        Op::WriteByte(0x1001, from_device),
        Op::ReadByte(0x1083),
        Op::ReadByte(0x1082),
        Op::StartIso {
            rx: from_device,
            tx: to_device,
        },
    ]
}

fn strip_sends(ops: &[Op]) -> Vec<Op> {
    ops.iter()
        .filter(|o| !matches!(o, Op::Send(_)))
        .cloned()
        .collect()
}

#[test]
fn start_sequence_in_order() {
    let bus = FakeBus::default();
    let omni = open(&bus);
    assert_eq!(omni.serial(), Some("31337"));
    let n = bus.node();
    let mut want = vec![Op::ReadQuadlet(reg::VENDOR), Op::ReadQuadlet(reg::SERIAL)];
    want.extend(start_ops(5, 9));
    // The first packet on the wire is the safe one, then streaming is switched on.
    assert!(matches!(n.ops[want.len()], Op::Send(_)));
    want.push(n.ops[want.len()].clone());
    want.push(Op::ReadByte(0x1087));
    want.push(Op::WriteByte(0x1087, 0x08));
    assert_eq!(n.ops, want);
    assert!(n.sent()[0].is_safe());
    assert!(n.streaming());
}

#[test]
fn stream_bit_is_set_without_touching_other_bits() {
    let bus = FakeBus::with(|n| {
        n.regs.insert(reg::CONTROL, 0x41);
    });
    let mut omni = open(&bus);
    assert_eq!(bus.node().regs[&reg::CONTROL], 0x49);
    omni.close().unwrap();
    assert_eq!(bus.node().regs[&reg::CONTROL], 0x41);
}

#[test]
fn wrong_vendor_is_refused_without_writing() {
    let bus = FakeBus::with(|n| n.vendor_quadlet = 0x0012_3400);
    let e = FireWireOmni::open(
        bus.clone(),
        "fake-fw0".into(),
        Duration::from_millis(10),
        1e3,
    )
    .err()
    .expect("a node of vendor 0x001234 opened");
    let DeviceError::NotFound { looked_for, hint } = &e else {
        panic!("expected NotFound, got {e}");
    };
    assert!(looked_for.contains("0x000b99"), "{looked_for}");
    assert!(hint.contains("0x001234"), "{hint}");
    assert_eq!(bus.node().ops, vec![Op::ReadQuadlet(reg::VENDOR)]);
}

#[test]
fn unexpected_register_value_aborts_and_frees_the_channels() {
    let bus = FakeBus::with(|n| {
        n.regs.insert(reg::CHECK_A, 0x80);
    });
    let e = FireWireOmni::open(bus.clone(), "fake".into(), Duration::from_millis(10), 1e3)
        .err()
        .expect("opened with 0x1083 = 0x80");
    let msg = e.to_string();
    assert!(
        msg.contains("0x1083") && msg.contains("0x80") && msg.contains("0xc0"),
        "{msg}"
    );
    let n = bus.node();
    assert_eq!(&n.ops[n.ops.len() - 2..], &[Op::Free(5), Op::Free(9)]);
    assert!(!n.streaming());
}

#[test]
fn no_free_channel_is_a_clear_error() {
    let bus = FakeBus::with(|n| n.free_channels = vec![3]);
    let e = FireWireOmni::open(bus.clone(), "fake".into(), Duration::from_millis(10), 1e3)
        .err()
        .expect("opened with one channel");
    assert!(e.to_string().contains("no free isochronous channel"), "{e}");
    assert_eq!(bus.node().ops.last(), Some(&Op::Free(3)));
}

#[test]
fn exchange_delivers_packets_and_counts_gaps() {
    let bus = FakeBus::with(|n| {
        n.script.extend([
            Next::Packet(50),
            Next::Packet(51),
            Next::Packet(55),
            Next::Packet(55),
            Next::Raw(vec![0; 20]),
            Next::Packet(56),
        ]);
    });
    let mut omni = open(&bus);
    let a = omni.exchange(&amps_on(1)).unwrap();
    assert_eq!(a.packet(), &state(50)[..]);
    omni.exchange(&amps_on(2)).unwrap();
    let c = omni.exchange(&amps_on(3)).unwrap();
    assert!((c.device_time_s - a.device_time_s - 5e-3).abs() < 1e-12);
    // Duplicate and short packet: dropped, the exchange waits for the next good one.
    let d = omni.exchange(&amps_on(4)).unwrap();
    assert_eq!(d.packet(), &state(56)[..]);
    let st = omni.stats();
    assert_eq!(
        (st.gaps, st.lost, st.duplicates, st.malformed),
        (1, 3, 1, 1)
    );
    // Amplifiers: off until the first sample, then as commanded.
    let sent = bus.node().sent();
    assert!(sent[0].is_safe() && sent[1].is_safe());
    assert!(sent[2].amps_on && sent[2].dac == [0x0A00, 0x0600, 0x07FF]);
    assert_wire_discipline(&sent[..2], 2);
}

#[test]
fn restart_after_a_bus_reset() {
    let bus = FakeBus::with(|n| n.reset_after = Some(5));
    let mut omni = open(&bus);
    let before = bus.node().ops.len();
    for k in 0..5 {
        omni.exchange(&amps_on(k)).unwrap();
    }
    assert!(bus.node().sent().last().unwrap().amps_on);
    // The reset: this tick is missed and the whole start sequence is redone on fresh
    // channels (the old ones are not freed: the reset voided them).
    let e = omni.exchange(&amps_on(5)).unwrap_err();
    assert!(matches!(e, DeviceError::Missed(_)), "{e}");
    assert_eq!(omni.stats().restarts, 1);
    assert_eq!(omni.stats().last_miss, MissReason::BusReset);
    {
        let n = bus.node();
        let after = strip_sends(&n.ops[before..]);
        let mut want = vec![Op::StopIso];
        want.extend(start_ops(12, 14));
        want.push(Op::ReadByte(0x1087));
        want.push(Op::WriteByte(0x1087, 0x08));
        assert_eq!(after, want);
        assert!(!n.ops.contains(&Op::Free(5)));
        assert!(n.streaming());
        assert_eq!(n.regs[&reg::CHANNEL_TO_DEVICE], 12);
    }
    // Streaming again; amplifiers stay off until a sample after the restart.
    let first = bus.node().sent().len();
    omni.exchange(&amps_on(6)).unwrap();
    omni.exchange(&amps_on(7)).unwrap();
    let sent = bus.node().sent();
    assert!(
        sent[first - 1].is_safe(),
        "restart sends the safe packet first"
    );
    assert!(
        sent[first].is_safe(),
        "amps on before a sample after the restart"
    );
    assert!(sent[first + 1].amps_on);
}

#[test]
fn a_reset_during_the_restart_is_retried() {
    let bus = FakeBus::with(|n| n.reset_after = Some(2));
    let mut omni = open(&bus);
    omni.exchange(&amps_on(0)).unwrap();
    omni.exchange(&amps_on(1)).unwrap();
    // Open wrote three registers; the restart's first write (the 4th) meets another reset.
    bus.node().reset_at_write = Some(4);
    assert!(matches!(
        omni.exchange(&amps_on(2)),
        Err(DeviceError::Missed(_))
    ));
    {
        let n = bus.node();
        assert!(n.streaming());
        // First attempt: channels 12 and 14 (void after the reset, not freed); second: 20, 21.
        assert_eq!(n.regs[&reg::CHANNEL_TO_DEVICE], 20);
        assert!(!n.ops.iter().any(|o| matches!(o, Op::Free(_))));
    }
    assert_eq!(omni.stats().restarts, 1);
    assert!(omni.exchange(&amps_on(3)).is_ok());
}

#[test]
fn stop_sequence_on_close() {
    let bus = FakeBus::default();
    let mut omni = open(&bus);
    omni.exchange(&amps_on(1)).unwrap();
    omni.exchange(&amps_on(2)).unwrap();
    let before = bus.node().ops.len();
    omni.close().unwrap();
    let n = bus.node();
    let tail = &n.ops[before..];
    assert_eq!(tail.len(), 6, "{tail:?}");
    let Op::Send(last) = &tail[0] else {
        panic!("close must first send the safe packet: {tail:?}");
    };
    assert!(decode_command(last).unwrap().is_safe());
    assert_eq!(
        &tail[1..],
        &[
            Op::ReadByte(0x1087),
            Op::WriteByte(0x1087, 0x00),
            Op::StopIso,
            Op::Free(5),
            Op::Free(9),
        ]
    );
    drop(n);
    omni.close().unwrap();
    assert_eq!(bus.node().ops.len(), before + 6, "close is idempotent");
}

#[test]
fn drop_without_close_stops_the_device() {
    let bus = FakeBus::default();
    {
        let mut omni = open(&bus);
        omni.exchange(&amps_on(1)).unwrap();
        omni.exchange(&amps_on(2)).unwrap();
    }
    let n = bus.node();
    assert!(!n.streaming());
    assert!(n.sent().last().unwrap().is_safe());
    assert_eq!(n.ops.last(), Some(&Op::Free(9)));
}

#[test]
fn unplug_is_disconnected() {
    let bus = FakeBus::with(|n| n.script.extend([Next::Packet(1), Next::Gone]));
    let mut omni = open(&bus);
    omni.exchange(&amps_on(1)).unwrap();
    let e = omni.exchange(&amps_on(2)).unwrap_err();
    assert!(matches!(e, DeviceError::Disconnected(_)), "{e}");
    let n_ops = bus.node().ops.len();
    assert!(matches!(
        omni.exchange(&amps_on(3)),
        Err(DeviceError::Disconnected(_))
    ));
    omni.close().unwrap();
    assert_eq!(
        bus.node().ops.len(),
        n_ops,
        "nothing is tried on a node that is gone"
    );
}

#[test]
fn config_validation_names_fields() {
    FirewireConfig::default().validate().unwrap();
    for (cfg, field) in [
        (
            FirewireConfig {
                device: "/dev/sda".into(),
                ..Default::default()
            },
            "firewire.device",
        ),
        (
            FirewireConfig {
                timeout_ms: 0,
                ..Default::default()
            },
            "firewire.timeout_ms",
        ),
        (
            FirewireConfig {
                register_timeout_ms: 9000,
                ..Default::default()
            },
            "firewire.register_timeout_ms",
        ),
    ] {
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains(field), "{e}");
    }
    FirewireConfig {
        device: "/dev/fw12".into(),
        ..Default::default()
    }
    .validate()
    .unwrap();
    let text = toml::to_string(&FirewireConfig::default()).unwrap();
    for (key, _) in FIREWIRE_FIELD_DOCS.iter().skip(1) {
        let field = key.strip_prefix("firewire.").unwrap();
        assert!(text.contains(&format!("{field} = ")), "{key}");
    }
}

fn node(path: &str, vendor: Option<u32>, access: NodeAccess) -> NodeInfo {
    NodeInfo {
        path: PathBuf::from(path),
        vendor,
        guid: None,
        vendor_name: None,
        model_name: None,
        access,
    }
}

#[test]
fn candidates_pick_omnis_and_explain_the_rest() {
    let cfg = FirewireConfig::default();
    let e = candidate_nodes(&[], &cfg).unwrap_err();
    assert!(matches!(&e, DeviceError::NotFound { hint, .. } if hint.contains("no /dev/fw*")));
    let controller = node("/dev/fw0", Some(0x001B8C), NodeAccess::Ok);
    let e = candidate_nodes(std::slice::from_ref(&controller), &cfg).unwrap_err();
    let DeviceError::NotFound { hint, .. } = &e else {
        panic!("{e}")
    };
    assert!(hint.contains("/dev/fw0 vendor 0x001b8c"), "{hint}");
    let omni = node("/dev/fw1", Some(0x000B99), NodeAccess::Ok);
    assert_eq!(
        candidate_nodes(&[controller.clone(), omni.clone()], &cfg).unwrap(),
        vec![PathBuf::from("/dev/fw1")]
    );
    let locked = node("/dev/fw1", Some(0x000B99), NodeAccess::Denied);
    let e = candidate_nodes(&[controller.clone(), locked], &cfg).unwrap_err();
    let DeviceError::Permission { what, hint } = &e else {
        panic!("{e}")
    };
    assert!(what.contains("/dev/fw1") && hint.contains("ATTR{vendor}==\"0x000b99\""));
    assert!(hint.contains("plugdev"));
    let named = FirewireConfig {
        device: "/dev/fw7".into(),
        ..Default::default()
    };
    assert!(matches!(
        candidate_nodes(&[controller, omni], &named),
        Err(DeviceError::NotFound { .. })
    ));
}

#[test]
fn no_firewire_here_is_not_found_quickly() {
    // On a machine without /dev/fw* (this one, CI) opening fails fast, saying what was
    // looked for; with FireWire but no Omni it says what it found.
    let t = Instant::now();
    let nodes = cdev::scan_nodes(Path::new("/dev"), Path::new(cdev::SYSFS_FIREWIRE_DEVICES));
    if nodes.iter().any(|n| n.is_omni()) {
        eprintln!("SKIPPED: an Omni is connected");
        return;
    }
    let e = match open_firewire(&FirewireConfig::default()) {
        Ok(_) => panic!("opened an Omni that the scan did not see"),
        Err(e) => e,
    };
    assert!(t.elapsed() < Duration::from_secs(1));
    let DeviceError::NotFound { looked_for, hint } = &e else {
        panic!("{e}")
    };
    assert!(looked_for.contains("0x000B99"), "{looked_for}");
    if nodes.is_empty() {
        assert!(hint.contains("no /dev/fw* nodes"), "{hint}");
    }
}

/// The servo loop over the FireWire backend: every stop path ends safe on the wire.
mod servo_stop_paths {
    use super::*;

    fn run(bus: &FakeBus, max_ticks: u64, stop: Arc<AtomicBool>) -> crate::servo::ServoReport {
        let cfg = Config::default();
        run_servo(&cfg, Box::new(open(bus)), max_ticks, stop)
    }

    /// After close: streaming off in the device, channels freed, last packet safe.
    fn assert_stopped(bus: &FakeBus) {
        let n = bus.node();
        let sent = n.sent();
        assert!(
            sent.iter().any(|c| c.amps_on),
            "the run never applied torque"
        );
        assert_wire_discipline(&sent, 1);
        assert!(!n.streaming());
        assert!(n.ops.contains(&Op::WriteByte(0x1087, 0x00)));
    }

    #[test]
    fn end_of_run() {
        let bus = FakeBus::default();
        let report = run(&bus, 300, Arc::new(AtomicBool::new(false)));
        assert_eq!(report.end, EndReason::Completed);
        assert!(
            report.shutdown_error.is_none(),
            "{:?}",
            report.shutdown_error
        );
        assert_stopped(&bus);
    }

    #[test]
    fn device_stops_answering_then_fault() {
        let bus = FakeBus::with(|n| n.silent_after = Some(60));
        let report = run(&bus, 100_000, Arc::new(AtomicBool::new(false)));
        let EndReason::DeviceFault(msg) = &report.end else {
            panic!("expected a device fault, got {:?}", report.end);
        };
        // The loop's own policy (consecutive misses, link-quality floor) decides when; it
        // must be from the misses, within the configured count.
        assert!(msg.contains("packets"), "{msg}");
        let n = report.missed_packets;
        let max = u64::from(Config::default().safety.max_missed_ticks);
        assert!(n >= 1 && n <= max, "{n}");
        assert_stopped(&bus);
    }

    #[test]
    fn operator_stop() {
        let stop = Arc::new(AtomicBool::new(false));
        let bus = FakeBus::with(|n| n.stop_after = Some((40, stop.clone())));
        let report = run(&bus, 100_000, stop);
        assert_eq!(report.end, EndReason::OperatorStop);
        assert_stopped(&bus);
    }

    #[test]
    fn bus_reset_mid_run_then_end() {
        let bus = FakeBus::with(|n| n.reset_after = Some(100));
        let report = run(&bus, 300, Arc::new(AtomicBool::new(false)));
        assert_eq!(report.end, EndReason::Completed);
        assert_eq!(report.missed_packets, 1);
        assert_stopped(&bus);
    }

    #[test]
    fn unplug() {
        let bus = FakeBus::with(|n| n.gone_after = Some(50));
        let report = run(&bus, 100_000, Arc::new(AtomicBool::new(false)));
        let EndReason::DeviceFault(msg) = &report.end else {
            panic!("expected a device fault, got {:?}", report.end);
        };
        assert!(msg.contains("disconnected"), "{msg}");
        // The node is gone: nothing more could be sent; the loop says its safe packet did
        // not go.
        let e = report.shutdown_error.as_deref().unwrap_or("");
        assert!(e.contains("final zero-torque packet"), "{e}");
        assert!(bus.node().sent().iter().any(|c| c.amps_on));
    }
}

#[test]
fn shipped_udev_files_match_and_are_not_world_writable() {
    let fw = include_str!("../../../udev/99-omnid-firewire.rules");
    let rules: Vec<&str> = fw
        .lines()
        .filter(|l| !l.trim_start().starts_with('#') && !l.trim().is_empty())
        .collect();
    assert_eq!(rules, [FIREWIRE_UDEV_RULE]);
    for file in [fw, include_str!("../../../udev/99-omnid-usb.rules")] {
        for line in file.lines().filter(|l| l.contains("MODE=")) {
            let mode = line
                .split("MODE=\"")
                .nth(1)
                .unwrap()
                .split('"')
                .next()
                .unwrap();
            let bits = u32::from_str_radix(mode, 8).unwrap();
            assert_eq!(bits & 0o007, 0, "world access in {line}");
            assert!(line.contains("GROUP=\"plugdev\""), "{line}");
        }
    }
    let limits = include_str!("../../../udev/omnid-limits.conf");
    assert!(limits
        .lines()
        .any(|l| l.starts_with("@plugdev") && l.contains("rtprio")));
    assert!(limits
        .lines()
        .any(|l| l.starts_with("@plugdev") && l.contains("memlock")));
}

//! The FireWire protocol over the fake bus of `fake.rs`, whose packets come from a byte table
//! written from the open drivers (not from `codec.rs`), and golden packets.

use super::fake::{
    device_packet, read_command, state, wire, ArmState, FakeBus, Next, Op, SERIAL_LABEL,
    SERIAL_QUADLET,
};
use super::*;
use crate::config::Config;
use crate::device::codec::{
    decode_command, decode_state, encode_command, encode_state, MotorCommand, StatePacket, DAC_ZERO,
};
use crate::device::stream::{Byte7, WireFormat};
use crate::device::testkit::{assert_wire_discipline, run_servo};
use crate::device::{Device, DeviceError, MissReason};
use crate::servo::EndReason;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Options with every motor's DAC sign measured (+1), so that commanded torque reaches the
/// wire.
fn measured() -> FireWireOptions {
    FireWireOptions {
        format: WireFormat {
            dac_sign: [1; 3],
            ..WireFormat::DRIVERS
        },
        busy_retry: Duration::from_millis(1),
        ..FireWireOptions::new(Duration::from_millis(10), 1000.0)
    }
}

fn open(bus: &FakeBus) -> FireWireOmni<FakeBus> {
    FireWireOmni::open_with(bus.clone(), "fake-fw1".into(), measured()).expect("open")
}

fn open_err(bus: &FakeBus, opts: FireWireOptions) -> DeviceError {
    match FireWireOmni::open_with(bus.clone(), "fake-fw1".into(), opts) {
        Ok(_) => panic!("opened"),
        Err(e) => e,
    }
}

fn amps_on(byte7: u8) -> [u8; 16] {
    let mut c = MotorCommand::safe(byte7);
    c.amps_on = true;
    c.dac = [0x0A00, 0x0600, 0x07FF];
    encode_command(&c)
}

/// A device packet as the backend delivers it: encoder words in the OpenHaptics directions
/// (joints 1 and 2 negated, docs/FIREWIRE.md §6).
fn delivered(p: [u8; 44]) -> [u8; 44] {
    let mut p = p;
    for (j, &at) in wire::ENCODER.iter().enumerate() {
        if OPENHAPTICS_ENCODER_SIGN[j] < 0 {
            let v = u16::from_le_bytes([p[at], p[at + 1]]).wrapping_neg();
            p[at..at + 2].copy_from_slice(&v.to_le_bytes());
        }
    }
    p
}

/// The start sequence as the fake sees it, with the channels it hands out: the vendor
/// trace's order (minimal-test/opensource.c:194-224), after the check for a stale stream bit,
/// up to omnid's own iso start.
fn start_ops(to_device: u8, from_device: u8) -> Vec<Op> {
    vec![
        Op::ReadByte(0x1087),
        Op::Allocate(to_device),
        Op::Allocate(from_device),
        Op::WriteByte(0x1000, to_device),
        Op::WriteByte(0x1001, from_device),
        Op::WriteQuadlet(0x20010, 0x0000_0FF8),
        Op::ReadByte(0x1001),
        Op::WriteByte(0x1001, 0x40),
        Op::ReadByte(0x1001),
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

// ---- Golden packets: literal bytes, written from the sources, against the codec and the fake.

/// State packets of a unit at rest: encoders x = 0x0123, y = 0xFEDC, z = 0x0042, gimbal
/// 0x4000/0x8000/0xC000, counter 0x01020304; only the switch byte differs.
fn golden_state(switches: u8) -> [u8; 44] {
    [
        0x00, 0x00, 0x1E, 0x00, // PhantomSpec.h:55-56: 0x0000, 0x001e
        0x23, 0x01, 0xDC, 0xFE, 0x42, 0x00, // encoders x, y, z (u16 LE)
        0x00, 0x40, 0x00, 0x80, 0x00, 0xC0, // gimbal pots
        0x00, 0x00,     // v0 / unknown8
        0x04,     // tx packet number (omnifirewire.h:105)
        switches, // byte 19: the switches (omnifirewire.h:107-119, PhantomSpec.h:63-77)
        0x07, 0x10, // PhantomSpec.h:78: 0x1007
        0xFF, 0xBF, 0xFF, 0x7F, 0xFF, 0x3F, // the gimbal's complement
        0x46, 0x57, // PhantomSpec.h:80: 0x5746
        0x00, 0x00, // unknown15
        0x04, 0x03, 0x02, 0x01, // count0 = 0x01020304 (PhantomSpec.h:82)
        0x00, 0x00, 0x00, 0x00, // unknown18/19
        0x82, 0x01, 0x00, 0x00, // count1 (the fake's half of count0), unknown21
    ]
}

const GOLDEN_ARM: ArmState = ArmState {
    encoder: [0x0123, 0xFEDC, 0x0042],
    gimbal: [0x4000, 0x8000, 0xC000],
    buttons: [false, false],
    docked: false,
};

#[test]
fn golden_state_packets_decode_to_the_switches_the_drivers_read() {
    // (switch byte, buttons, docked): idle bits 0x90, active-low switches in bits 0..2.
    for (byte, buttons, docked) in [
        (0x97, [false, false], false), // undocked, nothing pressed
        (0x93, [false, false], true),  // stylus in the inkwell
        (0x96, [true, false], false),  // button 1
        (0x95, [false, true], false),  // button 2
        (0x90, [true, true], true),    // all three
    ] {
        let golden = golden_state(byte);
        let arm = ArmState {
            buttons,
            docked,
            ..GOLDEN_ARM
        };
        // The fake's table builds exactly these bytes...
        assert_eq!(device_packet(&arm, 0x0102_0304, 4), golden, "{byte:#04x}");
        // ...and the codec reads them as the drivers do.
        let s = decode_state(&golden).unwrap();
        assert_eq!(s.buttons, buttons, "{byte:#04x}");
        assert_eq!(s.inkwell, docked, "{byte:#04x}");
        assert_eq!(s.encoder, [0x0123, 0xFEDC, 0x0042]);
        assert_eq!(s.gimbal, [0x4000, 0x8000, 0xC000]);
        assert_eq!(s.counter, 0x0102_0304);
    }
    // Byte 16, where omnid used to look for the switches, says nothing about them.
    let mut p = golden_state(0x97);
    p[16] = 0x00;
    assert!(!decode_state(&p).unwrap().inkwell);
    // The codec's own encoder writes the switches where the drivers read them.
    let e = encode_state(&StatePacket {
        inkwell: true,
        buttons: [true, false],
        ..Default::default()
    });
    assert_eq!(e[19], 0x92);
    assert_eq!(e[16], 0x00);
}

#[test]
fn golden_command_packets_are_the_drivers_bytes() {
    // minimal-test/opensource.c:42: {0x07ff07ff, 0x53c007ff, 0, 0} as x86 memory.
    let trace: Vec<u8> = [0x07ff_07ffu32, 0x53c0_07ff, 0, 0]
        .iter()
        .flat_map(|q| q.to_le_bytes())
        .collect();
    let safe = encode_command(&MotorCommand::safe(0x53));
    assert_eq!(safe.to_vec(), trace);
    assert_eq!(
        safe,
        [0xFF, 0x07, 0xFF, 0x07, 0xFF, 0x07, 0xC0, 0x53, 0, 0, 0, 0, 0, 0, 0, 0]
    );
    // opensource.c:238: 0x53c307ff, the dock lamp bits on.
    let lamp = encode_command(&MotorCommand {
        lamp: 0b11,
        ..MotorCommand::safe(0x53)
    });
    assert_eq!(&lamp[4..8], &0x53c3_07ffu32.to_le_bytes());
    // Amplifiers on (bit 3, omnifirewire.h:72) with torque on motors 1 and 3.
    let amps = encode_command(&MotorCommand {
        dac: [0x0500, DAC_ZERO, 0x0A00],
        amps_on: true,
        lamp: 0b11,
        watchdog: 0x53,
    });
    assert_eq!(
        amps,
        [0x00, 0x05, 0xFF, 0x07, 0x00, 0x0A, 0xCB, 0x53, 0, 0, 0, 0, 0, 0, 0, 0]
    );
    let read = read_command(&amps).unwrap();
    assert!(read.motors_on && read.lamp == 3 && read.force == [0x0500, 0x07FF, 0x0A00]);
    assert_eq!(
        decode_command(&amps).unwrap().dac,
        [0x0500, DAC_ZERO, 0x0A00]
    );
    // What omnid sent before issue 19 (byte 6 without 0xC0, a counter in byte 7) is not what
    // the drivers send, and the fake says which byte.
    let mut old = safe;
    old[6] = 0x00;
    old[7] = 0x01;
    assert!(read_command(&old).unwrap_err().contains("bytes 6-7"));
}

#[test]
fn backend_wire_is_the_drivers_word_and_delivers_openhaptics_signs() {
    let bus = FakeBus::with(|n| {
        n.arm = ArmState {
            encoder: [100, 200, 0xFFFF],
            docked: true,
            ..ArmState::default()
        }
    });
    let mut omni = open(&bus);
    let s = omni.exchange(&amps_on(9)).unwrap();
    let p = decode_state(s.packet()).unwrap();
    // OpenHaptics directions: joints 1 and 2 negated, joint 3 as counted.
    assert_eq!(
        p.encoder,
        [100u16.wrapping_neg(), 200u16.wrapping_neg(), 0xFFFF]
    );
    assert!(p.inkwell);
    omni.exchange(&amps_on(10)).unwrap();
    omni.close().unwrap();
    let n = bus.node();
    let wire_cmds = n.sent_wire();
    assert!(wire_cmds[0].is_safe());
    assert!(wire_cmds
        .iter()
        .any(|c| c.motors_on && c.force == [0x0A00, 0x0600, 0x07FF]));
    assert!(n
        .ops
        .iter()
        .all(|o| !matches!(o, Op::Send(b) if b[7] != 0x53 || b[6] & 0xC0 != 0xC0)));
}

#[test]
fn unmeasured_dac_signs_put_no_torque_on_the_wire() {
    let bus = FakeBus::default();
    let opts = FireWireOptions::new(Duration::from_millis(10), 1000.0);
    assert_eq!(opts.format.dac_sign, [0; 3]);
    let mut omni = FireWireOmni::open_with(bus.clone(), "fake".into(), opts).unwrap();
    omni.exchange(&amps_on(1)).unwrap();
    omni.exchange(&amps_on(2)).unwrap();
    let sent = bus.node().sent_wire();
    assert!(sent.iter().all(|c| c.force == [0x07FF; 3]), "{sent:?}");
}

#[test]
fn serial_is_read_in_the_label_form() {
    let bus = FakeBus::default();
    let omni = open(&bus);
    assert_eq!(omni.serial(), Some(SERIAL_LABEL));
    assert_eq!(omni.serial_quadlet(), Some(SERIAL_QUADLET));
    let cfg = FirewireConfig {
        serial: SERIAL_LABEL.into(),
        ..Default::default()
    };
    cfg.validate().unwrap();
    assert!(cfg.wants_serial(SERIAL_QUADLET));
    assert!(!cfg.wants_serial(SERIAL_QUADLET ^ 0x2));
    assert!(FirewireConfig::default().wants_serial(1));
}

#[test]
fn start_sequence_in_order() {
    let bus = FakeBus::default();
    let omni = open(&bus);
    assert_eq!(omni.serial(), Some(SERIAL_LABEL));
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
    assert_eq!(n.quadlets[&0x20010].to_be_bytes(), [0x00, 0x00, 0x0F, 0xF8]);
    assert!(!omni.stale_stream_cleared());
}

#[test]
fn vendor_init_and_scratch_test_are_configuration() {
    let bus = FakeBus::default();
    let opts = FireWireOptions {
        vendor_init: false,
        scratch_test: false,
        ..measured()
    };
    let _omni = FireWireOmni::open_with(bus.clone(), "fake".into(), opts).unwrap();
    let ops = strip_sends(&bus.node().ops);
    assert!(!ops.iter().any(|o| matches!(o, Op::WriteQuadlet(..))));
    assert!(!ops.contains(&Op::WriteByte(0x1001, 0x40)));
    assert!(ops.contains(&Op::WriteByte(0x1001, 9)));
    // The defaults are the vendor trace's.
    let d = FirewireConfig::default();
    assert!(d.vendor_init && d.scratch_test);
}

#[test]
fn a_failed_scratch_test_names_register_and_value() {
    let bus = FakeBus::with(|n| n.scratch_broken = true);
    let e = open_err(&bus, measured()).to_string();
    assert!(
        e.contains("0x1001") && e.contains("0x00") && e.contains("0x40") && e.contains("scratch"),
        "{e}"
    );
    let n = bus.node();
    assert!(!n.streaming());
    assert_eq!(&n.ops[n.ops.len() - 2..], &[Op::Free(5), Op::Free(9)]);
}

#[test]
fn busy_answers_are_retried_then_reported() {
    // Two busy answers on 0x1083: retried, the start goes through.
    let bus = FakeBus::with(|n| {
        n.busy.insert(reg::CHECK_A, 2);
    });
    let _omni = open(&bus);
    let reads = bus
        .node()
        .ops
        .iter()
        .filter(|o| **o == Op::ReadByte(0x1083))
        .count();
    assert_eq!(reads, 3);
    // Busy beyond the retries: the error names the register and the retries.
    let bus = FakeBus::with(|n| {
        n.busy.insert(reg::CHANNEL_TO_DEVICE, 100);
    });
    let e = open_err(
        &bus,
        FireWireOptions {
            busy_retries: 3,
            ..measured()
        },
    )
    .to_string();
    assert!(
        e.contains("writing 0x05 to register 0x1000")
            && e.contains("busy")
            && e.contains("3 retries"),
        "{e}"
    );
    let writes = bus
        .node()
        .ops
        .iter()
        .filter(|o| **o == Op::WriteByte(0x1000, 5))
        .count();
    assert_eq!(writes, 4);
}

#[test]
fn a_stream_bit_left_by_a_crashed_run_is_cleared_first() {
    let bus = FakeBus::with(|n| {
        n.regs.insert(reg::CONTROL, 0x08);
    });
    let omni = open(&bus);
    assert!(omni.stale_stream_cleared());
    let n = bus.node();
    assert_eq!(
        &n.ops[2..5],
        &[
            Op::ReadByte(0x1087),
            Op::WriteByte(0x1087, 0x00),
            Op::Allocate(5)
        ]
    );
    assert!(n.streaming());
}

#[test]
fn the_packet_rate_is_measured_and_a_mismatch_refused_with_numbers() {
    let bus = FakeBus::default();
    let mut omni = open(&bus);
    let m = omni.check_rate().unwrap();
    assert!((m.rate_hz() - 1000.0).abs() < 1.0, "{m:?}");
    // The measurement leaves the amplifiers off until the next sample.
    omni.exchange(&amps_on(1)).unwrap();
    let sent = bus.node().sent();
    assert!(sent.last().unwrap().is_safe());
    assert!(sent.iter().all(|c| !c.amps_on));
    drop(sent);
    let bus = FakeBus::with(|n| n.rate_hz = 500.0);
    let mut omni = open(&bus);
    let e = omni.check_rate().unwrap_err().to_string();
    assert!(
        e.contains("500.0 Hz") && e.contains("2.000 ms") && e.contains("device.rate_hz = 1000"),
        "{e}"
    );
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
    assert_eq!(a.packet(), &delivered(state(50))[..]);
    omni.exchange(&amps_on(2)).unwrap();
    let c = omni.exchange(&amps_on(3)).unwrap();
    assert!((c.device_time_s - a.device_time_s - 5e-3).abs() < 1e-12);
    // Duplicate and short packet: dropped, the exchange waits for the next good one.
    let d = omni.exchange(&amps_on(4)).unwrap();
    assert_eq!(d.packet(), &delivered(state(56))[..]);
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
    assert_eq!(omni.stats().last_miss, Some(MissReason::BusReset));
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
    // Open wrote six registers (0x1000, 0x1001, 0x20010, 0x1001 twice for the scratch test,
    // 0x1087); the restart's first write (the 7th) meets another reset.
    bus.node().reset_at_write = Some(7);
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
        (
            FirewireConfig {
                serial: "31337".into(),
                ..Default::default()
            },
            "firewire.serial",
        ),
        (
            FirewireConfig {
                encoder_sign: [1, 0, 1],
                ..Default::default()
            },
            "firewire.encoder_sign[1]",
        ),
        (
            FirewireConfig {
                dac_sign: [1, 1, 2],
                ..Default::default()
            },
            "firewire.dac_sign[2]",
        ),
        (
            FirewireConfig {
                command_byte7: "83".into(),
                ..Default::default()
            },
            "firewire.command_byte7",
        ),
        (
            FirewireConfig {
                busy_retries: 51,
                ..Default::default()
            },
            "firewire.busy_retries",
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
    for (text, want) in [
        ("0x53", Byte7::Constant(0x53)),
        ("0x00", Byte7::Constant(0)),
        ("counter", Byte7::Counter),
    ] {
        let c = FirewireConfig {
            command_byte7: text.into(),
            ..Default::default()
        };
        assert_eq!(c.byte7(), Some(want));
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
    let e = match find_firewire(&FirewireConfig::default(), 1000.0) {
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
    let fw = include_str!("../../../../../udev/99-omnid-firewire.rules");
    let rules: Vec<&str> = fw
        .lines()
        .filter(|l| !l.trim_start().starts_with('#') && !l.trim().is_empty())
        .collect();
    assert_eq!(rules, [FIREWIRE_UDEV_RULE]);
    for file in [fw, include_str!("../../../../../udev/99-omnid-usb.rules")] {
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
    let limits = include_str!("../../../../../udev/omnid-limits.conf");
    assert!(limits
        .lines()
        .any(|l| l.starts_with("@plugdev") && l.contains("rtprio")));
    assert!(limits
        .lines()
        .any(|l| l.starts_with("@plugdev") && l.contains("memlock")));
}

/// Two arms on one Omni, whatever their names: the second start is refused before it writes
/// anything, naming the unit and who holds it; once the first closes, the unit is free. Another
/// serial is another unit. (Real host-wide locks, under a prefix only this test uses.)
#[test]
fn a_second_start_on_the_same_unit_is_refused_before_any_write() {
    let prefix = format!("omnid-test-{}-unit-", std::process::id());
    let bus_for = |serial: u32| {
        FakeBus::with(|n| {
            n.unit_lock_prefix = Some(prefix.clone());
            n.serial = serial;
        })
    };
    let first_bus = bus_for(SERIAL_QUADLET);
    let mut first = open(&first_bus);

    let second_bus = bus_for(SERIAL_QUADLET);
    let mut second = FireWireOmni::with_options(second_bus.clone(), "fake-fw2".into(), measured());
    second.identify().unwrap();
    let e = second.start().expect_err("the unit is taken");
    let DeviceError::InUse { what, holder } = &e else {
        panic!("expected InUse, got {e:?}");
    };
    assert!(
        what.contains("10203400567") && what.contains("fake-fw2"),
        "{what}"
    );
    assert!(holder.contains("this same omnid process"), "{holder}");
    let wrote = second_bus
        .node()
        .ops
        .iter()
        .any(|op| !matches!(op, Op::ReadQuadlet(_) | Op::ReadByte(_)));
    assert!(
        !wrote,
        "the refused start touched the bus: {:?}",
        second_bus.node().ops
    );

    // Another serial is another unit.
    let other_bus = bus_for(SERIAL_QUADLET ^ (1 << 1));
    let mut other = FireWireOmni::with_options(other_bus, "fake-fw3".into(), measured());
    other.identify().unwrap();
    other.start().expect("another unit");
    other.close().unwrap();

    first.close().unwrap();
    second.start().expect("free once the first closed");
    second.close().unwrap();
}

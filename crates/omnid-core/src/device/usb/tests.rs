use super::*;
use crate::config::Config;
use crate::device::codec::{encode_command, encode_state, MotorCommand, StatePacket};
use crate::device::testkit::{assert_wire_discipline, decode_all, run_servo};
use crate::device::{Device, DeviceError, MissReason, STATE_LEN};
use crate::servo::EndReason;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

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
    let hex: UsbConfig = toml::from_str("vendor_id = 0x0B99\ntransfer = \"interrupt\"\n").unwrap();
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
    let file = include_str!("../../../../../udev/99-omnid-usb.rules");
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

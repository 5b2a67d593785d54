//! Test helpers shared by the backend tests: drive the real servo loop over a device.

use crate::config::Config;
use crate::control::{ControllerKind, ControllerSet, Reference, Trajectory};
use crate::device::codec::{decode_command, MotorCommand};
use crate::device::Device;
use crate::servo::{Servo, ServoReport};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Run the servo loop (PD, hold trajectory) on `device` for at most `max_ticks`, the way
/// `omnid run` builds it, and return its report.
pub fn run_servo(
    cfg: &Config,
    device: Box<dyn Device>,
    max_ticks: u64,
    stop: Arc<AtomicBool>,
) -> ServoReport {
    let (tx, rx) = crossbeam_channel::bounded(cfg.telemetry.channel_capacity);
    let reference = Reference::new(Trajectory::Hold, &cfg.reference, cfg.sim.seed);
    let servo = Servo::new(
        cfg,
        device,
        ControllerSet::new(cfg, ControllerKind::Pd, 0.0),
        reference,
        tx,
        stop,
        Some(max_ticks),
        true,
    );
    let report = servo.run();
    drop(rx);
    report
}

/// Decode every command packet; a malformed one fails the test.
pub fn decode_all(packets: &[[u8; 16]]) -> Vec<MotorCommand> {
    packets
        .iter()
        .map(|p| decode_command(p).expect("the backend sent a malformed command"))
        .collect()
}

/// Checks every property of what a backend put on the wire during a run: amplifiers never on
/// before `first_sample_at` (index of the first packet sent after a sample was delivered),
/// byte 7 the open drivers' constant on every packet (docs/FIREWIRE.md §3), and the last packet
/// safe.
pub fn assert_wire_discipline(sent: &[MotorCommand], first_sample_at: usize) {
    assert!(!sent.is_empty(), "nothing was sent");
    for (i, c) in sent.iter().enumerate().take(first_sample_at) {
        assert!(
            !c.amps_on,
            "packet {i} switched the amplifiers on before a sample was delivered"
        );
    }
    for (i, c) in sent.iter().enumerate() {
        assert_eq!(
            c.watchdog,
            crate::device::codec::DRIVERS_BYTE7,
            "packet {i}: byte 7 must be the drivers' constant 0x53"
        );
    }
    let last = sent.last().unwrap();
    assert!(last.is_safe(), "the last packet is not safe: {last:?}");
}

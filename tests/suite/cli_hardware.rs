//! Real-hardware paths on a machine without the device: a clear message, fast, no panic.
//! (With a device attached these tests would see it; they only assert on the absent case.)

use crate::common;
use common::omnid;
use std::time::{Duration, Instant};

fn has_hardware() -> bool {
    std::path::Path::new("/dev/bus/usb").exists()
        || std::fs::read_dir("/dev")
            .map(|d| {
                d.flatten()
                    .any(|e| e.file_name().to_string_lossy().starts_with("fw"))
            })
            .unwrap_or(false)
}

#[test]
fn usb_and_firewire_without_hardware_fail_fast_and_say_what_was_looked_for() {
    if has_hardware() {
        eprintln!("skipping: this machine has USB or FireWire");
        return;
    }
    for (device, says) in [("usb", "USB bridge with id"), ("firewire", "0x000B99")] {
        let t0 = Instant::now();
        let out = omnid().args(["run", "--device", device]).output().unwrap();
        let took = t0.elapsed();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(3), "{device}: {err}");
        assert!(
            err.contains("no device found") && err.contains(says),
            "{device}: {err}"
        );
        assert!(!err.contains("panicked"));
        // Generous bound for a loaded CI machine; it takes milliseconds.
        assert!(took < Duration::from_secs(5), "{device} took {took:?}");
    }
}

#[test]
fn devices_reports_none_with_the_reason() {
    if has_hardware() {
        eprintln!("skipping: this machine has USB or FireWire");
        return;
    }
    let out = omnid().arg("devices").output().unwrap();
    assert!(out.status.success());
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("No usable Omni found"), "{text}");
    assert!(
        text.contains("No USB and no FireWire on this machine"),
        "{text}"
    );
}

#[test]
fn fast_is_refused_for_real_hardware() {
    let out = omnid()
        .args(["run", "--device", "usb", "--fast"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("--fast works only"));
}

#[test]
fn probe_without_hardware_says_what_it_looked_for_and_writes_nothing() {
    if has_hardware() {
        eprintln!("skipping: this machine has USB or FireWire");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let capture = dir.path().join("capture.txt");
    let out = omnid()
        .args(["probe", "--seconds", "1", "--capture"])
        .arg(&capture)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(
        err.contains("no device found") && err.contains("0x000B99"),
        "{err}"
    );
    assert!(!capture.exists(), "a capture was written without a device");
    assert!(!err.contains("panicked"));
}

#[test]
fn probe_refuses_bad_options_before_touching_anything() {
    for (args, says) in [
        (&["probe", "--counts", "500"][..], "--counts 500"),
        (&["probe", "--seconds", "0"][..], "--seconds 0"),
        (&["probe", "--device", "usb"][..], "only firewire"),
    ] {
        let out = omnid().args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(says), "{args:?}: {err}");
    }
}

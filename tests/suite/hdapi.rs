//! The OpenHaptics-compatible libHD (clients/hdapi, docs/HDAPI.md) against this build's
//! `omnid serve --device sim`: the ABI and constants of our headers, the exported names and
//! the SONAME, C programs replaying the call orders of CHAI3D, the ROS driver, the JHU driver
//! and VRPN, and pyOpenHaptics from PyPI (tests/suite/hdapi_python.rs).

use crate::common;
use crate::hd;

use crate::common::Served;
use hd::{run, HD};
use omnid::omni::kinematics::{jacobian, tip_position_mm, Geometry};
use omnid::transport::client::Message;
use std::io::{BufRead, BufReader};
use std::process::Stdio;
use std::time::{Duration, Instant};

/// Every constant of docs/HDAPI.md's table, written from that table (not from our header).
const TABLE: &[(&str, u64)] = &[
    ("HD_TRUE", 1),
    ("HD_FALSE", 0),
    ("HD_CALLBACK_DONE", 0),
    ("HD_CALLBACK_CONTINUE", 1),
    ("HD_WAIT_CHECK_STATUS", 0),
    ("HD_WAIT_INFINITE", 1),
    ("HD_INVALID_HANDLE", 0xFFFF_FFFF),
    ("HD_MAX_SCHEDULER_PRIORITY", 65535),
    ("HD_MIN_SCHEDULER_PRIORITY", 0),
    ("HD_DEFAULT_SCHEDULER_PRIORITY", 32767),
    ("HD_DEVICE_BUTTON_1", 1),
    ("HD_DEVICE_BUTTON_2", 2),
    ("HD_DEVICE_BUTTON_3", 4),
    ("HD_DEVICE_BUTTON_4", 8),
    ("HD_CALIBRATION_OK", 0x5000),
    ("HD_CALIBRATION_NEEDS_UPDATE", 0x5001),
    ("HD_CALIBRATION_NEEDS_MANUAL_INPUT", 0x5002),
    ("HD_CALIBRATION_ENCODER_RESET", 1),
    ("HD_CALIBRATION_AUTO", 2),
    ("HD_CALIBRATION_INKWELL", 4),
    ("HD_SUCCESS", 0),
    ("HD_INVALID_ENUM", 0x100),
    ("HD_INVALID_VALUE", 0x101),
    ("HD_INVALID_OPERATION", 0x102),
    ("HD_INVALID_INPUT_TYPE", 0x103),
    ("HD_BAD_HANDLE", 0x104),
    ("HD_WARM_MOTORS", 0x200),
    ("HD_EXCEEDED_MAX_FORCE", 0x201),
    ("HD_EXCEEDED_MAX_FORCE_IMPULSE", 0x202),
    ("HD_EXCEEDED_MAX_VELOCITY", 0x203),
    ("HD_FORCE_ERROR", 0x204),
    ("HD_DEVICE_FAULT", 0x300),
    ("HD_DEVICE_ALREADY_INITIATED", 0x301),
    ("HD_COMM_ERROR", 0x302),
    ("HD_COMM_CONFIG_ERROR", 0x303),
    ("HD_TIMER_ERROR", 0x304),
    ("HD_ILLEGAL_BEGIN", 0x400),
    ("HD_ILLEGAL_END", 0x401),
    ("HD_FRAME_ERROR", 0x402),
    ("HD_INVALID_PRIORITY", 0x500),
    ("HD_SCHEDULER_FULL", 0x501),
    ("HD_INVALID_LICENSE", 0x600),
    ("HD_CURRENT_BUTTONS", 0x2000),
    ("HD_CURRENT_SAFETY_SWITCH", 0x2001),
    ("HD_CURRENT_INKWELL_SWITCH", 0x2002),
    ("HD_CURRENT_ENCODER_VALUES", 0x2010),
    ("HD_CURRENT_POSITION", 0x2050),
    ("HD_CURRENT_VELOCITY", 0x2051),
    ("HD_CURRENT_TRANSFORM", 0x2052),
    ("HD_CURRENT_ANGULAR_VELOCITY", 0x2053),
    ("HD_CURRENT_JACOBIAN", 0x2054),
    ("HD_CURRENT_JOINT_ANGLES", 0x2100),
    ("HD_CURRENT_GIMBAL_ANGLES", 0x2150),
    ("HD_LAST_BUTTONS", 0x2200),
    ("HD_LAST_SAFETY_SWITCH", 0x2201),
    ("HD_LAST_INKWELL_SWITCH", 0x2202),
    ("HD_LAST_ENCODER_VALUES", 0x2210),
    ("HD_LAST_POSITION", 0x2250),
    ("HD_LAST_VELOCITY", 0x2251),
    ("HD_LAST_TRANSFORM", 0x2252),
    ("HD_LAST_ANGULAR_VELOCITY", 0x2253),
    ("HD_LAST_JACOBIAN", 0x2254),
    ("HD_LAST_JOINT_ANGLES", 0x2300),
    ("HD_LAST_GIMBAL_ANGLES", 0x2350),
    ("HD_VERSION", 0x2500),
    ("HD_DEVICE_MODEL_TYPE", 0x2501),
    ("HD_DEVICE_DRIVER_VERSION", 0x2502),
    ("HD_DEVICE_VENDOR", 0x2503),
    ("HD_DEVICE_SERIAL_NUMBER", 0x2504),
    ("HD_DEVICE_FIRMWARE_VERSION", 0x2505),
    ("HD_MAX_WORKSPACE_DIMENSIONS", 0x2550),
    ("HD_USABLE_WORKSPACE_DIMENSIONS", 0x2551),
    ("HD_TABLETOP_OFFSET", 0x2552),
    ("HD_INPUT_DOF", 0x2553),
    ("HD_OUTPUT_DOF", 0x2554),
    ("HD_CALIBRATION_STYLE", 0x2555),
    ("HD_UPDATE_RATE", 0x2600),
    ("HD_INSTANTANEOUS_UPDATE_RATE", 0x2601),
    ("HD_NOMINAL_MAX_STIFFNESS", 0x2602),
    ("HD_NOMINAL_MAX_FORCE", 0x2603),
    ("HD_NOMINAL_MAX_CONTINUOUS_FORCE", 0x2604),
    ("HD_MOTOR_TEMPERATURE", 0x2605),
    ("HD_SOFTWARE_VELOCITY_LIMIT", 0x2606),
    ("HD_SOFTWARE_FORCE_IMPULSE_LIMIT", 0x2607),
    ("HD_FORCE_RAMPING_RATE", 0x2608),
    ("HD_NOMINAL_MAX_DAMPING", 0x2609),
    ("HD_CURRENT_FORCE", 0x2700),
    ("HD_CURRENT_TORQUE", 0x2701),
    ("HD_CURRENT_JOINT_TORQUE", 0x2703),
    ("HD_CURRENT_GIMBAL_TORQUE", 0x2704),
    ("HD_CURRENT_MOTOR_DAC_VALUES", 0x2750),
    ("HD_LAST_FORCE", 0x2800),
    ("HD_LAST_TORQUE", 0x2801),
    ("HD_LAST_JOINT_TORQUE", 0x2802),
    ("HD_LAST_GIMBAL_TORQUE", 0x2803),
    ("HD_FORCE_OUTPUT", 0x4000),
    ("HD_MAX_FORCE_CLAMPING", 0x4001),
    ("HD_FORCE_RAMPING", 0x4002),
    ("HD_SOFTWARE_FORCE_LIMIT", 0x4003),
    ("HD_ONE_FRAME_LIMIT", 0x4004),
    ("HD_DEFAULT_DEVICE_IS_NULL", 1),
    ("HD_DEVICE_ERROR", 1),
];

/// The 36 functions the library exports (docs/HDAPI.md, Functions).
const EXPORTS: [&str; 36] = [
    "hdBeginFrame",
    "hdCheckCalibration",
    "hdCheckCalibrationStyle",
    "hdDeploymentLicense",
    "hdDisable",
    "hdDisableDevice",
    "hdEnable",
    "hdEndFrame",
    "hdGetBooleanv",
    "hdGetCurrentDevice",
    "hdGetDoublev",
    "hdGetError",
    "hdGetErrorString",
    "hdGetFloatv",
    "hdGetIntegerv",
    "hdGetLongv",
    "hdGetSchedulerTimeStamp",
    "hdGetString",
    "hdInitDevice",
    "hdIsEnabled",
    "hdMakeCurrentDevice",
    "hdScaleGimbalAngles",
    "hdScheduleAsynchronous",
    "hdScheduleSynchronous",
    "hdSetBooleanv",
    "hdSetDoublev",
    "hdSetFloatv",
    "hdSetIntegerv",
    "hdSetLongv",
    "hdSetSchedulerRate",
    "hdStartScheduler",
    "hdStopScheduler",
    "hdUnschedule",
    "hdUpdateCalibration",
    "hdUpdateCalibrationMessage",
    "hdWaitForCompletion",
];

#[test]
#[ignore = "paced"]
fn headers_match_the_abi_and_every_constant_of_the_table() {
    let hd = HD::get();
    for exe in ["abi", "abi_cpp"] {
        let out = run(hd.exe(exe), &[], &[]);
        let printed: Vec<(String, u64)> = out
            .lines()
            .filter(|l| !l.starts_with("HDU") && !l.starts_with("ROS"))
            .map(|l| {
                let (k, v) = l.split_once(' ').expect("NAME VALUE");
                (k.to_string(), v.parse().expect("a number"))
            })
            .collect();
        let expected: Vec<(String, u64)> = TABLE.iter().map(|(k, v)| (k.to_string(), *v)).collect();
        assert_eq!(printed, expected, "{exe}");
        if exe == "abi_cpp" {
            // (1,2,3)·(4,5,6) = 32; a quarter turn about z then (10,20,30); a unit quaternion.
            assert!(
                out.contains("HDU 32.0 8.0 21.0 33.0 1.000"),
                "HDU helpers: {out}"
            );
            // (3·1 − 4·4 + 1) / 0.002 = −6000.
            assert!(out.contains("ROS 0.0 1.000 -6000.0"), "HDU helpers: {out}");
        }
    }
}

#[test]
#[ignore = "paced"]
fn library_exports_the_36_names_under_its_soname_with_the_links() {
    let hd = HD::get();
    let lib = hd.prefix.join("lib");
    let nm = std::process::Command::new("nm")
        .args(["-D", "--defined-only"])
        .arg(lib.join("libHD.so.3.4.0"))
        .output()
        .expect("nm runs");
    assert!(nm.status.success());
    let mut names: Vec<String> = String::from_utf8_lossy(&nm.stdout)
        .lines()
        .filter_map(|l| l.split_whitespace().nth(2).map(String::from))
        .collect();
    names.sort();
    assert_eq!(names, EXPORTS, "exactly the 36 names, nothing else");
    let readelf = std::process::Command::new("readelf")
        .arg("-d")
        .arg(lib.join("libHD.so.3.4.0"))
        .output()
        .expect("readelf runs");
    assert!(
        String::from_utf8_lossy(&readelf.stdout).contains("Library soname: [libHD.so.3.4]"),
        "{}",
        String::from_utf8_lossy(&readelf.stdout)
    );
    for link in ["libHD.so.3.4", "libHD.so.3.0", "libHD.so"] {
        let target = std::fs::read_link(lib.join(link)).expect("a link");
        assert_eq!(target.to_str(), Some("libHD.so.3.4.0"), "{link}");
    }
}

#[test]
#[ignore = "paced"]
fn no_daemon_is_a_communication_error_not_a_crash() {
    let hd = HD::get();
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.sock");
    let out = run(
        hd.exe("nodaemon"),
        &[],
        &[("OMNID_SOCKET", missing.to_str().unwrap())],
    );
    assert_eq!(out.trim(), "handle 0xffffffff error 0x302 then 0");
}

/// A printed sample's fields after `tag`.
struct Sample {
    pos: [f64; 3],
    q: [f64; 3],
    tr: [f64; 3],
    gimbal: [f64; 3],
    buttons: i64,
}

fn sample(out: &str, tag: &str) -> Sample {
    let line = out
        .lines()
        .find(|l| l.starts_with(&format!("{tag} pos ")))
        .unwrap_or_else(|| panic!("no `{tag}` sample in:\n{out}"));
    let w: Vec<&str> = line.split_whitespace().collect();
    let three = |key: &str| -> [f64; 3] {
        let k = w.iter().position(|x| *x == key).unwrap();
        std::array::from_fn(|j| w[k + 1 + j].parse().unwrap())
    };
    let b = w.iter().position(|x| *x == "buttons").unwrap();
    Sample {
        pos: three("pos"),
        q: three("q"),
        tr: three("tr"),
        gimbal: three("g"),
        buttons: w[b + 1].parse().unwrap(),
    }
}

/// Position in mm as omnid's own forward kinematics puts it for the joint angles read in
/// the same frame; the transform's translation the same; the simulator's gimbal at 0 and no
/// button pressed.
fn consistent(s: &Sample, what: &str) {
    let fk = tip_position_mm(&Geometry::default(), &s.q.into());
    for j in 0..3 {
        assert!(
            (s.pos[j] - fk[j]).abs() < 1e-6,
            "{what}: {:?} vs {fk:?}",
            s.pos
        );
        assert_eq!(s.tr[j], s.pos[j], "{what}: transform translation");
        assert_eq!(s.gimbal[j], 0.0, "{what}: gimbal");
    }
    // A stylus near the simulator's start pose, a plausible Omni tip: not a zero vector.
    assert!(s.pos.iter().any(|v| v.abs() > 1.0), "{what}: {:?}", s.pos);
    assert_eq!(s.buttons, 0, "{what}");
}

fn field<'a>(out: &'a str, key: &str) -> &'a str {
    out.lines()
        .find_map(|l| l.strip_prefix(&format!("{key} ")))
        .unwrap_or_else(|| panic!("no `{key}` in:\n{out}"))
}

#[test]
#[ignore = "paced"]
fn ros_jhu_and_vrpn_call_orders_read_the_simulated_omni() {
    let hd = HD::get();
    let daemon = Served::sim(&[], None);
    let env = [("OMNID_SOCKET", daemon.sock.to_str().unwrap())];

    // ROS: calibration loop on the main thread, schedule after start.
    let ros = run(hd.exe("ros"), &[], &env);
    assert!(field(&ros, "model").starts_with("PHANTOM Omni"), "{ros}");
    assert_eq!(field(&ros, "vendor"), "SensAble Technologies");
    assert!(field(&ros, "driver").starts_with("omnid "), "{ros}");
    assert_eq!(field(&ros, "calibration-style"), "4", "inkwell");
    assert_eq!(field(&ros, "calibration-final"), "0x5000", "{ros}");
    assert_eq!(
        field(&ros, "rate"),
        "1000.0 max-force 3.30 workspace -80.0 80.0"
    );
    let ticks = field(&ros, "ticks");
    assert!(ticks.ends_with(" servo-error 0"), "{ros}");
    assert!(
        ticks.split(' ').next().unwrap().parse::<u32>().unwrap() >= 200,
        "{ros}"
    );
    consistent(&sample(&ros, "sample"), "ros");
    assert!(ros.ends_with("done\n"), "{ros}");

    // JHU: schedule before start, unschedule after stop, priorities, completion.
    let jhu = run(hd.exe("jhu"), &[], &env);
    assert_eq!(field(&jhu, "once"), "1");
    assert_eq!(field(&jhu, "scheduled-while-running"), "1");
    assert_eq!(field(&jhu, "scheduled-after-unschedule"), "0");
    let ticks = field(&jhu, "ticks");
    assert!(ticks.ends_with(" order 1 stopped-on-error 0"), "{jhu}");
    assert!(
        ticks.split(' ').next().unwrap().parse::<u32>().unwrap() >= 300,
        "{jhu}"
    );
    consistent(&sample(&jhu, "sample"), "jhu");

    // VRPN: synchronous reads outside a frame (one sample per tick); a read on the main
    // thread before the scheduler runs (each call the latest sample: the idle arm may move
    // between them, a little); usage errors.
    let vrpn = run(hd.exe("vrpn"), &[], &env);
    let outside = sample(&vrpn, "outside");
    let fk = tip_position_mm(&Geometry::default(), &outside.q.into());
    assert!(
        (0..3).all(|j| (outside.pos[j] - fk[j]).abs() < 5.0),
        "{vrpn}"
    );
    consistent(&sample(&vrpn, "sync"), "vrpn sync");
    // Requests answered while the scheduler's thread reads the socket: no error, no hang.
    assert_eq!(field(&vrpn, "rate"), "0 0", "{vrpn}");
    assert_eq!(field(&vrpn, "errors"), "0x104 0x100 0x401 0");
    assert!(field(&vrpn, "string").contains("omnid"), "{vrpn}");

    // The stylus the programs read is the daemon's: its own stream agrees on the pose.
    let mut c = daemon.connect("check");
    c.request(serde_json::json!({"op": "stream", "rate_hz": 100}))
        .unwrap();
    let s = c.next_state(5000).unwrap();
    let fk = tip_position_mm(&Geometry::default(), &s.q.into());
    assert!((0..3).all(|j| (fk[j] - s.tip_mm[j]).abs() < 1e-9));
    assert_eq!(s.gimbal, [0.0; 3]);
}

/// CHAI3D's order (constructor init, blocking set-force) puts a force on the simulated arm
/// and killing the program takes it off.
#[test]
#[ignore = "paced"]
fn a_force_set_in_a_frame_reaches_the_device_and_killing_the_client_drops_it() {
    let hd = HD::get();
    // No compensation: the motors' torque is exactly the program's (Jᵀ F). The daemon's
    // config is the default (a stale stream holds): the library's lease asks for idle.
    let daemon = Served::sim(&["--controller", "off"], None);
    let mut watch = daemon.connect("watch");
    watch
        .request(serde_json::json!({"op": "stream", "rate_hz": 1000}))
        .unwrap();
    let mut chai = std::process::Command::new(hd.exe("chai"))
        .arg("0.5")
        .env("OMNID_SOCKET", &daemon.sock)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("chai replay starts");
    let _watchdog = hd::Watchdog::new(&chai, Duration::from_secs(60));
    let mut lines = BufReader::new(chai.stdout.take().unwrap()).lines();
    let mut printed = String::new();
    for line in lines.by_ref() {
        let line = line.unwrap();
        printed.push_str(&line);
        printed.push('\n');
        if line.starts_with("force-set") {
            break;
        }
    }
    consistent(&sample(&printed, "sample"), "chai");
    assert!(printed.contains("force-set 0.500000 0 0"), "{printed}");

    // Where realtime priorities are permitted, the frame's round trip runs on them: the
    // program's scheduler thread below the daemon's client hub (the arm's hub thread), both below
    // the servo (docs/HDAPI.md, Scheduler).
    if hd::may_use_fifo(70) {
        assert_eq!(hd::thread_sched(chai.id(), "omnid-hd-servo"), Some((1, 60)));
        assert_eq!(
            hd::thread_sched(daemon.pid() as u32, "omnid-hub-sim"),
            Some((1, 70))
        );
    }

    // The servo applies Jᵀ F (within a DAC step of 2.2e-4 N·m and the tick's motion) once
    // its start-up ramp is over, and the arm turns about its base towards +x.
    let until = Instant::now() + Duration::from_secs(30);
    let (mut first_x, mut applied, mut moved, mut last) = (None, false, false, None);
    while !(applied && moved) {
        assert!(
            Instant::now() < until,
            "the force never reached the device (applied {applied}, moved {moved}); last \
             state in a stream mode: {last:?}"
        );
        let Ok(s) = watch.next_state(2000) else {
            continue;
        };
        if !s.mode.starts_with("servo_") {
            continue;
        }
        let x = *first_x.get_or_insert(s.tip_mm[0]);
        let j = jacobian(&Geometry::default(), &s.q.into());
        let want = j.transpose() * omnid::omni::Joint3::new(0.5, 0.0, 0.0);
        // +x at the tip is a negative base torque. The base joint only: gravity takes the
        // uncompensated arm down into its soft walls, whose torque adds to the other joints.
        applied |= s.amps && s.tau[0] < -0.01 && (s.tau[0] - want[0]).abs() < 2e-3;
        moved |= s.tip_mm[0] > x + 1.0;
        last = Some(s);
    }

    chai.kill().unwrap();
    chai.wait().unwrap();
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        assert!(Instant::now() < until, "the force outlived its client");
        match watch.recv(2000) {
            Ok(Message::State(s)) if !s.mode.starts_with("servo_") => {
                assert_eq!(s.tau, [0.0; 3], "zero force once the client is gone");
                assert!(!s.amps && s.mode == "idle", "{s:?}");
                break;
            }
            _ => {}
        }
    }
}

/// The daemon stopping under a running program is a communication error in its servo
/// callback (which ends on it), never a hang.
#[test]
#[ignore = "paced"]
fn a_daemon_that_stops_is_a_communication_error_in_the_servo_callback() {
    let hd = HD::get();
    let mut daemon = Served::sim(&[], None);
    let mut child = std::process::Command::new(hd.exe("gone"))
        .env("OMNID_SOCKET", &daemon.sock)
        .stdout(Stdio::piped())
        .spawn()
        .expect("starts");
    let watchdog = hd::Watchdog::new(&child, Duration::from_secs(60));
    let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
    assert_eq!(lines.next().unwrap().unwrap(), "running");
    daemon.stop();
    let rest: Vec<String> = lines.map(|l| l.unwrap()).collect();
    let status = child.wait().unwrap();
    drop(watchdog);
    assert!(status.success(), "{status}: {rest:?}");
    assert_eq!(rest, ["servo-error 0x302"]);
}

/// A test that fails while its C program runs must not leave the program behind (one outlived
/// a failed run by an hour before the watchdog killed children on a panic).
#[test]
#[ignore = "paced"]
fn a_failing_test_does_not_leave_its_program_running() {
    use std::os::unix::process::ExitStatusExt;
    let mut child = std::process::Command::new("sleep")
        .arg("30")
        .spawn()
        .expect("sleep runs");
    let failed = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let _watchdog = hd::Watchdog::new(&child, Duration::from_secs(60));
        panic!("a test failing while its program runs");
    }));
    assert!(failed.is_err());
    let status = child.wait().unwrap();
    assert_eq!(status.signal(), Some(libc::SIGKILL), "{status:?}");
}

/// Two arms of one daemon opened by the vendor's dual-device names (`[[arm]] aliases`), forces
/// rendered on both in one scheduler callback: each arm turns the way its own force pushes.
#[test]
#[ignore = "paced"]
fn two_devices_by_their_vendor_names_in_one_scheduler_callback() {
    let hd = HD::get();
    let (left, right) = (
        format!("hdl-{}", std::process::id()),
        format!("hdr-{}", std::process::id()),
    );
    let config = format!(
        "[[arm]]\nname = \"{left}\"\naliases = [\"PHANToM 1\"]\n\
         [[arm]]\nname = \"{right}\"\naliases = [\"PHANToM 2\"]\n"
    );
    let d = common::Served::start(&["--controller", "off"], Some(&config), &[&left, &right]);
    let runtime = d.dir.path().display().to_string();
    let out = run(
        hd.exe("two"),
        &[],
        &[("XDG_RUNTIME_DIR", &runtime), ("RUNTIME_DIRECTORY", "")],
    );
    assert!(out.contains("done 1500"), "{out}");
    let x = |tag: &str| -> f64 {
        let line = out.lines().find(|l| l.starts_with(tag)).unwrap();
        line.split_whitespace().nth(2).unwrap().parse().unwrap()
    };
    // Both start docked at x = 0 (the base turned to the middle); +0.5 N along x turns the left
    // arm to +x, -0.5 N the right one to -x. How far depends on how many device ticks the
    // program's 1500 frames span (fewer on a loaded machine: 4.5 mm seen in a full run), so
    // the bound is out of the inkwell's hold (0.02 rad, about 2.6 mm at the tip), not a
    // distance in time.
    let (xl, xr) = (x("left "), x("right "));
    assert!(
        xl > 3.0 && xr < -3.0,
        "left x {xl} mm, right x {xr} mm\n{out}"
    );
}

/// A servo callback slower than the force's 20 ms time to live: the force holds between its
/// frames (the amplifiers do not cycle), and frames further apart than a force can be held
/// (100 ms) raise HD_TIMER_ERROR instead of losing the force silently.
#[test]
#[ignore = "paced"]
fn a_slow_servo_callback_keeps_its_force_or_is_told() {
    let hd = HD::get();
    // 30 ms frames: slower than the default time to live (20 ms), 70 ms inside the longest.
    for (frame_ms, told) in [(30, false), (150, true)] {
        let daemon = Served::sim(&[], None);
        let mut watch = daemon.connect("watch");
        watch
            .request(serde_json::json!({"op": "stream", "rate_hz": 1000}))
            .unwrap();
        let slow = std::process::Command::new(hd.exe("slow"))
            .arg(frame_ms.to_string())
            .env("OMNID_SOCKET", &daemon.sock)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("slow starts");
        let _watchdog = hd::Watchdog::new(&slow, Duration::from_secs(60));
        // Amplifier drops while the program pushes: from its first force to its end.
        let (mut pushing, mut drops) = (false, 0);
        let until = Instant::now() + Duration::from_millis(2300);
        while Instant::now() < until {
            let Ok(s) = watch.next_state(500) else {
                continue;
            };
            if s.mode.starts_with("servo_") && s.amps {
                pushing = true;
            } else if pushing && s.mode == "idle" {
                drops += 1;
                pushing = false;
            }
        }
        let out = slow.wait_with_output().unwrap();
        let printed = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "{printed}");
        let errors: u32 = field(&printed, "timer-errors").parse().unwrap();
        if told {
            assert!(errors >= 1, "{frame_ms} ms frames: {printed}");
        } else {
            assert_eq!(errors, 0, "{frame_ms} ms frames: {printed}");
            // The last frame's force lapses once when the program stops: at most that drop.
            assert!(
                drops <= 1,
                "{frame_ms} ms frames: the amplifiers dropped {drops} times"
            );
        }
    }
}

/// The HDU headers install.sh lays out (docs/HDAPI.md, libHDU).
const HDU_HEADERS: [&str; 7] = [
    "hdu.h",
    "hduError.h",
    "hduLineSegment.h",
    "hduMath.h",
    "hduMatrix.h",
    "hduQuaternion.h",
    "hduVector.h",
];

/// Compile `source` (given on stdin, in `lang`) with `flags` against the installed headers:
/// whether it compiled, and the compiler's messages.
fn compile_snippet(compiler: &str, lang: &str, flags: &[&str], source: &str) -> (bool, String) {
    use std::io::Write;
    let hd = HD::get();
    let mut child = std::process::Command::new(compiler)
        .args(["-x", lang])
        .args(flags)
        .arg("-I")
        .arg(hd.prefix.join("include"))
        .args(["-fsyntax-only", "-"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{compiler}: {e} (a C/C++ compiler is needed)"));
    child
        .stdin
        .take()
        .unwrap()
        .write_all(source.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
#[ignore = "paced"]
fn every_hdu_header_compiles_alone_in_c_and_in_cpp() {
    let hd = HD::get();
    let mut installed: Vec<String> = std::fs::read_dir(hd.prefix.join("include/HDU"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    installed.sort();
    assert_eq!(installed, HDU_HEADERS, "the installed HDU headers");
    for header in HDU_HEADERS {
        // Twice: the include guard holds.
        let source = format!(
            "#include <HDU/{header}>\n#include <HDU/{header}>\nint main(void) {{ return 0; }}\n"
        );
        for (compiler, lang, std) in [
            ("cc", "c", "-std=c99"),
            ("cc", "c", "-std=c11"),
            ("c++", "c++", "-std=c++11"),
            ("c++", "c++", "-std=c++17"),
        ] {
            let (ok, messages) = compile_snippet(
                compiler,
                lang,
                &[std, "-Wall", "-Wextra", "-Wpedantic", "-Werror"],
                &source,
            );
            assert!(ok, "{header} alone as {lang} ({std}):\n{messages}");
        }
    }
}

#[test]
#[ignore = "paced"]
fn hl_stops_the_build_with_one_error_naming_hd_hdu_and_the_docs() {
    let source = "#include <HL/hl.h>\nint main(void) { return 0; }\n";
    for (compiler, lang) in [("cc", "c"), ("c++", "c++")] {
        let (ok, messages) = compile_snippet(compiler, lang, &[], source);
        assert!(!ok, "HL/hl.h compiled as {lang}");
        // Diagnostics are "file:line:col: error: …" (the quoted source lines after them are not).
        let errors: Vec<&str> = messages
            .lines()
            .filter(|l| l.contains(": error:"))
            .collect();
        assert_eq!(errors.len(), 1, "exactly one error as {lang}:\n{messages}");
        for needle in ["HL", "HDU", "Haptic Library API", "docs/HDAPI.md"] {
            assert!(errors[0].contains(needle), "{needle} in: {}", errors[0]);
        }
        // The ROS driver includes it and calls nothing of HL: the opt-in lets it build.
        let (ok, messages) = compile_snippet(compiler, lang, &["-DOMNID_HL_INCLUDE_ONLY"], source);
        assert!(ok, "with OMNID_HL_INCLUDE_ONLY as {lang}:\n{messages}");
    }
}

/// A program's "key v1 v2 ..." lines: the numbers after `key` (panics if absent).
fn numbers(out: &str, key: &str) -> Vec<f64> {
    let line = out
        .lines()
        .find(|l| l.split_whitespace().next() == Some(key))
        .unwrap_or_else(|| panic!("no {key} in:\n{out}"));
    line.split_whitespace()
        .skip(1)
        .filter_map(|w| w.parse().ok())
        .collect()
}

fn assert_close(out: &str, key: &str, expected: &[f64], tol: f64) {
    let got = numbers(out, key);
    assert_eq!(got.len(), expected.len(), "{key}: {got:?} vs {expected:?}");
    for (g, e) in got.iter().zip(expected) {
        assert!((g - e).abs() <= tol, "{key}: {got:?} vs {expected:?}");
    }
}

/// Link flags of the SDK's HD console examples' Makefiles, and nothing else.
const SDK_LIBS: [&str; 4] = ["-lHDU", "-lHD", "-lrt", "-lncurses"];

/// Two of the SDK's example Makefiles leave out a library their program calls (Vibration's
/// `-lm`, CommandMotorDAC's `-lncurses`): linked with `-lHDU -lHD` alone such a program still
/// links, through the linker script install.sh puts at libHDU.so (docs/HDAPI.md, libHDU).
#[test]
#[ignore = "paced"]
fn a_program_linked_with_only_lhdu_lhd_gets_libm_and_ncurses() {
    let hd = HD::get();
    let (_own, exe) = hd.compile_with(
        "unnamed_libs",
        "unnamed_libs.c",
        "cc",
        &["-std=c11"],
        &["-lHDU", "-lHD"],
    );
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.sock");
    let out = run(exe, &[], &[("OMNID_SOCKET", missing.to_str().unwrap())]);
    assert!(out.contains(&format!("sin {:.6}", 0.5f64.sin())), "{out}");
}

#[test]
#[ignore = "paced"]
fn hdu_c_functions_and_error_helpers_link_as_the_sdk_examples_do() {
    use nalgebra::Vector3;
    let hd = HD::get();
    let (_own, exe) = hd.compile_with("hdu_c", "hdu.c", "cc", &["-std=c11", "-Wextra"], &SDK_LIBS);
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("none.sock");
    let out = run(exe, &[], &[("OMNID_SOCKET", missing.to_str().unwrap())]);
    let v = |x: Vector3<f64>| [x.x, x.y, x.z];
    let a = Vector3::new(1.0, 2.0, 3.0);
    let b = Vector3::new(-4.0, 0.5, 2.0);
    let eps = 1e-12;
    assert_close(&out, "add", &v(a + b), eps);
    assert_close(&out, "sub", &v(a - b), eps);
    assert_close(&out, "scale", &v(a * 2.5), eps);
    assert_close(&out, "scale-in-place", &v(b * -3.0), eps);
    assert_close(&out, "scale-non-uniform", &v(a.component_mul(&b)), eps);
    assert_close(
        &out,
        "scale-non-uniform-in-place",
        &v(a.component_mul(&b)),
        eps,
    );
    assert_close(&out, "negate", &v(-b), eps);
    assert_close(&out, "cross", &v(a.cross(&b)), eps);
    assert_close(&out, "cross-aliased", &v(a.cross(&b)), eps);
    assert_close(&out, "normalize", &v(b.normalize()), eps);
    assert_close(&out, "normalize-in-place", &v(a.normalize()), eps);
    assert_close(&out, "normalize-zero", &[0.0; 3], 0.0);
    assert_close(&out, "magnitude", &[a.norm()], eps);
    assert_close(&out, "dot", &[a.dot(&b)], eps);
    assert_close(&out, "distance", &[(a - b).norm()], eps);
    assert_close(&out, "equal", &[1.0, 0.0, 0.0], 0.0);
    let spring = (Vector3::new(10.0, -20.0, 5.0) - Vector3::new(12.0, -18.0, 4.0)) * 0.25;
    assert_close(&out, "spring", &v(spring), eps);
    let pi = std::f64::consts::PI;
    assert_close(&out, "math", &[pi / 2.0, 45.0, 3.0, 0.0, -7.0, 2.0], eps);

    // Which codes are which kind (docs/HDAPI.md, libHDU), from the table's names.
    let code = |name: &str| TABLE.iter().find(|(n, _)| *n == name).unwrap().1;
    let scheduler = [
        "HD_COMM_ERROR",
        "HD_COMM_CONFIG_ERROR",
        "HD_TIMER_ERROR",
        "HD_DEVICE_FAULT",
        "HD_INVALID_PRIORITY",
        "HD_SCHEDULER_FULL",
    ]
    .map(code);
    let force = [
        "HD_WARM_MOTORS",
        "HD_EXCEEDED_MAX_FORCE",
        "HD_EXCEEDED_MAX_FORCE_IMPULSE",
        "HD_EXCEEDED_MAX_VELOCITY",
        "HD_FORCE_ERROR",
    ]
    .map(code);
    let com = ["HD_COMM_ERROR", "HD_COMM_CONFIG_ERROR"].map(code);
    let kinds: Vec<&str> = out.lines().filter(|l| l.starts_with("kind ")).collect();
    assert_eq!(kinds.len(), 22, "every error code:\n{out}");
    for line in kinds {
        let n: Vec<u64> = line[5..]
            .split_whitespace()
            .map(|w| w.parse().unwrap())
            .collect();
        let flag = |set: &[u64]| u64::from(set.contains(&n[0]));
        assert_eq!(
            n[1..],
            [flag(&scheduler), flag(&force), flag(&com)],
            "{line}"
        );
    }
    assert!(out.contains("kind-null 0 0 0"), "{out}");

    // hduPrintError on the real error of hdInitDevice without a daemon.
    let printed: Vec<&str> = out
        .split("print-begin\n")
        .skip(1)
        .map(|s| s.split("print-end").next().unwrap())
        .collect();
    assert_eq!(printed.len(), 2, "{out}");
    for needle in [
        "HD_COMM_ERROR",
        "0x0302",
        "Communication error",
        "internal error code: 1",
        "Failed to initialize haptic device",
    ] {
        assert!(printed[0].contains(needle), "{needle} in:\n{}", printed[0]);
    }
    assert!(printed[1].contains("0x0777"), "{}", printed[1]);
    assert!(
        out.contains(&format!("init-error {} 1", code("HD_COMM_ERROR"))),
        "{out}"
    );
    assert!(
        !out.contains("no error given") && !out.contains("no stream"),
        "NULL error or stream prints nothing:\n{out}"
    );
    assert!(out.ends_with("done\n"), "{out}");
}

#[test]
#[ignore = "paced"]
fn hdu_cpp_vectors_matrices_and_quaternions_agree_with_nalgebra() {
    use nalgebra::{Matrix4, Rotation3, Unit, UnitQuaternion, Vector3};
    let hd = HD::get();
    let (_own, exe) = hd.compile_with(
        "hdu_cpp",
        "hdu.cpp",
        "c++",
        &["-std=c++11", "-Wextra"],
        &SDK_LIBS,
    );
    let out = run(exe, &[], &[]);
    let v = |x: Vector3<f64>| [x.x, x.y, x.z];
    let eps = 1e-12;
    let a = Vector3::new(1.0, 2.0, 3.0);
    let b = Vector3::new(-4.0, 0.5, 2.0);
    assert_close(&out, "ops", &v((a + b) * 2.0 - b / 4.0), eps);
    assert_close(&out, "neg", &v(-a), eps);
    assert_close(&out, "cross", &v(a.cross(&b)), eps);
    assert_close(&out, "cross-free", &v(a.cross(&b)), eps);
    assert_close(&out, "dot", &[a.dot(&b), a.dot(&b)], eps);
    assert_close(&out, "magnitude", &[a.norm()], eps);
    assert_close(&out, "distance", &[(a - b).norm()], eps);
    assert_close(&out, "normalize-free", &v(b.normalize()), eps);
    assert_close(&out, "normalize", &v(b.normalize()), eps);
    assert_close(&out, "unchanged", &[1.0], 0.0);
    assert_close(&out, "stream", &[1.0], 0.0);
    assert_close(&out, "c-add", &v(a + b), eps);

    // A quarter turn about each axis, right-handed: x to y, y to z, z to x.
    assert_close(&out, "rz-x", &[0.0, 1.0, 0.0], eps);
    assert_close(&out, "rx-y", &[0.0, 0.0, 1.0], eps);
    assert_close(&out, "ry-z", &[1.0, 0.0, 0.0], eps);

    let axis = Vector3::new(1.0, 2.0, 3.0);
    let angle = 0.7;
    let r = Rotation3::from_axis_angle(&Unit::new_normalize(axis), angle);
    let p = Vector3::new(0.3, -1.0, 2.0);
    // hduMatrix holds points as rows (p' = p M): its m[row][col] is R(col, row).
    let mut rows = Vec::new();
    let rt = Matrix4::from(r).transpose();
    for row in 0..4 {
        for col in 0..4 {
            rows.push(rt[(row, col)]);
        }
    }
    assert_close(&out, "rot", &rows, eps);
    assert_close(&out, "rot-p", &v(r * p), eps);
    // s * rot * t: scale, then rotate, then translate.
    let scaled = p.component_mul(&Vector3::new(2.0, 3.0, 4.0));
    assert_close(
        &out,
        "srt-p",
        &v(r * scaled + Vector3::new(10.0, 20.0, 30.0)),
        1e-9,
    );
    assert_close(&out, "srt-dir", &v(r * scaled), 1e-9);
    assert_close(&out, "mult", &[0.0, 0.0], 0.0);
    assert_close(&out, "inverse", &[0.0, 0.0], 1e-9);
    assert_close(&out, "invert", &[1.0, 0.0, 1.0], 0.0);
    assert_close(&out, "transpose", &[0.0, 0.0], 1e-12);
    assert_close(&out, "determinant", &[24.0, 1.0], 1e-9);
    assert_close(&out, "storage", &[10.0, 20.0, 30.0, 10.0, 1.0], 0.0);
    assert_close(&out, "translation", &[10.0, 20.0, 30.0], 0.0);
    assert_close(&out, "rotation-part", &[0.0, 0.0, 0.0], 0.0);
    assert_close(&out, "matrix-stream", &[1.0], 0.0);

    let q = UnitQuaternion::from_axis_angle(&Unit::new_normalize(axis), angle);
    assert_close(&out, "q", &[q.w, q.i, q.j, q.k, 1.0], eps);
    for key in [
        "q-matrix",
        "q-rotate",
        "q-from-matrix",
        "q-round-trip",
        "q-compose",
        "q-inverse",
        "q-slerp",
    ] {
        assert_close(&out, key, &[0.0], 1e-12);
    }
    assert_close(&out, "q-axis-angle", &[0.0, angle], 1e-12);

    assert_close(&out, "seg-project", &[5.0, 0.0, 0.0], eps);
    assert_close(&out, "seg-t", &[0.5, 3.0, 5f64.sqrt(), 10.0], eps);
    assert_close(&out, "seg-beyond", &[10.0, 0.0, 0.0], eps);
    assert_close(&out, "math", &[5.0, std::f64::consts::PI, 0.5, 1.0], eps);
    assert!(out.contains("error-stream names"), "{out}");
    assert_close(&out, "error-kind", &[1.0, 0.0, 0.0], 0.0);
    assert!(out.ends_with("done\n"), "{out}");
}

#[test]
#[ignore = "paced"]
fn hdu_vectors_in_cpp_linked_by_gcc_need_no_cpp_runtime() {
    use nalgebra::Vector3;
    let hd = HD::get();
    // As the SDK's CommandJointTorque builds: gcc on a .cpp, "-lHDU -lHD -lrt", no libstdc++.
    let (_own, exe) = hd.compile_with(
        "hdu_gcc",
        "hdu_gcc.cpp",
        "cc",
        &["-std=c++11", "-Wextra"],
        &["-lHDU", "-lHD", "-lrt"],
    );
    let out = run(exe, &[], &[]);
    let f = (Vector3::new(10.0, -20.0, 5.0) - Vector3::new(12.0, -18.0, 4.0)) * 0.25;
    let max_torque = Vector3::new(188.0, 188.0, 48.0);
    let expected = [
        f.x,
        f.y,
        f.z,
        f.dot(&max_torque),
        f.cross(&max_torque).z,
        2.0 * f.x,
        f.norm_squared(),
        1.0,
    ];
    assert_close(&out, "gcc", &expected, 1e-9);
}

#[test]
#[ignore = "paced"]
fn motor_temperature_comes_from_the_thermal_model_and_an_unsupported_parameter_is_refused_once() {
    let hd = HD::get();
    let daemon = Served::sim(&[], None);
    let out = std::process::Command::new(hd.exe("temp"))
        .env("OMNID_SOCKET", &daemon.sock)
        .output()
        .unwrap();
    let printed = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{printed}");
    let ticks: u32 = field(&printed, "ticks").parse().unwrap();
    assert!(ticks > 500, "{printed}");
    // Read or written every tick, refused once each: the velocity limit read, the DAC values
    // read, the DAC values written (a read refused first does not hide the write's refusal).
    assert_eq!(field(&printed, "invalid-enum"), "3", "{printed}");
    assert_eq!(field(&printed, "other-errors"), "0", "{printed}");
    let temps = |key: &str| -> Vec<f64> {
        field(&printed, key)
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect()
    };
    let (first, last) = (temps("temp-first"), temps("temp-last"));
    assert_eq!((first.len(), last.len()), (3, 3));
    for k in 0..3 {
        assert!((0.0..=1.0).contains(&last[k]), "{printed}");
        assert!(
            last[k] >= first[k],
            "motor {k} cooled while pushing: {printed}"
        );
    }
    // The motors that carry the push warm up (the model integrates τ²).
    assert!(
        (0..3).any(|k| last[k] > first[k]),
        "no motor warmed: {printed}"
    );
}

#[test]
#[ignore = "paced"]
fn occasional_frames_that_push_nothing_leave_the_arm_alone() {
    let hd = HD::get();
    let daemon = Served::sim(&[], None);
    let mut watch = daemon.connect("watch");
    watch
        .request(serde_json::json!({"op": "stream", "rate_hz": 1000}))
        .unwrap();
    let program = std::process::Command::new(hd.exe("occasional"))
        .arg("300")
        .env("OMNID_SOCKET", &daemon.sock)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("occasional starts");
    let _watchdog = hd::Watchdog::new(&program, Duration::from_secs(60));
    // Every state while it runs: the amplifiers never come on, the mode never leaves idle.
    let (mut states, mut amps_on, mut modes) = (0, 0, std::collections::BTreeSet::new());
    let until = Instant::now() + Duration::from_millis(2200);
    while Instant::now() < until {
        let Ok(s) = watch.next_state(500) else {
            continue;
        };
        states += 1;
        amps_on += usize::from(s.amps);
        modes.insert(s.mode.clone());
    }
    let out = program.wait_with_output().unwrap();
    let printed = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{printed}");
    assert!(
        field(&printed, "frames").parse::<u32>().unwrap() >= 6,
        "{printed}"
    );
    assert!(states > 1000, "{states} states watched");
    assert_eq!(amps_on, 0, "the amplifiers came on; modes {modes:?}");
    assert_eq!(modes.into_iter().collect::<Vec<_>>(), ["idle"]);
}

/// The SDK's QueryDevice way of waiting for button 1 (synchronous reads on the main thread)
/// sees the simulator's hand click it on the schedule of `[sim] stylus`, and exits.
#[test]
#[ignore = "paced"]
fn a_program_waiting_for_button_1_sees_the_scheduled_click() {
    let hd = HD::get();
    // A click a second from the daemon's start, then one every second (so a program that
    // starts late, on a loaded machine, still gets one).
    let clicks: Vec<String> = (1..=30)
        .map(|s| format!("{{ at_s = {s}.0, action = \"click\", button = 1 }}"))
        .collect();
    let config = format!("[sim]\nstylus = [{}]\n", clicks.join(", "));
    let daemon = Served::sim(&[], Some(&config));
    let out = run(
        hd.exe("query"),
        &["40"],
        &[("OMNID_SOCKET", daemon.sock.to_str().unwrap())],
    );
    let line = field(&out, "pressed");
    // Button 1 down (bit 0), button 2 up, the stylus still in its inkwell.
    assert!(line.starts_with("buttons 1 inkwell 1 "), "{out}");
}

/// `omnid ctl` as the simulator's hand: the inkwell switch a program reads follows undock and
/// dock, a button pressed and released shows in HD_CURRENT_BUTTONS; a read-only request, an
/// unknown action and a third button are refused by name.
#[test]
#[ignore = "paced"]
fn the_inkwell_switch_and_buttons_follow_omnid_ctl() {
    let hd = HD::get();
    let daemon = Served::sim(&[], None);
    let ctl = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_omnid"))
            .args(["ctl", "--socket"])
            .arg(&daemon.sock)
            .args(args)
            .output()
            .unwrap()
    };
    let mut program = std::process::Command::new(hd.exe("inkwell"))
        .args(["2", "40"])
        .env("OMNID_SOCKET", &daemon.sock)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("inkwell starts");
    let _watchdog = hd::Watchdog::new(&program, Duration::from_secs(60));
    let mut lines = BufReader::new(program.stdout.take().unwrap()).lines();
    let mut next = || lines.next().expect("a line").unwrap();
    // The simulator starts docked.
    assert_eq!(next(), "inkwell 1");
    assert_eq!(next(), "buttons 0");
    let out = ctl(&["button", "2", "press"]);
    assert!(out.status.success(), "{out:?}");
    // A person reads a sentence; `--json` gives a program the daemon's reply.
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        "simulated hand: button 2 press"
    );
    assert_eq!(next(), "buttons 2");
    let out = ctl(&["--json", "button", "2", "press"]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        r#"{"button":2,"op":"stylus","stylus":"press"}"#
    );
    assert!(ctl(&["button", "2", "release"]).status.success());
    assert_eq!(next(), "buttons 0");
    assert!(ctl(&["undock"]).status.success());
    assert_eq!(next(), "inkwell 0");
    assert!(ctl(&["dock"]).status.success());
    assert_eq!(next(), "inkwell 1");
    assert_eq!(next(), "done 2");
    assert!(program.wait().unwrap().success());

    // Refusals name what is wrong (the client library's request, as any program sends it).
    let mut c = daemon.connect("check");
    let e = c
        .request(serde_json::json!({"op": "stylus", "action": "press", "button": 3}))
        .unwrap_err()
        .to_string();
    assert!(e.contains("button") && e.contains("1 or 2"), "{e}");
    let e = c
        .request(serde_json::json!({"op": "stylus", "action": "squeeze", "button": 1}))
        .unwrap_err()
        .to_string();
    assert!(e.contains("squeeze") && e.contains("undock"), "{e}");
    let out = ctl(&["button", "1", "hold"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("press, release or click"));
}

/// A program that drives the arm faster than `[safety] max_velocity_rad_s`: the daemon's
/// speed trip comes back as HD_EXCEEDED_MAX_VELOCITY, a force error with its own string.
#[test]
#[ignore = "paced"]
fn driving_the_arm_too_fast_is_an_exceeded_max_velocity_error() {
    let hd = HD::get();
    let daemon = Served::sim(
        &["--controller", "off"],
        Some("[safety]\nmax_velocity_rad_s = [0.5, 0.5, 0.5]\n"),
    );
    let out = run(
        hd.exe("speed"),
        &["2.5"],
        &[("OMNID_SOCKET", daemon.sock.to_str().unwrap())],
    );
    assert_eq!(field(&out, "velocity-errors"), "1", "{out}");
    assert_eq!(
        field(&out, "error"),
        "0x203 internal 8 force-error 1 scheduler-error 0",
        "{out}"
    );
    assert!(field(&out, "string").contains("maximum velocity"), "{out}");
    // The daemon tripped for it (the arm is idle, the trip latched), and said why.
    let mut c = daemon.connect("check");
    c.request(serde_json::json!({"op": "stream", "rate_hz": 100}))
        .unwrap();
    let s = c.next_state(5000).unwrap();
    assert_eq!((s.mode.as_str(), s.amps), ("idle", false));
}

/// The daemon's servo loop stalling past its deadline (an injected 200 ms wait in the
/// exchange) comes back to a running program as a scheduler error: HD_TIMER_ERROR with the
/// internal code of a servo stall.
#[test]
#[ignore = "paced"]
fn a_servo_stall_is_a_scheduler_error() {
    let hd = HD::get();
    // A stall every 3 s of device time, so a program that starts late still meets one.
    let stalls: Vec<String> = (1..=10).map(|k| format!("slow@{}:200", 3 * k)).collect();
    let mut args = Vec::new();
    for s in &stalls {
        args.extend(["--inject", s.as_str()]);
    }
    let daemon = Served::sim(&args, None);
    let out = run(
        hd.exe("stall"),
        &["40"],
        &[("OMNID_SOCKET", daemon.sock.to_str().unwrap())],
    );
    assert_eq!(field(&out, "scheduler-errors"), "1", "{out}");
    assert_eq!(
        field(&out, "error"),
        "0x304 internal 9 scheduler-error 1",
        "{out}"
    );
    assert!(field(&out, "string").contains("deadline"), "{out}");
    assert_eq!(field(&out, "other-errors"), "0", "{out}");
}

//! The daemon's safety against its own clients (issue "Safety first"): force ends with the
//! client that made it, whichever way it leaves; `mode idle` cannot be refused or crowded out;
//! a trip latches; a holder that stops reading loses its lease; fault dumps are bounded.

use crate::common;

use common::Served;
use omnid::transport::client::{Client, ClientError, Message};
use omnid::transport::protocol::State;
use serde_json::json;
use std::time::{Duration, Instant};

/// States until `pred` holds, within `secs` seconds of waiting.
fn until(c: &mut Client, secs: f64, mut pred: impl FnMut(&State) -> bool) -> State {
    let end = Instant::now() + Duration::from_secs_f64(secs);
    loop {
        assert!(Instant::now() < end, "condition not reached in {secs} s");
        let s = c.next_state(5000).expect("state");
        if pred(&s) {
            return s;
        }
    }
}

#[test]
#[ignore = "paced"]
fn a_killed_clients_effects_and_free_mode_end_with_it() {
    let d = Served::start(&[], None, &["sim"]);
    let mut watch = d.client("sim", "watch");
    watch
        .request(json!({"op": "stream", "rate_hz": 1000}))
        .unwrap();
    // A haptic program, in a process of its own: a 3 N constant force in free mode, then it
    // is killed without a word.
    let mut program = std::process::Command::new("python3")
        .arg("-c")
        .arg(format!(
            r#"
import json, socket, time
s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
s.connect({socket:?})
def ask(m):
    s.send(json.dumps(m).encode())
    while True:
        r = json.loads(s.recv(65536))
        if r.get("type") in ("reply", "error"):
            return r
s.send(json.dumps({{"op": "hello", "protocol": 1, "name": "haptic"}}).encode())
assert json.loads(s.recv(65536))["type"] == "hello"
print(ask({{"op": "effect", "slot": 0, "effect": {{"type": "constant", "force_n": [0, 3, 0]}}}}), flush=True)
print(ask({{"op": "mode", "mode": "free"}}), flush=True)
print("ready", flush=True)
time.sleep(60)
"#,
            socket = d.socket("sim").display().to_string()
        ))
        .stdout(std::process::Stdio::piped())
        .spawn()
        .expect("python3 runs");
    let mut out = std::io::BufReader::new(program.stdout.take().unwrap());
    let mut line = String::new();
    loop {
        line.clear();
        use std::io::BufRead;
        assert!(
            out.read_line(&mut line).unwrap() > 0,
            "the program ended early"
        );
        assert!(!line.contains("\"error\""), "{line}");
        if line.starts_with("ready") {
            break;
        }
    }
    // Its force is on the arm.
    until(&mut watch, 10.0, |s| s.mode == "free" && s.amps);
    program.kill().unwrap();
    program.wait().unwrap();
    // Within the default time to live (20 ms) of its leaving being noticed the arm rests.
    let gone = until(&mut watch, 5.0, |s| !s.amps);
    assert_eq!(gone.mode, "idle");
    // And stays so: nothing of the program's comes back.
    for _ in 0..500 {
        let s = watch.next_state(5000).unwrap();
        assert!(!s.amps && s.tau == [0.0; 3], "{s:?}");
    }
}

#[test]
#[ignore = "paced"]
fn a_hung_holder_and_silent_connections_cannot_stop_mode_idle() {
    let d = Served::start(&[], None, &["sim"]);
    // The holder takes the arm and then never reads again (as if SIGSTOPped).
    let mut holder = d.client("sim", "hung holder");
    holder
        .request(json!({"op": "mode", "mode": "hold"}))
        .unwrap();
    // 140 connections that never say hello (more than serve.max_clients).
    let silent: Vec<_> = (0..140)
        .filter_map(|_| omnid::transport::socket::Conn::connect(&d.socket("sim")).ok())
        .collect();
    assert_eq!(silent.len(), 140);
    let mut watch = d.client("sim", "watch");
    watch
        .request(json!({"op": "stream", "rate_hz": 100}))
        .unwrap();
    until(&mut watch, 10.0, |s| s.amps);
    let out = d.omnid(&["ctl", "mode", "idle"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    until(&mut watch, 5.0, |s| s.mode == "idle" && !s.amps);
    // The holder is told, and a stream of its own does not re-arm the arm.
    let mut told = false;
    while let Ok(m) = holder.recv(200) {
        if let Message::Other(v) = m {
            told |= v["event"] == "stopped";
        }
    }
    assert!(told, "the holder was not told who stopped the arm");
    let e = holder
        .request(json!({"op": "servo_jp", "seq": 1, "q": [0.0, 0.6, 0.3], "id": 9}))
        .unwrap_err();
    assert!(
        matches!(&e, ClientError::Refused(m) if m.contains("stopped by")),
        "{e}"
    );
    drop(silent);
}

#[test]
#[ignore = "paced"]
fn a_trip_latches_until_a_mode_is_asked_for_and_dumps_are_bounded() {
    // A speed limit the tracking motion exceeds: every `track` trips.
    let config = "[safety]\nmax_velocity_rad_s = [0.1, 0.1, 0.1]\n\
                  [serve]\ndump_interval_s = 3600\nmax_dumps = 1\n";
    let d = Served::start(&[], Some(config), &["sim"]);
    let mut c = d.client("sim", "c");
    c.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    for round in 0..3 {
        c.request(json!({"op": "mode", "mode": "track"})).unwrap();
        let end = Instant::now() + Duration::from_secs(20);
        loop {
            assert!(Instant::now() < end, "round {round}: no trip");
            if let Message::Other(v) = c.recv(5000).unwrap() {
                if v["event"] == "safety-trip" {
                    break;
                }
            }
        }
        // Latched: a stream command does not re-arm it.
        let e = c
            .request(json!({"op": "servo_jp", "seq": round, "q": [0.0, 0.6, 0.3], "id": 1}))
            .unwrap_err();
        assert!(
            matches!(&e, ClientError::Refused(m) if m.contains("tripped")),
            "{e}"
        );
        let s = c.next_state(5000).unwrap();
        assert!(!s.amps, "{s:?}");
    }
    // Three trips, one dump: the others were within the interval.
    let faults = d.dir.path().join("state").join("faults");
    let dumps: Vec<_> = std::fs::read_dir(&faults).unwrap().collect();
    assert_eq!(dumps.len(), 1, "{dumps:?}");
}

#[test]
#[ignore = "paced"]
fn a_holder_that_stops_reading_loses_its_lease() {
    let config = "[serve]\nlease_lapse_ms = 200\nclient_queue = 16\n";
    let d = Served::start(&[], Some(config), &["sim"]);
    let mut holder = d.client("sim", "holder");
    holder
        .request(json!({"op": "mode", "mode": "hold"}))
        .unwrap();
    // It asks for every state and then reads nothing: its socket fills.
    holder
        .request(json!({"op": "stream", "rate_hz": 1000}))
        .unwrap();
    let mut other = d.client("sim", "other");
    let end = Instant::now() + Duration::from_secs(20);
    loop {
        match other.request(json!({"op": "mode", "mode": "track"})) {
            Ok(_) => break,
            Err(ClientError::Refused(m)) if m.contains("lease") => {
                assert!(Instant::now() < end, "the lease never lapsed: {m}");
                std::thread::sleep(Duration::from_millis(50));
            }
            Err(e) => panic!("{e}"),
        }
    }
}

//! Several arms in one daemon (issue "the arm becomes the unit"): each on its own socket with
//! its own lease and safety, a trip on one leaving the other tracking, clients choosing an arm
//! by name or alias, and an arm held by one process refused to another, which is named.

use crate::common;

use common::Served;
use omnid::transport::client::{Client, Message};
use serde_json::json;
use std::time::{Duration, Instant};

/// Arm names unique to this test process: a configured arm is locked for this user across
/// every process (real hardware: machine-wide).
fn unique(name: &str) -> String {
    format!("{name}-{}", std::process::id())
}

/// Stream states for `n` ticks while answering each with a setpoint: the sequence numbers
/// seen, and whether the daemon reported a loss.
fn stream_and_command(mut c: Client, n: usize) -> (Vec<u64>, bool) {
    c.request(json!({"op": "mode", "mode": "hold"})).unwrap();
    c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
    let (mut seqs, mut lost) = (Vec::with_capacity(n), false);
    while seqs.len() < n {
        match c.recv(5000).expect("the daemon keeps streaming") {
            Message::State(s) => {
                c.send(&json!({"op": "servo_jp", "seq": s.seq, "q": [0.0, 0.6, 0.3]}))
                    .unwrap();
                seqs.push(s.seq);
            }
            Message::Other(v) if v["type"] == "lost" => lost = true,
            Message::Other(_) => {}
        }
    }
    (seqs, lost)
}

#[test]
#[ignore = "paced"]
fn two_simulated_arms_are_served_side_by_side_each_with_its_own_client() {
    let d = Served::start(
        &["--device", "sim", "--device", "sim"],
        None,
        &["sim", "sim-2"],
    );
    let hello = d.client("sim-2", "who").hello().clone();
    assert_eq!(
        (hello.arm.as_str(), hello.device.as_str()),
        ("sim-2", "sim")
    );
    let workers: Vec<_> = ["sim", "sim-2"]
        .into_iter()
        .map(|arm| {
            let c = d.client(arm, "commander");
            std::thread::spawn(move || stream_and_command(c, 3000))
        })
        .collect();
    for (arm, w) in ["sim", "sim-2"].into_iter().zip(workers) {
        let (seqs, lost) = w.join().unwrap();
        assert!(!lost, "{arm}: the daemon reported lost samples");
        assert!(
            seqs.windows(2).all(|p| p[1] == p[0] + 1),
            "{arm}: a sample is missing"
        );
    }
    // Each arm's own status, through `--arm`.
    for arm in ["sim", "sim-2"] {
        let out = d.omnid(&["ctl", "--arm", arm, "--json", "status"]);
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let status: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(status["arm"], arm, "{text}");
    }
}

#[test]
#[ignore = "paced"]
fn a_trip_on_one_arm_leaves_the_other_tracking() {
    let (left, right) = (unique("left"), unique("right"));
    let config = format!(
        "[[arm]]\nname = \"{left}\"\naliases = [\"PHANToM 1\"]\n\n[[arm]]\nname = \"{right}\"\n\
         [arm.safety]\nmax_velocity_rad_s = [0.1, 0.1, 0.1]\n"
    );
    let mut d = Served::start(&[], Some(&config), &[&left, &right]);
    // By alias, as an OpenHaptics program names its first device.
    let out = d.omnid(&["ctl", "--arm", "PHANToM 1", "mode", "track"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut r = d.client(&right, "r");
    r.request(json!({"op": "mode", "mode": "track"})).unwrap();
    let mut l = d.client(&left, "l");
    l.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    r.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    // The right arm's speed limit is far below the trajectory's: it trips and goes idle.
    let until = Instant::now() + Duration::from_secs(20);
    loop {
        assert!(Instant::now() < until, "the right arm never tripped");
        match r.recv(5000).unwrap() {
            Message::Other(v) if v["event"] == "safety-trip" => break,
            _ => {}
        }
    }
    // The left one tracks on, amplifiers on, for seconds after.
    let start = l.next_state(5000).unwrap().t;
    loop {
        let s = l.next_state(5000).unwrap();
        assert!(s.amps && (s.mode == "track" || s.mode == "blend"), "{s:?}");
        if s.t - start > 2.0 {
            break;
        }
    }
    // `omnid devices` lists both, served.
    let cfg = d.dir.path().join("omnid.toml");
    let out = d.omnid(&["devices", "--config", cfg.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    for name in [&left, &right] {
        let line = text
            .lines()
            .find(|l| l.contains(name.as_str()))
            .unwrap_or("");
        assert!(line.contains("served") && line.contains("sim"), "{text}");
    }
    let (code, err) = d.stop();
    assert_eq!(code, Some(130), "{err}");
    assert!(
        err.contains(&format!("arm {left}: stopped by the operator")),
        "{err}"
    );
}

#[test]
#[ignore = "paced"]
fn an_arm_a_daemon_serves_is_refused_to_run_and_probe_naming_the_holder() {
    let name = unique("bench");
    let config = format!("[[arm]]\nname = \"{name}\"\n");
    let d = Served::start(&[], Some(&config), &[&name]);
    let cfg = d.dir.path().join("omnid.toml");
    let cfg = cfg.to_str().unwrap();
    for args in [
        vec![
            "run",
            "--config",
            cfg,
            "--arm",
            &name,
            "--fast",
            "--duration",
            "1",
        ],
        vec!["probe", "--config", cfg, "--arm", &name],
    ] {
        let out = d.omnid(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains(&format!("`{name}` is in use by omnid (pid {}", d.pid())),
            "{args:?}: {err}"
        );
        assert!(
            err.contains("serve"),
            "the holder's command is named: {err}"
        );
    }
    // A name nobody configured is refused with the ones that are.
    let out = d.omnid(&["run", "--config", cfg, "--arm", "nobody", "--fast"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("no arm named `nobody`") && err.contains(&name),
        "{err}"
    );
}

/// The pair's console in a running daemon (`omnid ctl teleop start`, issue "Teleoperation"):
/// each side taken up on its own arm's socket, the follower copying the leader that the
/// simulated hand moves, both arms holding when the console ends; a console whose arm is
/// held by someone else, or that names an arm the daemon does not have, is refused.
#[test]
#[ignore = "paced"]
fn ctl_teleop_couples_two_arms_of_a_daemon_and_leaves_both_holding() {
    let (leader, follower) = (unique("lead"), unique("follow"));
    let config = format!(
        "[teleop]\noperator = \"always\"\n\n[[arm]]\nname = \"{leader}\"\n\
         [arm.haptics.hand]\npattern = \"path\"\nspeed_m_s = 0.05\n\n[[arm]]\nname = \"{follower}\"\n"
    );
    let d = Served::start(&[], Some(&config), &[&leader, &follower]);
    // Someone else holds the follower: the console is refused, naming the lease.
    let mut other = d.client(&follower, "someone");
    other
        .request(json!({"op": "mode", "mode": "hold"}))
        .unwrap();
    let out = d.omnid(&[
        "ctl",
        "teleop",
        "start",
        "--leader",
        &leader,
        "--follower",
        &follower,
        "--seconds",
        "1",
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("lease is held by"), "{err}");
    drop(other);
    // An arm this daemon does not serve, as the peer: named, with the arms it has.
    let mut c = d.client(&leader, "asker");
    let e = c
        .request(json!({"op": "teleop", "role": "leader", "peer": "nobody"}))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no arm `nobody`") && e.contains(&follower),
        "{e}"
    );
    // Said once, without a stack of `teleop: ` prefixes (the client names the op it asked).
    assert!(!e.contains("teleop: "), "{e}");
    drop(c);

    // Watch both arms while a console couples them for 5 s.
    let mut watch = [d.client(&leader, "watch-l"), d.client(&follower, "watch-f")];
    for w in &mut watch {
        w.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    }
    let console = d
        .teleop_console(&leader, &follower, "5")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // (leader tip, follower tip) at the same tick numbers while both are engaged.
    let mut engaged: Vec<([f64; 3], [f64; 3])> = Vec::new();
    let mut last_f: Option<omnid::transport::protocol::State> = None;
    let until = Instant::now() + Duration::from_secs(30);
    while engaged.len() < 150 {
        assert!(Instant::now() < until, "never 1.5 s engaged: {last_f:?}");
        let f = watch[1].next_state(5000).unwrap();
        let l = loop {
            let l = watch[0].next_state(5000).unwrap();
            if l.t >= f.t - 0.005 {
                break l;
            }
        };
        if l.teleop.as_deref() == Some("engaged") && f.teleop.as_deref() == Some("engaged") {
            assert_eq!((l.mode.as_str(), f.mode.as_str()), ("teleop", "teleop"));
            engaged.push((l.tip_mm, f.tip_mm));
        }
        last_f = Some(f);
    }
    // The follower's status says whose follower it is.
    let out = d.omnid(&["ctl", "--arm", &follower, "status"]);
    let status = String::from_utf8_lossy(&out.stdout);
    assert!(
        status.contains(&format!("follower of {leader} (pp, motion ×1")),
        "{status}"
    );
    // And, for programs, the side's live state and the round trip it measures (its own
    // packets' times echoed back by the other side: docs/TELEOP.md §5, §8).
    let out = d.omnid(&["ctl", "--arm", &follower, "--json", "status"]);
    let status: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let side = &status["teleop"];
    assert_eq!(
        (&side["role"], &side["peer"]),
        (&json!("follower"), &json!(leader))
    );
    assert_eq!(side["state"], "engaged", "{side}");
    // The default delay control for pp in one daemon: wave variables (docs/TELEOP.md §5).
    assert_eq!(side["delay_control"], "wave", "{side}");
    let rtt = side["round_trip_ms"].as_f64().unwrap_or(f64::NAN);
    assert!(rtt.is_finite() && rtt > 0.0, "{side}");
    let out = console.wait_with_output().unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(
        stdout.contains(&format!("{leader} leads, {follower} follows (pp")),
        "{stdout}"
    );
    assert!(stdout.contains("leader engaged"), "{stdout}");
    // The follower copied the leader's motion since engaging: the hand moved the leader by
    // centimetres, the follower stayed within a few millimetres of where it should be.
    let (l0, f0) = engaged[0];
    let (mut moved, mut err2) = (0.0f64, 0.0);
    for (l, f) in &engaged {
        let dl: Vec<f64> = (0..3).map(|k| l[k] - l0[k]).collect();
        let df: Vec<f64> = (0..3).map(|k| f[k] - f0[k]).collect();
        moved = moved.max(dl.iter().map(|v| v * v).sum::<f64>().sqrt());
        err2 += (0..3).map(|k| (df[k] - dl[k]).powi(2)).sum::<f64>();
    }
    let rms = (err2 / engaged.len() as f64).sqrt();
    eprintln!("follower off the leader's motion by {rms:.2} mm RMS");
    assert!(moved > 10.0, "the hand moved the leader only {moved:.1} mm");
    assert!(
        rms < 3.0,
        "follower off the leader's motion by {rms:.2} mm RMS"
    );
    // Uncoupled: both arms hold.
    for (w, name) in watch.iter_mut().zip([&leader, &follower]) {
        let until = Instant::now() + Duration::from_secs(10);
        loop {
            let s = w.next_state(5000).unwrap();
            if s.mode == "hold" {
                assert_eq!(s.teleop, None, "{name}: {s:?}");
                break;
            }
            assert!(Instant::now() < until, "{name} never held: {s:?}");
        }
    }
}

/// A trip on the follower ends the pair: the console says which arm left teleop and exits
/// non-zero, the follower is idle (the trip's), the leader holds.
#[test]
#[ignore = "paced"]
fn a_trip_on_the_follower_ends_the_console_and_leaves_the_leader_holding() {
    let (leader, follower) = (unique("lead2"), unique("follow2"));
    let config = format!(
        "[teleop]\noperator = \"always\"\n\n[[arm]]\nname = \"{leader}\"\n\
         [arm.haptics.hand]\npattern = \"path\"\nspeed_m_s = 0.05\n\n[[arm]]\nname = \"{follower}\"\n\
         [arm.safety]\nmax_velocity_rad_s = [0.1, 0.1, 0.1]\n"
    );
    let d = Served::start(&[], Some(&config), &[&leader, &follower]);
    let mut watch = d.client(&leader, "watch-l");
    watch
        .request(json!({"op": "stream", "rate_hz": 100}))
        .unwrap();
    let out = d.teleop_console(&leader, &follower, "20").output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{err}");
    assert!(
        err.contains(&format!("{follower} left teleop (now idle)")),
        "{err}"
    );
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let s = watch.next_state(5000).unwrap();
        if s.mode == "hold" {
            break;
        }
        assert!(Instant::now() < until, "the leader never held: {s:?}");
    }
}

/// A console killed outright (SIGKILL: no chance to uncouple) loses its sessions, and with them
/// the pair: each side is its lease holder's, so both arms leave teleop and hold.
#[test]
#[ignore = "paced"]
fn a_console_killed_outright_leaves_both_arms_uncoupled_and_holding() {
    let (leader, follower) = (unique("lead3"), unique("follow3"));
    let config = format!(
        "[teleop]\noperator = \"always\"\n\n[[arm]]\nname = \"{leader}\"\n\
         [arm.haptics.hand]\npattern = \"path\"\nspeed_m_s = 0.05\n\n[[arm]]\nname = \"{follower}\"\n"
    );
    let d = Served::start(&[], Some(&config), &[&leader, &follower]);
    let mut watch = [d.client(&leader, "watch-l"), d.client(&follower, "watch-f")];
    for w in &mut watch {
        w.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    }
    let mut console = d
        .teleop_console(&leader, &follower, "60")
        .arg("--json")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // For programs: a JSON object a line, notes and once a second both arms' states.
    let mut lines =
        std::io::BufRead::lines(std::io::BufReader::new(console.stdout.take().unwrap()));
    loop {
        let line = lines
            .next()
            .expect("a pair line before the console ends")
            .unwrap();
        let v: serde_json::Value = serde_json::from_str(&line).expect(&line);
        if v["type"] == "pair" {
            let sides = v["sides"].as_array().unwrap();
            assert_eq!(sides.len(), 2, "{v}");
            assert_eq!(sides[0]["arm"], json!(leader), "{v}");
            assert_eq!(sides[1]["state"]["mode"], "teleop", "{v}");
            break;
        }
        assert_eq!(v["type"], "note", "{v}");
    }
    // Both sides engaged (each stream read up to now).
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        let l = watch[0].next_state(5000).unwrap();
        let f = watch[1].next_state(5000).unwrap();
        if l.teleop.as_deref() == Some("engaged") && f.teleop.as_deref() == Some("engaged") {
            break;
        }
        assert!(Instant::now() < until, "never engaged: {l:?}\n{f:?}");
    }
    console.kill().unwrap();
    console.wait().unwrap();
    for (w, name) in watch.iter_mut().zip([&leader, &follower]) {
        let until = Instant::now() + Duration::from_secs(10);
        loop {
            let s = w.next_state(5000).unwrap();
            if s.mode != "teleop" {
                // Its side is down (it tells the other side so every tick) and it holds.
                assert_eq!(s.mode, "hold", "{name}: {s:?}");
                assert!(s.amps, "{name}: {s:?}");
                assert_eq!(s.teleop.as_deref(), Some("down"), "{name}: {s:?}");
                break;
            }
            assert!(Instant::now() < until, "{name} stayed coupled: {s:?}");
        }
    }
}

/// `--align`: before coupling, the console brings the follower to the leader's pose (a
/// bounded `servo_jp` ramp), so the follower then stands where the leader is — not only
/// moves as it does from wherever gravity left it.
#[test]
#[ignore = "paced"]
fn ctl_teleop_align_brings_the_follower_to_the_leaders_pose_before_coupling() {
    let (leader, follower) = (unique("alead"), unique("afollow"));
    // The leader starts out of its inkwell, the hand then moving it along its path; the
    // follower starts in its inkwell, centimetres away.
    let config = format!(
        "[teleop]\noperator = \"always\"\n\n[[arm]]\nname = \"{leader}\"\n\
         [arm.sim]\nstart_pose = [0.3, 0.65, 0.3]\ndocked = false\n\
         [arm.haptics.hand]\npattern = \"path\"\nspeed_m_s = 0.02\n\n[[arm]]\nname = \"{follower}\"\n"
    );
    let d = Served::start(&[], Some(&config), &[&leader, &follower]);
    let mut watch = [d.client(&leader, "watch-l"), d.client(&follower, "watch-f")];
    for w in &mut watch {
        w.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    }
    let apart =
        |l: [f64; 3], f: [f64; 3]| (0..3).map(|k| (l[k] - f[k]).powi(2)).sum::<f64>().sqrt();
    // Let the hand settle, then see how far apart they start.
    std::thread::sleep(Duration::from_secs(2));
    let (l, f) = (
        watch[0].next_state(5000).unwrap(),
        watch[1].next_state(5000).unwrap(),
    );
    let before = apart(l.tip_mm, f.tip_mm);
    let mut c = d.teleop_console(&leader, &follower, "30");
    c.arg("--align")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    let mut console = c.spawn().unwrap();
    let until = Instant::now() + Duration::from_secs(40);
    let mut engaged = 0;
    let mut e2 = 0.0f64;
    while engaged < 100 {
        assert!(Instant::now() < until, "never 1 s engaged");
        let f = watch[1].next_state(5000).unwrap();
        let l = loop {
            let l = watch[0].next_state(5000).unwrap();
            if l.t >= f.t - 0.005 {
                break l;
            }
        };
        if l.teleop.as_deref() == Some("engaged") && f.teleop.as_deref() == Some("engaged") {
            engaged += 1;
            e2 += apart(l.tip_mm, f.tip_mm).powi(2);
        }
    }
    let _ = console.kill();
    let out = console.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("aligning"), "{stdout}");
    assert!(before > 10.0, "they started only {before:.1} mm apart");
    let rms = (e2 / engaged as f64).sqrt();
    assert!(
        rms < 3.0,
        "coupled {rms:.1} mm RMS from the leader (they started {before:.1} mm apart)"
    );
}

/// A daemon leaves no runtime directory of its own behind (issue "Leftovers and shared
/// state"): the `omnid/` it made for its arms' sockets goes with the last of them, whichever
/// arm ends last; one that was already there, or that holds another daemon's socket, stays.
#[test]
#[ignore = "paced"]
fn a_daemon_removes_the_runtime_directory_it_made_and_only_that() {
    let (a, b) = (unique("dir-a"), unique("dir-b"));
    let config = format!("[[arm]]\nname = \"{a}\"\n\n[[arm]]\nname = \"{b}\"\n");
    let mut d = Served::start(&[], Some(&config), &[&a, &b]);
    let runtime = d.path("omnid");
    assert!(runtime.is_dir(), "the daemon made {}", runtime.display());
    let (code, err) = d.stop();
    assert_eq!(code, Some(130), "{err}");
    assert!(
        !runtime.exists(),
        "left behind: {}\n{err}",
        runtime.display()
    );

    // Made by someone else (here, the test): left in place when the daemon ends.
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("omnid")).unwrap();
    let mut d = Served::start_in(dir, &["--device", "sim"], None, &["sim"]);
    let (code, err) = d.stop();
    assert_eq!(code, Some(130), "{err}");
    assert!(
        d.path("omnid").is_dir(),
        "a directory it did not make was removed"
    );
    assert!(!d.socket("sim").exists(), "its socket goes: {err}");

    // Made by this daemon, but another daemon's socket is in it when it ends: kept.
    let name = unique("dir-c");
    let config = format!("[[arm]]\nname = \"{name}\"\n");
    let mut first = Served::start(&[], Some(&config), &[&name]);
    let other = first.path("omnid").join("other.sock");
    let _theirs = std::os::unix::net::UnixListener::bind(&other).unwrap();
    let (code, err) = first.stop();
    assert_eq!(code, Some(130), "{err}");
    assert!(other.exists(), "another daemon's socket was removed");
}

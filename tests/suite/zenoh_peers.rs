//! omnid over zenoh (docs/ZENOH.md), checked by peers that are not omnid: a Rust zenoh session
//! of the test's own, and PyPI's eclipse-zenoh, rosbags and xxhash (tests/zenoh/check_ros.py,
//! in a virtual environment; skipped, loudly, only when PyPI is out of reach).

use crate::common;
use common::Served;
use omnid::ros2::rmw_zenoh::{self as rmw, parse_token, read_attachment};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};
use zenoh::Wait;

/// `omnid serve --device sim` with zenoh listening on loopback `port`.
fn serve(port: u16, extra: &str) -> Served {
    let config = format!(
        "[zenoh]\nenabled = true\nlisten = [\"tcp/127.0.0.1:{port}\"]\nconnect = []\n{extra}"
    );
    Served::start(&["--device", "sim"], Some(&config), &["sim"])
}

/// A zenoh peer connected to the daemon listening on loopback `port`.
fn peer(port: u16) -> zenoh::Session {
    common::zenoh_peer(&format!("tcp/127.0.0.1:{port}"))
}

/// Every ROS 2 token seen within a few seconds (the daemon's session may still be joining).
fn tokens(s: &zenoh::Session, want: usize) -> Vec<String> {
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let replies = s.liveliness().get("@ros2_lv/**").wait().unwrap();
        let mut got = Vec::new();
        while let Ok(r) = replies.recv_timeout(Duration::from_secs(2)) {
            let Some(r) = r else { break };
            if let Ok(sample) = r.result() {
                got.push(sample.key_expr().to_string());
            }
        }
        if got.len() >= want || Instant::now() > until {
            return got;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
#[ignore = "paced"]
fn a_zenoh_peer_finds_the_node_and_reads_measured_js_with_rmw_zenohs_attachments() {
    let port = common::free_port();
    let mut d = serve(port, "");
    let s = peer(port);
    // Read-only by default: the node, six publishers, no subscriptions.
    let toks = tokens(&s, 7);
    let parsed: Vec<_> = toks.iter().filter_map(|t| parse_token(t)).collect();
    assert_eq!(parsed.len(), toks.len(), "every token parses: {toks:?}");
    assert!(parsed
        .iter()
        .any(|t| t.kind == "NN" && t.node_name == "omnid"));
    assert!(
        !parsed.iter().any(|t| t.kind == "MS"),
        "commands are off unless allowed: {toks:?}"
    );
    let (js_token, js) = toks
        .iter()
        .zip(&parsed)
        .find(|(_, t)| t.topic.as_deref() == Some("/sim/measured_js"))
        .expect("a measured_js publisher");
    assert_eq!(js.kind, "MP");
    assert_eq!(js.hash.as_deref(), Some(rmw::JOINT_STATE.hash));
    let key = rmw::data_key(0, "/sim/measured_js", &rmw::JOINT_STATE, Default::default());
    let sub = s.declare_subscriber(key).wait().unwrap();
    let want_gid = rmw::gid(js_token);
    let mut seqs = Vec::new();
    let until = Instant::now() + Duration::from_secs(20);
    while seqs.len() < 500 && Instant::now() < until {
        let Ok(sample) = sub.recv_timeout(Duration::from_secs(5)) else {
            continue;
        };
        let Some(sample) = sample else { continue };
        let att = sample.attachment().expect("every sample has an attachment");
        let (seq, time_ns, gid) = read_attachment(&att.to_bytes()).unwrap();
        assert_eq!(gid, want_gid, "GID = XXH3-128 of the publisher's token");
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_nanos() as i64;
        assert!((now - time_ns).abs() < 5_000_000_000, "source time is now");
        let (q, _, _) =
            omnid::ros2::msgs::read_joint_state_n::<3>(&sample.payload().to_bytes()).unwrap();
        assert!(q.iter().all(|v| v.is_finite()));
        seqs.push(seq);
    }
    assert_eq!(seqs.len(), 500);
    let gaps = seqs.windows(2).filter(|w| w[1] != w[0] + 1).count();
    // The subscriber's own queue may drop on this loaded machine; the numbers only grow.
    assert!(
        seqs.windows(2).all(|w| w[1] > w[0]),
        "sequence numbers grow"
    );
    assert!(gaps < 50, "{gaps} gaps in 500 samples");
    drop(sub);
    s.close().wait().unwrap();
    let (code, err) = d.stop();
    assert!(err.contains("zenoh session"), "{err}");
    assert_eq!(code, Some(130), "{err}");
}

/// A remote client of the test's own on arm `sim` (docs/ZENOH.md, Remote clients): its
/// liveliness token, its `out` key read into a channel, and after a hello that was answered
/// with the daemon's key, the sealer of its requests (`omnid::transport::zenoh::bind`).
struct Remote {
    s: zenoh::Session,
    cid: String,
    rx: std::sync::mpsc::Receiver<serde_json::Value>,
    sealer: Option<omnid::transport::zenoh::bind::Sealer>,
    /// Its public key, base64 (as in its hello).
    public: String,
    next_id: u64,
    _sub: zenoh::pubsub::Subscriber<()>,
    _token: zenoh::liveliness::LivelinessToken,
}

impl Remote {
    /// A client with a fresh key and the id `<prefix><its fingerprint>`, greeted: returns it
    /// and the daemon's first answer (its hello, or the hello's refusal).
    fn connect(s: &zenoh::Session, prefix: &str) -> (Remote, serde_json::Value) {
        Remote::try_connect(s, prefix, Duration::from_secs(20)).expect("an answer to the hello")
    }

    /// [`Remote::connect`], or None when no answer came within `wait`.
    fn try_connect(
        s: &zenoh::Session,
        prefix: &str,
        wait: Duration,
    ) -> Option<(Remote, serde_json::Value)> {
        let key = omnid::transport::zenoh::bind::ClientKey::new().unwrap();
        let cid = key.cid(prefix);
        let (tx, rx) = std::sync::mpsc::channel();
        let sub = s
            .declare_subscriber(format!("omnid/sim/out/{cid}"))
            .callback(move |m| {
                let v: serde_json::Value =
                    serde_json::from_slice(&m.payload().to_bytes()).unwrap_or_default();
                let _ = tx.send(v);
            })
            .wait()
            .unwrap();
        let token = s
            .liveliness()
            .declare_token(format!("omnid/sim/client/{cid}"))
            .wait()
            .unwrap();
        let public = key.public_base64();
        let hello = json!({"op": "hello", "protocol": 1, "name": cid, "key": public});
        // Put again until answered: the daemon's subscription may still be on its way.
        let until = Instant::now() + wait;
        let answer = loop {
            if Instant::now() > until {
                return None;
            }
            s.put(format!("omnid/sim/in/{cid}"), hello.to_string())
                .wait()
                .unwrap();
            if let Ok(a) = rx.recv_timeout(Duration::from_millis(1000)) {
                break a;
            }
        };
        let sealer = (answer["type"] == "hello")
            .then(|| key.finish(&cid, answer["key"].as_str().unwrap()).unwrap());
        let r = Remote {
            s: s.clone(),
            cid,
            rx,
            sealer,
            public,
            next_id: 1,
            _sub: sub,
            _token: token,
        };
        Some((r, answer))
    }

    /// Put a request on this client's `in` key, sealed; returns its bytes and attachment.
    fn put(&mut self, request: &serde_json::Value) -> (Vec<u8>, Vec<u8>) {
        let body = request.to_string().into_bytes();
        let tag = self.sealer.as_mut().expect("greeted").seal(&body).to_vec();
        self.s
            .put(format!("omnid/sim/in/{}", self.cid), body.clone())
            .attachment(tag.clone())
            .wait()
            .unwrap();
        (body, tag)
    }

    /// A request and its answer (the message that echoes its id); the request's bytes and
    /// attachment too.
    fn request(&mut self, mut request: serde_json::Value) -> (serde_json::Value, Vec<u8>, Vec<u8>) {
        let id = self.next_id;
        self.next_id += 1;
        request["id"] = json!(id);
        let (body, tag) = self.put(&request);
        let until = Instant::now() + Duration::from_secs(20);
        loop {
            let left = until.saturating_duration_since(Instant::now());
            let m = self.rx.recv_timeout(left).expect("an answer");
            if m["id"] == json!(id) {
                return (m, body, tag);
            }
        }
    }
}

fn python() -> Option<PathBuf> {
    let py = common::venv(
        "zenoh-venv",
        &["eclipse-zenoh==1.10.2", "rosbags==0.11.9", "xxhash>=3"],
        "rosbags",
    );
    if py.is_none() {
        eprintln!("SKIPPED: PyPI is out of reach, so eclipse-zenoh and rosbags are not here");
    }
    py
}

fn check(python: &Path, mode: &str, port: u16, d: &Served) -> serde_json::Value {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new(python)
        .arg(root.join("tests/zenoh/check_ros.py"))
        .arg(mode)
        .arg(format!("tcp/127.0.0.1:{port}"))
        .arg("sim")
        .arg(d.socket("sim"))
        .arg(root.join("clients/python"))
        .output()
        .expect("python runs");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "check_ros.py {mode}: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_str(text.trim()).expect("one JSON line")
}

const COMMANDS: &str = "allow_commands = true\n";

#[test]
#[ignore = "paced"]
fn ros2_tools_see_omnid_as_rmw_zenoh_does_and_servo_cf_pushes_the_arm() {
    let Some(py) = python() else { return };
    let port = common::free_port();
    let d = serve(port, COMMANDS);
    let r = check(&py, "ros", port, &d);
    eprintln!("{r:#}");
    assert_eq!(r["node"], serde_json::json!(["omnid"]));
    assert_eq!(r["js_hash_ok"], true);
    for (leaf, ok) in r["hashes_ok"].as_object().unwrap() {
        assert_eq!(ok, true, "{leaf}'s type hash is rosbags'");
    }
    assert_eq!(r["js_qos"], "::,100:,:,:,,");
    let rate = r["rate_hz"].as_f64().unwrap();
    assert!((950.0..=1050.0).contains(&rate), "measured_js at {rate} Hz");
    assert_eq!(r["bad_attachments"], 0);
    assert_eq!(r["bad_timestamps"], 0);
    assert_eq!(r["seq_gaps"], 0, "no sequence gap in 5 s");
    let (n, matched) = (
        r["socket_states"].as_u64().unwrap(),
        r["socket_matched"].as_u64().unwrap(),
    );
    assert!(n > 4000, "{n} socket states");
    // The socket's stream starts a moment before the ROS window and ends after it.
    assert!(matched as f64 >= 0.9 * n as f64, "{matched} of {n} matched");
    for leaf in ["measured_cp", "measured_cv"] {
        assert_eq!(r["decoded"][leaf], true, "{leaf}");
    }
    assert!(r["decoded"]["operating_state"].is_string());
    assert!(r["push_modes"]
        .as_array()
        .unwrap()
        .contains(&serde_json::json!("servo_cf")));
    // 0.6 N at the tip is Jᵀ F of several tens of mN·m on the shoulder.
    let dtau = r["push_dtau_nm"].as_f64().unwrap();
    assert!(dtau > 0.02, "0.6 N up changed the torque by {dtau} N·m");
    assert_ne!(r["mode_after"], "servo_cf");
    assert!(
        r["lease_after"].is_null(),
        "a quiet ROS 2 commander loses the lease"
    );
}

#[test]
#[ignore = "paced"]
fn a_remote_python_client_streams_and_commands_and_loses_its_command_when_it_dies() {
    let Some(py) = python() else { return };
    let port = common::free_port();
    let d = serve(port, COMMANDS);
    let r = check(&py, "remote", port, &d);
    eprintln!("{r:#}");
    assert_eq!(r["access"], "control");
    assert_eq!(r["rate"], 100.0);
    assert!(r["states_1s"].as_u64().unwrap() >= 80);
    assert_eq!(r["holder"], true);
    assert!(r["modes"]
        .as_array()
        .unwrap()
        .contains(&serde_json::json!("servo_cf")));
    assert!(r["status_zenoh"]["received"].as_u64().unwrap() > 0);
    assert_eq!(r["doomed_mode"], "servo_cf");
    // Its 50 ms time to live, plus a loaded machine's scheduling.
    let gone = r["command_gone_ms"].as_f64().unwrap();
    assert!(gone < 1000.0, "the dead client's command lasted {gone} ms");
    assert!(
        r["lease_gone_s"].is_f64(),
        "the dead client's lease is freed"
    );
}

#[test]
#[ignore = "paced"]
fn bad_samples_and_floods_from_the_network_are_refused_and_counted() {
    let Some(py) = python() else { return };
    let port = common::free_port();
    let mut d = serve(port, COMMANDS);
    let r = check(&py, "hostile", port, &d);
    eprintln!("{r:#}");
    let z = &r["zenoh"];
    // Truncated, garbage, NaN, empty, 10 MB: each refused.
    assert!(z["refused"].as_u64().unwrap() >= 5, "{z}");
    assert!(
        r["states_after"].as_u64().unwrap() > 300,
        "the daemon goes on"
    );
    assert_ne!(r["mode"], "servo_cf");
    let (code, err) = d.stop();
    assert_eq!(code, Some(130), "{err}");
}

#[test]
#[ignore = "paced"]
fn without_allow_commands_a_remote_client_is_read_only() {
    let Some(py) = python() else { return };
    let port = common::free_port();
    let d = serve(port, "");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let script = format!(
        "import sys; sys.path.insert(0, {:?}); import omnid_client as o\n\
         c = o.Client(remote='tcp/127.0.0.1:{port}', arm='sim')\n\
         print(c.access)\n\
         try:\n    c.take_lease(); print('taken')\n\
         except o.RefusedError as e:\n    print('refused:', e)\n",
        root.join("clients/python")
    );
    let out = Command::new(&py).args(["-c", &script]).output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("read"));
    let second = lines.next().unwrap_or_default();
    assert!(
        second.starts_with("refused:") && second.contains("allow_commands"),
        "{second}"
    );
    drop(d);
}

// Teleoperation between two daemons over zenoh (docs/TELEOP.md §9).

mod teleop_over_zenoh {
    use omnid::experiment::teleop::{run_pair, run_pair_over, Link, PairSim, Scene, CHANNELS};
    use omnid::teleop::{Architecture, TeleopConfig};
    use std::sync::{Arc, Mutex};
    use std::time::{Duration, Instant};

    const PRESS: Scene = Scene::Press {
        force_n: 1.0,
        wall_n_per_mm: 1.0,
    };

    #[test]
    #[ignore = "paced"]
    fn a_pair_over_zenoh_on_loopback_does_what_the_local_pair_does() {
        // Two sessions as two daemons' (each its own zenoh session on TCP loopback), ticked in
        // real time; the in-process run of the same row beside it.
        let base = TeleopConfig::default();
        let (z, _) = run_pair_over(
            &base,
            Architecture::Pf,
            true,
            &PRESS,
            &CHANNELS[0],
            true,
            Link::Zenoh,
        )
        .unwrap();
        let (local, _) =
            run_pair(&base, Architecture::Pf, true, &PRESS, &CHANNELS[0], true).unwrap();
        assert_eq!(z.link, "zenoh");
        assert!(z.stable, "{:?}", z.why);
        // The issue's local floors hold over the network too.
        assert!(z.force_rms_n <= 0.15, "force RMS {} N", z.force_rms_n);
        assert!(z.stiffness_ratio >= 0.7, "k ratio {}", z.stiffness_ratio);
        assert!(
            (z.force_rms_n - local.force_rms_n).abs() < 0.1,
            "zenoh {} N vs local {} N",
            z.force_rms_n,
            local.force_rms_n
        );
        // A packet each way every tick (a few lost to a loaded machine's scheduling at most).
        assert!(z.packets_per_s > 1500.0, "{} packets/s", z.packets_per_s);
        // Loopback adds a tick or two at most on top of the lockstep's own.
        assert!(
            z.measured_rt_ms > 0.0 && z.measured_rt_ms < 20.0,
            "measured round trip {} ms",
            z.measured_rt_ms
        );
    }

    /// The pair `l`/`f`'s key in these tests (base64 of 32 bytes).
    const KEY: &str = "2dEoOzyuZk8W2mWRzN0kqxUJ1NQ3gHc6kBzYw3h0n3U=";

    /// Two sessions on loopback as two daemons', and a third: an intruder on the same keys.
    fn zenoh_cfg(listen: &str, connect: &[String]) -> omnid::transport::zenoh::ZenohConfig {
        omnid::transport::zenoh::ZenohConfig {
            teleop_keys: [("l/f".to_string(), KEY.into())].into(),
            enabled: true,
            listen: vec![listen.to_string()],
            connect: connect.to_vec(),
            ros2: false,
            protocol: false,
            allow_commands: true,
            ..Default::default()
        }
    }

    /// The key as the test's intruders hold it (the lab's, or another).
    fn pair_key(b64: &str) -> omnid::teleop::wire::PairKey {
        use base64::Engine;
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(b64)
            .unwrap();
        omnid::teleop::wire::PairKey::new(&bytes).unwrap()
    }

    #[test]
    #[ignore = "paced"]
    fn frames_that_are_malformed_disagree_or_come_from_a_second_sender_are_refused_and_counted() {
        use omnid::teleop::wire::{encode, seal, Agreement};
        use omnid::teleop::{Packet, Role};
        use omnid::transport::zenoh::ZenohNet;
        use zenoh::Wait;
        let port = super::common::free_port();
        let at = vec![format!("tcp/127.0.0.1:{port}")];
        let lnet = ZenohNet::start(&zenoh_cfg(&at[0], &[])).unwrap();
        let fnet = ZenohNet::start(&zenoh_cfg("tcp/127.0.0.1:0", &at)).unwrap();
        let cfg = TeleopConfig::default();
        let (mut le, _ll) = lnet.teleop().open("l", "f", Role::Leader, &cfg, 1).unwrap();
        let (mut fe, fl) = fnet
            .teleop()
            .open("f", "l", Role::Follower, &cfg, 2)
            .unwrap();
        // An intruder's session, listening to what the leader sends from the start.
        let evil = super::peer(port);
        let heard = Arc::new(Mutex::new(Vec::<(String, Vec<u8>)>::new()));
        let h = heard.clone();
        let _tap = evil
            .declare_subscriber("omnid/teleop/l/f/to_follower/*")
            .callback(move |s| {
                h.lock().unwrap().push((
                    s.key_expr().as_str().to_string(),
                    s.payload().to_bytes().to_vec(),
                ))
            })
            .wait()
            .unwrap();
        // The leader is heard first: its session is the peer.
        let until = Instant::now() + Duration::from_secs(10);
        while fe.receive(0.0).is_none() || heard.lock().unwrap().is_empty() {
            assert!(Instant::now() < until, "the link never came up");
            le.send(Packet {
                seq: 1,
                ..Packet::default()
            });
            std::thread::sleep(Duration::from_millis(5));
        }
        let leader_key = format!("omnid/teleop/l/f/to_follower/{}", lnet.zid());
        let captured = heard.lock().unwrap()[0].clone();
        assert_eq!(captured.0, leader_key);
        // The intruder puts on the follower's keys. Without the pair's key: as the leader
        // itself (its session id as the last segment), bare, sealed with another key, and a
        // frame the leader sent, put again. With the pair's key (an insider's mistakes): garbage,
        // the other architecture, a NaN, and well-formed frames as a second session.
        let lab = pair_key(KEY);
        let wrong = pair_key("c29tZSBvdGhlciBrZXkgb2YgMzIgYnl0ZXMgLi4uLi4=");
        let good = Agreement::of(&cfg.on_channel(true));
        let pf = Agreement {
            architecture: Architecture::Pf,
            passivity: true,
            delay_control: omnid::teleop::DelayControl::Gains,
        };
        let marked = Packet {
            seq: 666,
            ..Packet::default()
        };
        let mut nan = encode(&Packet::default(), good);
        nan[32..40].copy_from_slice(&f64::NAN.to_le_bytes());
        let intruder = "omnid/teleop/l/f/to_follower/intruder";
        let frames: Vec<(&str, Vec<u8>, &str)> = vec![
            (
                &leader_key,
                encode(&marked, good).to_vec(),
                "a frame without an authentication code",
            ),
            (
                &leader_key,
                seal(&encode(&marked, good), u64::MAX, &leader_key, &wrong).to_vec(),
                "the authentication code does not match",
            ),
            (
                // Sealed with the lab's key for the intruder's own key, put on the leader's.
                &leader_key,
                seal(&encode(&marked, good), u64::MAX, intruder, &lab).to_vec(),
                "the authentication code does not match",
            ),
            (&captured.0, captured.1.clone(), "was already taken"),
            (
                intruder,
                b"not a frame".to_vec(),
                "a sealed frame is 160 bytes; this one is 11",
            ),
            (
                intruder,
                seal(&encode(&marked, pf), 1, intruder, &lab).to_vec(),
                "the peer runs pf, passivity on, delay control gains; this side runs pp",
            ),
            (
                intruder,
                seal(&nan, 2, intruder, &lab).to_vec(),
                "bytes 32..40: pos_mm = NaN",
            ),
            (
                intruder,
                seal(&encode(&marked, good), 3, intruder, &lab).to_vec(),
                "session intruder sends as the peer while session",
            ),
        ];
        for (key, frame, why) in &frames {
            let before = fl.stats().refused;
            let until = Instant::now() + Duration::from_secs(10);
            while fl.stats().refused == before {
                assert!(Instant::now() < until, "{why}: {:?}", fl.stats());
                evil.put(*key, frame.clone()).wait().unwrap();
                // The real leader keeps talking.
                le.send(Packet {
                    seq: 2,
                    ..Packet::default()
                });
                std::thread::sleep(Duration::from_millis(20));
                while let Some(p) = fe.receive(0.0) {
                    assert_ne!(p.seq, 666, "an intruder's frame reached the arm");
                }
            }
            let last = fl.stats().last_refusal.unwrap_or_default();
            assert!(last.contains(why), "{why}: {last}");
        }
        let stats = fl.stats();
        assert!(stats.received >= 2, "{stats:?}");
        assert_eq!(stats.peer_session, Some(lnet.zid()), "{stats:?}");
        evil.close().wait().unwrap();
    }

    #[test]
    #[ignore = "paced"]
    fn a_channel_to_another_daemon_needs_allow_commands_and_a_plain_arm_name() {
        use omnid::teleop::Role;
        use omnid::transport::zenoh::ZenohNet;
        let cfg = TeleopConfig::default();
        let closed = ZenohNet::start(&omnid::transport::zenoh::ZenohConfig {
            allow_commands: false,
            ..zenoh_cfg("tcp/127.0.0.1:0", &[])
        })
        .unwrap();
        let e = closed
            .teleop()
            .open("l", "f", Role::Leader, &cfg, 1)
            .err()
            .unwrap();
        assert!(e.contains("allow_commands = false"), "{e}");
        // A pair across daemons without a key: refused, naming the setting and how to make one.
        let keyless = ZenohNet::start(&omnid::transport::zenoh::ZenohConfig {
            teleop_keys: Default::default(),
            ..zenoh_cfg("tcp/127.0.0.1:0", &[])
        })
        .unwrap();
        let e = keyless
            .teleop()
            .open("f", "l", Role::Follower, &cfg, 1)
            .err()
            .unwrap();
        assert!(
            e.contains("[zenoh.teleop_keys]")
                && e.contains("\"l/f\"")
                && e.contains("head -c32 /dev/urandom | base64"),
            "{e}"
        );
        let open = ZenohNet::start(&zenoh_cfg("tcp/127.0.0.1:0", &[])).unwrap();
        for bad in ["f/*", "**", "a b", ""] {
            let e = open
                .teleop()
                .open("l", bad, Role::Leader, &cfg, 1)
                .err()
                .unwrap();
            assert!(e.contains("arm name"), "{bad}: {e}");
        }
    }

    #[test]
    #[ignore = "paced"]
    fn a_cut_zenoh_link_fades_the_leaders_force_within_50_ms_and_the_follower_holds() {
        let base = TeleopConfig::default();
        let mut sim = PairSim::build(
            &base,
            Architecture::Pf,
            true,
            &PRESS,
            &CHANNELS[0],
            10.0,
            false,
            Link::Zenoh,
        )
        .unwrap();
        let mut last = None;
        for _ in 0..2500 {
            last = Some(sim.tick().unwrap());
        }
        let pressed = last.unwrap();
        let f0 = nalgebra::Vector3::from(pressed.leader.haptic_force());
        assert!(f0.norm() > 0.5, "no force to fade: {f0:?}");
        let held = nalgebra::Vector3::from(pressed.follower.tip_mm());
        // The follower's daemon's session closes: nothing crosses any more.
        sim.cut_network();
        let zero_at = crate::common::ticks_to_fade(f0.into(), base.fade_ms, 200, || {
            sim.tick().unwrap().leader.haptic_force()
        });
        let ms = zero_at.expect("the leader's force reached zero");
        assert!(ms <= 50, "zero {ms} ms after the cut");
        assert_eq!(sim.leader.teleop().unwrap().state().as_str(), "link_lost");
        assert_eq!(sim.follower.teleop().unwrap().state().as_str(), "link_lost");
        // The follower holds where it was (pressed into its floor), within a millimetre.
        let t = sim.tick().unwrap();
        let moved = (nalgebra::Vector3::from(t.follower.tip_mm()) - held).norm();
        assert!(moved < 1.0, "the follower moved {moved} mm after the cut");
    }
}

fn spawn_piped(mut c: Command) -> std::process::Child {
    c.stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// Two daemons, as on two PCs (each its own runtime directory, so each console finds only
/// its own arm), joined by zenoh on loopback, the leader's arm moved by the simulated hand;
/// each streaming to a watcher at 100 Hz.
struct TwoDaemons {
    a: Served,
    b: Served,
    leader: String,
    follower: String,
    wl: omnid::transport::client::Client,
    wf: omnid::transport::client::Client,
}

fn two_daemons(tag: &str) -> TwoDaemons {
    let (leader, follower) = (
        format!("zl{tag}-{}", std::process::id()),
        format!("zf{tag}-{}", std::process::id()),
    );
    let port = common::free_port();
    // The pair's key, the same on both daemons.
    let common = format!(
        "ros2 = false\nallow_commands = true\nteleop_keys = {{ \"{leader}/{follower}\" = \
         \"2dEoOzyuZk8W2mWRzN0kqxUJ1NQ3gHc6kBzYw3h0n3U=\" }}\n"
    );
    let a = Served::start(
        &[],
        Some(&format!(
            "[teleop]\noperator = \"always\"\n\n[zenoh]\nenabled = true\n{common}\
             listen = [\"tcp/127.0.0.1:{port}\"]\nconnect = []\n\n[[arm]]\nname = \"{leader}\"\n\
             [arm.haptics.hand]\npattern = \"path\"\nspeed_m_s = 0.05\n"
        )),
        &[&leader],
    );
    let b = Served::start(
        &[],
        Some(&format!(
            "[teleop]\noperator = \"always\"\n\n[zenoh]\nenabled = true\n{common}\
             listen = [\"tcp/127.0.0.1:0\"]\nconnect = [\"tcp/127.0.0.1:{port}\"]\n\n\
             [[arm]]\nname = \"{follower}\"\n"
        )),
        &[&follower],
    );
    let mut wl = a.client(&leader, "watch-l");
    let mut wf = b.client(&follower, "watch-f");
    for w in [&mut wl, &mut wf] {
        w.request(json!({"op": "stream", "rate_hz": 100})).unwrap();
    }
    TwoDaemons {
        a,
        b,
        leader,
        follower,
        wl,
        wf,
    }
}

/// The newest state a stream has (waiting for one if none is queued).
fn newest(c: &mut omnid::transport::client::Client) -> omnid::transport::protocol::State {
    let mut s = c.next_state(5000).unwrap();
    while let Ok(n) = c.next_state(0) {
        s = n;
    }
    s
}

/// The end of a side reaches the other daemon as `down` (issue #42: the follower showed
/// `link_lost` and stayed in `teleop` until its own console ended): the leader's console
/// killed outright, its daemon ends that side (the holder left) and says so on the channel;
/// the follower shows `down`, its console ends naming the leader (exit 3) and it holds.
#[test]
#[ignore = "paced"]
fn two_daemons_over_zenoh_the_leaders_console_killed_puts_the_follower_down() {
    let TwoDaemons {
        a,
        b,
        leader,
        follower,
        mut wl,
        mut wf,
    } = two_daemons("d");
    let mut ca = spawn_piped(a.teleop_console(&leader, &follower, "60"));
    let cb = spawn_piped(b.teleop_console(&leader, &follower, "60"));
    let until = Instant::now() + Duration::from_secs(40);
    let mut both = 0;
    while both < 50 {
        let (l, f) = (newest(&mut wl), newest(&mut wf));
        assert!(Instant::now() < until, "never engaged: {l:?}\n{f:?}");
        if l.teleop.as_deref() == Some("engaged") && f.teleop.as_deref() == Some("engaged") {
            both += 1;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = ca.kill();
    let killed = Instant::now();
    let _ = ca.wait();
    // The follower's states from the kill on, until `down`.
    let mut seen: Vec<String> = Vec::new();
    let until = Instant::now() + Duration::from_secs(10);
    let after = loop {
        let s = wf.next_state(5000).unwrap();
        let state = s.teleop.clone().unwrap_or_else(|| s.mode.clone());
        if seen.last() != Some(&state) {
            seen.push(state.clone());
        }
        if state == "down" {
            assert_eq!(s.mode, "teleop", "{s:?}");
            break killed.elapsed();
        }
        assert!(
            Instant::now() < until,
            "the follower never went down: {seen:?}"
        );
    };
    // (Reported, not asserted: the guide keeps timing out of tests. The state stream's 10 ms
    // period and the kill's own delivery are in it.)
    eprintln!(
        "follower `down` {:.0} ms after the leader's console was killed; states {seen:?}",
        after.as_secs_f64() * 1e3
    );
    let out = cb.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{stderr}");
    assert!(
        stderr.contains(&format!("{leader}'s side is down")),
        "{stderr}"
    );
    // Its console ended the follower's side: it holds.
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let s = wf.next_state(5000).unwrap();
        if s.mode == "hold" {
            break;
        }
        assert!(Instant::now() < until, "the follower never held: {s:?}");
    }
}

/// The follower copies the leader over the network; the follower's daemon killed, the leader
/// loses the link and stays coupled, free.
#[test]
#[ignore = "paced"]
fn two_daemons_over_zenoh_pair_their_arms_and_a_killed_peer_leaves_the_leader_link_lost() {
    let TwoDaemons {
        a,
        mut b,
        leader,
        follower,
        mut wl,
        mut wf,
    } = two_daemons("");
    let ca = spawn_piped(a.teleop_console(&leader, &follower, "60"));
    let cb = spawn_piped(b.teleop_console(&leader, &follower, "60"));
    // Both engaged; the tips sampled together every 10 ms, each the newest its stream has
    // (the daemons' clocks differ: pair by arrival).
    let mut engaged: Vec<([f64; 3], [f64; 3])> = Vec::new();
    let until = Instant::now() + Duration::from_secs(40);
    while engaged.len() < 300 {
        let (l, f) = (newest(&mut wl), newest(&mut wf));
        assert!(Instant::now() < until, "never 3 s engaged: {l:?}\n{f:?}");
        if l.teleop.as_deref() == Some("engaged") && f.teleop.as_deref() == Some("engaged") {
            engaged.push((l.tip_mm, f.tip_mm));
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    // The follower's motion since engaging against the leader's, allowing for the lag of the
    // path through two daemons (up to 200 ms: the samples' own skew on a loaded machine).
    let (l0, f0) = engaged[0];
    let motion = |p: [f64; 3], o: [f64; 3]| nalgebra::Vector3::from(p) - nalgebra::Vector3::from(o);
    let moved = engaged
        .iter()
        .map(|(l, _)| motion(*l, l0).norm())
        .fold(0.0, f64::max);
    let rms_at = |lag: usize| {
        let n = engaged.len() - lag;
        let e2: f64 = (0..n)
            .map(|k| (motion(engaged[k + lag].1, f0) - motion(engaged[k].0, l0)).norm_squared())
            .sum();
        (e2 / n as f64).sqrt()
    };
    let (lag, rms) = (0..=20)
        .map(|lag| (lag, rms_at(lag)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .unwrap();
    assert!(moved > 10.0, "the hand moved the leader only {moved:.1} mm");
    // (Reported, not asserted beyond the bound: the run's numbers for the docs.)
    eprintln!(
        "follower off the leader's motion by {rms:.2} mm RMS (best lag {} ms; none: {:.2} mm)",
        lag * 10,
        rms_at(0)
    );
    assert!(
        rms < 3.0,
        "follower off the leader's motion by {rms:.2} mm RMS (best lag {} ms; none: {:.2} mm)",
        lag * 10,
        rms_at(0)
    );
    // Each side's status: the zenoh channel, frames flowing, none refused, a round trip.
    for (d, arm) in [(&a, &leader), (&b, &follower)] {
        let out = d.omnid(&["ctl", "--arm", arm, "--json", "status"]);
        let status: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        let side = &status["teleop"];
        assert_eq!(side["channel"], "zenoh", "{side}");
        // The default delay control across daemons: wave variables (docs/TELEOP.md §5).
        assert_eq!(side["delay_control"], "wave", "{side}");
        let net = &side["network"];
        assert!(net["received"].as_u64().unwrap_or(0) > 1000, "{side}");
        assert_eq!(net["refused"], 0, "{side}");
        let rtt = side["round_trip_ms"].as_f64().unwrap_or(f64::NAN);
        assert!(rtt > 0.0 && rtt < 500.0, "{side}");
    }
    let out = b.omnid(&["ctl", "--arm", &follower, "status"]);
    let human = String::from_utf8_lossy(&out.stdout);
    assert!(
        human.contains("teleop net  zenoh, peer session "),
        "{human}"
    );
    // The follower's PC goes: its daemon is killed outright.
    // SAFETY: kill with a live child's pid.
    unsafe { libc::kill(b.pid(), libc::SIGKILL) };
    let _ = b.child.take().unwrap().wait();
    let until = Instant::now() + Duration::from_secs(10);
    loop {
        let s = wl.next_state(5000).unwrap();
        if s.teleop.as_deref() == Some("link_lost") {
            assert_eq!(s.mode, "teleop", "{s:?}");
            assert!(s.amps, "the leader stays powered, its force faded: {s:?}");
            break;
        }
        assert!(
            Instant::now() < until,
            "the leader never saw the link go: {s:?}"
        );
    }
    // The follower's console sees its daemon go; the leader's is stopped by its operator.
    let out = cb.wait_with_output().unwrap();
    assert!(!out.status.success());
    unsafe { libc::kill(ca.id() as i32, libc::SIGINT) };
    let out = ca.wait_with_output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(130), "{stdout}");
    assert!(
        stdout.contains(&format!("`{follower}` is not served on this PC")),
        "{stdout}"
    );
}

/// The README's remote-client block, pasted as written into a shell (its `pip` and `python3`
/// those of a fresh virtual environment with eclipse-zenoh) from the clone's top directory,
/// against a daemon started as the README says: `omnid serve --zenoh`, no configuration.
#[test]
#[ignore = "paced"]
fn the_readmes_remote_python_example_works_as_pasted() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let start = readme
        .find("pip install ./clients/python eclipse-zenoh")
        .expect("the README's remote example");
    let block = &readme[start..];
    let block = &block[..block.find("```").unwrap()];
    let Some(py) = common::venv("readme-remote-venv", &["eclipse-zenoh==1.10.2"], "zenoh") else {
        eprintln!("SKIPPED: PyPI is out of reach");
        return;
    };
    let path = format!(
        "{}:{}",
        py.parent().unwrap().display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let mut d = Served::start(&["--device", "sim", "--zenoh"], None, &["sim"]);
    let out = Command::new("sh")
        .args(["-ec", block])
        .current_dir(root)
        .env("PATH", path)
        .env_remove("PYTHONPATH")
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    let (_, err) = d.stop();
    assert!(
        err.contains("listening on tcp/127.0.0.1:7448"),
        "the daemon says where it listens: {err}"
    );
    assert!(
        out.status.success(),
        "{text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The tip, three numbers in millimetres (pip's own lines before it).
    let last = text.lines().last().unwrap_or_default();
    let tip: Vec<f64> = last
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(|v| v.trim().parse().unwrap())
        .collect();
    assert_eq!(tip.len(), 3, "{text}");
    assert!(tip.iter().all(|v| v.abs() < 500.0), "{text}");
}

/// `omnid serve` with commands allowed on an endpoint other machines reach and no zenoh
/// authentication: refused at start naming `insecure = true`; with it, started, saying at
/// start-up that anyone who reaches it can command the arms.
#[test]
#[ignore = "paced"]
fn serve_refuses_commands_on_a_reachable_endpoint_without_authentication_unless_insecure() {
    let arm = format!("zi-{}", std::process::id());
    let config = |insecure: bool| {
        format!(
            "[zenoh]\nenabled = true\nros2 = false\nallow_commands = true\ninsecure = {insecure}\n\
             listen = [\"tcp/0.0.0.0:{}\"]\nconnect = []\n\n[[arm]]\nname = \"{arm}\"\n",
            common::free_port()
        )
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("omnid.toml");
    std::fs::write(&path, config(false)).unwrap();
    let out = common::omnid()
        .args(["serve", "--config"])
        .arg(&path)
        .env("XDG_RUNTIME_DIR", dir.path())
        .env_remove("RUNTIME_DIRECTORY")
        .env_remove("OMNID_SOCKET")
        .env("OMNID_STATE_DIR", dir.path().join("state"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{err}");
    assert!(
        err.contains("allow_commands = true")
            && err.contains("tcp/0.0.0.0:")
            && err.contains("insecure = true"),
        "{err}"
    );
    assert!(
        !dir.path()
            .join("omnid")
            .join(format!("{arm}.sock"))
            .exists(),
        "an arm was served"
    );
    let mut d = Served::start(&[], Some(&config(true)), &[&arm]);
    let (_, err) = d.stop();
    assert!(
        err.contains("commands from ANYONE who reaches tcp/0.0.0.0:")
            && err.contains("warning: [zenoh] insecure = true"),
        "{err}"
    );
}

/// A peer declares 200 client liveliness tokens and says no hello: they take no slot, so a
/// legitimate client is greeted, and its key cannot take a second slot. A peer that greets
/// from every slot: a further hello gets an explicit refusal, not silence.
#[test]
#[ignore = "paced"]
fn squatted_tokens_take_no_slot_and_a_hello_that_finds_every_slot_greeted_is_refused() {
    let port = common::free_port();
    let d = serve(port, "");
    let squatter = peer(port);
    let _tokens: Vec<_> = (0..200)
        .map(|i| {
            squatter
                .liveliness()
                .declare_token(format!("omnid/sim/client/squat{i}"))
                .wait()
                .unwrap()
        })
        .collect();
    let client = peer(port);
    // The squatter's tokens have spread (the client's session sees them all), and a moment
    // more for the daemon's hub to take them.
    let until = Instant::now() + Duration::from_secs(20);
    loop {
        let seen = client
            .liveliness()
            .get("omnid/sim/client/squat$*")
            .wait()
            .unwrap()
            .iter()
            .count();
        if seen >= 200 {
            break;
        }
        assert!(Instant::now() < until, "only {seen} tokens seen");
        std::thread::sleep(Duration::from_millis(100));
    }
    std::thread::sleep(Duration::from_millis(500));
    let (legit, v) = Remote::connect(&client, "legit-");
    assert_eq!(
        v["type"], "hello",
        "200 squatted tokens kept a client out: {v}"
    );
    // One slot per key: the greeted client's key on a second id (ending with its
    // fingerprint) is refused, saying so.
    let again = format!("again-{}", &legit.cid[legit.cid.len() - 32..]);
    let answers = client
        .declare_subscriber(format!("omnid/sim/out/{again}"))
        .wait()
        .unwrap();
    let hello = json!({"op": "hello", "protocol": 1, "key": legit.public});
    client
        .put(format!("omnid/sim/in/{again}"), hello.to_string())
        .wait()
        .unwrap();
    let v: serde_json::Value = serde_json::from_slice(
        &answers
            .recv_timeout(Duration::from_secs(20))
            .unwrap()
            .expect("an answer")
            .payload()
            .to_bytes(),
    )
    .unwrap();
    assert_eq!(v["type"], "error", "{v}");
    assert!(
        v["message"]
            .as_str()
            .unwrap_or("")
            .contains("one client per key"),
        "{v}"
    );
    // Every other slot taken by greeted clients: the next hello is refused, saying so.
    let mut held = Vec::new();
    for i in 0..63 {
        let (r, v) = Remote::connect(&squatter, &format!("held{i}-"));
        assert_eq!(v["type"], "hello", "held{i}: {v}");
        held.push(r);
    }
    let (_late, v) = Remote::connect(&client, "late-");
    assert_eq!(v["type"], "error", "{v}");
    assert!(
        v["message"].as_str().unwrap_or("").contains("no room"),
        "{v}"
    );
    drop(d);
}

#[test]
#[ignore = "paced"]
fn a_ros2_command_under_another_type_hash_is_counted_and_said() {
    // Issue #43: a node built against other message definitions publishes servo_cf under a
    // type hash that is not ours: the sample never reached a subscriber, and nothing said so.
    let port = common::free_port();
    let mut d = serve(port, "allow_commands = true\n");
    let s = peer(port);
    let ours = rmw::data_key(0, "/sim/servo_cf", &rmw::WRENCH_STAMPED, Default::default());
    let (topic, _) = ours.rsplit_once('/').unwrap();
    let wrong = format!("{topic}/RIHS01_{}", "0".repeat(64));
    let refused = |d: &Served| -> u64 {
        let mut c = d.client("sim", "counter");
        let r = c.request(serde_json::json!({"op": "status"})).unwrap();
        r["status"]["zenoh"]["refused"].as_u64().unwrap_or(0)
    };
    let before = refused(&d);
    let until = Instant::now() + Duration::from_secs(20);
    while refused(&d) < before + 3 && Instant::now() < until {
        s.put(&wrong, vec![0u8; 80]).wait().unwrap();
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(
        refused(&d) >= before + 3,
        "samples under another hash not counted"
    );
    s.close().wait().unwrap();
    let (_, err) = d.stop();
    let said = err
        .matches("its type or type hash is not this daemon's")
        .count();
    assert_eq!(said, 1, "said once a minute at most:\n{err}");
    assert!(err.contains("RIHS01_000"), "{err}");
}

/// docs/ZENOH.md, "A lab network": `[zenoh] users_file` and `commanders` on loopback, with
/// PyPI's eclipse-zenoh (through omnid's Python client) as the other side. The commander's
/// client commands; a client without credentials, or with a wrong password, cannot connect;
/// an authenticated principal that is not a commander reads the arm's topics but cannot put a
/// request, so it gets no hello.
#[test]
#[ignore = "paced"]
fn only_the_labs_commander_commands_and_an_unauthenticated_peer_cannot_connect() {
    let Some(py) = python() else { return };
    let dir = tempfile::tempdir().unwrap();
    let users = dir.path().join("zenoh-users");
    std::fs::write(&users, "lab:lab-secret\nviewer:viewer-secret\n").unwrap();
    let port = common::free_port();
    let mut d = serve(
        port,
        &format!(
            "allow_commands = true\nusers_file = \"{}\"\ncommanders = [\"lab\"]\n",
            users.display()
        ),
    );
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new(&py)
        .arg(root.join("tests/zenoh/check_auth.py"))
        .arg(format!("tcp/127.0.0.1:{port}"))
        .arg("sim")
        .arg(root.join("clients/python"))
        .output()
        .expect("python runs");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "check_auth.py: {text}{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r: serde_json::Value = serde_json::from_str(text.trim()).expect("one JSON line");
    eprintln!("{r:#}");
    assert_eq!(r["commander"]["hello"], true, "{r}");
    assert_eq!(r["commander"]["access"], "control", "{r}");
    assert_eq!(r["commander"]["mode"], "hold", "{r}");
    for who in ["anonymous", "wrong_password", "viewer"] {
        assert_eq!(r[who]["hello"], false, "{who}: {r}");
    }
    assert!(r["viewer_reads"].as_u64().unwrap() > 100, "{r}");
    assert_eq!(r["anonymous_reads"], 0, "{r}");
    let status = d.omnid(&["ctl", "status", "--json"]);
    let status: serde_json::Value = serde_json::from_slice(&status.stdout).unwrap();
    assert_eq!(status["mode"], "hold", "{status}");
    let (_, err) = d.stop();
    assert!(
        err.contains("only lab") && err.contains("user/password"),
        "the start-up line says who may command: {err}"
    );
    assert!(!err.contains("lab-secret"), "{err}");
}

/// docs/ZENOH.md, "Budgets": a read-only zenoh peer flooding `status` beside a local haptic
/// client (the socket, 1 kHz state stream, a `servo_cf` answer to every state). The port
/// spends bounded time per wake-up on the network's requests and lets each remote client
/// only a few requests wait for the arm, so the local stream never goes stale; status says
/// who was throttled.
#[test]
#[ignore = "paced"]
fn a_status_flood_over_zenoh_never_makes_a_local_force_stream_stale() {
    use omnid::transport::client::Message;
    let port = common::free_port();
    let d = serve(port, "ros2 = false\n");
    let mut c = d.client("sim", "haptic");
    c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
    // The flooding peer: a remote client that says hello, then asks for status as fast as
    // zenoh takes it.
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let flood = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let s = peer(port);
            let (mut flood, v) = Remote::connect(&s, "flood-");
            assert_eq!(v["type"], "hello", "the flooding client was greeted: {v}");
            let mut sent = 0u64;
            let status = json!({"op": "status"});
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                flood.put(&status);
                sent += 1;
            }
            // Still connected: status names it while it is here.
            (sent, flood, s)
        })
    };
    // The haptic client: a zero force answering every state (50 ms to live: a loaded test
    // machine's own scheduling stays well inside it; the stalls a flood made were longer). It
    // runs as a haptic client's 1 kHz thread does (libHD's scheduler: SCHED_FIFO 60, where
    // permitted): on 2 cores the flooding peer's own threads, in this process, could otherwise
    // starve it past its time to live, which would say nothing about the daemon.
    let fifo = omnid_client::realtime::set_fifo_priority(60).is_ok();
    let until = Instant::now() + Duration::from_secs(6);
    let (mut stale, mut states) = (0, 0);
    while Instant::now() < until {
        match c.recv(5000).unwrap() {
            Message::State(s) => {
                states += 1;
                c.send(
                    &json!({"op": "servo_cf", "seq": s.seq, "force": [0.0, 0.0, 0.0],
                               "ttl_ms": 50}),
                )
                .unwrap();
            }
            Message::Other(v) if v["event"] == "stream-stale" => stale += 1,
            Message::Other(_) => {}
        }
    }
    if fifo {
        let _ = omnid_client::realtime::set_fifo_priority(0);
    }
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let (sent, flood_client, session) = flood.join().unwrap();
    assert!(sent > 1000, "a flood: {sent} status requests");
    assert!(states > 3000, "{states} states in 6 s");
    assert_eq!(
        stale, 0,
        "the force stream went stale {stale} times beside the flood"
    );
    let status = c.request(json!({"op": "status"})).unwrap();
    let z = &status["status"]["zenoh"];
    assert!(z["throttled"].as_u64().unwrap() > 0, "{z}");
    let flooder = z["throttled_clients"]
        .as_object()
        .unwrap()
        .iter()
        .find(|(cid, _)| cid.starts_with("flood-"));
    assert!(flooder.is_some_and(|(_, n)| n.as_u64().unwrap() > 0), "{z}");
    assert_eq!(
        z["forged"], 0,
        "the flooding client's own requests are its own: {z}"
    );
    // Its queued puts may outlast zenoh's close wait: the session goes either way.
    drop(flood_client);
    let _ = session.close().wait();
}

/// Issue #40, a remote client's id used by another peer: a second zenoh session that reads
/// the victim's `in` and `out` keys (as any peer that reaches the daemon can) puts requests on
/// the victim's id: plainly, a captured request of the victim's put again, the victim's tag on
/// other bytes, a hello with its own key, and the victim's own hello again. Every one is
/// refused and counted (`forged`), the arm keeps the victim's mode, and the victim's next
/// request is still served.
#[test]
#[ignore = "paced"]
fn a_peer_that_reads_a_remote_clients_traffic_cannot_act_as_it() {
    let port = common::free_port();
    let d = serve(port, COMMANDS);
    // The attacker records everything put on any client's id, from before the victim comes.
    let thief = peer(port);
    let (tx, captured) = std::sync::mpsc::channel::<(String, Vec<u8>, Option<Vec<u8>>)>();
    let _spy = thief
        .declare_subscriber("omnid/sim/in/*")
        .callback(move |m| {
            let tag = m.attachment().map(|a| a.to_bytes().into_owned());
            let key = m.key_expr().to_string();
            let _ = tx.send((key, m.payload().to_bytes().into_owned(), tag));
        })
        .wait()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let victim_session = peer(port);
    // The thief reads the victim's puts once the two sessions meet (zenoh's gossip).
    let until = Instant::now() + Duration::from_secs(20);
    while !victim_session
        .info()
        .peers_zid()
        .wait()
        .any(|z| z == thief.zid())
    {
        assert!(
            Instant::now() < until,
            "the thief's session never met the victim's"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    std::thread::sleep(Duration::from_millis(300));
    let (mut victim, hello) = Remote::connect(&victim_session, "victim-");
    assert_eq!(hello["access"], "control", "{hello}");
    let key = format!("omnid/sim/in/{}", victim.cid);
    let seen = thief
        .declare_subscriber(format!("omnid/sim/out/{}", victim.cid))
        .wait()
        .unwrap();
    // Its subscription reaches the daemon before the victim's next replies leave.
    std::thread::sleep(Duration::from_millis(500));
    let (r, free, _) = victim.request(json!({"op": "mode", "mode": "free"}));
    assert_eq!(r["type"], "reply", "{r}");
    let (r, _, hold_tag) = victim.request(json!({"op": "mode", "mode": "hold"}));
    assert_eq!(r["type"], "reply", "{r}");
    // The spy read the victim's hello and requests, tags and all; and its replies.
    std::thread::sleep(Duration::from_millis(500));
    let got: Vec<_> = captured.try_iter().filter(|(k, ..)| *k == key).collect();
    let free_tag = got
        .iter()
        .find(|(_, b, t)| *b == free && t.is_some())
        .and_then(|(_, _, t)| t.clone())
        .expect("the spy read the victim's request");
    let victims_hello = got
        .iter()
        .find(|(_, b, _)| String::from_utf8_lossy(b).contains(r#""op":"hello""#))
        .map(|(_, b, _)| b.clone())
        .expect("the spy read the victim's hello");
    let mut replies = 0;
    while let Ok(Some(_)) = seen.recv_timeout(Duration::from_millis(300)) {
        replies += 1;
    }
    assert!(replies >= 2, "the spy read the victim's replies");
    let status = |d: &Served| -> (u64, String) {
        let mut c = d.client("sim", "checker");
        let r = c.request(json!({"op": "status"})).unwrap();
        let z = r["status"]["zenoh"]["forged"].as_u64().unwrap_or(0);
        (z, r["status"]["mode"].as_str().unwrap_or("").to_string())
    };
    let (before, mode) = status(&d);
    assert_eq!(mode, "hold");
    // 1. A plain request on the victim's id (on the code before the binding, it was served).
    thief
        .put(&key, r#"{"op":"mode","mode":"idle","id":"x1"}"#)
        .wait()
        .unwrap();
    // 2. The victim's captured `free` put again, tag and all.
    thief
        .put(&key, free.clone())
        .attachment(free_tag)
        .wait()
        .unwrap();
    // 3. The victim's newest tag on other bytes.
    thief
        .put(&key, r#"{"op":"mode","mode":"idle","id":2}"#)
        .attachment(hold_tag)
        .wait()
        .unwrap();
    // 4. A hello on the victim's id with the thief's own key; 5. the victim's hello again.
    let own = omnid::transport::zenoh::bind::ClientKey::new().unwrap();
    let hello = json!({"op": "hello", "protocol": 1, "key": own.public_base64()});
    thief.put(&key, hello.to_string()).wait().unwrap();
    thief.put(&key, victims_hello).wait().unwrap();
    let until = Instant::now() + Duration::from_secs(20);
    let (after, mode) = loop {
        let (n, mode) = status(&d);
        if n >= before + 5 || Instant::now() > until {
            break (n, mode);
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(mode, "hold", "another session's request moved the arm");
    assert_eq!(after - before, 5, "each of the five was refused as forged");
    // None of them was answered on the victim's key.
    if let Ok(Some(m)) = seen.recv_timeout(Duration::from_millis(500)) {
        panic!(
            "a forged request was answered: {}",
            String::from_utf8_lossy(&m.payload().to_bytes())
        );
    }
    let (r, _, _) = victim.request(json!({"op": "mode", "mode": "idle"}));
    assert_eq!(r["type"], "reply", "the victim still commands: {r}");
    assert_eq!(status(&d).1, "idle");
}

/// docs/ZENOH.md, "A lab network", TLS: a CA and certificates made here (rcgen), the daemon
/// listening on a `tls/` endpoint with `tls_certificate`, `tls_private_key` and `tls_root_ca`.
/// A client that trusts the lab's CA connects and is greeted; one that does not (the system's
/// roots only) gets no session. With `tls_mutual = true`, a client trusting the CA but showing
/// no certificate of its own gets none either, and one with a certificate the CA signed does.
#[test]
#[ignore = "paced"]
fn over_tls_a_client_with_the_labs_ca_connects_and_one_without_it_cannot() {
    use rcgen::{
        BasicConstraints, CertificateParams, CertifiedIssuer, DnType, ExtendedKeyUsagePurpose,
        IsCa, KeyPair, KeyUsagePurpose,
    };
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, text: String| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path.display().to_string()
    };
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "omnid test lab CA");
    ca_params.key_usages = vec![KeyUsagePurpose::KeyCertSign, KeyUsagePurpose::CrlSign];
    let ca = CertifiedIssuer::self_signed(ca_params, KeyPair::generate().unwrap()).unwrap();
    let ca_pem = write("ca.pem", ca.pem());
    // A certificate the CA signed, for loopback, usable by a server and a client.
    let leaf = |name: &str| -> (String, String) {
        let mut p =
            CertificateParams::new(vec!["localhost".to_string(), "127.0.0.1".to_string()]).unwrap();
        p.distinguished_name.push(DnType::CommonName, name);
        p.extended_key_usages = vec![
            ExtendedKeyUsagePurpose::ServerAuth,
            ExtendedKeyUsagePurpose::ClientAuth,
        ];
        let key = KeyPair::generate().unwrap();
        let cert = p.signed_by(&key, &ca).unwrap();
        (
            write(&format!("{name}.pem"), cert.pem()),
            write(&format!("{name}.key"), key.serialize_pem()),
        )
    };
    let (daemon_cert, daemon_key) = leaf("daemon");
    let (client_cert, client_key) = leaf("client");
    // A client session to `port` over TLS: trusting the CA or not, with a certificate or not.
    let client = |port: u16, ca: bool, cert: bool| -> Option<zenoh::Session> {
        let mut c = zenoh::Config::default();
        let mut keys = vec![
            ("mode", "\"peer\"".to_string()),
            ("connect/endpoints", format!("[\"tls/127.0.0.1:{port}\"]")),
            ("listen/endpoints", "[]".into()),
            ("scouting/multicast/enabled", "false".into()),
        ];
        if ca {
            keys.push((
                "transport/link/tls/root_ca_certificate",
                format!("{ca_pem:?}"),
            ));
        }
        if cert {
            keys.push(("transport/link/tls/enable_mtls", "true".into()));
            keys.push((
                "transport/link/tls/connect_certificate",
                format!("{client_cert:?}"),
            ));
            keys.push((
                "transport/link/tls/connect_private_key",
                format!("{client_key:?}"),
            ));
        }
        for (k, v) in keys {
            c.insert_json5(k, &v).unwrap();
        }
        zenoh::open(c).wait().ok()
    };
    let greeted = |s: Option<zenoh::Session>, who: &str| -> bool {
        let Some(s) = s else { return false };
        let answer = Remote::try_connect(&s, "tls-", Duration::from_secs(5));
        let _ = s.close().wait();
        answer.is_some_and(|(_, v)| {
            assert_eq!(v["type"], "hello", "{who}: {v}");
            true
        })
    };
    for mutual in [false, true] {
        let port = common::free_port();
        let config = format!(
            "[zenoh]\nenabled = true\nros2 = false\nlisten = [\"tls/127.0.0.1:{port}\"]\n\
             connect = []\ntls_certificate = {daemon_cert:?}\ntls_private_key = \
             {daemon_key:?}\ntls_root_ca = {ca_pem:?}\ntls_mutual = {mutual}\n"
        );
        let mut d = Served::start(&["--device", "sim"], Some(&config), &["sim"]);
        if mutual {
            assert!(greeted(client(port, true, true), "CA + certificate"));
            assert!(
                !greeted(client(port, true, false), "CA, no certificate"),
                "mutual TLS greeted a client without a certificate"
            );
        } else {
            assert!(greeted(client(port, true, false), "with the CA"));
        }
        assert!(
            !greeted(client(port, false, mutual), "without the CA"),
            "a client that does not trust the lab's CA was greeted (mutual: {mutual})"
        );
        let (_, err) = d.stop();
        assert!(err.contains(&format!("tls/127.0.0.1:{port}")), "{err}");
    }
}

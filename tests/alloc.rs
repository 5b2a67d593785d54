//! The servo loop allocates nothing per tick: a counting global allocator watches the servo
//! thread (only) over thousands of ticks after warm-up.

use nalgebra::Vector3;
use omnid::config::Config;
use omnid::control::{ControllerKind, ControllerSet, Reference, Trajectory};
use omnid::device::sim::SimOmni;
use omnid::identifier::{Identifier, IdentifierConfig};
use omnid::servo::{EndReason, Servo};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

struct Counting;

thread_local! {
    // Per thread, so tests running in parallel do not see each other's allocations.
    static WATCHED: Cell<bool> = const { Cell::new(false) };
    static ALLOCATIONS: Cell<u64> = const { Cell::new(0) };
}

fn note() {
    // try_with: TLS may be gone while a thread is being torn down.
    if WATCHED.try_with(|w| w.get()).unwrap_or(false) {
        let _ = ALLOCATIONS.try_with(|n| n.set(n.get() + 1));
    }
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc(layout) }
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note();
        unsafe { System.alloc_zeroed(layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note();
        unsafe { System.realloc(ptr, layout, new_size) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// Allocations on this thread while `f` runs.
fn count_allocations(f: impl FnOnce()) -> u64 {
    let before = ALLOCATIONS.with(|n| n.get());
    WATCHED.with(|w| w.set(true));
    f();
    WATCHED.with(|w| w.set(false));
    ALLOCATIONS.with(|n| n.get()) - before
}

#[test]
fn the_counter_sees_an_allocation() {
    // The instrument itself must be able to fail.
    let n = count_allocations(|| {
        std::hint::black_box(vec![1u8; 100]);
    });
    assert!(n >= 1);
}

fn ticks_allocate_nothing(kind: ControllerKind, trajectory: Trajectory) {
    ticks_allocate_nothing_with(Config::default(), kind, trajectory);
}

fn ticks_allocate_nothing_with(cfg: Config, kind: ControllerKind, trajectory: Trajectory) {
    let device = Box::new(SimOmni::new(&cfg, false));
    let controller = ControllerSet::new(&cfg, kind, 0.0);
    let reference = Reference::new(trajectory, &cfg.reference, cfg.sim.seed);
    // A small channel drained by a consumer thread: both the send and the full (dropped)
    // paths are taken.
    let (tx, rx) = crossbeam_channel::bounded(64);
    let consumer = std::thread::spawn(move || {
        let mut n = 0u64;
        for _ in rx.iter() {
            n += 1;
            if n.is_multiple_of(512) {
                std::thread::yield_now();
            }
        }
        n
    });
    let stop = Arc::new(AtomicBool::new(false));
    // paced = true: the realtime configuration (telemetry by try_send; the simulator itself
    // is unpaced so the test runs fast).
    let mut servo = Servo::new(&cfg, device, controller, reference, tx, stop, None, true);
    // Adapting identifier on, from the weights a run of this controller would start with.
    let (id, _) = omnid::cmd::run::make_identifier(&cfg, kind, None, false, None).unwrap();
    assert!(cfg.identifier.adapt);
    servo.set_identifier(id);
    for _ in 0..2_500 {
        assert!(servo.tick().is_none());
    }
    let n = count_allocations(|| {
        for _ in 0..5_000 {
            assert!(servo.tick().is_none());
        }
    });
    assert_eq!(n, 0, "{kind:?}: {n} allocations in 5000 ticks");
    let report = servo.finish(EndReason::Completed);
    assert!(report.last_command.is_safe());
    assert!(consumer.join().unwrap() > 0);
}

#[test]
fn sim_pd_sine_allocates_nothing_per_tick() {
    ticks_allocate_nothing(ControllerKind::Pd, Trajectory::Sine);
}

#[test]
fn sim_pd_multisine_allocates_nothing_per_tick() {
    ticks_allocate_nothing(ControllerKind::Pd, Trajectory::Multisine);
}

#[test]
fn sim_nnidc_adapting_allocates_nothing_per_tick() {
    ticks_allocate_nothing(ControllerKind::Nnidc, Trajectory::Sine);
}

#[test]
fn sim_nnidc_adapting_with_the_lag_matched_error_allocates_nothing_per_tick() {
    let mut cfg = Config::default();
    cfg.identifier.lag_match = true;
    ticks_allocate_nothing_with(cfg, ControllerKind::Nnidc, Trajectory::Sine);
}

#[test]
fn sim_ct_allocates_nothing_per_tick() {
    ticks_allocate_nothing(ControllerKind::Ct, Trajectory::Multisine);
}

#[test]
fn sim_off_allocates_nothing_per_tick() {
    ticks_allocate_nothing(ControllerKind::Off, Trajectory::Hold);
}

/// Every effect kind at once, the tip inside most of them.
fn every_effect(centre: [f64; 3]) -> Vec<omnid::haptics::Effect> {
    use omnid::haptics::Effect;
    let [x, y, z] = centre;
    vec![
        Effect::Spring {
            center_mm: [x + 5.0, y, z],
            stiffness_n_per_mm: 0.05,
            damping_n_s_per_m: 0.5,
        },
        Effect::Damper {
            damping_n_s_per_m: 1.0,
        },
        Effect::Plane {
            point_mm: [x, y - 15.0, z],
            normal: [0.0, 1.0, 0.0],
            stiffness_n_per_mm: 2.31,
            damping_n_s_per_m: 1.0,
        },
        Effect::Box {
            min_mm: [x - 30.0, y - 30.0, z - 30.0],
            max_mm: [x + 30.0, y + 30.0, z + 30.0],
            stiffness_n_per_mm: 1.0,
            damping_n_s_per_m: 0.0,
        },
        Effect::Constant {
            force_n: [0.0, -0.2, 0.1],
        },
    ]
}

/// Free mode with every effect (or none), the passivity controller on, and the simulated hand
/// doing `hand` (each pattern in turn), through the scene changes a client makes; `inertia`:
/// the partial inertia compensation's fraction.
fn haptic_ticks_allocate_nothing(hand: &str, effects: bool, inertia: f64) {
    let mut cfg = Config::default();
    cfg.haptics.inertia_compensation = inertia;
    cfg.sim.start_pose = cfg.reference.center;
    cfg.haptics.hand.pattern = omnid::haptics::HandPattern::try_from(hand.to_string()).unwrap();
    cfg.haptics.hand.release_s = 4.0;
    assert!(cfg.haptics.passivity);
    let device = Box::new(SimOmni::new(&cfg, false));
    let controller = ControllerSet::new(&cfg, ControllerKind::Nnidc, 0.0);
    let reference = Reference::new(Trajectory::Hold, &cfg.reference, cfg.sim.seed);
    let (tx, rx) = crossbeam_channel::bounded(64);
    let consumer = std::thread::spawn(move || rx.iter().count());
    let stop = Arc::new(AtomicBool::new(false));
    let mut servo = Servo::new(&cfg, device, controller, reference, tx, stop, None, true);
    let (id, _) =
        omnid::cmd::run::make_identifier(&cfg, ControllerKind::Nnidc, None, false, None).unwrap();
    servo.set_identifier(id);
    servo.start_free();
    let centre: [f64; 3] =
        omnid::omni::tip_position_mm(&cfg.geometry, &cfg.reference.center.into()).into();
    if effects {
        servo.set_effects(&every_effect(centre));
    }
    for _ in 0..1_500 {
        assert!(servo.tick().is_none());
    }
    let n = count_allocations(|| {
        for _ in 0..4_000 {
            assert!(servo.tick().is_none());
        }
    });
    assert_eq!(n, 0, "hand {hand}: {n} allocations in 4000 haptic ticks");
    let report = servo.finish(EndReason::Completed);
    assert!(report.last_command.is_safe());
    assert!(consumer.join().unwrap() > 0);
}

#[test]
fn free_mode_with_every_effect_and_each_hand_allocates_nothing() {
    for hand in ["path", "push-y", "hold"] {
        haptic_ticks_allocate_nothing(hand, true, 0.0);
    }
}

#[test]
fn free_mode_with_inertia_compensation_allocates_nothing() {
    // Without effects the gate stays open (the compensation acts every tick); with them it
    // closes and reopens as the tip meets them.
    let most = omnid::haptics::MAX_INERTIA_COMPENSATION;
    haptic_ticks_allocate_nothing("path", false, most);
    for hand in ["path", "push-y"] {
        haptic_ticks_allocate_nothing(hand, true, most);
    }
}

#[test]
fn replay_allocates_nothing_per_tick() {
    replay_ticks_allocate_nothing("sim.csv");
}

#[test]
fn replay_of_an_mcap_log_allocates_nothing_per_tick() {
    // Decoded on a thread of its own and handed over in blocks that go back and forth (6000
    // ticks span several blocks).
    replay_ticks_allocate_nothing("sim.mcap");
}

/// The replay's reader waits for its decoding thread when that falls behind (a loaded
/// machine): the wait must not allocate either. A slow source makes every block late, so the
/// reading thread waits on each (a blocking channel receive allocated its waiter on the first
/// wait: 2 allocations, seen once in a full run under load).
#[test]
fn reading_an_mcap_log_that_decodes_late_allocates_nothing() {
    use omnid::telemetry::mcap_log::read::McapPrefetch;
    use std::io::Read;
    struct Slow(std::fs::File);
    impl Read for Slow {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            std::thread::sleep(std::time::Duration::from_millis(2));
            let n = buf.len().min(4096);
            self.0.read(&mut buf[..n])
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.mcap");
    record_sim_log(&Config::default(), &log, 3.0);

    let mut text = McapPrefetch::new(Slow(std::fs::File::open(&log).unwrap()), false).unwrap();
    let mut buf = [0u8; 512];
    let mut total = 0usize;
    let n = count_allocations(|| loop {
        match text.read(&mut buf) {
            Ok(0) => break,
            Ok(k) => total += k,
            Err(e) => panic!("{e}"),
        }
    });
    assert!(
        total > 1 << 17,
        "only {total} bytes: the wait was never taken"
    );
    assert_eq!(n, 0, "{n} allocations while waiting for late blocks");
}

/// A simulator run of `duration_s` with PD on the multisine, logged to `log` (its format
/// from the extension).
fn record_sim_log(cfg: &Config, log: &std::path::Path, duration_s: f64) {
    let opts = omnid::cmd::run::RunOptions {
        controller: ControllerKind::Pd,
        trajectory: Trajectory::Multisine,
        duration_s,
        log: Some(log.to_path_buf()),
        fast: true,
        ..omnid::cmd::run::RunOptions::default()
    };
    let mut sim_cfg = cfg.clone();
    sim_cfg.safety.persist_heat = false;
    omnid::cmd::run::execute(&opts, &sim_cfg, Arc::new(AtomicBool::new(false))).unwrap();
}

fn replay_ticks_allocate_nothing(name: &str) {
    // The replay device reads the next row of the file inside `exchange`: that must reuse its
    // buffers too. Record a simulator log first (outside the watched window).
    let cfg = Config::default();
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join(name);
    record_sim_log(&cfg, &log, 8.0);

    let device = Box::new(
        omnid::device::replay::ReplayDevice::open(&log, &cfg.device, false, false, &Arc::default())
            .unwrap(),
    );
    let reference = Reference::new(Trajectory::Multisine, &cfg.reference, cfg.sim.seed);
    let (tx, rx) = crossbeam_channel::bounded(64);
    let consumer = std::thread::spawn(move || rx.iter().count());
    let stop = Arc::new(AtomicBool::new(false));
    let controller = ControllerSet::new(&cfg, ControllerKind::Pd, 0.0);
    let mut servo = Servo::new(&cfg, device, controller, reference, tx, stop, None, true);
    let (id, _) =
        omnid::cmd::run::make_identifier(&cfg, ControllerKind::Nnidc, None, false, None).unwrap();
    servo.set_identifier(id);
    for _ in 0..1_000 {
        assert!(servo.tick().is_none());
    }
    let n = count_allocations(|| {
        for _ in 0..6_000 {
            assert!(servo.tick().is_none());
        }
    });
    assert_eq!(n, 0, "replay of {name}: {n} allocations in 6000 ticks");
    let report = servo.finish(EndReason::Completed);
    assert!(report.last_command.is_safe());
    assert!(consumer.join().unwrap() > 0);
}

#[test]
fn serve_servo_allocates_nothing_with_clients_connected() {
    use omnid::transport::client::Client;
    use serde_json::json;
    use std::sync::atomic::{AtomicU64, Ordering};

    let dir = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    cfg.safety.persist_heat = false;
    // The user's kept weights are neither read nor written by a test.
    cfg.identifier.persist = false;
    cfg.serve.dump_dir = dir.path().display().to_string();
    let socket = dir.path().join("sim.sock");
    let opts = omnid::cmd::serve::ServeOptions {
        devices: vec![omnid::cmd::run::DeviceSpec::Sim],
        socket: Some(socket.clone()),
        ..Default::default()
    };
    let stop = Arc::new(AtomicBool::new(false));
    // The daemon as `omnid serve` assembles it; its servo ticks on this (watched) thread.
    let prepared = omnid::cmd::serve::prepare(&opts, &cfg, stop).unwrap();
    let mut servo = prepared.pipeline.servo;
    // The live view's tap on the hub too: its encoder thread works on every tick.
    let view = omnid::transport::foxglove::LiveView::start("127.0.0.1:0".parse().unwrap()).unwrap();
    let tap = view.tap_for(&prepared.station, false);
    // And zenoh: the ROS 2 topics, read by a peer of this test (so every topic is encoded).
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let zcfg = omnid::transport::zenoh::ZenohConfig {
        listen: vec![format!("tcp/127.0.0.1:{port}")],
        ..Default::default()
    };
    let net = omnid::transport::zenoh::ZenohNet::start(&zcfg).unwrap();
    let (ztap, zdoor) = net.arm(&prepared.station, &cfg.serve).unwrap();
    let ros_reader = {
        use zenoh::Wait;
        let mut c = zenoh::Config::default();
        c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]"))
            .unwrap();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        let s = zenoh::open(c).wait().unwrap();
        let got = Arc::new(AtomicU64::new(0));
        let g = got.clone();
        let sub = s
            .declare_subscriber("0/sim/**")
            .callback(move |_| {
                g.fetch_add(1, Ordering::Relaxed);
            })
            .wait()
            .unwrap();
        (s, sub, got)
    };
    let hub = std::thread::spawn(move || {
        let mut host = omnid::transport::host::Host::new(prepared.station);
        host.add_port(Box::new(omnid::transport::unix::SocketPort::new(
            prepared.socket,
        )));
        host.add_tap(tap);
        host.add_tap(ztap);
        host.add_port(Box::new(omnid::transport::zenoh::port::ZenohPort::new(
            zdoor,
            cfg.serve.hello_timeout_ms,
        )));
        host.run()
    });

    let readers: Vec<_> = (0..3)
        .map(|k| {
            let path = socket.clone();
            std::thread::spawn(move || {
                let mut c = Client::connect(&path, &format!("reader {k}")).unwrap();
                c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
                let mut n = 0u64;
                while c.next_state(5000).is_ok() {
                    n += 1;
                }
                n
            })
        })
        .collect();
    // The commander: a setpoint stream answering every state, and every other command kind
    // in turn, once the counting has begun.
    let counting = Arc::new(AtomicBool::new(false));
    let cycles = Arc::new(AtomicU64::new(0));
    let commander = {
        let (path, counting, cycles) = (socket.clone(), counting.clone(), cycles.clone());
        let weights = dir.path().join("w.json");
        std::thread::spawn(move || {
            let mut c = Client::connect(&path, "commander").unwrap();
            c.request(json!({"op": "mode", "mode": "hold"})).unwrap();
            // Recording MCAP all along (chunks compressed on the writer's thread).
            let rec = path.with_file_name("session.mcap");
            c.request(json!({"op": "record_start", "path": rec}))
                .unwrap();
            c.request(json!({"op": "weights_save", "path": weights}))
                .unwrap();
            c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
            let controllers = ["pd", "ct", "nnidc"];
            let mut k = 0usize;
            loop {
                let Ok(s) = c.next_state(5000) else { return };
                let q = [s.q[0], 0.6, 0.3];
                // Joint setpoints, and in every other half second a tip force stream.
                let sent = if counting.load(Ordering::SeqCst) && s.seq / 500 % 2 == 1 {
                    c.send(
                        &json!({"op": "servo_cf", "seq": s.seq, "force": [0.0, 0.1, 0.0],
                                   "ttl_ms": 100}),
                    )
                } else {
                    c.send(&json!({"op": "servo_jp", "seq": s.seq, "q": q}))
                };
                if sent.is_err() {
                    return;
                }
                if counting.load(Ordering::SeqCst) && s.seq % 100 == 0 {
                    let effect = json!({"type": "damper", "damping_n_s_per_m": 0.5});
                    let r = match k % 6 {
                        0 => c.request(
                            json!({"op": "controller", "controller": controllers[k / 6 % 3]}),
                        ),
                        1 => c.request(json!({"op": "status"})),
                        2 => c.request(json!({"op": "weights_load", "path": weights})),
                        3 => c.request(json!({"op": "effect", "slot": k % 8, "effect": effect})),
                        4 => c.request(json!({"op": "passivity", "on": k % 12 != 4})),
                        _ => c.request(json!({"op": "adapt", "on": k % 12 != 5})),
                    };
                    if r.is_err() {
                        return;
                    }
                    k += 1;
                    cycles.store(k as u64, Ordering::SeqCst);
                }
            }
        })
    };
    for _ in 0..1_500 {
        assert!(servo.tick().is_none());
    }
    counting.store(true, Ordering::SeqCst);
    // Ticks counted while a client's stream drove the arm (a loaded machine may stall the
    // commander past a stream's time to live now and then: the arm holds meanwhile).
    let mut streamed = 0u32;
    let n = count_allocations(|| {
        for _ in 0..3_000 {
            assert!(servo.tick().is_none());
            streamed += matches!(
                servo.activity(),
                omnid::servo::Activity::ServoJp | omnid::servo::Activity::ServoCf
            ) as u32;
        }
    });
    let done = cycles.load(Ordering::SeqCst);
    assert!(
        streamed > 100,
        "only {streamed} of the counted ticks were streamed"
    );
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
    hub.join().unwrap();
    commander.join().unwrap();
    for r in readers {
        assert!(r.join().unwrap() > 1_000, "readers were served");
    }
    let (_session, _sub, got) = ros_reader;
    let got = got.load(Ordering::Relaxed);
    assert!(got > 1_000, "the ROS 2 reader over zenoh got {got} samples");
    drop(net);
    assert!(
        done >= 8,
        "only {done} commands besides the stream in the window"
    );
    assert_eq!(
        n, 0,
        "serve: {n} allocations in 3000 ticks with clients connected"
    );
}

#[test]
fn two_served_arms_allocate_nothing_with_a_client_streaming_each() {
    use omnid::transport::client::Client;
    use serde_json::json;

    let dir = tempfile::tempdir().unwrap();
    let mut cfg = Config::default();
    cfg.safety.persist_heat = false;
    // The user's kept weights are neither read nor written by a test.
    cfg.identifier.persist = false;
    cfg.serve.dump_dir = dir.path().display().to_string();
    let opts = omnid::cmd::serve::ServeOptions {
        devices: vec![
            omnid::cmd::run::DeviceSpec::Sim,
            omnid::cmd::run::DeviceSpec::Sim,
        ],
        ..Default::default()
    };
    let stop = Arc::new(AtomicBool::new(false));
    let mut servos = Vec::new();
    let mut hubs = Vec::new();
    let mut clients = Vec::new();
    for (k, mut arm) in omnid::cmd::serve::arms(&opts, &cfg)
        .unwrap()
        .into_iter()
        .enumerate()
    {
        arm.socket = Some(dir.path().join(format!("arm{k}.sock")));
        let p = omnid::cmd::serve::prepare_arm(&arm, &opts, &cfg, stop.clone()).unwrap();
        servos.push(p.pipeline.servo);
        hubs.push(std::thread::spawn(move || {
            let mut host = omnid::transport::host::Host::new(p.station);
            host.add_port(Box::new(omnid::transport::unix::SocketPort::new(p.socket)));
            host.run()
        }));
        let path = arm.socket.clone().unwrap();
        // A commander per arm: every state answered with a setpoint.
        clients.push(std::thread::spawn(move || {
            let mut c = Client::connect(&path, "commander").unwrap();
            c.request(json!({"op": "mode", "mode": "hold"})).unwrap();
            c.request(json!({"op": "stream", "rate_hz": 1000})).unwrap();
            let mut n = 0u64;
            while let Ok(s) = c.next_state(5000) {
                let sp = json!({"op": "servo_jp", "seq": s.seq, "q": [s.q[0], 0.6, 0.3]});
                if c.send(&sp).is_err() {
                    break;
                }
                n += 1;
            }
            n
        }));
    }
    for _ in 0..1_000 {
        for s in servos.iter_mut() {
            assert!(s.tick().is_none());
        }
    }
    let n = count_allocations(|| {
        for _ in 0..2_000 {
            for s in servos.iter_mut() {
                assert!(s.tick().is_none());
            }
        }
    });
    for s in &servos {
        assert_eq!(s.activity(), omnid::servo::Activity::ServoJp);
    }
    for s in servos {
        assert!(s.finish(EndReason::OperatorStop).last_command.is_safe());
    }
    for h in hubs {
        h.join().unwrap();
    }
    for c in clients {
        assert!(c.join().unwrap() > 1_000, "each arm's client was served");
    }
    assert_eq!(n, 0, "two arms: {n} allocations in 2 × 2000 ticks");
}

#[test]
fn a_pair_coupled_over_zenoh_allocates_nothing_per_tick_on_its_servo_thread() {
    // The channel to another daemon's arm: the servo hands its packet to the publishing
    // thread's queue and takes the peer's from the subscriber's; zenoh's own work (encoding,
    // the socket) is on those threads, not this one.
    use omnid::experiment::teleop::{Link, PairSim, Scene, CHANNELS};
    use omnid::teleop::{Architecture, TeleopConfig};
    let scene = Scene::Press {
        force_n: 1.0,
        wall_n_per_mm: 1.0,
    };
    let mut sim = PairSim::build(
        &TeleopConfig::default(),
        Architecture::Pf,
        true,
        &scene,
        &CHANNELS[0],
        10.0,
        false,
        Link::Zenoh,
    )
    .unwrap();
    for _ in 0..500 {
        sim.tick().unwrap();
    }
    let n = count_allocations(|| {
        for _ in 0..2000 {
            std::hint::black_box(sim.tick().unwrap());
        }
    });
    assert_eq!(n, 0, "{n} allocations over 2000 ticks coupled over zenoh");
    assert_eq!(
        sim.leader.teleop().unwrap().state().as_str(),
        "engaged",
        "the pair was coupled throughout"
    );
}

#[test]
fn a_coupled_teleoperation_pair_allocates_nothing_per_tick() {
    // Two servos coupled in one process, each with its side of the pair (the channel, the
    // delay line, the passivity port, the fast velocity filter), over a delayed, lossy
    // channel with the hand pushing the follower into its floor.
    use omnid::experiment::teleop::{PairSim, Scene, CHANNELS};
    use omnid::teleop::{Architecture, DelayControl, TeleopConfig};
    let scene = Scene::Press {
        force_n: 1.0,
        wall_n_per_mm: 1.0,
    };
    // Both delay controls: the delay-aware gains and the wave variables.
    let wave = TeleopConfig {
        delay_control: DelayControl::Wave,
        ..TeleopConfig::default()
    };
    for (arch, cfg) in [
        (Architecture::Pp, TeleopConfig::default()),
        (Architecture::Pf, TeleopConfig::default()),
        (Architecture::Pp, wave.clone()),
        (Architecture::Pf, wave),
    ] {
        let lossy = CHANNELS.iter().find(|c| c.loss > 0.0).unwrap();
        let mut sim = PairSim::new(&cfg, arch, true, &scene, lossy, 10.0, false).unwrap();
        for _ in 0..500 {
            sim.tick().unwrap();
        }
        let n = count_allocations(|| {
            for _ in 0..3000 {
                std::hint::black_box(sim.tick().unwrap());
            }
        });
        assert_eq!(
            n, 0,
            "{arch:?} {:?}: {n} allocations over 3000 coupled ticks",
            cfg.delay_control
        );
    }
}

// The identifier's per-tick path (update, predict, the model accessors) on its own.

fn tick_inputs(k: usize) -> [Vector3<f64>; 4] {
    let t = k as f64 * 1e-3;
    let q = Vector3::new(
        0.4 * t.sin(),
        0.65 + 0.3 * (1.3 * t).sin(),
        0.3 + 0.3 * t.cos(),
    );
    let qd = Vector3::new(0.4 * t.cos(), 0.39 * (1.3 * t).cos(), -0.3 * t.sin());
    let qdd = Vector3::new(-0.4 * t.sin(), -0.5 * (1.3 * t).sin(), -0.3 * t.cos());
    let tau = Vector3::new(0.01 * t.sin(), 0.03, -0.05 * q[2].sin());
    [q, qd, qdd, tau]
}

#[test]
fn update_and_accessors_do_not_allocate() {
    for cfg in [
        IdentifierConfig::default(),
        IdentifierConfig {
            friction_net: false,
            hidden: 5,
            // Tight eigenvalue bounds: the eigen-decomposition path runs every tick.
            eig_min: 3e-3,
            eig_max: 3.1e-3,
            ..IdentifierConfig::default()
        },
    ] {
        let mut id = Identifier::new(&cfg).unwrap();
        let mut sink = 0.0;
        let n = count_allocations(|| {
            for k in 0..2000 {
                let [q, qd, qdd, tau] = tick_inputs(k);
                let tau_hat = id.update(&q, &qd, &qdd, &tau, 1e-3);
                let v = id.inverse_dynamics(&q, &qd, &qdd);
                sink += tau_hat.sum() + v.sum() + id.last_errors().modified_norm;
                sink += id.mass(&q).sum() + id.coriolis(&q, &qd).sum();
                sink += id.gravity(&q).sum() + id.friction(&qd).sum();
                sink += id.weights_norm()[0] + id.weight_change_norm();
            }
        });
        assert!(sink.is_finite());
        assert!(id.healthy());
        assert_eq!(
            n, 0,
            "{n} allocations in 2000 ticks (hidden {})",
            cfg.hidden
        );
    }
}

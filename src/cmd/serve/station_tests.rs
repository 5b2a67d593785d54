//! A station driven directly, with no socket: a test-only transport and a test-only recorder,
//! each a few dozen lines over the station's API, as a new transport or recorder would be.
//! Here, above the station, because the daemon assembles the stations they drive.

use super::{prepare, ServeOptions};
use crate::servo::{EndReason, Servo};
use crate::station::*;
use crate::telemetry::record::{Mode, TickRecord};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::sync::Mutex;

/// A transport of its own: one session, ops called in-process, outputs collected.
struct Loopback {
    station: Station,
    session: SessionId,
    states: Vec<ArmState>,
    events: Vec<Event>,
    done: Vec<(u64, Result<Reply, OpError>)>,
}

/// A session of the daemon's own user, which may command.
fn commander(name: &str) -> SessionInfo {
    SessionInfo {
        name: name.into(),
        pid: 0,
        uid: 0,
        control: true,
        privileged: true,
        read_only_reason: String::new(),
        files: FileRights::Daemon,
    }
}

impl Loopback {
    fn new(mut station: Station, name: &str) -> Loopback {
        let session = station.open_session(commander(name));
        Loopback {
            station,
            session,
            states: Vec::new(),
            events: Vec::new(),
            done: Vec::new(),
        }
    }

    fn call(&mut self, op: Op) -> Result<Answer, OpError> {
        self.station.request(self.session, op)
    }

    fn pump(&mut self) {
        let (states, events, done) = (&mut self.states, &mut self.events, &mut self.done);
        self.station.pump(&mut |o| match o {
            Output::State(s) => states.push(s.clone()),
            Output::Event(e) => events.push(e.clone()),
            Output::Done { ticket, result, .. } => done.push((ticket, result)),
        });
    }
}

/// A recorder of its own: every tick's number and mode.
struct Counting(Arc<Mutex<Vec<(u64, Mode)>>>);

impl Tap for Counting {
    fn on_tick(&mut self, r: &TickRecord) {
        self.0.lock().unwrap().push((r.live.seq, r.mode));
    }
}

/// The daemon's pipeline for a simulated arm, and its station's setup (no socket served).
fn served_sim() -> (Servo, StationSetup, tempfile::TempDir) {
    let (servo, setup, dir, _) = served_sim_with(crate::control::ControllerKind::Pd, None);
    (servo, setup, dir)
}

/// A simulated arm under `controller`, its identifier started from the weights kept at
/// `kept` when they are there (as the daemon's start does); the pipeline's weights label.
fn served_sim_with(
    controller: crate::control::ControllerKind,
    kept: Option<&std::path::Path>,
) -> (Servo, StationSetup, tempfile::TempDir, String) {
    served_arm(controller, kept, crate::config::Config::default())
}

/// A served simulated arm of `cfg` (its heat and weights not kept).
fn served_arm(
    controller: crate::control::ControllerKind,
    kept: Option<&std::path::Path>,
    mut cfg: crate::config::Config,
) -> (Servo, StationSetup, tempfile::TempDir, String) {
    let dir = tempfile::tempdir().unwrap();
    cfg.safety.persist_heat = false;
    cfg.identifier.persist = false;
    cfg.serve.dump_dir = dir.path().display().to_string();
    let opts = ServeOptions {
        devices: vec![crate::cmd::run::DeviceSpec::Sim],
        controller,
        socket: Some(dir.path().join("unused.sock")),
        ..ServeOptions::default()
    };
    let mut p = prepare(&opts, &cfg, Arc::new(AtomicBool::new(false))).unwrap();
    if let Some(path) = kept {
        super::start_from_kept(path, false, &cfg, "sim", &mut p.pipeline);
    }
    (p.pipeline.servo, p.station, dir, p.pipeline.weights_label)
}

fn ticks(servo: &mut Servo, t: &mut Loopback, n: usize) {
    for _ in 0..n {
        assert!(servo.tick().is_none());
        t.pump();
    }
}

/// Tick until the late answer `ticket` is in (a removal is done on the saver thread), at most
/// a minute.
fn until_done(servo: &mut Servo, t: &mut Loopback, ticket: u64) -> Result<Reply, OpError> {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    loop {
        if let Some(i) = t.done.iter().position(|(k, _)| *k == ticket) {
            return t.done.remove(i).1;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no answer to {ticket}"
        );
        ticks(servo, t, 1);
        std::thread::yield_now();
    }
}

/// A writer of the kept weights that says when a save starts, then waits for the gate (a
/// message, or the gate's sender dropped) before writing it as the store does.
fn gated_writer() -> (
    WeightsWriter,
    std::sync::mpsc::Receiver<()>,
    std::sync::mpsc::Sender<()>,
) {
    let (started, entered) = std::sync::mpsc::channel();
    let (gate, opened) = std::sync::mpsc::channel::<()>();
    let writer: WeightsWriter = Box::new(move |path, id, arm, serial| {
        let _ = started.send(());
        let _ = opened.recv();
        crate::identifier::store::save(path, id, arm, serial)
    });
    (writer, entered, gate)
}

/// Tick until the saver has started a save, at most a minute.
fn until_a_save_starts(
    servo: &mut Servo,
    t: &mut Loopback,
    entered: &std::sync::mpsc::Receiver<()>,
) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while entered.try_recv().is_err() {
        assert!(std::time::Instant::now() < deadline, "no save started");
        ticks(servo, t, 1);
        std::thread::yield_now();
    }
}

/// A served arm whose weights are kept in its temporary directory, saved at every pump by
/// a gated writer.
fn kept_by_gated_writer() -> (
    Servo,
    Loopback,
    tempfile::TempDir,
    std::path::PathBuf,
    std::sync::mpsc::Receiver<()>,
    std::sync::mpsc::Sender<()>,
) {
    let (servo, mut setup, dir) = served_sim();
    let path = crate::identifier::store::weights_file(dir.path(), "sim");
    setup.weights_store = Some((path.clone(), "sim".into(), None));
    setup.weights_every_s = 0.0;
    let mut station = Station::new(setup);
    let (writer, entered, gate) = gated_writer();
    station.set_weights_writer(writer);
    (
        servo,
        Loopback::new(station, "keeper"),
        dir,
        path,
        entered,
        gate,
    )
}

#[test]
fn the_host_streams_and_answers_while_a_save_waits_on_the_disk() {
    // docs/DESIGN.md §4.7: the save is the saver thread's; here it is held at its start (a
    // disk that does not answer) while the station serves.
    let (mut servo, mut t, _dir, path, entered, gate) = kept_by_gated_writer();
    assert!(t.call(Op::Stream { rate_hz: 500.0 }).is_ok());
    assert!(t.call(Op::Mode(ModeRequest::Hold)).is_ok());
    until_a_save_starts(&mut servo, &mut t, &entered);
    let before = t.states.len();
    let Ok(Answer::Later(status)) = t.call(Op::Status) else {
        panic!("status not taken")
    };
    ticks(&mut servo, &mut t, 200);
    assert_eq!(
        t.states.len() - before,
        100,
        "states streamed during the save"
    );
    assert!(
        t.done.iter().any(|(k, r)| *k == status && r.is_ok()),
        "status not answered during the save"
    );
    assert!(!path.exists(), "the held save was written");
    drop(gate);
    let _ = t.station.finish();
    assert!(path.exists());
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn the_station_s_end_waits_for_the_save_in_progress() {
    let (mut servo, mut t, _dir, path, entered, gate) = kept_by_gated_writer();
    until_a_save_starts(&mut servo, &mut t, &entered);
    assert!(!path.exists());
    // Opened from another thread while the end waits for the saver.
    let opener = std::thread::spawn(move || drop(gate));
    let _ = t.station.finish();
    assert!(
        path.exists(),
        "the station ended before its save was written"
    );
    opener.join().unwrap();
    let cfg = crate::config::Config::default();
    assert!(matches!(
        crate::identifier::store::load(&path, &cfg.identifier, None),
        crate::identifier::store::Loaded::Weights(..)
    ));
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn weights_reset_removes_the_file_after_a_save_asked_before_it() {
    // A save of what the arm learned is held at its start; the reset asked meanwhile is
    // answered only once that save is written and then removed: the forgotten weights do not
    // come back.
    let (mut servo, mut t, _dir, path, entered, gate) = kept_by_gated_writer();
    assert!(t
        .call(Op::Mode(ModeRequest::Track(
            crate::control::Trajectory::Sine
        )))
        .is_ok());
    ticks(&mut servo, &mut t, 300);
    until_a_save_starts(&mut servo, &mut t, &entered);
    assert!(t.call(Op::Adapt(false)).is_ok());
    let Ok(Answer::Later(ticket)) = t.call(Op::WeightsReset) else {
        panic!("reset not taken")
    };
    ticks(&mut servo, &mut t, 50);
    assert!(
        t.done.iter().all(|(k, _)| *k != ticket),
        "the reset was answered before the save asked before it was written"
    );
    drop(gate);
    match until_done(&mut servo, &mut t, ticket) {
        Ok(Reply::WeightsReset { removed, .. }) => {
            // The held save wrote the file; the removal came after it.
            assert_eq!(removed.as_deref(), Some(path.as_path()));
        }
        other => panic!("{other:?}"),
    }
    // What is kept from here on is the shipped weights (frozen), never the forgotten ones.
    ticks(&mut servo, &mut t, 20);
    let _ = t.station.finish();
    let cfg = crate::config::Config::default();
    let shipped = crate::identifier::store::shipped(&cfg.identifier).unwrap();
    let q = crate::omni::Joint3::new(0.1, 0.6, 0.3);
    let z = crate::omni::Joint3::zeros();
    match crate::identifier::store::load(&path, &cfg.identifier, None) {
        crate::identifier::store::Loaded::Weights(mut id, _) => {
            assert_eq!(id.predict(&q, &z, &z), shipped.clone().predict(&q, &z, &z))
        }
        crate::identifier::store::Loaded::None => {}
        other => panic!("{other:?}"),
    }
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn a_station_serves_a_transport_and_a_recorder_of_a_few_lines_each() {
    let (mut servo, setup, _dir) = served_sim();
    let mut station = Station::new(setup);
    let recorded = Arc::new(Mutex::new(Vec::new()));
    station.add_tap(Box::new(Counting(recorded.clone())));
    let mut t = Loopback::new(station, "loopback");
    assert!(matches!(
        t.call(Op::Stream { rate_hz: 500.0 }),
        Ok(Answer::Now(Reply::Stream { every: 2, .. }))
    ));
    assert!(matches!(
        t.call(Op::Mode(ModeRequest::Hold)),
        Ok(Answer::Now(Reply::Mode { mode: "hold" }))
    ));
    ticks(&mut servo, &mut t, 200);
    // Every other tick streamed, in order; the recorder saw every one.
    assert!(t.states.len() >= 99, "{}", t.states.len());
    assert!(t.states.windows(2).all(|w| w[1].seq == w[0].seq + 2));
    let seen = recorded.lock().unwrap().clone();
    assert_eq!(seen.len(), 200);
    assert!(seen.windows(2).all(|w| w[1].0 == w[0].0 + 1));
    assert!(t
        .events
        .iter()
        .any(|e| e.event == "mode" && e.mode == Some("hold")));
    // An op the servo answers later comes back as Done with its ticket.
    let Ok(Answer::Later(ticket)) = t.call(Op::Status) else {
        panic!("status is answered later")
    };
    ticks(&mut servo, &mut t, 3);
    let (got, result) = t.done.pop().expect("answered");
    assert_eq!(got, ticket);
    let Ok(Reply::Status { status }) = result else {
        panic!("{result:?}")
    };
    assert_eq!((status.arm.as_str(), status.mode), ("sim", Some("hold")));
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn what_an_owner_set_up_that_makes_force_ends_when_it_leaves() {
    let (mut servo, setup, _dir) = served_sim();
    let station = Station::new(setup);
    let mut t = Loopback::new(station, "owner");
    let watcher = t.station.open_session(SessionInfo {
        name: "watcher".into(),
        pid: 0,
        uid: 1000,
        control: false,
        privileged: false,
        read_only_reason: "read-only".into(),
        files: FileRights::Daemon,
    });
    t.call(Op::Stream { rate_hz: 1000.0 }).unwrap();
    let effect = crate::haptics::Effect::Constant {
        force_n: [0.0, 1.0, 0.0],
    };
    t.call(Op::Effect {
        slot: 0,
        effect: Some(effect),
    })
    .unwrap();
    t.call(Op::Mode(ModeRequest::Free)).unwrap();
    ticks(&mut servo, &mut t, 300);
    assert_eq!(t.states.last().unwrap().mode, "free");
    // A read-only session cannot stop it, nor take the arm.
    assert!(matches!(
        t.station.request(watcher, Op::Mode(ModeRequest::Idle)),
        Err(OpError::ReadOnly(_))
    ));
    // The owner leaves: the arm rests, amplifiers off, from the next tick.
    let owner = t.session;
    t.station.close_session(owner);
    t.session = t.station.open_session(commander("next"));
    t.call(Op::Stream { rate_hz: 1000.0 }).unwrap();
    ticks(&mut servo, &mut t, 3);
    let last = t.states.last().unwrap();
    assert_eq!((last.mode.as_str(), last.amps), ("idle", false), "{last:?}");
    // The effect went with its owner: free mode again renders nothing of it.
    t.call(Op::Mode(ModeRequest::Free)).unwrap();
    t.states.clear();
    ticks(&mut servo, &mut t, 600);
    assert!(t.events.iter().any(|e| e.event == "stream-ended"));
    let s = t.states.last().unwrap();
    assert_eq!(s.mode, "free");
    // PD has no model to compensate with: in free mode only effects (and a soft wall the
    // falling arm reaches, on joint 3) make torque; the gone effect's pull on joint 2 is not
    // there.
    assert_eq!(s.tau[..2], [0.0; 2], "{s:?}");
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn an_identifier_that_stops_is_announced_once() {
    let (mut servo, setup, _dir) = served_sim();
    let mut t = Loopback::new(Station::new(setup), "loopback");
    // Holding: the identifier learns (it does not in idle).
    assert!(t.call(Op::Mode(ModeRequest::Hold)).is_ok());
    ticks(&mut servo, &mut t, 20);
    let mut stopped = servo.identifier().unwrap().clone();
    stopped.trip_for_test();
    servo.set_identifier(stopped);
    ticks(&mut servo, &mut t, 50);
    let told: Vec<&Event> = t
        .events
        .iter()
        .filter(|e| e.event == "identifier-fault")
        .collect();
    assert_eq!(told.len(), 1, "{:?}", t.events);
    assert!(told[0].message.as_deref().unwrap().contains("PD fallback"));
}

/// The simulator's hand: any session with control access works the stylus while another
/// holds the lease (the program waiting for the button), the press reaches the state's
/// `buttons` at the next tick and a click lets go by itself; a read-only session is refused,
/// and so is every session on a device that is not the simulator.
#[test]
fn the_simulators_hand_works_the_stylus_beside_the_lease_holder() {
    use crate::device::StylusAction;
    let (mut servo, setup, _dir) = served_sim();
    let mut t = Loopback::new(Station::new(setup), "holder");
    t.call(Op::Stream { rate_hz: 1000.0 }).unwrap();
    t.call(Op::Lease { fallback: None }).unwrap();
    let hand = t.station.open_session(commander("hand"));
    let reply = t.station.request(hand, Op::Stylus(StylusAction::Click(0)));
    assert!(
        matches!(
            reply,
            Ok(Answer::Now(Reply::Stylus {
                stylus: "click",
                button: Some(1)
            }))
        ),
        "{reply:?}"
    );
    assert_eq!(t.station.lease_holder(), Some(t.session), "the lease stays");
    ticks(&mut servo, &mut t, 2);
    assert_eq!(t.states.last().unwrap().buttons, [true, false]);
    // A click lasts CLICK_S (0.1 s): released by 150 ticks later.
    ticks(&mut servo, &mut t, 150);
    assert_eq!(t.states.last().unwrap().buttons, [false, false]);
    let watcher = t.station.open_session(SessionInfo {
        control: false,
        read_only_reason: "read-only".into(),
        ..commander("watcher")
    });
    assert!(matches!(
        t.station.request(watcher, Op::Stylus(StylusAction::Dock)),
        Err(OpError::ReadOnly(_))
    ));
    // The same station on a real device refuses the hand, naming the device.
    let (_other_servo, mut real, _other_dir) = served_sim();
    real.arm.kind = "firewire";
    let mut station = Station::new(real);
    let s = station.open_session(commander("hand"));
    let Err(OpError::Invalid(why)) = station.request(s, Op::Stylus(StylusAction::Press(1))) else {
        panic!("a real stylus is pressed by a real hand")
    };
    assert!(
        why.contains("firewire") && why.contains("simulator"),
        "{why}"
    );
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn the_station_saves_what_the_arm_learned_while_it_runs() {
    // The periodic save (here every pump): the servo hands its weights over in a snapshot,
    // the station writes them whole, and they load again as this arm's.
    let (mut servo, mut setup, dir) = served_sim();
    let path = crate::identifier::store::weights_file(dir.path(), "sim");
    setup.weights_store = Some((path.clone(), "sim".into(), Some("S1".into())));
    setup.weights_every_s = 0.0;
    let cfg = setup.identifier_cfg.clone();
    let station = Station::new(setup);
    let mut t = Loopback::new(station, "saver");
    assert!(matches!(
        t.call(Op::Mode(ModeRequest::Track(
            crate::control::Trajectory::Sine
        ))),
        Ok(Answer::Now(_))
    ));
    ticks(&mut servo, &mut t, 500);
    // The saver thread writes them: its end waits for every save asked.
    let _ = t.station.finish();
    assert!(path.exists(), "no weights kept at {}", path.display());
    let crate::identifier::store::Loaded::Weights(mut kept, _) =
        crate::identifier::store::load(&path, &cfg, Some("S1"))
    else {
        panic!("the kept weights do not load")
    };
    // They are the servo's as they were at a recent pump: within a few ticks' learning.
    let q = crate::omni::Joint3::new(0.1, 0.6, 0.3);
    let z = crate::omni::Joint3::zeros();
    let now = servo.identifier().unwrap().clone().predict(&q, &z, &z);
    let fresh = crate::identifier::Identifier::new(&cfg)
        .unwrap()
        .predict(&q, &z, &z);
    let got = kept.predict(&q, &z, &z);
    assert!((got - now).norm() < (fresh - now).norm(), "{got} vs {now}");
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
fn weights_reset_puts_the_shipped_weights_back_and_removes_what_the_arm_learned() {
    // The arm learns (from fresh weights, under pd) and the station keeps it every pump.
    let (mut servo, mut setup, dir) = served_sim();
    let path = crate::identifier::store::weights_file(dir.path(), "sim");
    setup.weights_store = Some((path.clone(), "sim".into(), None));
    setup.weights_every_s = 0.0;
    let cfg = setup.identifier_cfg.clone();
    let mut t = Loopback::new(Station::new(setup), "resetter");
    assert!(t
        .call(Op::Mode(ModeRequest::Track(
            crate::control::Trajectory::Sine
        )))
        .is_ok());
    ticks(&mut servo, &mut t, 300);
    let q = crate::omni::Joint3::new(0.1, 0.6, 0.3);
    let qd = crate::omni::Joint3::new(0.2, -0.3, 0.1);
    let z = crate::omni::Joint3::zeros();
    let shipped = crate::identifier::store::shipped(&cfg)
        .unwrap()
        .predict(&q, &qd, &z);
    let load = |path: &std::path::Path| match crate::identifier::store::load(path, &cfg, None) {
        crate::identifier::store::Loaded::Weights(mut id, _) => id.predict(&q, &qd, &z),
        other => panic!("{other:?}"),
    };
    assert_ne!(
        load(&path),
        shipped,
        "the arm has learned nothing to forget"
    );
    // Frozen, so that what the servo holds after the reset is exactly the shipped weights.
    assert!(t.call(Op::Adapt(false)).is_ok());
    let Ok(Answer::Later(ticket)) = t.call(Op::WeightsReset) else {
        panic!("reset not taken")
    };
    let reply = until_done(&mut servo, &mut t, ticket);
    match reply {
        Ok(Reply::WeightsReset { weights, removed }) => {
            assert_eq!(weights, "mock/nnidc-pretuned.json");
            assert_eq!(removed.as_deref(), Some(path.as_path()));
        }
        other => panic!("{other:?}"),
    }
    assert!(t
        .events
        .iter()
        .any(|e| e.message.as_deref().is_some_and(|m| m.contains("reset"))));
    assert_eq!(
        servo.identifier().unwrap().clone().predict(&q, &qd, &z),
        shipped
    );
    // The saves after the reset keep the shipped weights, not the forgotten ones.
    ticks(&mut servo, &mut t, 20);
    let _ = t.station.finish();
    assert_eq!(load(&path), shipped);
    let report = servo.finish(EndReason::OperatorStop);
    assert!(report.last_command.is_safe());
}

#[test]
#[ignore = "paced"] // a minute of debug-build ticks: the long-run tier, not the fast one
fn an_arm_restarted_after_a_minute_of_tracking_starts_from_what_it_learned_and_tracks_better() {
    // docs/IDENTIFIER.md "Kept per arm": a minute of the sine under nnidc, kept at the end as
    // the daemon keeps it; the next start on the arm loads it, and its first second tracks
    // better than a start from the shipped weights. The arm is not the simulator's nominal
    // one (a 20 g tool at its tip), as no real arm is: what it learned is its own dynamics,
    // which the shipped weights (pre-tuned on the nominal plant) do not know.
    use crate::control::{ControllerKind, Trajectory};
    let state = tempfile::tempdir().unwrap();
    let path = crate::identifier::store::weights_file(state.path(), "sim");
    let mut arm = crate::config::Config::default();
    arm.sim.payload_kg = 0.02;
    let first_second = |kept: Option<&std::path::Path>, seconds: usize| {
        let (mut servo, mut setup, _dir, label) =
            served_arm(ControllerKind::Nnidc, kept, arm.clone());
        assert_eq!(label, "shipped");
        setup.weights_store = Some((path.clone(), "sim".into(), None));
        setup.weights_every_s = 1e9;
        let mut t = Loopback::new(Station::new(setup), "tracker");
        assert!(t
            .call(Op::Mode(ModeRequest::Track(Trajectory::Sine)))
            .is_ok());
        ticks(&mut servo, &mut t, 1000 * seconds);
        let report = servo.finish(EndReason::OperatorStop);
        (report.stats.tracking_rms().unwrap(), report)
    };
    let (_, report) = first_second(None, 60);
    let id = report.identifier.as_ref().unwrap();
    crate::identifier::store::save(&path, id, "sim", None).unwrap();
    // The summary's tracking leaves out the blend and settling (2 s): its first second is the
    // third.
    let (fresh, _) = first_second(None, 3);
    let (learned, _) = first_second(Some(&path), 3);
    assert!(
        (0..3).all(|j| learned[j] < fresh[j]),
        "first second from the kept weights {learned:?} rad vs from the shipped {fresh:?}"
    );
    eprintln!("first tracked second: kept weights {learned:?} rad, shipped {fresh:?} rad");
}

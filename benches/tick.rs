//! Per-tick cost of each stage of the servo loop and of the whole tick, plus `--fast`
//! throughput on the simulated Omni. `cargo bench --bench tick`.

use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use omnid::cmd::run::{make_controller, make_identifier};
use omnid::config::Config;
use omnid::control::{ControlInput, Controller, Pd, Reference, Trajectory};
use omnid::control::{ControllerKind, ControllerSet};
use omnid::device::codec::encode_state;
use omnid::device::sim::SimOmni;
use omnid::device::{
    decode_state, encode_command, DacScale, Device, DeviceError, EncoderUnwrap, MotorCommand,
    RawSample, StatePacket, COMMAND_LEN,
};
use omnid::estimate::KalmanBank;
use omnid::omni::Joint3;
use omnid::servo::Servo;
use omnid::telemetry::writer;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// A device that answers instantly from a precomputed ring of packets: the whole tick's host
/// cost without the plant simulation.
struct Canned {
    packets: Vec<[u8; 44]>,
    i: usize,
}

impl Device for Canned {
    fn kind(&self) -> &'static str {
        "canned"
    }
    fn exchange(&mut self, _c: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        let k = self.i;
        self.i += 1;
        Ok(RawSample::new(
            self.packets[k % self.packets.len()],
            k as f64 * 1e-3,
        ))
    }
}

fn canned(cfg: &Config) -> Canned {
    let step = cfg.device.rad_per_count();
    let packets = (0..4000)
        .map(|k| {
            let t = k as f64 * 1e-3;
            let mut s = StatePacket::default();
            for j in 0..3 {
                let q = cfg.reference.center[j] + 0.3 * (std::f64::consts::PI * t).sin();
                s.encoder[j] = ((q / step).round() as i64) as u16;
            }
            s.counter = k;
            encode_state(&s)
        })
        .collect();
    Canned { packets, i: 0 }
}

fn stages(c: &mut Criterion) {
    let cfg = Config::default();
    let packet = canned(&cfg).packets[100];
    let mut g = c.benchmark_group("stage");
    g.bench_function("decode+unwrap", |b| {
        let mut u = EncoderUnwrap::new();
        b.iter(|| u.update(decode_state(black_box(&packet)).unwrap().encoder))
    });
    g.bench_function("kalman(3 joints)", |b| {
        let mut k = KalmanBank::new(&cfg.kalman);
        let mut t = 0.0;
        b.iter(|| {
            t += 1e-3;
            k.update(t, black_box(&Joint3::new(0.1, 0.5, 0.2)))
        })
    });
    g.bench_function("reference(sine)+pd", |b| {
        let mut pd = Pd::from_config(&cfg);
        let mut r = Reference::new(Trajectory::Sine, &cfg.reference, 1);
        let est = KalmanBank::new(&cfg.kalman).update(0.0, &Joint3::new(0.0, 0.6, 0.3));
        let mut t = 0.0;
        b.iter(|| {
            t += 1e-3;
            let reference = r.at(t, &est.q);
            pd.torque(
                &ControlInput {
                    t,
                    estimate: black_box(&est),
                    reference: &reference,
                },
                None,
            )
        })
    });
    g.bench_function("encode", |b| {
        let dac = DacScale {
            nm_per_count: cfg.device.nm_per_count,
        };
        b.iter(|| {
            let words = dac.to_words(black_box(&[0.01, -0.2, 0.3]));
            encode_command(&MotorCommand {
                dac: words,
                amps_on: true,
                lamp: 0,
                watchdog: 3,
            })
        })
    });
    g.finish();
}

fn identifier(c: &mut Criterion) {
    let cfg = Config::default();
    let mut g = c.benchmark_group("identifier");
    let (mut id, _) = make_identifier(&cfg, ControllerKind::Nnidc, None, false, None).unwrap();
    let q = Joint3::new(0.1, 0.6, 0.3);
    let qd = Joint3::new(0.4, -0.3, 0.2);
    let qdd = Joint3::new(1.0, 0.5, -2.0);
    let tau = Joint3::new(0.01, -0.02, 0.03);
    // Two points in turn: the identifier reuses a pass at an unchanged point and weights.
    let q2 = q + Joint3::repeat(1e-3);
    let mut flip = false;
    g.bench_function("forward (predict)", |b| {
        b.iter(|| {
            flip = !flip;
            id.predict(black_box(if flip { &q } else { &q2 }), &qd, &qdd)
        })
    });
    g.bench_function("update (forward + gradients + step)", |b| {
        b.iter(|| id.update(black_box(&q), &qd, &qdd, &tau, 1e-3))
    });
    g.finish();

    let mut g = c.benchmark_group("controller");
    let est = KalmanBank::new(&cfg.kalman).update(0.0, &q);
    let r = Reference::new(Trajectory::Sine, &cfg.reference, 1).target(0.3);
    let input = ControlInput {
        t: 0.3,
        estimate: &est,
        reference: &r,
    };
    for kind in [
        ControllerKind::Pd,
        ControllerKind::Ct,
        ControllerKind::Nnidc,
    ] {
        let mut ctl = make_controller(kind, &cfg);
        g.bench_function(kind.as_str(), |b| {
            b.iter(|| ctl.torque(black_box(&input), Some(&mut id)))
        });
    }
    g.finish();
}

fn whole_tick(c: &mut Criterion) {
    let cfg = Config::default();
    let mut g = c.benchmark_group("tick");
    for kind in [
        ControllerKind::Pd,
        ControllerKind::Ct,
        ControllerKind::Nnidc,
    ] {
        let name = format!("servo tick, {}, adapting, canned device", kind.as_str());
        g.bench_function(name, |b| {
            let (tx, rx) = crossbeam_channel::bounded(1 << 16);
            let mut servo = Servo::new(
                &cfg,
                Box::new(canned(&cfg)),
                ControllerSet::new(&cfg, kind, 0.0),
                Reference::new(Trajectory::Sine, &cfg.reference, 1),
                tx,
                Arc::new(AtomicBool::new(false)),
                None,
                true,
            );
            let (id, _) = make_identifier(&cfg, kind, None, false, None).unwrap();
            servo.set_identifier(id);
            b.iter(|| {
                servo.tick();
                // Keep the channel from filling, as the writer thread would.
                while rx.try_recv().is_ok() {}
            })
        });
    }
    // NNIDC with the lag-matched e1 and the preset's rates (mock/nnidc-lagmatch.toml): the
    // lag filter's 3×3 products against the default tick above (docs/IDENTIFIER.md).
    let preset: Config = toml::from_str(include_str!("../mock/nnidc-lagmatch.toml"))
        .expect("mock/nnidc-lagmatch.toml parses");
    g.bench_function(
        "servo tick, nnidc, adapting, lag-matched preset, canned device",
        |b| {
            let (tx, rx) = crossbeam_channel::bounded(1 << 16);
            let kind = ControllerKind::Nnidc;
            let mut servo = Servo::new(
                &preset,
                Box::new(canned(&preset)),
                ControllerSet::new(&preset, kind, 0.0),
                Reference::new(Trajectory::Sine, &preset.reference, 1),
                tx,
                Arc::new(AtomicBool::new(false)),
                None,
                true,
            );
            let (id, _) = make_identifier(&preset, kind, None, false, None).unwrap();
            servo.set_identifier(id);
            b.iter(|| {
                servo.tick();
                while rx.try_recv().is_ok() {}
            })
        },
    );
    g.bench_function("sim plant step (default RK4 substeps)", |b| {
        let mut sim = SimOmni::new(&cfg, false);
        let cmd = encode_command(&MotorCommand::safe(0));
        b.iter(|| sim.exchange(black_box(&cmd)).unwrap())
    });
    g.finish();
}

fn fast_throughput(c: &mut Criterion) {
    let cfg = Config::default();
    let ticks = 10_000u64;
    let mut g = c.benchmark_group("fast");
    g.throughput(Throughput::Elements(ticks));
    g.sample_size(20);
    for kind in [
        ControllerKind::Pd,
        ControllerKind::Ct,
        ControllerKind::Nnidc,
        ControllerKind::Off,
    ] {
        g.bench_function(format!("sim+{} 10 s run", kind.as_str()), |b| {
            b.iter(|| {
                let (tx, rx) = crossbeam_channel::bounded(1 << 14);
                // Polls like the log writer, so the servo never has to wake it.
                let drain = std::thread::spawn(move || {
                    let mut n = 0u64;
                    writer::for_each_polled(&rx, |_| n += 1);
                    n
                });
                let mut servo = Servo::new(
                    &cfg,
                    Box::new(SimOmni::new(&cfg, false)),
                    ControllerSet::new(&cfg, kind, 0.0),
                    Reference::new(Trajectory::Sine, &cfg.reference, 1),
                    tx,
                    Arc::new(AtomicBool::new(false)),
                    Some(ticks),
                    false,
                );
                let (id, _) = make_identifier(&cfg, kind, None, false, None).unwrap();
                servo.set_identifier(id);
                let report = servo.run();
                drain.join().unwrap();
                report.stats.ticks
            })
        });
    }
    g.finish();
}

criterion_group!(benches, stages, identifier, whole_tick, fast_throughput);
criterion_main!(benches);

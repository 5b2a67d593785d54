//! The simulated Omni: integrates the rigid-body model of `omni` under the torque its DAC words
//! command, quantises the joint angles into 16-bit encoder counts, and speaks the packet codec.
//! Paced by absolute deadlines (one packet per period), or not at all under `--fast`.

use super::codec::{decode_command, encode_state, DacScale, StatePacket};
use super::DeviceConfig;
use super::{Device, DeviceError, RawSample, StylusAction, COMMAND_LEN};
use crate::clock;
use crate::config_check::{self as check, ConfigError};
use crate::control::reference::quintic;
use crate::haptics::{tip_force_torque, Force3, Hand, HandConfig, HandPattern};
use crate::omni::{jacobian, tip_position_mm, Dynamics, Geometry, Joint3, ModelParams};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;
use serde::{Deserialize, Serialize};

/// The simulated Omni.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    /// Seeds all randomness of a run (noise, multisine phases).
    pub seed: u64,
    /// Viscous and Coulomb friction in the plant.
    pub friction: bool,
    /// Extra point mass at the tip, kg ...
    pub payload_kg: f64,
    /// ... added at this time, s.
    pub payload_at_s: f64,
    /// RK4 substeps per servo tick.
    pub substeps: u32,
    /// Standard deviation of a random torque disturbance (motor ripple), N·m.
    pub torque_noise_nm: f64,
    /// Joint angles at power-on, rad (default: stylus in the inkwell).
    #[serde(deserialize_with = "crate::config_check::exact")]
    pub start_pose: [f64; 3],
    /// The stylus starts docked in the inkwell (when `start_pose` is the inkwell's pose, the
    /// default), which holds it there as a real Omni's does until the motors or a hand lift it
    /// out.
    pub docked: bool,
    /// What the simulator's hand does with the stylus, and when: a list of
    /// `{ at_s = 2.0, action = "click", button = 1 }` (press, release, click: button 1 or 2)
    /// and `{ at_s = 5.0, action = "undock" }` (dock, undock), at seconds of device time.
    pub stylus: Vec<StylusEvent>,
    /// A physical wall in the simulated world (`[sim.wall]`): the plant meets it, whatever
    /// the servo renders (a teleoperation follower's environment).
    pub wall: SimWall,
}

/// `[sim.wall]`: a flat, stiff surface the simulated tip presses into (a spring-damper that
/// only pushes), inside the plant's integration like the hand: the servo can only feel it
/// through the encoders and its own torques, as with a real object (docs/TELEOP.md §4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SimWall {
    /// Whether the wall is there.
    pub enabled: bool,
    /// Which side of the workspace centre it stands on, and so the way the tip presses into
    /// it: +x, -x, +y, -y, +z or -z (OpenHaptics frame).
    pub side: String,
    /// How far from the workspace centre its surface is, mm.
    pub distance_mm: f64,
    /// Its stiffness, N/mm.
    pub stiffness_n_per_mm: f64,
    /// Its damping while pressed, N·s/m.
    pub damping_n_s_per_m: f64,
}

impl Default for SimWall {
    fn default() -> Self {
        SimWall {
            enabled: false,
            side: "-z".into(),
            distance_mm: 10.0,
            stiffness_n_per_mm: 1.0,
            damping_n_s_per_m: 1.0,
        }
    }
}

impl SimWall {
    /// The sides `side` may name.
    const SIDES: &'static str = "+x, -x, +y, -y, +z or -z";

    /// (axis, sign) of `side`.
    fn parse_side(side: &str) -> Option<(usize, f64)> {
        let sign = match side.as_bytes().first()? {
            b'+' => 1.0,
            b'-' => -1.0,
            _ => return None,
        };
        let axis = ["x", "y", "z"].iter().position(|a| *a == &side[1..])?;
        Some((axis, sign))
    }

    fn validate(&self) -> Result<(), ConfigError> {
        if Self::parse_side(&self.side).is_none() {
            return Err(check::invalid(
                "sim.wall.side",
                format!("{:?}", crate::text::cut(&self.side)),
                Self::SIDES,
            ));
        }
        check::in_range(
            "sim.wall.distance_mm",
            self.distance_mm,
            -200.0,
            200.0,
            "-200 ..= 200 mm",
        )?;
        check::in_range(
            "sim.wall.stiffness_n_per_mm",
            self.stiffness_n_per_mm,
            0.0,
            10.0,
            "0 ..= 10 N/mm",
        )?;
        check::in_range(
            "sim.wall.damping_n_s_per_m",
            self.damping_n_s_per_m,
            0.0,
            50.0,
            "0 ..= 50 N·s/m",
        )
    }
}

/// A [`SimWall`] placed in the world: the plane and its law, in SI units.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Wall {
    axis: usize,
    sign: f64,
    /// The surface's coordinate along `axis`, m.
    at_m: f64,
    k_n_per_m: f64,
    b_n_s_per_m: f64,
}

impl Wall {
    /// `cfg` placed `distance_mm` from `centre_mm` (the workspace centre's tip); `None` when
    /// the wall is off.
    pub(crate) fn place(cfg: &SimWall, centre_mm: &Joint3) -> Option<Wall> {
        let (axis, sign) = SimWall::parse_side(&cfg.side).filter(|_| cfg.enabled)?;
        Some(Wall {
            axis,
            sign,
            at_m: (centre_mm[axis] + sign * cfg.distance_mm) * 1e-3,
            k_n_per_m: cfg.stiffness_n_per_mm * 1e3,
            b_n_s_per_m: cfg.damping_n_s_per_m,
        })
    }

    /// The wall's force on a tip at `tip` (m) moving at `v` (m/s): zero outside it, a push
    /// back out of it inside (never a pull: the damping only brakes what the spring pushes).
    pub(crate) fn force(&self, tip: &Joint3, v: &Joint3) -> Force3 {
        let depth = self.sign * (tip[self.axis] - self.at_m);
        let mut f = Force3::zeros();
        if depth > 0.0 {
            let push =
                (self.k_n_per_m * depth + self.b_n_s_per_m * self.sign * v[self.axis]).max(0.0);
            f[self.axis] = -self.sign * push;
        }
        f
    }
}

/// One entry of `[sim] stylus`: at `at_s` s of device time the hand does `action` (with
/// `button` for press, release and click).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct StylusEvent {
    /// When, s of device time since the simulator started.
    pub at_s: f64,
    /// press, release, click, dock or undock.
    pub action: String,
    /// The button, 1 or 2 (press, release and click only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub button: Option<u64>,
}

/// Most entries `[sim] stylus` may list.
pub const MAX_STYLUS_EVENTS: usize = 1024;

/// How long a click keeps its button pressed, s (a quick press: about 8 frames of a 60 Hz
/// graphics loop, 100 ticks of a 1 kHz servo loop, so every kind of program sees it).
pub const CLICK_S: f64 = 0.1;

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            seed: 1,
            friction: true,
            payload_kg: 0.0,
            payload_at_s: 0.0,
            substeps: 2,
            torque_noise_nm: 2e-4,
            start_pose: INKWELL_POSE,
            docked: true,
            stylus: Vec::new(),
            wall: SimWall::default(),
        }
    }
}

impl SimConfig {
    /// Check every value; the first problem names its field (`sim.…`).
    pub fn validate(&self) -> Result<(), ConfigError> {
        check::in_range("sim.payload_kg", self.payload_kg, 0.0, 1.0, "0 ..= 1 kg")?;
        check::in_range(
            "sim.payload_at_s",
            self.payload_at_s,
            0.0,
            1e6,
            "0 ..= 1e6 s",
        )?;
        check::int_in("sim.substeps", self.substeps, 1, 100, "1 ..= 100")?;
        check::in_range(
            "sim.torque_noise_nm",
            self.torque_noise_nm,
            0.0,
            0.1,
            "0 ..= 0.1 N·m",
        )?;
        check::each("sim.start_pose", &self.start_pose, |f, v| {
            check::in_range(f, v, -3.2, 3.2, "-3.2 ..= 3.2 rad")
        })?;
        self.wall.validate()?;
        if self.stylus.len() > MAX_STYLUS_EVENTS {
            return Err(check::invalid(
                "sim.stylus",
                format!("{} entries", self.stylus.len()),
                format!("at most {MAX_STYLUS_EVENTS}"),
            ));
        }
        for (i, e) in self.stylus.iter().enumerate() {
            check::in_range(
                &format!("sim.stylus[{i}].at_s"),
                e.at_s,
                0.0,
                1e6,
                "0 ..= 1e6 s",
            )?;
            e.parsed().map_err(|(field, allowed)| {
                let value = match field {
                    "button" => e.button.map_or("none".into(), |b| b.to_string()),
                    _ => format!("{:?}", crate::text::cut(&e.action)),
                };
                check::invalid(format!("sim.stylus[{i}].{field}"), value, allowed)
            })?;
        }
        Ok(())
    }

    /// The schedule as (time, action), in time order (entries at the same time in the order
    /// written).
    fn stylus_schedule(&self) -> Vec<(f64, StylusAction)> {
        let mut list: Vec<(f64, StylusAction)> = self
            .stylus
            .iter()
            .filter_map(|e| Some((e.at_s, e.parsed().ok()?)))
            .collect();
        list.sort_by(|a, b| a.0.total_cmp(&b.0));
        list
    }
}

impl StylusEvent {
    /// The action, or the field at fault and why.
    pub fn parsed(&self) -> Result<StylusAction, (&'static str, &'static str)> {
        StylusAction::parse(&self.action, self.button)
    }
}

impl SimConfig {
    /// What the simulated plant needs beyond `validate` (checked when the simulator is the
    /// device, so a hardware configuration at another servo rate is not refused for it).
    /// An ordered list of checks, each naming its field: the substeps for the plant's own
    /// fastest mode, then each spring at the tip.
    pub(crate) fn check_plant(
        &self,
        d: &DeviceConfig,
        m: &ModelParams,
        geometry: Geometry,
        hand: Option<&HandConfig>,
    ) -> Result<(), ConfigError> {
        self.check_substeps(d, m, geometry)?;
        self.check_tip_springs(d, m, geometry, hand)
    }

    /// The RK4 substep against the plant's fastest mode; a refusal blames the servo rate, the
    /// substeps or the model's stiffest term, whichever a default would fix.
    fn check_substeps(
        &self,
        d: &DeviceConfig,
        m: &ModelParams,
        geometry: Geometry,
    ) -> Result<(), ConfigError> {
        let s = self;
        let least_inertia = m
            .mass_over_joint_range(geometry)
            .map(|(_, mass)| mass.symmetric_eigenvalues().min())
            .fold(f64::INFINITY, f64::min);
        // The RK4 substep must resolve the plant's fastest mode: near zero velocity
        // the smoothed Coulomb curve is a damper of slope coulomb/coulomb_velocity, on as little
        // as the smallest inertia. Past h·rate ≈ 2.8 RK4 blows up; we ask for h·rate ≤ 1.
        let coulomb = (0..3)
            .map(|i| m.coulomb[i] / m.coulomb_velocity)
            .fold(0.0, f64::max);
        let viscous = m.viscous.iter().copied().fold(0.0, f64::max);
        let terms = [
            (
                "model.coulomb_velocity",
                m.coulomb_velocity,
                coulomb / least_inertia,
            ),
            ("model.viscous", viscous, viscous / least_inertia),
            (
                "model.limit_damping",
                m.limit_damping,
                m.limit_damping / least_inertia,
            ),
            (
                "model.limit_stiffness",
                m.limit_stiffness,
                (m.limit_stiffness / least_inertia).sqrt(),
            ),
        ];
        let rate: f64 = terms.iter().map(|t| t.2).sum();
        let needed = (rate / d.rate_hz).ceil().max(1.0);
        if (s.substeps as f64) < needed {
            let why = format!(
                "its fastest mode, damping and limit spring on the smallest inertia \
                 {least_inertia:.2e} kg·m², runs at {rate:.0}/s"
            );
            // Blame the servo rate if the default rate would do, the substeps if the default
            // substeps would, else the model's stiffest term.
            let at_default_rate = (rate / DeviceConfig::default().rate_hz).ceil();
            return Err(if at_default_rate <= s.substeps as f64 {
                check::invalid(
                    "device.rate_hz",
                    d.rate_hz,
                    format!(
                        "≥ {:.0} Hz with sim.substeps = {}, or sim.substeps ≥ {needed} at \
                         {} Hz ({why})",
                        rate / s.substeps as f64,
                        s.substeps,
                        d.rate_hz
                    ),
                )
            } else if needed <= SimConfig::default().substeps as f64 {
                check::invalid(
                    "sim.substeps",
                    s.substeps,
                    format!("sim.substeps ≥ {needed} for this model ({why})"),
                )
            } else {
                let (field, value, _) = terms
                    .iter()
                    .fold(terms[0], |a, &b| if b.2 > a.2 { b } else { a });
                check::invalid(
                    field,
                    value,
                    format!(
                        "a plant that sim.substeps = {} resolves; this one needs \
                         sim.substeps ≥ {needed} ({why})",
                        s.substeps
                    ),
                )
            });
        }
        Ok(())
    }

    /// The hand on the stylus and the simulated wall, each a spring and a damper at the tip.
    fn check_tip_springs(
        &self,
        d: &DeviceConfig,
        m: &ModelParams,
        geometry: Geometry,
        hand: Option<&HandConfig>,
    ) -> Result<(), ConfigError> {
        let s = self;
        let mut springs = Vec::new();
        if let Some(h) = hand {
            springs.push((
                "haptics.hand.stiffness_n_per_m",
                h.stiffness_n_per_m,
                "haptics.hand.damping_n_s_per_m",
                h.damping_n_s_per_m,
            ));
        }
        if s.wall.enabled {
            springs.push((
                "sim.wall.stiffness_n_per_mm",
                s.wall.stiffness_n_per_mm * 1e3,
                "sim.wall.damping_n_s_per_m",
                s.wall.damping_n_s_per_m,
            ));
        }
        for (k_field, k, b_field, b) in springs {
            check_tip_spring((k_field, k), (b_field, b), d, s.substeps, m, geometry)?;
        }
        Ok(())
    }
}

/// A hand on the stylus (or a wall the tip presses) is a spring and a damper at the tip:
/// through the Jacobian it adds the joint-space rates b·λ and √(k·λ), λ the largest eigenvalue
/// of M⁻¹JᵀJ over the joint range. RK4 on a damping mode is stable while h·rate stays under
/// 2.78; we ask for ≤ 2. `k` in N/m, `b` in N·s/m, each with the field that sets it.
fn check_tip_spring(
    (k_field, k): (&'static str, f64),
    (b_field, b): (&'static str, f64),
    d: &DeviceConfig,
    substeps: u32,
    m: &ModelParams,
    geometry: Geometry,
) -> Result<(), ConfigError> {
    let gain = m
        .mass_over_joint_range(geometry)
        .filter_map(|((q2, q3), mass)| {
            let j = jacobian(&geometry, &Joint3::new(0.0, q2, q3));
            let l_inv = mass.cholesky()?.l().try_inverse()?;
            let a = l_inv * (j.transpose() * j) * l_inv.transpose();
            Some(a.symmetric_eigenvalues().max())
        })
        .fold(0.0, f64::max);
    let step = 1.0 / (d.rate_hz * f64::from(substeps));
    // The largest values the step resolves: b·λ·h ≤ 2 and √(k·λ)·h ≤ 2.
    let (max_b, max_k) = (2.0 / (step * gain), (2.0 / step).powi(2) / gain);
    for (field, value, most) in [(b_field, b, max_b), (k_field, k, max_k)] {
        if value > most {
            // Substeps scale the step: the damping bound with them, the stiffness bound with
            // their square.
            let over = if field == b_field {
                value / most
            } else {
                (value / most).sqrt()
            };
            let needed = (f64::from(substeps) * over).ceil();
            // A field in N/mm is told in its own unit.
            let unit = if field.ends_with("_per_mm") {
                1e-3
            } else {
                1.0
            };
            return Err(check::invalid(
                field,
                value * unit,
                format!(
                    "at most {:.3} with sim.substeps = {substeps} at {} Hz, or sim.substeps \
                     ≥ {needed} (faster than that the simulator diverges)",
                    most * unit,
                    d.rate_hz
                ),
            ));
        }
    }
    Ok(())
}

/// The sections of the configuration the simulator is built from.
#[derive(Debug, Clone, Copy)]
pub struct SimSetup<'a> {
    /// Encoder resolution, DAC scale, servo rate.
    pub device: &'a DeviceConfig,
    /// Noise, payload and seed of the simulation.
    pub sim: &'a SimConfig,
    /// The plant's rigid-body model.
    pub model: &'a ModelParams,
    /// Link lengths, for the tip position.
    pub geometry: &'a Geometry,
    /// The simulated hand on the stylus (none by default).
    pub hand: &'a HandConfig,
    /// Where the hand's paths are centred: the tip at this pose (the reference's centre), rad.
    pub center: [f64; 3],
}

/// Joint angles with the stylus in the inkwell, rad (the default power-on pose).
const INKWELL_POSE: [f64; 3] = [0.0, 0.27, -0.37];

/// How close to the inkwell's pose (rad) counts as "stylus in the inkwell".
const INKWELL_TOLERANCE: f64 = 0.02;

/// The inkwell's grip on a docked stylus, per joint: stiffness N·m/rad and damping
/// N·m·s/rad, and the torque beyond gravity's at the docked pose it holds against before the
/// stylus comes out, N·m.
const INKWELL_STIFFNESS: f64 = 20.0;
const INKWELL_DAMPING: f64 = 0.3;
const INKWELL_MARGIN_NM: f64 = 0.03;

/// The inkwell: while the stylus is docked it holds the arm at the docked pose with a
/// spring-damper whose torque saturates at a little more than gravity's there, so the
/// unpowered arm stays put (a real Omni's stylus rests in its inkwell) and anything that
/// pushes harder — the motors, a hand — lifts it out. It docks again when the arm comes back
/// to the pose slowly.
#[derive(Debug, Clone, Copy)]
struct Inkwell {
    pose: Joint3,
    hold: Joint3,
    docked: bool,
    /// Undocked, the stylus has been taken away from the pose (it can come back).
    away: bool,
}

impl Inkwell {
    /// The inkwell's torque on the arm at (q, q̇).
    fn torque(&self, q: &Joint3, qd: &Joint3) -> Joint3 {
        if !self.docked {
            return Joint3::zeros();
        }
        Joint3::from_fn(|j, _| {
            let t = -INKWELL_STIFFNESS * (q[j] - self.pose[j]) - INKWELL_DAMPING * qd[j];
            t.clamp(-self.hold[j], self.hold[j])
        })
    }

    /// After a step: out once pulled past the grip's reach, back in when at rest at the pose.
    fn update(&mut self, q: &Joint3, qd: &Joint3) {
        let off = q - self.pose;
        if self.docked {
            self.docked = (0..3).all(|j| off[j].abs() <= self.hold[j] / INKWELL_STIFFNESS + 0.01);
            self.away = false;
        } else if off.amax() > 2.0 * INKWELL_TOLERANCE {
            self.away = true;
        } else if self.away {
            self.docked = off.amax() < INKWELL_TOLERANCE && qd.amax() < 0.05;
        }
    }
}

/// The hand's grip when it carries the stylus (into the inkwell, out of it) or holds it: a
/// joint-space spring-damper around a smooth path, with the arm's weight carried, N·m/rad and
/// N·m·s/rad. Light: a motor's push moves the held stylus (3.3 N at the tip is about 0.05 rad).
const GRIP_STIFFNESS: f64 = 8.0;
const GRIP_DAMPING: f64 = 0.15;
/// The hand moves the stylus at most this fast along its path, rad/s, and takes at least
/// `CARRY_MIN_S`.
const CARRY_SPEED: f64 = 1.0;
const CARRY_MIN_S: f64 = 0.3;
/// A hand that cannot bring the stylus to its inkwell (the motors push it away) gives up this
/// long after its path ended, s.
const CARRY_GIVE_UP_S: f64 = 1.0;

/// The hand carrying the stylus from `from` to `to` (joint angles), starting at `t0` over
/// `dur` s, then holding it at `to`: into the inkwell (`dock`: it lets go once the stylus
/// rests there), or out of it (it keeps holding the stylus lightly, as a user does).
#[derive(Debug, Clone, Copy)]
struct Carry {
    from: Joint3,
    to: Joint3,
    t0: f64,
    dur: f64,
    dock: bool,
}

impl Carry {
    fn new(from: Joint3, to: Joint3, t0: f64, dock: bool) -> Carry {
        let dur = ((to - from).amax() / CARRY_SPEED).max(CARRY_MIN_S);
        Carry {
            from,
            to,
            t0,
            dur,
            dock,
        }
    }

    /// The hand's torque on the arm at time `t` and (q, q̇): gravity's, carried, and the grip
    /// towards the path.
    fn torque(&self, plant: &Dynamics, t: f64, q: &Joint3, qd: &Joint3) -> Joint3 {
        let (s, ds, _) = quintic((t - self.t0) / self.dur);
        let span = self.to - self.from;
        let (at, vel) = (self.from + span * s, span * (ds / self.dur));
        plant.gravity(q) + (at - q) * GRIP_STIFFNESS + (vel - qd) * GRIP_DAMPING
    }
}

/// The simulated Omni: the rigid-body model integrated at the servo rate, with encoder
/// quantisation, sensor and torque noise, an optional payload and a simulated hand, behind
/// the [`Device`] trait.
pub struct SimOmni {
    plant: Dynamics,
    payload_kg: f64,
    payload_at_s: f64,
    dac: DacScale,
    rad_per_count: f64,
    period_s: f64,
    substeps: u32,
    noise_nm: f64,
    rng: ChaCha8Rng,
    q: Joint3,
    qd: Joint3,
    tick: u64,
    last_watchdog: Option<u8>,
    paced: bool,
    start_ns: u64,
    /// The simulated hand on the stylus (docs/HAPTICS.md §7), and the force it put on the tip
    /// at the last sample, N.
    hand: Option<Hand>,
    hand_force: Force3,
    /// The world's wall (`[sim.wall]`), and the force it put on the tip at the last sample, N.
    wall: Option<Wall>,
    wall_force: Force3,
    inkwell: Inkwell,
    /// The stylus buttons, and when a click releases each (∞: it does not).
    buttons: [bool; 2],
    release_at: [f64; 2],
    /// `[sim] stylus` in time order, and the next entry due.
    schedule: Vec<(f64, StylusAction)>,
    next_event: usize,
    /// The hand carrying or holding the stylus (dock, undock).
    carry: Option<Carry>,
    /// Where the hand holds an undocked stylus: the workspace centre, rad.
    centre: Joint3,
}

impl SimOmni {
    /// A simulator from its sections of the configuration (a `&Config` gives them).
    pub fn new<'a>(cfg: impl Into<SimSetup<'a>>, paced: bool) -> Self {
        let cfg = cfg.into();
        let mut plant = Dynamics::new(*cfg.model, *cfg.geometry);
        plant.friction = cfg.sim.friction;
        let start_pose = Joint3::from(cfg.sim.start_pose);
        let tip = |q: [f64; 3]| tip_position_mm(cfg.geometry, &q.into()) * 1e-3;
        let hand = (cfg.hand.pattern != HandPattern::None)
            .then(|| Hand::new(cfg.hand, tip(cfg.sim.start_pose), tip(cfg.center)));
        let ink = Joint3::from(INKWELL_POSE);
        let hold = plant.gravity(&ink).map(|g| g.abs() + INKWELL_MARGIN_NM);
        SimOmni {
            plant,
            payload_kg: cfg.sim.payload_kg,
            payload_at_s: cfg.sim.payload_at_s,
            dac: DacScale {
                nm_per_count: cfg.device.nm_per_count,
            },
            rad_per_count: cfg.device.rad_per_count(),
            period_s: 1.0 / cfg.device.rate_hz,
            substeps: cfg.sim.substeps,
            noise_nm: cfg.sim.torque_noise_nm,
            // A separate stream from the one the reference uses, from the same seed.
            rng: ChaCha8Rng::seed_from_u64(cfg.sim.seed ^ 0x005E_ED0F_0A1D),
            q: start_pose,
            qd: Joint3::zeros(),
            tick: 0,
            last_watchdog: None,
            paced,
            start_ns: 0,
            hand,
            hand_force: Force3::zeros(),
            wall: Wall::place(
                &cfg.sim.wall,
                &tip_position_mm(cfg.geometry, &cfg.center.into()),
            ),
            wall_force: Force3::zeros(),
            inkwell: Inkwell {
                pose: ink,
                hold,
                docked: cfg.sim.docked && (start_pose - ink).amax() < INKWELL_TOLERANCE,
                away: (start_pose - ink).amax() > 2.0 * INKWELL_TOLERANCE,
            },
            buttons: [false; 2],
            release_at: [f64::INFINITY; 2],
            schedule: cfg.sim.stylus_schedule(),
            next_event: 0,
            carry: None,
            centre: Joint3::from(cfg.center),
        }
    }

    /// The stylus buttons pressed.
    pub fn buttons(&self) -> [bool; 2] {
        self.buttons
    }

    /// The hand acts on the stylus at device time `t`.
    fn act(&mut self, t: f64, action: StylusAction) {
        match action {
            StylusAction::Press(b) => {
                self.buttons[b] = true;
                self.release_at[b] = f64::INFINITY;
            }
            StylusAction::Release(b) => {
                self.buttons[b] = false;
                self.release_at[b] = f64::INFINITY;
            }
            StylusAction::Click(b) => {
                self.buttons[b] = true;
                self.release_at[b] = t + CLICK_S;
            }
            StylusAction::Dock => {
                if !self.inkwell.docked {
                    self.carry = Some(Carry::new(self.q, self.inkwell.pose, t, true));
                }
            }
            StylusAction::Undock => {
                if self.inkwell.docked || self.carry.is_some_and(|c| c.dock) {
                    self.inkwell.docked = false;
                    self.carry = Some(Carry::new(self.q, self.centre, t, false));
                }
            }
        }
    }

    /// After the step to device time `t`: the schedule's entries that are due, clicks that
    /// end, and a carried stylus that has come to rest in its inkwell.
    fn stylus_step(&mut self, t: f64) {
        while let Some(&(at, action)) = self.schedule.get(self.next_event) {
            if at > t {
                break;
            }
            self.next_event += 1;
            self.act(t, action);
        }
        for b in 0..2 {
            if t >= self.release_at[b] {
                self.buttons[b] = false;
                self.release_at[b] = f64::INFINITY;
            }
        }
        if let Some(c) = self.carry.filter(|c| c.dock && t >= c.t0 + c.dur) {
            let off = self.q - self.inkwell.pose;
            if self.inkwell.docked || (off.amax() < INKWELL_TOLERANCE && self.qd.amax() < 0.05) {
                self.inkwell.docked = true;
                self.inkwell.away = false;
                self.carry = None;
            } else if t >= c.t0 + c.dur + CARRY_GIVE_UP_S {
                self.carry = None;
            }
        }
    }

    /// True joint angles and velocities (for tests; the servo sees only encoder counts).
    pub fn true_state(&self) -> (Joint3, Joint3) {
        (self.q, self.qd)
    }

    /// Whether the stylus sits in the inkwell.
    pub fn docked(&self) -> bool {
        self.inkwell.docked
    }

    /// Put the arm at a pose with a velocity (tests); out of the inkwell.
    pub fn set_state(&mut self, q: Joint3, qd: Joint3) {
        self.inkwell.docked = false;
        self.q = q;
        self.qd = qd;
    }

    /// Total mechanical energy of the plant, J.
    pub fn energy(&self) -> f64 {
        self.plant.kinetic(&self.q, &self.qd) + self.plant.potential(&self.q)
    }

    /// Advance the plant by `dt` under constant torque `tau` (classic RK4, `substeps` steps).
    pub fn integrate(&mut self, tau: &Joint3, dt: f64) {
        self.integrate_from(0.0, tau, dt);
        self.inkwell.update(&self.q, &self.qd);
    }

    /// The force the hand puts on the tip at (q, q̇), `s` s into the tick starting at `t`.
    fn hand_force_at(&self, t: f64, s: f64, q: &Joint3, qd: &Joint3) -> Force3 {
        let Some(hand) = &self.hand else {
            return Force3::zeros();
        };
        let g = &self.plant.geometry;
        let tip = tip_position_mm(g, q) * 1e-3;
        hand.force(t + s, &tip, &(jacobian(g, q) * qd), s)
    }

    /// The wall's force on the tip at (q, q̇) (zero without a wall).
    fn wall_force_at(&self, q: &Joint3, qd: &Joint3) -> Force3 {
        let Some(wall) = &self.wall else {
            return Force3::zeros();
        };
        let g = &self.plant.geometry;
        wall.force(&(tip_position_mm(g, q) * 1e-3), &(jacobian(g, q) * qd))
    }

    /// [`integrate`](Self::integrate) over the tick starting at `t`, with the hand's force on
    /// the tip (through Jᵀ) inside every evaluation: the grip is stiff next to the arm.
    fn integrate_from(&mut self, t: f64, tau: &Joint3, dt: f64) {
        let h = dt / self.substeps as f64;
        let with_hand = self.hand.is_some() || self.wall.is_some();
        let inkwell = self.inkwell;
        let carry = self.carry;
        let f = |s: f64, q: &Joint3, qd: &Joint3| {
            let mut held = tau + inkwell.torque(q, qd);
            if let Some(c) = &carry {
                held += c.torque(&self.plant, t + s, q, qd);
            }
            if with_hand {
                let fh = self.hand_force_at(t, s, q, qd) + self.wall_force_at(q, qd);
                let ext = tip_force_torque(&self.plant.geometry, q, &fh);
                self.plant.forward_dynamics(q, qd, &(held + ext))
            } else {
                self.plant.forward_dynamics(q, qd, &held)
            }
        };
        let (mut q, mut qd) = (self.q, self.qd);
        for k in 0..self.substeps {
            let s = k as f64 * h;
            let a1 = f(s, &q, &qd);
            let (q2, v2) = (q + qd * (h / 2.0), qd + a1 * (h / 2.0));
            let a2 = f(s + h / 2.0, &q2, &v2);
            let (q3, v3) = (q + v2 * (h / 2.0), qd + a2 * (h / 2.0));
            let a3 = f(s + h / 2.0, &q3, &v3);
            let (q4, v4) = (q + v3 * h, qd + a3 * h);
            let a4 = f(s + h, &q4, &v4);
            q += (qd + v2 * 2.0 + v3 * 2.0 + v4) * (h / 6.0);
            qd += (a1 + a2 * 2.0 + a3 * 2.0 + a4) * (h / 6.0);
        }
        self.q = q;
        self.qd = qd;
    }

    /// One tick of the plant from time `t`: the hand moves on, the arm moves under the motor
    /// torque and the hand, and the hand's force at the new sample is kept for the log.
    fn step(&mut self, t: f64, tau: &Joint3) {
        let felt = self.hand_force;
        if let Some(hand) = &mut self.hand {
            hand.advance(t, self.period_s, &felt);
        }
        self.integrate_from(t, tau, self.period_s);
        self.inkwell.update(&self.q, &self.qd);
        let (q, qd) = (self.q, self.qd);
        self.hand_force = self.hand_force_at(t, self.period_s, &q, &qd);
        self.wall_force = self.wall_force_at(&q, &qd);
    }

    fn encoder_words(&self) -> [u16; 3] {
        let mut w = [0u16; 3];
        for j in 0..3 {
            // Counts wrap at 16 bits on the wire, exactly as the hardware's do.
            w[j] = ((self.q[j] / self.rad_per_count).round() as i64) as u16;
        }
        w
    }
}

impl Device for SimOmni {
    fn kind(&self) -> &'static str {
        "sim"
    }

    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        let cmd = decode_command(command)?;
        if self.tick == 0 {
            self.start_ns = clock::now_ns();
        } else {
            // Like the real amplifier board: a watchdog byte that stops advancing drops the
            // amplifiers.
            let alive = self.last_watchdog != Some(cmd.watchdog);
            let mut tau = if cmd.amps_on && alive {
                Joint3::from(self.dac.to_torque(&cmd.dac))
            } else {
                Joint3::zeros()
            };
            if self.noise_nm > 0.0 {
                for j in 0..3 {
                    tau[j] += self.noise_nm * self.rng.sample::<f64, _>(StandardNormal);
                }
            }
            let t = self.tick as f64 * self.period_s;
            self.plant.payload_kg = if t >= self.payload_at_s {
                self.payload_kg
            } else {
                0.0
            };
            self.step(t, &tau);
            self.stylus_step(t + self.period_s);
            if self.paced {
                clock::sleep_until_ns(
                    self.start_ns + (self.tick as f64 * self.period_s * 1e9) as u64,
                );
            }
        }
        self.last_watchdog = Some(cmd.watchdog);
        let state = StatePacket {
            encoder: self.encoder_words(),
            gimbal: [0x8000; 3],
            buttons: self.buttons,
            inkwell: self.inkwell.docked,
            counter: self.tick as u32,
        };
        let sample = RawSample::new(encode_state(&state), self.tick as f64 * self.period_s);
        self.tick += 1;
        Ok(sample)
    }

    fn plant_model(&self) -> Option<&Dynamics> {
        Some(&self.plant)
    }

    fn hand_force(&self) -> Option<[f64; 3]> {
        Some(self.hand_force.into())
    }

    fn contact_force(&self) -> Option<[f64; 3]> {
        Some(self.wall_force.into())
    }

    fn stylus(&mut self, action: StylusAction) -> bool {
        self.act(self.tick as f64 * self.period_s, action);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::device::codec::{encode_command, MotorCommand, DAC_ZERO};

    fn frictionless() -> Config {
        let mut cfg = Config::default();
        cfg.sim.friction = false;
        cfg.sim.torque_noise_nm = 0.0;
        cfg
    }

    #[test]
    fn free_swing_conserves_energy() {
        let mut cfg = frictionless();
        // Gravity in this model is unstable about the centre pose: without the limit springs
        // (which damp) the arm swings freely through the whole range.
        cfg.model.limit_lower = [-100.0; 3];
        cfg.model.limit_upper = [100.0; 3];
        let mut sim = SimOmni::new(&cfg, false);
        // Released from a raised pose with some velocity, well inside the joint limits.
        sim.set_state(Joint3::new(0.3, 1.0, 0.6), Joint3::new(0.5, 0.0, -0.5));
        let e0 = sim.energy();
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        let mut swing = 0.0f64;
        for _ in 0..10_000 {
            sim.integrate(&Joint3::zeros(), 1e-3);
            let e = sim.energy();
            lo = lo.min(e);
            hi = hi.max(e);
            swing = swing.max(sim.true_state().1.norm());
        }
        // Energy is only defined up to a constant: compare the drift to the kinetic energy
        // scale of the swing as well as to |E|.
        let drift = (hi - lo) / e0.abs();
        assert!(
            swing > 1.0,
            "the arm must actually swing, peak speed {swing}"
        );
        assert!(drift < 1e-3, "energy drift {drift:e} of |E0| = {e0:e}");
    }

    #[test]
    fn zero_dac_and_amps_off_apply_no_torque() {
        let cfg = frictionless();
        let mut a = SimOmni::new(&cfg, false);
        let mut b = SimOmni::new(&cfg, false);
        let mut on = MotorCommand::safe(0);
        on.amps_on = true;
        on.dac = [DAC_ZERO + 500; 3];
        for k in 0..200u8 {
            let off = MotorCommand::safe(k);
            let mut live = on;
            live.watchdog = k;
            a.exchange(&encode_command(&off)).unwrap();
            b.exchange(&encode_command(&live)).unwrap();
        }
        // Identical start, but b was pushed: it must have moved differently.
        assert!((a.true_state().0 - b.true_state().0).norm() > 1e-3);
    }

    #[test]
    fn stalled_watchdog_drops_the_amplifiers() {
        let cfg = frictionless();
        let mut pushed = SimOmni::new(&cfg, false);
        let mut stalled = SimOmni::new(&cfg, false);
        let mut idle = SimOmni::new(&cfg, false);
        let mut cmd = MotorCommand::safe(0);
        cmd.amps_on = true;
        cmd.dac = [DAC_ZERO + 800; 3];
        for k in 0..100u8 {
            let mut live = cmd;
            live.watchdog = k;
            pushed.exchange(&encode_command(&live)).unwrap();
            stalled.exchange(&encode_command(&cmd)).unwrap(); // watchdog stuck at 0
            idle.exchange(&encode_command(&MotorCommand::safe(k)))
                .unwrap();
        }
        assert_eq!(stalled.true_state().0, idle.true_state().0);
        assert!((pushed.true_state().0 - idle.true_state().0).norm() > 1e-3);
    }

    #[test]
    fn encoders_quantise_and_wrap() {
        let cfg = frictionless();
        let mut sim = SimOmni::new(&cfg, false);
        let step = cfg.device.rad_per_count();
        sim.set_state(Joint3::new(-3.0 * step, 0.4, 10.2 * step), Joint3::zeros());
        let w = sim.encoder_words();
        assert_eq!(w[0], 0xFFFD);
        assert_eq!(w[2], 10);
        assert_eq!(w[1], (0.4 / step).round() as u16);
    }

    /// Largest difference over one 1 ms tick between `substeps` and 64 RK4 substeps, as
    /// (angle in encoder counts, velocity in rad/s), from 3000 random states and torques.
    /// `smooth`: inside the limits and moving fast (the Coulomb curve saturated); otherwise also
    /// where the model is stiffest or kinked (near-zero velocity, where the Coulomb curve's
    /// slope is 1 N·m·s/rad on ~1e-3 kg·m²; across a limit spring's edge).
    fn tick_error_against_64_substeps(substeps: u32, smooth: bool) -> (f64, f64) {
        let mut cfg = Config::default();
        cfg.sim.torque_noise_nm = 0.0;
        let counts = cfg.device.rad_per_count();
        let mut one_tick = |n: u32, q: Joint3, qd: Joint3, tau: Joint3| {
            cfg.sim.substeps = n;
            let mut sim = SimOmni::new(&cfg, false);
            sim.set_state(q, qd);
            sim.integrate(&tau, 1e-3);
            sim.true_state()
        };
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let (mut dq, mut dqd) = (0.0f64, 0.0f64);
        for k in 0..3000 {
            let q = if smooth {
                Joint3::new(
                    rng.random_range(-0.8..0.8),
                    rng.random_range(0.2..1.55),
                    rng.random_range(-0.4..1.0),
                )
            } else {
                Joint3::new(
                    rng.random_range(-1.1..1.1),
                    rng.random_range(-0.1..1.85),
                    rng.random_range(-0.7..1.3),
                )
            };
            let qd = if smooth {
                Joint3::from_fn(|_, _| rng.random_range(1.0..3.0) * [-1.0, 1.0][k % 2])
            } else {
                let speed = [0.005, 0.05, 3.0][k % 3];
                Joint3::from_fn(|_, _| rng.random_range(-speed..speed))
            };
            let tau = Joint3::from_fn(|_, _| rng.random_range(-0.3..0.3));
            let (q_n, qd_n) = one_tick(substeps, q, qd, tau);
            let (q_ref, qd_ref) = one_tick(64, q, qd, tau);
            dq = dq.max((q_n - q_ref).amax() / counts);
            dqd = dqd.max((qd_n - qd_ref).amax());
        }
        (dq, dqd)
    }

    #[test]
    fn default_substeps_resolve_a_tick_far_below_one_encoder_count() {
        let (dq, dqd) = tick_error_against_64_substeps(Config::default().sim.substeps, false);
        assert!(dq < 0.01, "angle error {dq:e} counts in one tick");
        assert!(dqd < 0.01, "velocity error {dqd:e} rad/s in one tick");
        // Where the model is smooth the comparison sees RK4's fourth order: halving the step
        // cuts the error by about 16.
        let (dq1, dqd1) = tick_error_against_64_substeps(1, true);
        let (dq2, dqd2) = tick_error_against_64_substeps(2, true);
        assert!(
            dq1 > 8.0 * dq2 && dqd1 > 8.0 * dqd2,
            "{dq1:e} {dq2:e} {dqd1:e} {dqd2:e}"
        );
    }
}

#[cfg(test)]
mod stylus_tests {
    use super::*;
    use crate::config::Config;
    use crate::device::codec::{decode_state, encode_command, MotorCommand};

    fn config(stylus: &str) -> Result<Config, ConfigError> {
        let cfg = Config::from_toml(&format!("[sim]\nstylus = {stylus}\n"), "test")?;
        cfg.validate()?;
        Ok(cfg)
    }

    #[test]
    fn a_stylus_schedule_is_read_and_each_bad_entry_named_by_its_field() {
        let cfg = config(
            r#"[{ at_s = 2.0, action = "undock" }, { at_s = 0.5, action = "click", button = 2 }]"#,
        )
        .unwrap();
        assert_eq!(
            cfg.sim.stylus_schedule(),
            [(0.5, StylusAction::Click(1)), (2.0, StylusAction::Undock)]
        );
        for (entries, field, says) in [
            (
                r#"[{ at_s = 1.0, action = "press", button = 3 }]"#,
                "sim.stylus[0].button",
                "1 or 2",
            ),
            (
                r#"[{ at_s = 1.0, action = "press" }]"#,
                "sim.stylus[0].button",
                "1 or 2",
            ),
            (
                r#"[{ at_s = 1.0, action = "dock" }, { at_s = 2.0, action = "dock", button = 1 }]"#,
                "sim.stylus[1].button",
                "take no button",
            ),
            (
                r#"[{ at_s = 1.0, action = "wave" }]"#,
                "sim.stylus[0].action",
                "undock",
            ),
            (
                r#"[{ at_s = -1.0, action = "dock" }]"#,
                "sim.stylus[0].at_s",
                "0 ..= 1e6",
            ),
        ] {
            let e = config(entries).unwrap_err().to_string();
            assert!(e.contains(field) && e.contains(says), "{entries}: {e}");
        }
        // A key the entry does not have is refused by name.
        let e = config(r#"[{ at_s = 1.0, action = "dock", when = 2 }]"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("when"), "{e}");
    }

    /// The packets a program would read: buttons and inkwell, one tick at a time.
    fn run(sim: &mut SimOmni, ticks: usize) -> ([bool; 2], bool) {
        let mut last = ([false; 2], false);
        for k in 0..ticks {
            let raw = sim
                .exchange(&encode_command(&MotorCommand::safe(k as u8)))
                .unwrap();
            let p = decode_state(raw.packet()).unwrap();
            last = (p.buttons, p.inkwell);
        }
        last
    }

    #[test]
    fn the_hand_clicks_on_schedule_and_carries_the_stylus_out_of_and_into_its_inkwell() {
        let cfg = config(r#"[{ at_s = 0.2, action = "click", button = 1 }]"#).unwrap();
        let mut sim = SimOmni::new(&cfg, false);
        assert_eq!(run(&mut sim, 150), ([false, false], true));
        assert_eq!(
            run(&mut sim, 100),
            ([true, false], true),
            "clicked at 0.2 s"
        );
        assert_eq!(
            run(&mut sim, 100),
            ([false, false], true),
            "released 0.1 s later"
        );
        // Undocked, the unpowered arm is held out of the inkwell (not back in it) ...
        assert!(sim.stylus(StylusAction::Undock));
        assert!(!run(&mut sim, 3000).1);
        assert!((sim.true_state().0 - Joint3::from(INKWELL_POSE)).amax() > 0.1);
        // ... and docked again, it rests there with the amplifiers off.
        sim.stylus(StylusAction::Dock);
        assert!(run(&mut sim, 3000).1);
        let q = sim.true_state().0;
        assert!(run(&mut sim, 2000).1);
        assert!(
            (sim.true_state().0 - q).amax() < 1e-3,
            "stays in the inkwell"
        );
        sim.stylus(StylusAction::Press(1));
        assert_eq!(run(&mut sim, 1).0, [false, true]);
        sim.stylus(StylusAction::Release(1));
        assert_eq!(run(&mut sim, 1).0, [false, false]);
    }
}

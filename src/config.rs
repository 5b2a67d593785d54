//! Run configuration: TOML, every field optional with the defaults of DESIGN §2.4, unknown keys
//! refused, every value validated with an error that names the field and the allowed range.

pub use crate::device::firewire::FirewireConfig;
pub use crate::device::usb::UsbConfig;
pub use crate::ident::IdentifierConfig;
use crate::omni::{Geometry, ModelParams};
pub use crate::servo::realtime::RealtimeConfig;
pub use crate::servo::safety::SafetyConfig;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// The largest config file read (the full default config is about 12 kB).
pub const MAX_CONFIG_BYTES: u64 = 1 << 20;

#[derive(Debug, Error)]
pub enum ConfigError {
    #[error("cannot read config {path}: {source}")]
    Read {
        path: String,
        source: std::io::Error,
    },
    #[error("config {path}: {message}")]
    Parse { path: String, message: String },
    #[error("config: `{field}` = {} is out of range: allowed {allowed}", crate::text::cut(.value))]
    Invalid {
        field: String,
        value: String,
        allowed: String,
    },
}

impl ConfigError {
    /// Reading the file was stopped by the operator.
    pub fn is_stopped(&self) -> bool {
        matches!(self, ConfigError::Read { source, .. } if crate::input::is_stopped(source))
    }
}

/// Device-independent facts of the Omni's electronics.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DeviceConfig {
    /// Encoder counts per joint revolution.
    pub counts_per_rev: f64,
    /// Motor torque per DAC count, N·m (12-bit offset binary, ±2047 counts).
    #[serde(deserialize_with = "crate::config::exact")]
    pub nm_per_count: [f64; 3],
    /// Servo rate, Hz.
    pub rate_hz: f64,
}

impl Default for DeviceConfig {
    fn default() -> Self {
        DeviceConfig {
            counts_per_rev: 15000.0,
            nm_per_count: [2.2e-4; 3],
            rate_hz: 1000.0,
        }
    }
}

impl DeviceConfig {
    pub fn rad_per_count(&self) -> f64 {
        std::f64::consts::TAU / self.counts_per_rev
    }
}

/// The simulated Omni.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
    #[serde(deserialize_with = "crate::config::exact")]
    pub start_pose: [f64; 3],
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            seed: 1,
            friction: true,
            payload_kg: 0.0,
            payload_at_s: 0.0,
            substeps: 2,
            torque_noise_nm: 2e-4,
            start_pose: [0.0, 0.27, -0.37],
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct KalmanConfig {
    /// Spectral density of the white jerk driving the model, rad²/s⁵.
    pub jerk_psd: f64,
    /// Measurement variance R, rad² (default Δ²/12 of the encoder step).
    pub measurement_var: f64,
}

impl Default for KalmanConfig {
    fn default() -> Self {
        let step = std::f64::consts::TAU / 15000.0;
        KalmanConfig {
            jerk_psd: 100.0,
            measurement_var: step * step / 12.0,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ControlConfig {
    /// Closed-loop natural frequency, rad/s (K_p = ω², K_d = 2ζω, scaled by M₀ for PD).
    pub omega_n: f64,
    /// Closed-loop damping ratio.
    pub zeta: f64,
    /// Computed torque: its rigid-body model is the plant's parameters times this factor.
    pub ct_model_scale: f64,
    /// Computed torque: also compensate the model's viscous and Coulomb friction.
    pub ct_friction: bool,
}

impl Default for ControlConfig {
    fn default() -> Self {
        ControlConfig {
            omega_n: 25.0,
            zeta: 1.0,
            ct_model_scale: 1.0,
            ct_friction: false,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ReferenceConfig {
    /// Mid-workspace pose the trajectories move about, rad.
    #[serde(deserialize_with = "crate::config::exact")]
    pub center: [f64; 3],
    /// Sine amplitudes, rad.
    #[serde(deserialize_with = "crate::config::exact")]
    pub amplitude: [f64; 3],
    /// Sine frequency, Hz.
    pub frequency_hz: f64,
    /// Duration of the quintic blend from the start pose onto the reference, s.
    pub blend_s: f64,
    /// Tracking statistics start here (after the blend and its transient), s.
    pub settle_s: f64,
    /// Multisine: amplitude per joint (sum over components), rad.
    #[serde(deserialize_with = "crate::config::exact")]
    pub multisine_amplitude: [f64; 3],
    /// Multisine: lowest and highest component frequency, Hz.
    #[serde(deserialize_with = "crate::config::exact")]
    pub multisine_band_hz: [f64; 2],
    /// Multisine: number of components per joint.
    pub multisine_components: u32,
}

impl Default for ReferenceConfig {
    fn default() -> Self {
        ReferenceConfig {
            center: [0.0, 0.65, 0.3],
            amplitude: [0.4, 0.3, 0.3],
            frequency_hz: 0.5,
            blend_s: 1.0,
            settle_s: 2.0,
            multisine_amplitude: [0.45, 0.32, 0.32],
            multisine_band_hz: [0.1, 1.5],
            multisine_components: 6,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TelemetryConfig {
    /// Capacity of the bounded channel from the servo loop to the log writer, ticks.
    pub channel_capacity: usize,
}

impl Default for TelemetryConfig {
    fn default() -> Self {
        TelemetryConfig {
            channel_capacity: 8192,
        }
    }
}

/// Faults to inject (testing the safety layer); same specs as `--inject`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InjectConfig {
    pub faults: Vec<String>,
}

impl InjectConfig {
    pub fn parsed(&self) -> Result<Vec<crate::device::inject::Fault>, ConfigError> {
        self.faults
            .iter()
            .enumerate()
            .map(|(i, f)| {
                f.parse().map_err(
                    |e: crate::device::inject::FaultSpecError| ConfigError::Invalid {
                        field: format!("inject.faults[{i}]"),
                        value: format!("{f:?}"),
                        allowed: e.why,
                    },
                )
            })
            .collect()
    }
}

/// The whole configuration file.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    pub device: DeviceConfig,
    pub sim: SimConfig,
    pub model: ModelParams,
    pub geometry: Geometry,
    pub kalman: KalmanConfig,
    pub control: ControlConfig,
    pub reference: ReferenceConfig,
    pub safety: SafetyConfig,
    pub telemetry: TelemetryConfig,
    pub identifier: IdentifierConfig,
    pub realtime: RealtimeConfig,
    pub usb: UsbConfig,
    pub firewire: FirewireConfig,
    pub inject: InjectConfig,
    pub serve: crate::serve::ServeConfig,
    pub haptics: crate::haptics::HapticsConfig,
}

/// The Kalman filter must follow a sinusoidal motion of this frequency (a fast hand motion)...
pub const KALMAN_CHECK_HZ: f64 = 5.0;
/// ... with a position error of at most this fraction of the motion (the default: 1 %).
pub const KALMAN_MAX_LAG: f64 = 0.2;

/// One-line explanations of every key, used by `omnid config --print-default`.
pub const FIELD_DOCS: &[(&str, &str)] = &[
    (
        "device",
        "Electronics of the Omni, shared by every backend.",
    ),
    (
        "device.counts_per_rev",
        "encoder counts per joint revolution",
    ),
    (
        "device.nm_per_count",
        "motor torque per DAC count, N·m (±2047 counts about 0x07FF)",
    ),
    ("device.rate_hz", "servo rate, Hz"),
    ("sim", "The simulated Omni."),
    (
        "sim.seed",
        "seeds all randomness of a run (noise, multisine phases)",
    ),
    (
        "sim.friction",
        "viscous and Coulomb friction in the simulated plant",
    ),
    ("sim.payload_kg", "extra point mass at the tip, kg ..."),
    ("sim.payload_at_s", "... added at this time, s"),
    ("sim.substeps", "RK4 integration substeps per servo tick"),
    (
        "sim.torque_noise_nm",
        "standard deviation of a random torque disturbance, N·m",
    ),
    (
        "sim.start_pose",
        "joint angles at power-on, rad (stylus in the inkwell)",
    ),
    (
        "model",
        "Rigid-body model (DESIGN §4.2): the simulator's plant and CT's model.",
    ),
    ("model.k1", "inertia parameter, kg·m²"),
    ("model.k2", "inertia parameter, kg·m²"),
    ("model.k3", "inertia parameter, kg·m²"),
    ("model.k4", "inertia parameter, kg·m²"),
    ("model.k5", "inertia parameter, kg·m²"),
    ("model.k7", "inertia parameter, kg·m²"),
    ("model.k8", "gravity parameter, N·m"),
    ("model.k9", "gravity parameter, N·m"),
    (
        "model.rotor_inertia",
        "reflected rotor inertia per joint, kg·m²",
    ),
    ("model.viscous", "viscous friction per joint, N·m·s/rad"),
    ("model.coulomb", "Coulomb friction per joint, N·m"),
    (
        "model.coulomb_velocity",
        "velocity scale of the tanh smoothing Coulomb friction, rad/s",
    ),
    ("model.limit_lower", "lower joint limits, rad"),
    ("model.limit_upper", "upper joint limits, rad"),
    (
        "model.limit_stiffness",
        "joint-limit spring stiffness, N·m/rad",
    ),
    (
        "model.limit_damping",
        "joint-limit spring damping, N·m·s/rad",
    ),
    ("geometry", "Arm geometry (DESIGN §4.1), mm."),
    ("geometry.l1_mm", "upper arm length, mm"),
    ("geometry.l2_mm", "lower arm length, mm"),
    (
        "geometry.y_offset_mm",
        "tip y offset of the OpenHaptics origin, mm",
    ),
    (
        "geometry.z_offset_mm",
        "tip z offset of the OpenHaptics origin, mm",
    ),
    ("kalman", "Per-joint Kalman filter (DESIGN §4.3)."),
    (
        "kalman.jerk_psd",
        "white-jerk spectral density q_j, rad²/s⁵ (10 suits 0.5 Hz, 1000 suits 2 Hz)",
    ),
    (
        "kalman.measurement_var",
        "measurement variance R, rad² (encoder step²/12)",
    ),
    ("control", "Controller gains, shared by PD, CT and NNIDC."),
    ("control.omega_n", "closed-loop natural frequency, rad/s"),
    ("control.zeta", "closed-loop damping ratio"),
    (
        "control.ct_model_scale",
        "computed torque: model parameters = plant's × this factor",
    ),
    (
        "control.ct_friction",
        "computed torque: also compensate the model's friction",
    ),
    ("reference", "Reference trajectories."),
    ("reference.center", "pose the trajectories move about, rad"),
    ("reference.amplitude", "sine amplitudes, rad"),
    ("reference.frequency_hz", "sine frequency, Hz"),
    (
        "reference.blend_s",
        "quintic blend from the start pose onto the reference, s",
    ),
    (
        "reference.settle_s",
        "tracking statistics are taken from this time on, s",
    ),
    (
        "reference.multisine_amplitude",
        "multisine peak amplitude per joint, rad",
    ),
    (
        "reference.multisine_band_hz",
        "multisine lowest and highest frequency, Hz",
    ),
    (
        "reference.multisine_components",
        "multisine components per joint",
    ),
    (
        "telemetry",
        "Telemetry from the servo loop to the log writer.",
    ),
    ("inject", "Fault injection for tests of the safety layer (also --inject)."),
    (
        "inject.faults",
        "e.g. [\"disconnect@5\", \"stall@2:50\", \"corrupt:0.01\", \"encoder-jump@3:800\", \"nan@4\", \"slow@1:5\"]",
    ),
    (
        "telemetry.channel_capacity",
        "bounded channel capacity, ticks (drops are counted)",
    ),
];

/// `[T; N]` from exactly N values. serde's own impl for arrays stops after N elements without
/// looking further, so with `toml` a longer array was silently cut to its first N; every
/// fixed-length field of a config or stored-state file takes its values through this
/// (`#[serde(deserialize_with = "crate::config::exact")]`).
pub(crate) fn exact<'de, D, T, const N: usize>(d: D) -> Result<[T; N], D::Error>
where
    D: serde::Deserializer<'de>,
    T: Deserialize<'de>,
{
    let values = Vec::<T>::deserialize(d)?;
    let got = values.len();
    values
        .try_into()
        .map_err(|_| serde::de::Error::invalid_length(got, &ArrayOf(N)))
}

/// What [`exact`] expects, for its message.
struct ArrayOf(usize);

impl serde::de::Expected for ArrayOf {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "an array of exactly {} values", self.0)
    }
}

fn finite_in(field: &str, v: f64, lo: f64, hi: f64, allowed: &str) -> Result<(), ConfigError> {
    if v.is_finite() && v >= lo && v <= hi {
        Ok(())
    } else {
        Err(ConfigError::Invalid {
            field: field.to_string(),
            value: format!("{v}"),
            allowed: allowed.to_string(),
        })
    }
}

fn positive(field: &str, v: f64) -> Result<(), ConfigError> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(ConfigError::Invalid {
            field: field.to_string(),
            value: format!("{v}"),
            allowed: "finite and > 0".to_string(),
        })
    }
}

fn each<const N: usize>(
    field: &str,
    v: &[f64; N],
    check: impl Fn(&str, f64) -> Result<(), ConfigError>,
) -> Result<(), ConfigError> {
    for (i, x) in v.iter().enumerate() {
        check(&format!("{field}[{i}]"), *x)?;
    }
    Ok(())
}

impl Config {
    /// Parse TOML text; `origin` names the source in messages.
    pub fn from_toml(text: &str, origin: &str) -> Result<Self, ConfigError> {
        let cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: origin.to_string(),
            message: describe_toml_error(text, &e),
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Read and validate a config file (at most [`MAX_CONFIG_BYTES`]; `stop`, the operator's,
    /// ends a wait on a pipe, without it only a regular file is read: see
    /// [`crate::input::open`]).
    pub fn load(path: &Path, stop: Option<&Arc<AtomicBool>>) -> Result<Self, ConfigError> {
        let text = crate::input::read_capped(path, MAX_CONFIG_BYTES, stop).map_err(|source| {
            ConfigError::Read {
                path: path.display().to_string(),
                source,
            }
        })?;
        Self::from_toml(&text, &path.display().to_string())
    }

    /// M(q) of the configured model on a 5×5 grid of (q2, q3) spanning the joint limits
    /// (M does not depend on q1), with the grid point.
    fn mass_over_joint_range(&self) -> impl Iterator<Item = ((f64, f64), crate::omni::Mat3)> {
        let (m, dynamics) = (
            self.model,
            crate::omni::Dynamics::new(self.model, self.geometry),
        );
        let across = move |i: usize, k: usize| {
            m.limit_lower[i] + (m.limit_upper[i] - m.limit_lower[i]) * k as f64 / 4.0
        };
        (0..=4)
            .flat_map(move |a| (0..=4).map(move |b| (across(1, a), across(2, b))))
            .map(move |(q2, q3)| {
                let q = crate::omni::Joint3::new(0.0, q2, q3);
                ((q2, q3), dynamics.mass(&q))
            })
    }

    /// What the simulated Omni needs beyond `validate` (checked when the simulator is the
    /// device, so a hardware configuration at another servo rate is not refused for it).
    pub fn check_sim(&self) -> Result<(), ConfigError> {
        let (d, s, m) = (&self.device, &self.sim, &self.model);
        let least_inertia = self
            .mass_over_joint_range()
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
                ConfigError::Invalid {
                    field: "device.rate_hz".into(),
                    value: d.rate_hz.to_string(),
                    allowed: format!(
                        "≥ {:.0} Hz with sim.substeps = {}, or sim.substeps ≥ {needed} at \
                         {} Hz ({why})",
                        rate / s.substeps as f64,
                        s.substeps,
                        d.rate_hz
                    ),
                }
            } else if needed <= SimConfig::default().substeps as f64 {
                ConfigError::Invalid {
                    field: "sim.substeps".into(),
                    value: s.substeps.to_string(),
                    allowed: format!("sim.substeps ≥ {needed} for this model ({why})"),
                }
            } else {
                let (field, value, _) = terms
                    .iter()
                    .fold(terms[0], |a, &b| if b.2 > a.2 { b } else { a });
                ConfigError::Invalid {
                    field: field.into(),
                    value: value.to_string(),
                    allowed: format!(
                        "a plant that sim.substeps = {} resolves; this one needs \
                         sim.substeps ≥ {needed} ({why})",
                        s.substeps
                    ),
                }
            });
        }
        Ok(())
    }

    /// Check every value; the first problem is returned naming its field.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let d = &self.device;
        finite_in(
            "device.counts_per_rev",
            d.counts_per_rev,
            100.0,
            1e7,
            "100 ..= 1e7",
        )?;
        each("device.nm_per_count", &d.nm_per_count, positive)?;
        finite_in(
            "device.rate_hz",
            d.rate_hz,
            100.0,
            10_000.0,
            "100 ..= 10000 Hz",
        )?;

        let s = &self.sim;
        finite_in("sim.payload_kg", s.payload_kg, 0.0, 1.0, "0 ..= 1 kg")?;
        finite_in("sim.payload_at_s", s.payload_at_s, 0.0, 1e6, "0 ..= 1e6 s")?;
        if !(1..=100).contains(&s.substeps) {
            return Err(ConfigError::Invalid {
                field: "sim.substeps".into(),
                value: s.substeps.to_string(),
                allowed: "1 ..= 100".into(),
            });
        }
        finite_in(
            "sim.torque_noise_nm",
            s.torque_noise_nm,
            0.0,
            0.1,
            "0 ..= 0.1 N·m",
        )?;
        each("sim.start_pose", &s.start_pose, |f, v| {
            finite_in(f, v, -3.2, 3.2, "-3.2 ..= 3.2 rad")
        })?;

        let m = &self.model;
        for (name, v) in [("k1", m.k1), ("k5", m.k5), ("k7", m.k7)] {
            positive(&format!("model.{name}"), v)?;
        }
        for (name, v) in [
            ("k2", m.k2),
            ("k3", m.k3),
            ("k4", m.k4),
            ("k8", m.k8),
            ("k9", m.k9),
        ] {
            finite_in(&format!("model.{name}"), v, -1.0, 1.0, "-1 ..= 1")?;
        }
        each("model.rotor_inertia", &m.rotor_inertia, |f, v| {
            finite_in(f, v, 0.0, 1.0, "0 ..= 1 kg·m²")
        })?;
        each("model.viscous", &m.viscous, |f, v| {
            finite_in(f, v, 0.0, 1.0, "0 ..= 1 N·m·s/rad")
        })?;
        each("model.coulomb", &m.coulomb, |f, v| {
            finite_in(f, v, 0.0, 1.0, "0 ..= 1 N·m")
        })?;
        positive("model.coulomb_velocity", m.coulomb_velocity)?;
        for i in 0..3 {
            finite_in(
                &format!("model.limit_lower[{i}]"),
                m.limit_lower[i],
                -3.2,
                m.limit_upper[i],
                "-3.2 rad ..= model.limit_upper",
            )?;
            finite_in(
                &format!("model.limit_upper[{i}]"),
                m.limit_upper[i],
                m.limit_lower[i],
                3.2,
                "model.limit_lower ..= 3.2 rad",
            )?;
        }
        finite_in(
            "model.limit_stiffness",
            m.limit_stiffness,
            0.0,
            1e4,
            "0 ..= 1e4 N·m/rad",
        )?;
        finite_in(
            "model.limit_damping",
            m.limit_damping,
            0.0,
            100.0,
            "0 ..= 100 N·m·s/rad",
        )?;
        // The inertia must stay positive definite over the whole joint range.
        for ((q2, q3), mass) in self.mass_over_joint_range() {
            if mass.cholesky().is_none() {
                return Err(ConfigError::Invalid {
                    field: "model.k1..k7".into(),
                    value: format!("M(q) not positive definite at q = [0, {q2:.2}, {q3:.2}]"),
                    allowed: "parameters that give a positive definite inertia".into(),
                });
            }
        }
        let g = &self.geometry;
        finite_in("geometry.l1_mm", g.l1_mm, 1.0, 1000.0, "1 ..= 1000 mm")?;
        finite_in("geometry.l2_mm", g.l2_mm, 1.0, 1000.0, "1 ..= 1000 mm")?;
        finite_in(
            "geometry.y_offset_mm",
            g.y_offset_mm,
            -1000.0,
            1000.0,
            "-1000 ..= 1000 mm",
        )?;
        finite_in(
            "geometry.z_offset_mm",
            g.z_offset_mm,
            -1000.0,
            1000.0,
            "-1000 ..= 1000 mm",
        )?;

        positive("kalman.jerk_psd", self.kalman.jerk_psd)?;
        positive("kalman.measurement_var", self.kalman.measurement_var)?;
        // The safety limits also watch the encoders, but control acts on the estimate: one
        // that cannot follow a hand-speed motion is refused before any torque is sent.
        let lag = crate::estimate::kalman::tracking_error(
            self.kalman.jerk_psd,
            self.kalman.measurement_var,
            1.0 / self.device.rate_hz,
            KALMAN_CHECK_HZ,
        );
        if lag.is_nan() || lag > KALMAN_MAX_LAG {
            return Err(ConfigError::Invalid {
                field: "kalman.jerk_psd".into(),
                value: format!(
                    "{} with kalman.measurement_var = {:e}",
                    self.kalman.jerk_psd, self.kalman.measurement_var
                ),
                allowed: format!(
                    "an estimate that follows a {KALMAN_CHECK_HZ} Hz motion within {:.0} % (this \
                     one is off by {:.0} %): raise kalman.jerk_psd or lower \
                     kalman.measurement_var",
                    KALMAN_MAX_LAG * 100.0,
                    lag * 100.0
                ),
            });
        }

        finite_in(
            "control.omega_n",
            self.control.omega_n,
            0.1,
            200.0,
            "0.1 ..= 200 rad/s",
        )?;
        finite_in("control.zeta", self.control.zeta, 0.05, 10.0, "0.05 ..= 10")?;
        finite_in(
            "control.ct_model_scale",
            self.control.ct_model_scale,
            0.1,
            10.0,
            "0.1 ..= 10",
        )?;

        let r = &self.reference;
        for i in 0..3 {
            finite_in(
                &format!("reference.center[{i}]"),
                r.center[i],
                m.limit_lower[i],
                m.limit_upper[i],
                "inside model.limit_lower ..= model.limit_upper",
            )?;
        }
        each("reference.amplitude", &r.amplitude, |f, v| {
            finite_in(f, v, 0.0, 1.0, "0 ..= 1 rad")
        })?;
        finite_in(
            "reference.frequency_hz",
            r.frequency_hz,
            0.0,
            10.0,
            "0 ..= 10 Hz",
        )?;
        finite_in("reference.blend_s", r.blend_s, 0.05, 60.0, "0.05 ..= 60 s")?;
        finite_in("reference.settle_s", r.settle_s, 0.0, 1e6, "0 ..= 1e6 s")?;
        each(
            "reference.multisine_amplitude",
            &r.multisine_amplitude,
            |f, v| finite_in(f, v, 0.0, 1.0, "0 ..= 1 rad"),
        )?;
        finite_in(
            "reference.multisine_band_hz[0]",
            r.multisine_band_hz[0],
            0.01,
            r.multisine_band_hz[1],
            "0.01 Hz ..= multisine_band_hz[1]",
        )?;
        finite_in(
            "reference.multisine_band_hz[1]",
            r.multisine_band_hz[1],
            r.multisine_band_hz[0],
            10.0,
            "multisine_band_hz[0] ..= 10 Hz",
        )?;
        if !(1..=32).contains(&r.multisine_components) {
            return Err(ConfigError::Invalid {
                field: "reference.multisine_components".into(),
                value: r.multisine_components.to_string(),
                allowed: "1 ..= 32".into(),
            });
        }

        self.safety.validate()?;
        self.identifier.validate()?;
        self.realtime.validate()?;
        self.serve.validate()?;
        self.usb.validate()?;
        self.firewire.validate()?;
        self.haptics.validate()?;

        let faults = self.inject.parsed()?;
        if faults.len() > crate::device::inject::MAX_FAULTS {
            return Err(ConfigError::Invalid {
                field: "inject.faults".into(),
                value: format!("{} faults", faults.len()),
                allowed: format!("at most {}", crate::device::inject::MAX_FAULTS),
            });
        }

        let cap = self.telemetry.channel_capacity;
        if !(16..=10_000_000).contains(&cap) {
            return Err(ConfigError::Invalid {
                field: "telemetry.channel_capacity".into(),
                value: cap.to_string(),
                allowed: "16 ..= 10000000".into(),
            });
        }
        Ok(())
    }

    /// The default configuration as commented TOML.
    pub fn default_toml() -> String {
        let text = toml::to_string(&Config::default()).expect("default config serialises");
        let mut out =
            String::from("# omnid configuration: every key is optional; these are the defaults.\n");
        let mut section = String::new();
        for line in text.lines() {
            let trimmed = line.trim();
            if let Some(name) = trimmed.strip_prefix('[').and_then(|s| s.strip_suffix(']')) {
                section = name.to_string();
                out.push('\n');
                if let Some(doc) = doc_for(&section) {
                    out.push_str(&format!("# {doc}\n"));
                }
                out.push_str(line);
                out.push('\n');
            } else if let Some((key, _)) = trimmed.split_once(" = ") {
                match doc_for(&format!("{section}.{key}")) {
                    Some(doc) => out.push_str(&format!("{line}  # {doc}\n")),
                    None => out.push_str(&format!("{line}\n")),
                }
            } else if !trimmed.is_empty() {
                out.push_str(line);
                out.push('\n');
            }
        }
        out
    }
}

fn doc_for(key: &str) -> Option<&'static str> {
    [
        FIELD_DOCS,
        crate::servo::safety::SAFETY_FIELD_DOCS,
        crate::servo::realtime::REALTIME_FIELD_DOCS,
        crate::serve::config::SERVE_FIELD_DOCS,
        crate::ident::IDENTIFIER_FIELD_DOCS,
        crate::device::usb::USB_FIELD_DOCS,
        crate::device::firewire::FIREWIRE_FIELD_DOCS,
        crate::haptics::config::HAPTICS_FIELD_DOCS,
    ]
    .into_iter()
    .flatten()
    .find(|(k, _)| *k == key)
    .map(|(_, d)| *d)
}

/// One line from a TOML error: where it is (line and the text there) and what is wrong.
fn describe_toml_error(text: &str, e: &toml::de::Error) -> String {
    let message = e.message().trim().replace('\n', " ");
    match e.span() {
        Some(span) => {
            let line_no = text[..span.start.min(text.len())].matches('\n').count() + 1;
            let line = text.lines().nth(line_no - 1).unwrap_or("").trim();
            format!("line {line_no} (`{line}`): {message}")
        }
        None => message,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err(text: &str) -> String {
        Config::from_toml(text, "test.toml")
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn empty_file_is_the_defaults() {
        assert_eq!(Config::from_toml("", "x").unwrap(), Config::default());
        Config::default().validate().unwrap();
    }

    #[test]
    fn too_few_substeps_for_a_stiff_friction_curve_are_refused() {
        let err = |text: &str| {
            let cfg = Config::from_toml(text, "test.toml").unwrap();
            cfg.check_sim().unwrap_err().to_string()
        };
        Config::default().check_sim().unwrap();
        // Ten times steeper Coulomb smoothing needs ten times the substeps.
        let e = err("[model]\ncoulomb_velocity = 0.001\n");
        assert!(
            e.contains("`model.coulomb_velocity` = 0.001") && e.contains("sim.substeps ≥ 11"),
            "{e}"
        );
        Config::from_toml(
            "[model]\ncoulomb_velocity = 0.001\n[sim]\nsubsteps = 11\n",
            "x",
        )
        .unwrap()
        .check_sim()
        .unwrap();
        // The defaults sit at the bound: one substep is too few for them.
        let e = err("[sim]\nsubsteps = 1\n");
        assert!(
            e.contains("`sim.substeps` = 1") && e.contains("sim.substeps ≥ 2"),
            "{e}"
        );
        // A slower servo rate means longer ticks.
        let e = err("[device]\nrate_hz = 200\n");
        assert!(e.contains("`device.rate_hz` = 200"), "{e}");
    }

    #[test]
    fn default_toml_round_trips_and_documents_every_key() {
        let text = Config::default_toml();
        assert_eq!(
            Config::from_toml(&text, "default").unwrap(),
            Config::default()
        );
        for line in text
            .lines()
            .filter(|l| !l.starts_with('#') && l.contains(" = "))
        {
            assert!(line.contains("  # "), "undocumented key: {line}");
        }
    }

    #[test]
    fn unknown_key_names_the_key_and_line() {
        let e = err("[kalman]\njerk_psd = 10.0\njerk_pds = 3.0\n");
        assert!(e.contains("jerk_pds") && e.contains("line 3"), "{e}");
        assert!(!e.contains('\n'));
        let e = err("[kalmann]\n");
        assert!(e.contains("kalmann"), "{e}");
    }

    #[test]
    fn wrong_type_names_the_line() {
        let e = err("[sim]\nseed = \"one\"\n");
        assert!(e.contains("line 2") && e.contains("seed"), "{e}");
    }

    #[test]
    fn negative_gain_names_field_and_range() {
        let e = err("[control]\nomega_n = -5.0\n");
        assert!(
            e.contains("control.omega_n") && e.contains("0.1 ..= 200"),
            "{e}"
        );
    }

    #[test]
    fn non_finite_values_are_refused() {
        let e = err("[kalman]\njerk_psd = nan\n");
        assert!(e.contains("kalman.jerk_psd") && e.contains("finite"), "{e}");
        let e = err("[control]\nzeta = inf\n");
        assert!(e.contains("control.zeta"), "{e}");
    }

    #[test]
    fn arrays_of_the_wrong_length_are_refused() {
        // serde alone read the first three of four and dropped the 99 without a word.
        for (text, got) in [
            ("[safety]\nmax_torque_nm = [0.4, 0.4, 0.4, 99]\n", "4"),
            ("[safety]\nmax_torque_nm = [0.4, 0.4]\n", "2"),
            ("[reference]\nmultisine_band_hz = [0.1, 1.5, 3.0]\n", "3"),
        ] {
            let e = err(text);
            let key = text.lines().nth(1).unwrap().split(" = ").next().unwrap();
            assert!(
                e.contains("line 2") && e.contains(key) && e.contains(&format!("length {got}")),
                "{e}"
            );
        }
        let e = err("[safety]\nmax_torque_nm = [0.4, 0.4, 0.4, 99]\n");
        assert!(e.contains("exactly 3 values"), "{e}");
        let e = err("[reference]\nmultisine_band_hz = [0.1, 1.5, 3.0]\n");
        assert!(e.contains("exactly 2 values"), "{e}");
    }

    #[test]
    fn torque_limit_must_be_positive() {
        for bad in ["0.0", "-0.1"] {
            let e = err(&format!("[safety]\nmax_torque_nm = [0.4, {bad}, 0.4]\n"));
            assert!(
                e.contains("safety.max_torque_nm[1]") && e.contains("> 0"),
                "{e}"
            );
        }
    }

    #[test]
    fn non_positive_definite_inertia_is_refused() {
        let e = err("[model]\nk1 = 1e-6\nk2 = 0.5\n");
        assert!(
            e.contains("positive definite") || e.contains("model."),
            "{e}"
        );
    }
}

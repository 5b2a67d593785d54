//! Teleoperation between two arms (docs/TELEOP.md): a leader a person moves and a follower that
//! copies it and touches something, the leader letting the person feel it. Each arm's servo runs
//! its side of the coupling every tick ([`coupling::Coupling`]), on its own fresh state and the
//! freshest packet from the other side ([`channel`]); time-domain passivity on each port
//! ([`passivity`]) keeps the pair stable under delay and loss. `[teleop]` configures it.

pub mod channel;
pub mod console;
pub mod coupling;
pub mod passivity;
pub mod rendezvous;
pub mod wire;

pub use channel::{pair, Endpoint, Impairment, Packet};
pub use coupling::{Coupling, Role, SideInput, TeleopState};
pub use rendezvous::{
    LineStats, OnTheLine, RemoteChannels, RemoteLine, Rendezvous, RendezvousError,
};

use crate::config_check::{self as check, ConfigError};
use serde::{Deserialize, Serialize};

/// What the leader feels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Architecture {
    /// Position–position: each side is pulled toward the other's position by a spring and
    /// damper; the leader feels the coupling (no force sensor, no model).
    Pp,
    /// Position–force: the follower tracks the leader's position; the leader feels the
    /// follower's external force estimated from its motors and model.
    Pf,
}

impl Architecture {
    /// Its name in the config and the results.
    pub fn as_str(self) -> &'static str {
        match self {
            Architecture::Pp => "pp",
            Architecture::Pf => "pf",
        }
    }

    /// From its name.
    pub fn parse(s: &str) -> Option<Architecture> {
        match s {
            "pp" => Some(Architecture::Pp),
            "pf" => Some(Architecture::Pf),
            _ => None,
        }
    }
}

/// How the pair stays stable under delay (docs/TELEOP.md §5).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum DelayControl {
    /// Delay-aware gains: beyond `delay_gain_ms` the coupling is softened in proportion to
    /// the measured round trip (stable, loose at long delays).
    Gains,
    /// Wave variables with drift compensation: the leader and follower exchange waves
    /// (velocity and force combined through the wave impedance), a channel passive for any
    /// constant delay, so the follower keeps its full stiffness; its position is pulled back
    /// onto the leader's at `wave_drift_hz` (docs/TELEOP.md §5).
    Wave,
    /// The default: wave variables, except for a position–force pair between two arms of one
    /// daemon, which runs the delay-aware gains. Across daemons a network's delay is unknown
    /// and changes, and the waves hold at every delay up to 1 s and 50 % loss; in one daemon
    /// (a round trip of a tick or two, where the gains keep full stiffness) the gains press
    /// a stiff floor more quietly in pf, while pp's full-stiffness spring with a tick each
    /// way rings at about 35 Hz that waves do not. Chosen when the channel opens
    /// ([`DelayControl::on_channel`]; docs/TELEOP.md §5); a coupling given it unresolved
    /// runs the gains.
    Auto,
}

impl DelayControl {
    /// Its name in the config and the results.
    pub fn as_str(self) -> &'static str {
        match self {
            DelayControl::Gains => "gains",
            DelayControl::Wave => "wave",
            DelayControl::Auto => "auto",
        }
    }

    /// What runs on a channel (`across_daemons` or not) for `architecture`: `auto` is wave
    /// variables but for pf in one daemon, which runs the gains; a choice stays.
    pub fn on_channel(self, across_daemons: bool, architecture: Architecture) -> DelayControl {
        match self {
            DelayControl::Auto if across_daemons || architecture == Architecture::Pp => {
                DelayControl::Wave
            }
            DelayControl::Auto => DelayControl::Gains,
            chosen => chosen,
        }
    }
}

/// When the leader's operator counts as present (the pair follows only then).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Operator {
    /// While the leader's button 1 is held (dVRK's Omni set-up).
    Button1,
    /// Always, once the link is up (experiments, a foot pedal outside omnid).
    Always,
}

/// `[teleop]`: the coupling between a leader and a follower arm.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct TeleopConfig {
    /// pp (position–position) or pf (position–force, the force from the follower's estimate).
    pub architecture: Architecture,
    /// The follower moves this many mm per mm of the leader (changed live without a jump).
    pub motion_scale: f64,
    /// The leader feels this times the force (the coupling's in pp, the estimate's in pf).
    pub force_scale: f64,
    /// The coupling spring, N/mm.
    pub stiffness_n_per_mm: f64,
    /// The coupling damper on the follower, N·s/m.
    pub damping_n_s_per_m: f64,
    /// The damper in the force the leader feels in pp, N·s/m (the hand damps the leader; a
    /// damper on two differentiated positions is mostly felt as noise).
    pub leader_damping_n_s_per_m: f64,
    /// pf: the follower's integral action, as the frequency below which it removes the
    /// position error (0: none), Hz. In contact it presses until the follower is as deep as
    /// the leader, so the hand feels the environment's stiffness rather than the coupling
    /// spring's in series with it. Not in pp, where the error is what the leader feels.
    pub integral_hz: f64,
    /// Largest force the coupling puts on either tip, N.
    pub max_force_n: f64,
    /// The leader's force ramps in over this time after engaging, s.
    pub ramp_s: f64,
    /// Estimated forces below this are not felt in pf (the estimate's noise), N.
    pub force_deadband_n: f64,
    /// No packet for this long and the link counts as lost, ms.
    pub link_timeout_ms: f64,
    /// On a lost link the leader's force fades to zero over this time, ms.
    pub fade_ms: f64,
    /// After a break in an engagement (a lost link, an arm down for a moment) the follower
    /// resumes from where it is and comes back to the pair's mapping at most this fast, mm/s
    /// (docs/TELEOP.md §4): a dropout never shifts the mapping.
    pub realign_mm_s: f64,
    /// When the operator counts as present: button1 (held) or always.
    pub operator: Operator,
    /// Time-domain passivity on both ports.
    pub passivity: bool,
    /// Delay-aware gains: beyond this round trip (measured on the channel) the coupling's
    /// spring is softened in proportion, so the energy its delayed springs make stays within
    /// what the arms' damping takes, ms (0: fixed gains).
    pub delay_gain_ms: f64,
    /// How the pair stays stable under delay: `auto` (wave variables, but the delay-aware
    /// gains for a pf pair of two arms of this daemon), `gains` (delay-aware gains) or `wave`
    /// (wave variables with drift compensation). Both sides must agree.
    pub delay_control: DelayControl,
    /// Wave variables: the wave impedance b, N·s/m. A stiff contact a one-way delay T away
    /// feels at most b / T in series with it; free motion drags like a mass b·T.
    pub wave_impedance_n_s_per_m: f64,
    /// Wave variables: the follower's commanded position is pulled onto the leader's
    /// (delayed) position at this rate, Hz (0: no drift compensation).
    pub wave_drift_hz: f64,
    /// Largest damping the passivity controller adds, N·s/m; 0: no cap but its own (it never
    /// takes back more than the coupling force's work, so it never pushes back). A cap lets a
    /// demand beyond it pass (the port is then not strictly passive); without one the damper
    /// switching on and off on a noisy velocity is itself felt as a vibration
    /// (docs/TELEOP.md §5).
    pub passivity_max_damping_n_s_per_m: f64,
    /// Most energy a port keeps in hand from the far side, J.
    pub passivity_reserve_j: f64,
    /// The coupling's own velocity estimate: jerk spectral density of its Kalman filter,
    /// rad²/s⁵ (far faster than `[kalman]`'s: a stiff coupling needs a velocity with little
    /// lag, or its damping comes too late and the pair oscillates).
    pub velocity_jerk_psd: f64,
    /// Delay, jitter and loss injected on what the leader receives.
    pub to_leader: Impairment,
    /// Delay, jitter and loss injected on what the follower receives.
    pub to_follower: Impairment,
}

impl Default for TeleopConfig {
    fn default() -> Self {
        TeleopConfig {
            architecture: Architecture::Pp,
            motion_scale: 1.0,
            force_scale: 1.0,
            stiffness_n_per_mm: 2.5,
            damping_n_s_per_m: 7.0,
            leader_damping_n_s_per_m: 0.0,
            integral_hz: 1.0,
            max_force_n: 3.3,
            ramp_s: 0.5,
            force_deadband_n: 0.02,
            link_timeout_ms: 25.0,
            fade_ms: 20.0,
            realign_mm_s: 100.0,
            operator: Operator::Button1,
            passivity: true,
            delay_gain_ms: 3.0,
            delay_control: DelayControl::Auto,
            wave_impedance_n_s_per_m: 10.0,
            wave_drift_hz: 3.0,
            passivity_max_damping_n_s_per_m: 10.0,
            passivity_reserve_j: 0.02,
            velocity_jerk_psd: 1e6,
            to_leader: Impairment::default(),
            to_follower: Impairment::default(),
        }
    }
}

impl TeleopConfig {
    /// These settings on a channel to another daemon's arm (`across_daemons`) or between two
    /// arms of one daemon: `delay_control = "auto"` resolved for the architecture
    /// ([`DelayControl::on_channel`]).
    pub fn on_channel(&self, across_daemons: bool) -> TeleopConfig {
        TeleopConfig {
            delay_control: self
                .delay_control
                .on_channel(across_daemons, self.architecture),
            ..self.clone()
        }
    }

    /// Check every value; the first problem names its field (`teleop.…`).
    pub fn validate(&self) -> Result<(), ConfigError> {
        self.check_delay_control()?;
        self.check_coupling()?;
        self.check_link()?;
        self.check_passivity()?;
        self.check_estimator()?;
        check_impairment("to_leader", &self.to_leader)?;
        check_impairment("to_follower", &self.to_follower)
    }

    /// The delay control's settings: the wave impedance and drift, the delay-aware gains.
    fn check_delay_control(&self) -> Result<(), ConfigError> {
        check_ranges(&[
            (
                "teleop.wave_impedance_n_s_per_m",
                self.wave_impedance_n_s_per_m,
                1.0,
                1000.0,
                "1 ..= 1000 N·s/m",
            ),
            (
                "teleop.wave_drift_hz",
                self.wave_drift_hz,
                0.0,
                20.0,
                "0 ..= 20 Hz",
            ),
            (
                "teleop.delay_gain_ms",
                self.delay_gain_ms,
                0.0,
                1000.0,
                "0 ..= 1000 ms",
            ),
        ])
    }

    /// The coupling's gains, scales and force limits.
    fn check_coupling(&self) -> Result<(), ConfigError> {
        check_ranges(&[
            (
                "teleop.leader_damping_n_s_per_m",
                self.leader_damping_n_s_per_m,
                0.0,
                100.0,
                "0 ..= 100 N·s/m",
            ),
            (
                "teleop.integral_hz",
                self.integral_hz,
                0.0,
                20.0,
                "0 ..= 20 Hz",
            ),
            (
                "teleop.motion_scale",
                self.motion_scale,
                0.05,
                20.0,
                "0.05 ..= 20",
            ),
            ("teleop.force_scale", self.force_scale, 0.0, 5.0, "0 ..= 5"),
            (
                "teleop.stiffness_n_per_mm",
                self.stiffness_n_per_mm,
                0.0,
                10.0,
                "0 ..= 10 N/mm",
            ),
            (
                "teleop.damping_n_s_per_m",
                self.damping_n_s_per_m,
                0.0,
                100.0,
                "0 ..= 100 N·s/m",
            ),
            (
                "teleop.max_force_n",
                self.max_force_n,
                0.0,
                10.0,
                "0 ..= 10 N",
            ),
            ("teleop.ramp_s", self.ramp_s, 0.0, 10.0, "0 ..= 10 s"),
            (
                "teleop.force_deadband_n",
                self.force_deadband_n,
                0.0,
                2.0,
                "0 ..= 2 N",
            ),
        ])
    }

    /// The link's watch: its timeout, the fade when it drops, the realignment when it returns.
    fn check_link(&self) -> Result<(), ConfigError> {
        check_ranges(&[
            (
                "teleop.link_timeout_ms",
                self.link_timeout_ms,
                2.0,
                1000.0,
                "2 ..= 1000 ms",
            ),
            ("teleop.fade_ms", self.fade_ms, 1.0, 1000.0, "1 ..= 1000 ms"),
            (
                "teleop.realign_mm_s",
                self.realign_mm_s,
                1.0,
                500.0,
                "1 ..= 500 mm/s",
            ),
        ])
    }

    /// The passivity ports' damper cap and energy reserve.
    fn check_passivity(&self) -> Result<(), ConfigError> {
        check_ranges(&[
            (
                "teleop.passivity_max_damping_n_s_per_m",
                self.passivity_max_damping_n_s_per_m,
                0.0,
                1000.0,
                "0 ..= 1000 N·s/m",
            ),
            (
                "teleop.passivity_reserve_j",
                self.passivity_reserve_j,
                0.0,
                1.0,
                "0 ..= 1 J",
            ),
        ])
    }

    /// The velocity estimator's process noise.
    fn check_estimator(&self) -> Result<(), ConfigError> {
        check::in_range(
            "teleop.velocity_jerk_psd",
            self.velocity_jerk_psd,
            1.0,
            1e9,
            "1 ..= 1e9 rad²/s⁵",
        )
    }
}

/// Each `(field, value, lo, hi, allowed)` in order; the first out of range is the error.
fn check_ranges(ranges: &[(&str, f64, f64, f64, &str)]) -> Result<(), ConfigError> {
    for &(field, v, lo, hi, allowed) in ranges {
        check::in_range(field, v, lo, hi, allowed)?;
    }
    Ok(())
}

/// One direction's injected channel (`teleop.{side}.…`): delay, jitter within what is left of
/// the delay's ceiling, loss.
fn check_impairment(side: &str, imp: &Impairment) -> Result<(), ConfigError> {
    let max = channel::MAX_DELAY_MS;
    check::in_range(
        &format!("teleop.{side}.delay_ms"),
        imp.delay_ms,
        0.0,
        max,
        "0 ..= 1500 ms",
    )?;
    check::in_range(
        &format!("teleop.{side}.jitter_ms"),
        imp.jitter_ms,
        0.0,
        max - imp.delay_ms,
        "0 ..= 1500 ms minus the delay",
    )?;
    check::in_range(
        &format!("teleop.{side}.loss"),
        imp.loss,
        0.0,
        1.0,
        "0 ..= 1",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_runs_waves_but_for_pf_in_one_daemon_and_a_choice_stays() {
        let cfg: TeleopConfig = toml::from_str("").unwrap();
        assert_eq!(cfg.delay_control, DelayControl::Auto);
        for (architecture, in_one, across) in [
            (Architecture::Pp, DelayControl::Wave, DelayControl::Wave),
            (Architecture::Pf, DelayControl::Gains, DelayControl::Wave),
        ] {
            let cfg = TeleopConfig {
                architecture,
                ..cfg.clone()
            };
            assert_eq!(cfg.on_channel(false).delay_control, in_one);
            assert_eq!(cfg.on_channel(true).delay_control, across);
        }
        for (text, chosen) in [("gains", DelayControl::Gains), ("wave", DelayControl::Wave)] {
            for arch in ["pp", "pf"] {
                let cfg: TeleopConfig = toml::from_str(&format!(
                    "delay_control = \"{text}\"\narchitecture = \"{arch}\""
                ))
                .unwrap();
                for across in [false, true] {
                    assert_eq!(cfg.on_channel(across).delay_control, chosen);
                }
            }
        }
        // The rest of the settings go through untouched.
        let cfg = TeleopConfig {
            stiffness_n_per_mm: 1.5,
            ..TeleopConfig::default()
        };
        assert_eq!(cfg.on_channel(true).stiffness_n_per_mm, 1.5);
    }
}

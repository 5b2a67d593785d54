//! One side of a teleoperation pair (docs/TELEOP.md §4), stepped by its arm's servo every tick:
//! its own state in, the freshest packet from the other side, the force to put on its own tip
//! out. The leader decides when the pair is engaged (operator present, clutch) and numbers each
//! engagement; each side measures motion from where it stood when it took that engagement up,
//! so engaging, re-indexing after the clutch and changing the scale never make a jump. Plain
//! data: nothing allocates after construction.

use super::channel::{packet_flags, ChannelStats, Endpoint, Packet};
use super::passivity::Port;
use super::{Architecture, DelayControl, Operator, TeleopConfig};
use nalgebra::Vector3;
use serde::Serialize;

type V3 = Vector3<f64>;

/// Which side of the pair.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// The arm a person moves.
    Leader,
    /// The arm that copies it.
    Follower,
}

/// Where a side is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TeleopState {
    /// Not following: waiting for the operator (leader), holding still (follower).
    Waiting,
    /// Following.
    Engaged,
    /// The leader's clutch is pressed: the follower holds, the leader is free.
    Clutched,
    /// No packet within the timeout, or the other side is down: the leader's force fades to
    /// zero, the follower holds; the operator engages again once the link is back.
    LinkLost,
    /// The pair is disabled: this side's arm is not coupled (fault, idle, its side ended) and
    /// it tells the other side so, or the other side said so of itself.
    Down,
}

impl TeleopState {
    /// Its name in the state stream and the results.
    pub fn as_str(self) -> &'static str {
        match self {
            TeleopState::Waiting => "waiting",
            TeleopState::Engaged => "engaged",
            TeleopState::Clutched => "clutched",
            TeleopState::LinkLost => "link_lost",
            TeleopState::Down => "down",
        }
    }
}

/// What a side knows of its own arm this tick.
#[derive(Debug, Clone, Copy)]
pub struct SideInput {
    /// Device time, s.
    pub t: f64,
    /// The tip, mm (OpenHaptics frame).
    pub tip_mm: V3,
    /// The tip's velocity, mm/s.
    pub vel_mm_s: V3,
    /// The outside's force on the tip (the arm's estimate), N.
    pub fext_n: V3,
    /// Stylus buttons 1 and 2.
    pub buttons: [bool; 2],
    /// The arm is coupled (in teleop); false: it is idle or faulted, the pair is down.
    pub active: bool,
    /// The arm acts with its full authority (the safety layer's start-up ramp after idle is
    /// over). A follower takes an engagement up only then: an arm still ramping up cannot
    /// follow, and the motion it missed was pulled in at once when it could (docs/TELEOP.md
    /// §3). The leader needs none: its force ramps in anyway, and the follower copies the
    /// motion its ramp makes (what keeps a pair `--align`ed).
    pub ready: bool,
}

/// A link that came back counts as up again after this long (operator `always`), s.
const REARM_S: f64 = 0.5;

/// One side of the pair.
pub struct Coupling {
    role: Role,
    cfg: TeleopConfig,
    endpoint: Endpoint,
    port: Port,
    dt: f64,
    seq: u64,
    state: TeleopState,
    /// The freshest packet from the other side, and when (local time) it was delivered.
    peer: Option<Packet>,
    peer_at: f64,
    /// Since when the link has been up without a break, s.
    up_since: f64,
    /// Leader: the engagement number (0: never engaged). Follower: the one taken up.
    epoch: u32,
    /// Where this side's motion is measured from, mm.
    origin_mm: V3,
    /// Leader: when it engaged (the force's ramp); its scaled motion held while clutched.
    engaged_at: f64,
    held_mm: V3,
    /// Leader: button 1 a tick ago (an engage after a lost link needs a fresh press).
    button_was: bool,
    fresh_press_needed: bool,
    /// Follower: where it holds while not following, mm.
    hold_mm: V3,
    holding: bool,
    /// Follower (pf): the integral action's force, N.
    integral_n: V3,
    /// The last force put out, N; a fade's start and time.
    force: V3,
    fade_from: V3,
    fade_at: f64,
    /// The last own tip (a scale change re-measures from it).
    last_tip: V3,
    /// The `t` of the newest packet from the other side (echoed back in ours), s.
    peer_t: f64,
    /// The round trip as measured from the echoes, s: up at once, down over a second.
    rtt_s: f64,
    /// A packet from the other side was delivered this tick.
    got_packet: bool,
    /// Leader: when the last packet of this engagement arrived (local time), and the force
    /// put out on that tick, N: through a silence the force never exceeds it (§4).
    matched_at: f64,
    matched_force_n: f64,
    /// Leader: the fraction of that force a silence left on the last tick (1: none).
    silence_left: f64,
    /// Leader: the next engagement resumes this one's mapping (it ended on a lost link).
    resume: bool,
    /// Follower: how far its target stands off the engagement's mapping after a break, mm;
    /// brought back to zero at `realign_mm_s` (docs/TELEOP.md §4).
    offset_mm: V3,
    /// Follower, wave variables: the commanded position the waves integrate to, in the
    /// mapping's frame (the leader's scaled motion), mm (docs/TELEOP.md §5).
    wave_x_mm: V3,
    /// Wave variables: the wave from the other side, low-passed (docs/TELEOP.md §5).
    wave_in: V3,
    /// Leader, wave variables: its own velocity through the same low-pass, mm/s.
    wave_v: V3,
}

/// Wave variables: the received wave is low-passed at this frequency, Hz. A filter of gain at
/// most 1 on a wave keeps the channel passive; without it every tick's reflection between the
/// two ends rang at the sample rate on the arms' noisy velocities.
pub const WAVE_FILTER_HZ: f64 = 20.0;

/// Leader: through a silence shorter than this the force is held at most at its value on the
/// last packet; beyond it that bound falls linearly to zero at the link timeout, s.
pub const SILENCE_HOLD_S: f64 = 0.005;

/// pf: beyond this round trip the passivity damping cap falls inversely with it, s
/// ([`Coupling::damping_cap`]).
pub const PF_LONG_RTT_S: f64 = 0.5;

/// The measured round trip comes down over this time constant, s (it goes up at once).
const RTT_FALL_S: f64 = 1.0;

impl Coupling {
    /// A side in `role` over `endpoint`, stepped every `dt` s.
    pub fn new(role: Role, cfg: &TeleopConfig, mut endpoint: Endpoint, dt: f64) -> Coupling {
        // Wave variables stay passive only under a constant delay: a playout buffer makes a
        // jittery one constant (docs/TELEOP.md §5).
        endpoint.set_playout(cfg.delay_control == DelayControl::Wave);
        Coupling {
            role,
            cfg: cfg.clone(),
            endpoint,
            port: Port::new(
                cfg.passivity_reserve_j,
                cfg.passivity_max_damping_n_s_per_m,
                cfg.passivity,
            ),
            dt,
            seq: 0,
            state: TeleopState::Waiting,
            peer: None,
            peer_at: f64::NEG_INFINITY,
            up_since: f64::INFINITY,
            epoch: 0,
            origin_mm: V3::zeros(),
            engaged_at: 0.0,
            held_mm: V3::zeros(),
            button_was: false,
            fresh_press_needed: false,
            hold_mm: V3::zeros(),
            holding: false,
            integral_n: V3::zeros(),
            force: V3::zeros(),
            fade_from: V3::zeros(),
            fade_at: f64::NEG_INFINITY,
            last_tip: V3::zeros(),
            peer_t: 0.0,
            rtt_s: 0.0,
            got_packet: false,
            matched_at: f64::NEG_INFINITY,
            matched_force_n: 0.0,
            silence_left: 1.0,
            resume: false,
            offset_mm: V3::zeros(),
            wave_x_mm: V3::zeros(),
            wave_in: V3::zeros(),
            wave_v: V3::zeros(),
        }
    }

    /// Which side this is.
    pub fn role(&self) -> Role {
        self.role
    }

    /// Where this side is.
    pub fn state(&self) -> TeleopState {
        self.state
    }

    /// The force put on this side's tip on the last tick, N.
    pub fn force(&self) -> V3 {
        self.force
    }

    /// The engagement this side is in or has taken up (0: none yet).
    pub fn epoch(&self) -> u32 {
        self.epoch
    }

    /// This side's passivity port (energies in, out and dissipated).
    pub fn port(&self) -> &Port {
        &self.port
    }

    /// The round trip this side measures from the echoes of its packets, s (0 before any).
    pub fn round_trip_s(&self) -> f64 {
        self.rtt_s
    }

    /// What the coupling's stiffness is scaled by now: 1 up to a round trip of
    /// `delay_gain_ms`, then inversely with the round trip (docs/TELEOP.md §5).
    pub fn delay_gain(&self) -> f64 {
        let tau = self.cfg.delay_gain_ms * 1e-3;
        if self.wave() {
            // The wave channel is passive for any delay: the springs are local and keep
            // their stiffness.
            1.0
        } else if tau > 0.0 && self.rtt_s > tau {
            tau / self.rtt_s
        } else {
            1.0
        }
    }

    /// The passivity controller's damping cap now, N·s/m (0: no cap): `[teleop]
    /// passivity_max_damping_n_s_per_m`, and in position–force that times 1 + tick / round
    /// trip (the round trip taken as at least a tick) and, beyond a round trip of
    /// [`PF_LONG_RTT_S`], times that over the round trip: twice the cap in one process, the
    /// cap itself from some 10 ms to 500 ms, half of it at 1 s (docs/TELEOP.md §5). In pf the
    /// leader displays the floor through the estimate's lag, which at a stiff floor makes
    /// energy faster than 10 N·s/m takes back (a 2 N press into 2 N/mm oscillated); at a long
    /// round trip the leader's port has no budget for what arrives and its damper, switching
    /// with the velocity's sign, is itself felt (the let-go at 1 s). In pp the higher cap is
    /// itself felt in a stiff press, and the configured one is quiet everywhere. Under wave
    /// variables, in both architectures, only the fall beyond [`PF_LONG_RTT_S`]: the wave
    /// channel itself is passive, and what the ports take back is the drift compensation's
    /// energy, which at a 1 s round trip kept their dampers switching at the cap (a 2 N press
    /// into 0.5 N/mm: 0.16 N above 20 Hz at 10, 0.08 N at 5).
    pub fn damping_cap(&self) -> f64 {
        let cap = self.cfg.passivity_max_damping_n_s_per_m;
        let rtt = self.rtt_s.max(self.dt);
        let long = (PF_LONG_RTT_S / rtt).min(1.0);
        if cap <= 0.0 {
            cap
        } else if self.wave() {
            cap * long
        } else if self.cfg.architecture == Architecture::Pf {
            cap * (1.0 + self.dt / rtt) * long
        } else {
            cap
        }
    }

    /// The pair runs wave variables (docs/TELEOP.md §5).
    fn wave(&self) -> bool {
        self.cfg.delay_control == DelayControl::Wave
    }

    /// This side's channel counters.
    pub fn channel(&self) -> ChannelStats {
        self.endpoint.stats()
    }

    /// The settings in force.
    pub fn config(&self) -> &TeleopConfig {
        &self.cfg
    }

    /// Change the motion scale now without a jump: the leader re-measures its motion so the
    /// follower's target stays where it is.
    pub fn set_motion_scale(&mut self, scale: f64) {
        if !(scale.is_finite() && scale > 0.0) {
            return;
        }
        let mapped = self.state == TeleopState::Engaged
            || (self.state == TeleopState::LinkLost && self.resume);
        if self.role == Role::Leader && mapped {
            let d = (self.last_tip - self.origin_mm) * self.cfg.motion_scale;
            self.origin_mm = self.last_tip - d / scale;
        }
        self.cfg.motion_scale = scale;
    }

    /// Change the force scale (applies from the next tick; the leader's force is continuous
    /// in it only as the force itself is, so callers change it in small steps or at rest).
    pub fn set_force_scale(&mut self, scale: f64) {
        if scale.is_finite() && scale >= 0.0 {
            self.cfg.force_scale = scale;
        }
    }

    /// Change the impairment injected on what this side receives.
    pub fn set_impairment(&mut self, impairment: super::Impairment) {
        self.endpoint.set_impairment(impairment);
    }

    /// One tick: the force to put on this side's tip, N (zero when not active).
    pub fn step(&mut self, x: &SideInput) -> V3 {
        self.got_packet = false;
        if let Some(p) = self.endpoint.receive(x.t) {
            self.got_packet = true;
            if self.peer_at < x.t - self.cfg.link_timeout_ms * 1e-3 || self.peer.is_none() {
                self.up_since = x.t;
            }
            self.peer_t = p.t;
            if p.echo_t > 0.0 && p.echo_t <= x.t {
                let sample = x.t - p.echo_t;
                self.rtt_s = if sample > self.rtt_s {
                    sample
                } else {
                    self.rtt_s + (sample - self.rtt_s) * (self.dt / RTT_FALL_S).min(1.0)
                };
            }
            self.peer = Some(p);
            self.peer_at = x.t;
        }
        let fresh = x.t - self.peer_at <= self.cfg.link_timeout_ms * 1e-3;
        let peer_down = self.peer.is_some_and(|p| p.flags & packet_flags::DOWN != 0);
        let link_up = fresh && !peer_down;
        if !link_up {
            self.up_since = f64::INFINITY;
        }
        self.last_tip = x.tip_mm;
        let force = if !x.active {
            self.down(x)
        } else {
            match self.role {
                Role::Leader => self.lead(x, link_up, peer_down),
                Role::Follower => self.follow(x, link_up, peer_down),
            }
        };
        self.force = force;
        force
    }

    /// What this side echoes at local time `t`: the `t` of the newest packet it has received
    /// plus how long it has held it (0 before any). The other side's round trip is then the
    /// channel's alone: a side that heard nothing for a while (a dropout, a stalled peer) does
    /// not make the next echo read as a round trip that long, which would soften the springs
    /// for seconds after every dropout (docs/TELEOP.md §5).
    fn echo(&self, t: f64) -> f64 {
        if self.peer.is_some() {
            self.peer_t + (t - self.peer_at).max(0.0)
        } else {
            0.0
        }
    }

    /// This side ends (its coupling is being taken off the arm), at local time `t` (the clock
    /// [`SideInput::t`] runs on): it tells the other side it is down, so the other daemon
    /// disables the pair at once rather than after the link timeout (docs/TELEOP.md §4). Sent
    /// three times, so one lost packet does not hide it.
    pub fn end(&mut self, t: f64) {
        self.state = TeleopState::Down;
        for _ in 0..3 {
            self.seq += 1;
            self.endpoint.send(Packet {
                seq: self.seq,
                t,
                engage: 0,
                flags: packet_flags::DOWN,
                energy_in_j: self.port.energy_in,
                echo_t: self.echo(t),
                ..Packet::default()
            });
        }
    }

    /// Not coupled: say so every tick, put out nothing.
    fn down(&mut self, x: &SideInput) -> V3 {
        self.state = TeleopState::Down;
        self.holding = false;
        self.resume = false;
        self.send(x, 0, packet_flags::DOWN, V3::zeros(), V3::zeros());
        V3::zeros()
    }

    /// Leader: its engagement and clutch this tick, the packet it sends and the force on its
    /// tip.
    fn lead(&mut self, x: &SideInput, link_up: bool, peer_down: bool) -> V3 {
        self.lead_engagement(x, link_up, peer_down);
        self.lead_clutch(x);
        let (d, dv, engage, flags) = self.lead_motion(x);
        if !self.wave() {
            self.send(x, engage, flags, d, dv);
            return self.lead_force(x, link_up, d, dv);
        }
        self.lead_wave(x, link_up, d, dv, engage, flags)
    }

    /// Leader: engage, fade out or go down as the operator, the link and the other side say.
    fn lead_engagement(&mut self, x: &SideInput, link_up: bool, peer_down: bool) {
        let present = match self.cfg.operator {
            Operator::Button1 => x.buttons[0],
            Operator::Always => true,
        };
        let pressed_now = x.buttons[0] && !self.button_was;
        self.button_was = x.buttons[0];
        let following = matches!(self.state, TeleopState::Engaged | TeleopState::Clutched);
        if following && peer_down {
            // The other side ended or faulted: a later engagement is a new one.
            self.fade(x.t, TeleopState::Down);
            self.resume = false;
        } else if following && !link_up {
            // A lost link is no re-index: the next engagement resumes this mapping (§4); a
            // clutch pressed now counts as released here.
            if self.state == TeleopState::Clutched {
                self.origin_mm = x.tip_mm - self.held_mm / self.cfg.motion_scale;
            }
            self.fade(x.t, TeleopState::LinkLost);
            self.fresh_press_needed = true;
            self.resume = true;
        } else if following && !present {
            self.fade(x.t, TeleopState::Waiting);
            self.resume = false;
        } else if !following && link_up && present {
            let may = match self.cfg.operator {
                Operator::Button1 => !self.fresh_press_needed || pressed_now,
                // A resumed engagement keeps the mapping (the follower comes back to it at a
                // bounded speed), so it need not wait for the link to prove itself.
                Operator::Always => {
                    x.t - self.up_since >= REARM_S || self.epoch == 0 || self.resume
                }
            };
            if may {
                self.engage(x);
            }
        }
        if peer_down && !matches!(self.state, TeleopState::Engaged | TeleopState::Clutched) {
            self.state = TeleopState::Down;
        } else if self.state == TeleopState::Down && !peer_down {
            self.state = if link_up {
                TeleopState::Waiting
            } else {
                TeleopState::LinkLost
            };
        }
    }

    /// Leader: a new engagement (a new epoch and origin), or the resumed one after a lost link.
    fn engage(&mut self, x: &SideInput) {
        if !(self.resume && self.epoch != 0) {
            self.epoch += 1;
            self.origin_mm = x.tip_mm;
        }
        self.resume = false;
        // No packet of this engagement yet: no force until one (see `lead_force`), then the
        // ramp from the engagement on.
        self.matched_at = f64::NEG_INFINITY;
        self.matched_force_n = 0.0;
        self.silence_left = 1.0;
        self.held_mm = V3::zeros();
        self.engaged_at = x.t;
        self.fresh_press_needed = false;
        self.state = TeleopState::Engaged;
    }

    /// Leader: the clutch holds the scaled motion where it is, and on release measures again
    /// from where the leader is so the follower does not jump.
    fn lead_clutch(&mut self, x: &SideInput) {
        let clutch = x.buttons[1];
        let s = self.cfg.motion_scale;
        match self.state {
            TeleopState::Engaged if clutch => {
                self.held_mm = (x.tip_mm - self.origin_mm) * s;
                self.fade(x.t, TeleopState::Clutched);
            }
            TeleopState::Clutched if !clutch => {
                self.origin_mm = x.tip_mm - self.held_mm / s;
                self.state = TeleopState::Engaged;
                self.engaged_at = x.t;
            }
            _ => {}
        }
    }

    /// Leader: the scaled motion `d` and velocity `dv` it sends, with the engagement and flags.
    fn lead_motion(&self, x: &SideInput) -> (V3, V3, u32, u32) {
        let s = self.cfg.motion_scale;
        match self.state {
            TeleopState::Engaged => (
                (x.tip_mm - self.origin_mm) * s,
                x.vel_mm_s * s,
                self.epoch,
                0,
            ),
            TeleopState::Clutched => (self.held_mm, V3::zeros(), self.epoch, packet_flags::CLUTCH),
            _ => (V3::zeros(), V3::zeros(), 0, 0),
        }
    }

    /// Leader under wave variables: the force on its tip, and the wave it sends.
    fn lead_wave(
        &mut self,
        x: &SideInput,
        link_up: bool,
        d: V3,
        dv: V3,
        engage: u32,
        flags: u32,
    ) -> V3 {
        // The wave impedance is a damper on this side's velocity: on the coupling's fast,
        // noisy velocity it was felt as a buzz, so it acts on the velocity low-passed like
        // the waves (what the port relation below is kept on).
        let a = self.dt * std::f64::consts::TAU * WAVE_FILTER_HZ;
        self.wave_v += (dv - self.wave_v) * (a / (1.0 + a));
        let dv = self.wave_v;
        // Wave variables: the wave out is made of this tick's velocity and the force
        // actually put on the arm (clamps, ramp and fades included), so what leaves the port
        // is what entered it (docs/TELEOP.md §5).
        let f = self.lead_force(x, link_up, d, dv);
        let b = self.cfg.wave_impedance_n_s_per_m;
        let u = if engage != 0 && flags == 0 {
            let fs = self.cfg.force_scale;
            let f_in = if fs > 1e-9 { -f / fs } else { V3::zeros() };
            (dv * 1e-3 * b + f_in) / (2.0 * b).sqrt()
        } else {
            V3::zeros()
        };
        self.send(x, engage, flags, d, u);
        f
    }

    /// Leader: the force on its tip this tick, given its scaled motion `d` and velocity `dv`.
    fn lead_force(&mut self, x: &SideInput, link_up: bool, d: V3, dv: V3) -> V3 {
        let peer = self
            .peer
            .filter(|p| p.engage == self.epoch && self.epoch != 0);
        if self.state != TeleopState::Engaged || !link_up {
            // A fade never outlasts a silence's bound either.
            let bound = self.matched_force_n * self.silence_factor(x.t);
            return crate::haptics::limit_force(&self.faded(x.t), bound);
        }
        // A packet of this engagement this tick: the force follows it. Without one (a silence,
        // or the follower not in this engagement) it never grows: at most what it was on the
        // last such packet, then less, to nothing at the link timeout (docs/TELEOP.md §4).
        let fresh = self.got_packet && peer.is_some();
        // What scales the force as packets come back after a silence took some away: it rises
        // back at the slope it fell, so nothing steps and the two sides' springs are unequal
        // for no longer than the silence's fall (a slow ramp here, with the follower pulled at
        // full stiffness, set the pair oscillating).
        let mut back = 1.0;
        if fresh {
            self.matched_at = x.t;
            if self.silence_left < 1.0 {
                let span = self.cfg.link_timeout_ms * 1e-3 - SILENCE_HOLD_S;
                self.silence_left = (self.silence_left + self.dt / span.max(self.dt)).min(1.0);
                back = self.silence_left;
            }
        } else if self.matched_at.is_finite() {
            self.silence_left = self.silence_factor(x.t).min(self.silence_left);
        }
        let f = match peer {
            Some(p) => {
                let k = self.cfg.stiffness_n_per_mm * self.delay_gain();
                let raw = match self.cfg.architecture {
                    _ if self.wave() => {
                        // The follower's wave back, less the wave impedance's damping on
                        // this side's own velocity (docs/TELEOP.md §5).
                        let b = self.cfg.wave_impedance_n_s_per_m;
                        let w = self.wave_filter(V3::from(p.vel_mm_s));
                        (w * (2.0 * b).sqrt() - dv * (b * 1e-3)) * self.cfg.force_scale
                    }
                    Architecture::Pp => {
                        let e = V3::from(p.pos_mm) - d;
                        let ev = V3::from(p.vel_mm_s) - dv;
                        (e * k + ev * (self.cfg.leader_damping_n_s_per_m * 1e-3))
                            * self.cfg.force_scale
                    }
                    Architecture::Pf => {
                        let f = V3::from(p.force_n);
                        let n = f.norm();
                        let db = self.cfg.force_deadband_n;
                        let felt = if n > db {
                            f * ((n - db) / n)
                        } else {
                            V3::zeros()
                        };
                        felt * self.cfg.force_scale
                    }
                };
                let ramp = if self.cfg.ramp_s > 0.0 {
                    ((x.t - self.engaged_at) / self.cfg.ramp_s).clamp(0.0, 1.0)
                } else {
                    1.0
                };
                let f = crate::haptics::limit_force(&(raw * ramp), self.cfg.max_force_n);
                let f = if fresh {
                    f * back
                } else {
                    crate::haptics::limit_force(&f, self.matched_force_n * self.silence_left)
                };
                // (The port only takes force away along the velocity: the bound holds.)
                self.passive(f, x, p.energy_in_j)
            }
            None => {
                crate::haptics::limit_force(&self.force, self.matched_force_n * self.silence_left)
            }
        };
        if fresh {
            self.matched_force_n = f.norm();
        }
        f
    }

    fn follow(&mut self, x: &SideInput, link_up: bool, peer_down: bool) -> V3 {
        // An arm still ramping up holds: it takes the engagement up (or back) once it can
        // follow (docs/TELEOP.md §3).
        let leader = self
            .peer
            .filter(|p| link_up && x.ready && p.engage != 0 && p.flags & packet_flags::DOWN == 0);
        match leader {
            Some(p) => {
                let here = x.tip_mm - V3::from(p.pos_mm);
                if p.engage != self.epoch {
                    // Take a new engagement up from where this arm is: its target starts here.
                    self.epoch = p.engage;
                    self.origin_mm = here;
                    self.offset_mm = V3::zeros();
                    self.integral_n = V3::zeros();
                    self.wave_x_mm = V3::from(p.pos_mm);
                    self.wave_in = V3::zeros();
                } else if !matches!(self.state, TeleopState::Engaged | TeleopState::Clutched) {
                    // The same engagement after a break (a lost link, this arm down): its
                    // mapping is kept. The target starts where the arm is and comes back to
                    // the mapping at a bounded speed (docs/TELEOP.md §4).
                    self.offset_mm = here - self.origin_mm;
                    self.integral_n = V3::zeros();
                    self.wave_x_mm = V3::from(p.pos_mm);
                    self.wave_in = V3::zeros();
                } else if p.flags & packet_flags::CLUTCH == 0 {
                    let n = self.offset_mm.norm();
                    let step = self.cfg.realign_mm_s * self.dt;
                    self.offset_mm = if n <= step {
                        V3::zeros()
                    } else {
                        self.offset_mm * (1.0 - step / n)
                    };
                }
                self.state = if p.flags & packet_flags::CLUTCH != 0 {
                    TeleopState::Clutched
                } else {
                    TeleopState::Engaged
                };
                self.holding = false;
            }
            None => {
                if !self.holding {
                    self.hold_mm = x.tip_mm;
                    self.holding = true;
                    self.integral_n = V3::zeros();
                }
                self.state = if peer_down {
                    TeleopState::Down
                } else if link_up || self.peer.is_none() {
                    TeleopState::Waiting
                } else {
                    TeleopState::LinkLost
                };
            }
        }
        let origin = self.origin_mm + self.offset_mm;
        let own = x.tip_mm - origin;
        let engage = if self.holding { 0 } else { self.epoch };
        if self.wave() {
            if let Some(p) = leader {
                return self.follow_wave(x, &p, origin, own);
            }
        }
        self.send(x, engage, 0, own, x.vel_mm_s);
        let (target, target_v) = match leader {
            Some(p) => (origin + V3::from(p.pos_mm), V3::from(p.vel_mm_s)),
            None => (self.hold_mm, V3::zeros()),
        };
        // Under delay the spring is softened (docs/TELEOP.md §5); holding is the arm's own.
        let k = if leader.is_some() {
            self.cfg.stiffness_n_per_mm * self.delay_gain()
        } else {
            self.cfg.stiffness_n_per_mm
        };
        if leader.is_some() && self.cfg.architecture == Architecture::Pf {
            // Bounded, so a follower held off its target cannot wind up a push.
            let ki = k * std::f64::consts::TAU * self.cfg.integral_hz;
            let i = self.integral_n + (target - x.tip_mm) * (ki * self.dt);
            self.integral_n = crate::haptics::limit_force(&i, 0.5 * self.cfg.max_force_n);
        }
        let pull = (target - x.tip_mm) * k
            + (target_v - x.vel_mm_s) * (self.cfg.damping_n_s_per_m * 1e-3)
            + self.integral_n;
        let f = crate::haptics::limit_force(&pull, self.cfg.max_force_n);
        match leader {
            Some(p) => self.passive(f, x, p.energy_in_j),
            // Holding is this arm's own spring, not the channel's: no passivity accounting.
            None => f,
        }
    }

    /// Follower, wave variables (docs/TELEOP.md §5): the leader's wave `p.vel_mm_s` and this
    /// arm's spring-damper (and pf's integral action) to a commanded position give the
    /// commanded velocity; the drift compensation pulls the commanded position onto the
    /// leader's delayed position `p.pos_mm`; the wave back is made of the commanded velocity
    /// and the force actually put on the arm.
    fn follow_wave(&mut self, x: &SideInput, p: &Packet, origin: V3, own: V3) -> V3 {
        let b = self.cfg.wave_impedance_n_s_per_m;
        let k = self.cfg.stiffness_n_per_mm * 1e3;
        let c = self.cfg.damping_n_s_per_m;
        let dt = self.dt;
        let v = x.vel_mm_s * 1e-3;
        let clutch = p.flags & packet_flags::CLUTCH != 0;
        let integral = if self.cfg.architecture == Architecture::Pf && !clutch {
            self.integral_n
        } else {
            V3::zeros()
        };
        // The force is k (e0 + ẋd dt) + c (ẋd − v) + i and the wave gives ẋd = (√(2b) u − F) / b:
        // solved for ẋd in closed form (no iteration).
        let e0 = (origin + self.wave_x_mm - x.tip_mm) * 1e-3;
        let u = self.wave_filter(V3::from(p.vel_mm_s));
        let mut xd_dot = (u * (2.0 * b).sqrt() - e0 * k + v * c - integral) / (b + k * dt + c);
        let lambda = std::f64::consts::TAU * self.cfg.wave_drift_hz;
        xd_dot += (V3::from(p.pos_mm) - self.wave_x_mm) * (1e-3 * lambda);
        self.wave_x_mm += xd_dot * (1e3 * dt);
        let target = origin + self.wave_x_mm;
        let pull = (target - x.tip_mm) * (k * 1e-3) + (xd_dot - v) * c + integral;
        if self.cfg.architecture == Architecture::Pf && !clutch {
            let ki = k * 1e-3 * std::f64::consts::TAU * self.cfg.integral_hz;
            let i = self.integral_n + (target - x.tip_mm) * (ki * dt);
            self.integral_n = crate::haptics::limit_force(&i, 0.5 * self.cfg.max_force_n);
        }
        let f = crate::haptics::limit_force(&pull, self.cfg.max_force_n);
        let f = self.passive(f, x, p.energy_in_j);
        let wave_back = (xd_dot * b - f) / (2.0 * b).sqrt();
        self.send(x, self.epoch, 0, own, wave_back);
        f
    }

    /// The received wave `w` through the low-pass of [`WAVE_FILTER_HZ`].
    fn wave_filter(&mut self, w: V3) -> V3 {
        let a = self.dt * std::f64::consts::TAU * WAVE_FILTER_HZ;
        self.wave_in += (w - self.wave_in) * (a / (1.0 + a));
        self.wave_in
    }

    /// Leader: the fraction of the force at the last packet of the engagement that a silence
    /// lets through at `t`: all of it for [`SILENCE_HOLD_S`], then linearly less, none from
    /// `link_timeout_ms` on.
    fn silence_factor(&self, t: f64) -> f64 {
        let silence = t - self.matched_at;
        let span = self.cfg.link_timeout_ms * 1e-3 - SILENCE_HOLD_S;
        if silence <= SILENCE_HOLD_S {
            1.0
        } else if span > 0.0 {
            (1.0 - (silence - SILENCE_HOLD_S) / span).clamp(0.0, 1.0)
        } else {
            0.0
        }
    }

    /// The force through this side's passivity port.
    fn passive(&mut self, f: V3, x: &SideInput, remote_in: f64) -> V3 {
        let cap = self.damping_cap();
        self.port.set_max_damping(cap);
        self.port.pass(f, &(x.vel_mm_s * 1e-3), self.dt, remote_in)
    }

    /// Leave following for `to`, the force fading from where it is.
    fn fade(&mut self, t: f64, to: TeleopState) {
        self.fade_from = self.force;
        self.fade_at = t;
        self.state = to;
    }

    /// The fading force at `t`: linear to zero over `fade_ms`.
    fn faded(&self, t: f64) -> V3 {
        let k = 1.0 - (t - self.fade_at) / (self.cfg.fade_ms * 1e-3);
        self.fade_from * k.clamp(0.0, 1.0)
    }

    fn send(&mut self, x: &SideInput, engage: u32, flags: u32, pos: V3, vel: V3) {
        self.seq += 1;
        self.endpoint.send(Packet {
            seq: self.seq,
            t: x.t,
            engage,
            flags,
            pos_mm: pos.into(),
            vel_mm_s: vel.into(),
            force_n: x.fext_n.into(),
            energy_in_j: self.port.energy_in,
            echo_t: self.echo(x.t),
        });
    }
}

#[cfg(test)]
mod tests {
    use super::super::{pair, Impairment};
    use super::*;

    const DT: f64 = 1e-3;

    fn sides(cfg: &TeleopConfig) -> (Coupling, Coupling) {
        let (l, f) = pair(Impairment::default(), Impairment::default(), 3);
        (
            Coupling::new(Role::Leader, cfg, l, DT),
            Coupling::new(Role::Follower, cfg, f, DT),
        )
    }

    fn input(t: f64, tip: [f64; 3]) -> SideInput {
        SideInput {
            t,
            tip_mm: tip.into(),
            vel_mm_s: V3::zeros(),
            fext_n: V3::zeros(),
            buttons: [false; 2],
            active: true,
            ready: true,
        }
    }

    fn always() -> TeleopConfig {
        TeleopConfig {
            operator: Operator::Always,
            ramp_s: 0.0,
            passivity: false,
            ..TeleopConfig::default()
        }
    }

    /// Step the pair `n` ticks from tick `k0` with the leader at `l` and the follower at `f`.
    fn run(
        pair: &mut (Coupling, Coupling),
        k0: usize,
        n: usize,
        l: SideInput,
        f: SideInput,
    ) -> (V3, V3) {
        let mut out = (V3::zeros(), V3::zeros());
        for k in k0..k0 + n {
            let t = k as f64 * DT;
            out.0 = pair.0.step(&SideInput { t, ..l });
            out.1 = pair.1.step(&SideInput { t, ..f });
        }
        out
    }

    #[test]
    fn engaging_starts_from_where_each_arm_is_and_then_the_follower_is_pulled_along() {
        let cfg = always();
        let mut p = sides(&cfg);
        let (lf, ff) = run(
            &mut p,
            0,
            20,
            input(0.0, [10.0, 0.0, 0.0]),
            input(0.0, [-5.0, 3.0, 0.0]),
        );
        assert_eq!(
            (p.0.state(), p.1.state()),
            (TeleopState::Engaged, TeleopState::Engaged)
        );
        assert!(lf.norm() < 1e-12 && ff.norm() < 1e-12, "{lf:?} {ff:?}");
        // The leader moves 1 mm along x: the follower is pulled 1 mm's worth, the leader held
        // back as much (position–position), the follower not having moved yet.
        let (lf, ff) = run(
            &mut p,
            20,
            3,
            input(0.0, [11.0, 0.0, 0.0]),
            input(0.0, [-5.0, 3.0, 0.0]),
        );
        let k = cfg.stiffness_n_per_mm;
        assert!((ff - V3::new(k, 0.0, 0.0)).norm() < 1e-9, "{ff:?}");
        assert!((lf - V3::new(-k, 0.0, 0.0)).norm() < 1e-9, "{lf:?}");
    }

    /// Issue #42: a follower that entered teleop from idle rested on its stops while its
    /// authority ramped up, and the leader's motion meanwhile was pulled in at once when it
    /// could (up to 25 mm, the arm rushing at 0.5 m/s). A follower still ramping up does not
    /// take the engagement up; it takes it up where it then stands.
    #[test]
    fn a_follower_still_ramping_up_takes_the_engagement_up_only_once_it_can_follow() {
        let cfg = always();
        let ramping = |tip: [f64; 3]| SideInput {
            ready: false,
            ..input(0.0, tip)
        };
        // The follower ramping up: the leader engages, the follower holds and the leader's
        // motion puts no force on either.
        let mut p = sides(&cfg);
        let (lf, ff) = run(
            &mut p,
            0,
            40,
            input(0.0, [10.0, 0.0, 0.0]),
            ramping([-5.0, 3.0, 0.0]),
        );
        assert_eq!(p.0.state(), TeleopState::Engaged);
        assert_eq!(p.1.state(), TeleopState::Waiting);
        let (lf2, ff2) = run(
            &mut p,
            40,
            40,
            input(0.0, [30.0, 0.0, 0.0]),
            ramping([-5.0, 3.0, 0.0]),
        );
        for f in [lf, ff, lf2, ff2] {
            assert!(f.norm() < 1e-12, "{f:?}");
        }
        // Ready: it takes the engagement up where it stands (no pull), then follows.
        let (_, ff) = run(
            &mut p,
            80,
            5,
            input(0.0, [30.0, 0.0, 0.0]),
            input(0.0, [-5.0, 3.0, 0.0]),
        );
        assert_eq!(p.1.state(), TeleopState::Engaged);
        assert!(ff.norm() < 1e-12, "{ff:?}");
        let (_, ff) = run(
            &mut p,
            85,
            3,
            input(0.0, [31.0, 0.0, 0.0]),
            input(0.0, [-5.0, 3.0, 0.0]),
        );
        let k = cfg.stiffness_n_per_mm;
        assert!((ff - V3::new(k, 0.0, 0.0)).norm() < 1e-9, "{ff:?}");
    }

    #[test]
    fn the_clutch_holds_the_follower_frees_the_leader_and_re_indexes_on_release() {
        let cfg = always();
        let mut p = sides(&cfg);
        run(
            &mut p,
            0,
            10,
            input(0.0, [0.0; 3]),
            input(0.0, [50.0, 0.0, 0.0]),
        );
        // The leader moves 2 mm; the follower gets there.
        run(
            &mut p,
            10,
            10,
            input(0.0, [2.0, 0.0, 0.0]),
            input(0.0, [52.0, 0.0, 0.0]),
        );
        // Clutch pressed at 2, then the leader goes back 5 mm; the follower's target stays
        // at 52.
        let press = SideInput {
            buttons: [false, true],
            ..input(0.0, [2.0, 0.0, 0.0])
        };
        run(&mut p, 20, 1, press, input(0.0, [52.0, 0.0, 0.0]));
        let clutched = SideInput {
            buttons: [false, true],
            ..input(0.0, [-3.0, 0.0, 0.0])
        };
        let (lf, ff) = run(&mut p, 21, 99, clutched, input(0.0, [52.0, 0.0, 0.0]));
        assert_eq!(p.0.state(), TeleopState::Clutched);
        assert_eq!(p.1.state(), TeleopState::Clutched);
        assert!(lf.norm() < 1e-12, "leader not freed: {lf:?}");
        assert!(ff.norm() < 1e-9, "follower pulled while clutched: {ff:?}");
        // Released at −3: from there, +1 mm of the leader is +1 mm of target (53).
        run(
            &mut p,
            120,
            5,
            input(0.0, [-3.0, 0.0, 0.0]),
            input(0.0, [52.0, 0.0, 0.0]),
        );
        let (_, ff) = run(
            &mut p,
            125,
            3,
            input(0.0, [-2.0, 0.0, 0.0]),
            input(0.0, [52.0, 0.0, 0.0]),
        );
        assert!((ff[0] - cfg.stiffness_n_per_mm).abs() < 1e-9, "{ff:?}");
    }

    #[test]
    fn a_motion_scale_change_moves_no_target_and_scales_what_follows() {
        let cfg = always();
        let mut p = sides(&cfg);
        run(&mut p, 0, 10, input(0.0, [0.0; 3]), input(0.0, [0.0; 3]));
        run(
            &mut p,
            10,
            10,
            input(0.0, [0.0, 4.0, 0.0]),
            input(0.0, [0.0, 4.0, 0.0]),
        );
        p.0.set_motion_scale(0.5);
        let (_, ff) = run(
            &mut p,
            20,
            5,
            input(0.0, [0.0, 4.0, 0.0]),
            input(0.0, [0.0, 4.0, 0.0]),
        );
        assert!(
            ff.norm() < 1e-9,
            "the scale change moved the target: {ff:?}"
        );
        // 2 mm of the leader at scale 0.5 is 1 mm of the follower.
        let (_, ff) = run(
            &mut p,
            25,
            3,
            input(0.0, [0.0, 6.0, 0.0]),
            input(0.0, [0.0, 4.0, 0.0]),
        );
        assert!((ff[1] - cfg.stiffness_n_per_mm).abs() < 1e-9, "{ff:?}");
    }

    #[test]
    fn a_cut_link_fades_the_leader_within_50_ms_without_a_step_and_the_follower_holds() {
        for arch in [Architecture::Pf, Architecture::Pp] {
            let cfg = TeleopConfig {
                architecture: arch,
                ..always()
            };
            let mut p = sides(&cfg);
            // Pressing: the follower feels 1 N from outside and lags 0.3 mm behind.
            let pressed = SideInput {
                fext_n: V3::new(0.0, 0.0, 1.0),
                ..input(0.0, [0.0, 0.0, 0.0])
            };
            run(&mut p, 0, 10, input(0.0, [0.0; 3]), pressed);
            let (before, _) = run(&mut p, 10, 50, input(0.0, [0.0, 0.0, -0.3]), pressed);
            assert!(
                before.norm() > 0.5,
                "{arch:?}: no force to fade: {before:?}"
            );
            // The follower goes silent at tick 60.
            let mut last = before;
            let mut zero_at = None;
            for k in 60..200 {
                let f = p.0.step(&input(k as f64 * DT, [0.0, 0.0, -0.3]));
                let step = (f - last).norm();
                assert!(
                    step <= before.norm() * DT / (cfg.fade_ms * 1e-3) + 1e-9,
                    "{arch:?}: a step of {step} N at tick {k}"
                );
                last = f;
                if f.norm() == 0.0 && zero_at.is_none() {
                    zero_at = Some(k);
                }
            }
            let ms = (zero_at.expect("the force reached zero") - 60) as f64;
            assert!(ms <= 50.0, "{arch:?}: zero after {ms} ms");
            assert_eq!(p.0.state(), TeleopState::LinkLost);
            // The leader goes silent for the follower: it holds where it is.
            for k in 200..260 {
                p.1.step(&SideInput {
                    t: k as f64 * DT,
                    ..pressed
                });
            }
            assert_eq!(p.1.state(), TeleopState::LinkLost);
            let held = p.1.step(&SideInput { t: 0.26, ..pressed });
            assert!(held.norm() < 1e-9, "{arch:?}: {held:?}");
            let pushed = p.1.step(&SideInput {
                t: 0.261,
                ..input(0.0, [0.0, 0.0, 1.0])
            });
            assert!(
                (pushed[2] + cfg.stiffness_n_per_mm).abs() < 1e-9,
                "{arch:?}: {pushed:?}"
            );
        }
    }

    #[test]
    fn through_a_silence_the_leaders_force_never_grows_and_is_gone_by_the_link_timeout() {
        // The hand moves the leader on at 0.1 m/s through each silence: in pp the follower's
        // last position, taken as still valid, would pull harder every tick (0.25 N a tick).
        for arch in [Architecture::Pp, Architecture::Pf] {
            let cfg = TeleopConfig {
                architecture: arch,
                ..always()
            };
            let mut p = sides(&cfg);
            let mut k = 20usize;
            let mut x = 0.0f64;
            let side = |k: usize, x: f64| SideInput {
                fext_n: V3::new(0.0, 0.0, 1.0),
                ..input(k as f64 * DT, [x, 0.0, 0.0])
            };
            run(&mut p, 0, k, side(0, 0.0), side(0, 0.0));
            for cut in 0..20 {
                // Engaged and moving for 300 ms, the follower 1 mm behind.
                for _ in 0..300 {
                    p.0.step(&side(k, x));
                    p.1.step(&side(k, x - 1.0));
                    x += 0.1;
                    k += 1;
                }
                assert_eq!(p.0.state(), TeleopState::Engaged, "{arch:?}, cut {cut}");
                // The follower goes silent for 3 to 60 ms; the leader's first tick alone
                // takes the follower's last packet.
                let silence = 3 + 3 * cut;
                let at_last = p.0.step(&side(k, x)).norm();
                assert!(at_last > 0.5, "{arch:?}, cut {cut}: no force: {at_last}");
                for s in 1..silence {
                    x += 0.1;
                    let f = p.0.step(&side(k + s, x)).norm();
                    assert!(
                        f <= at_last + 0.05,
                        "{arch:?}, cut {cut}: {f} N after {s} ms of silence, {at_last} N at the \
                         last packet"
                    );
                    if s as f64 >= cfg.link_timeout_ms {
                        assert!(f < 1e-9, "{arch:?}, cut {cut}: still {f} N after {s} ms");
                    }
                }
                k += silence;
            }
        }
    }

    #[test]
    fn a_dropout_keeps_the_mapping_and_the_follower_comes_back_to_it_at_a_bounded_speed() {
        let cfg = always();
        let mut p = sides(&cfg);
        // Engaged with the follower 50 mm off the leader: its mapping is x_f = x_l + 50.
        run(
            &mut p,
            0,
            20,
            input(0.0, [0.0; 3]),
            input(0.0, [50.0, 0.0, 0.0]),
        );
        // Both silent for 40 ms (the link is lost both ways) while the leader moves 4 mm and
        // the follower sags 1 mm.
        let (l, f) = (input(0.0, [4.0, 0.0, 0.0]), input(0.0, [49.0, 0.0, 0.0]));
        for k in 20..60 {
            // (Each side's packets are lost: the other end's queue is emptied unread.)
            p.0.step(&SideInput {
                t: k as f64 * DT,
                ..l
            });
            p.1.endpoint.clear();
            p.1.step(&SideInput {
                t: k as f64 * DT,
                ..f
            });
            p.0.endpoint.clear();
        }
        assert_eq!(p.0.state(), TeleopState::LinkLost);
        assert_eq!(p.1.state(), TeleopState::LinkLost);
        // Back: the same engagement resumes, the follower's target starting where it is...
        let epoch = p.0.epoch();
        let (_, ff) = run(&mut p, 60, 3, l, f);
        assert_eq!((p.0.epoch(), p.1.epoch()), (epoch, epoch));
        assert_eq!(p.1.state(), TeleopState::Engaged);
        // (A jump to the mapping, 5 mm away, would pull with the force limit.)
        assert!(ff.norm() < 0.5, "a jump to the mapping: {ff:?}");
        // ...and moving back to the mapping (54) at `realign_mm_s`: never faster.
        let step = cfg.realign_mm_s * DT;
        let mut target_was = 49.0 + ff[0] / cfg.stiffness_n_per_mm;
        let mut at = f;
        for k in 63..1000 {
            p.0.step(&SideInput {
                t: k as f64 * DT,
                ..l
            });
            let ff = p.1.step(&SideInput {
                t: k as f64 * DT,
                ..at
            });
            // The follower sits on its target (the pull is zero there): read the target
            // from the pull at a known position.
            let target = at.tip_mm[0] + ff[0] / cfg.stiffness_n_per_mm;
            assert!(
                target - target_was <= step + 1e-9,
                "tick {k}: the target moved {} mm",
                target - target_was
            );
            target_was = target;
            at.tip_mm[0] = target;
        }
        assert!((target_was - 54.0).abs() < 1e-9, "mapping {target_was}");
    }

    #[test]
    fn a_side_that_goes_down_disables_the_pair_at_once() {
        let cfg = TeleopConfig {
            architecture: Architecture::Pf,
            ..always()
        };
        let mut p = sides(&cfg);
        let pressed = SideInput {
            fext_n: V3::new(1.0, 0.0, 0.0),
            ..input(0.0, [0.0; 3])
        };
        run(&mut p, 0, 30, input(0.0, [0.0; 3]), pressed);
        assert!(p.0.force().norm() > 0.5);
        // The follower's arm faults: its side says so on its next packet.
        let down = SideInput {
            active: false,
            ..pressed
        };
        let (lf, ff) = run(&mut p, 30, 23, input(0.0, [0.0; 3]), down);
        assert_eq!(ff, V3::zeros());
        assert_eq!(p.1.state(), TeleopState::Down);
        // The leader says so too: the pair is down, not a link that may come back.
        assert_eq!(p.0.state(), TeleopState::Down);
        assert_eq!(
            lf,
            V3::zeros(),
            "faded within fade_ms, not after the timeout"
        );
    }

    #[test]
    fn each_side_measures_the_round_trip_from_echoes_and_softens_its_spring_beyond_it() {
        let cfg = always();
        // In process (lockstep, the leader first): the follower's echo reaches the leader a
        // tick later; the leader's reaches the follower after the follower's next send.
        let mut p = sides(&cfg);
        run(&mut p, 0, 50, input(0.0, [0.0; 3]), input(0.0, [0.0; 3]));
        for side in [&p.0, &p.1] {
            assert!(
                side.round_trip_s() <= 2.0 * DT + 1e-9,
                "{}",
                side.round_trip_s()
            );
            assert_eq!(side.delay_gain(), 1.0);
        }
        // 100 ms each way: both measure a 200 ms round trip and scale the spring by 3/200.
        let slow = Impairment {
            delay_ms: 100.0,
            ..Impairment::default()
        };
        let (l, f) = pair(slow, slow, 5);
        let mut p = (
            Coupling::new(Role::Leader, &cfg, l, DT),
            Coupling::new(Role::Follower, &cfg, f, DT),
        );
        // (The first samples, taken as the link comes up, are longer; the estimate comes down
        // over a second.)
        run(&mut p, 0, 3000, input(0.0, [0.0; 3]), input(0.0, [0.0; 3]));
        for side in [&p.0, &p.1] {
            let rtt = side.round_trip_s();
            assert!((rtt - 0.2).abs() <= 2.0 * DT, "{rtt}");
            assert!((side.delay_gain() - cfg.delay_gain_ms * 1e-3 / rtt).abs() < 1e-12);
        }
        // The follower's pull for 1 mm of the leader's motion is the softened spring's.
        let (_, ff) = run(
            &mut p,
            3000,
            300,
            input(0.0, [1.0, 0.0, 0.0]),
            input(0.0, [0.0; 3]),
        );
        let k = cfg.stiffness_n_per_mm * p.1.delay_gain();
        assert!((ff[0] - k).abs() < 1e-9, "{ff:?} vs {k}");
        assert!(k < 0.1 * cfg.stiffness_n_per_mm);
    }

    #[test]
    fn the_pf_damping_cap_is_raised_in_process_and_halved_at_a_one_second_round_trip() {
        let cap = TeleopConfig::default().passivity_max_damping_n_s_per_m;
        for (arch, dc, rt_ms, lo, hi) in [
            // In process a side measures a round trip of a tick or two: 1.5 to 2 times the cap.
            (Architecture::Pf, 0.0, 1.5 * cap - 1e-9, 2.0 * cap + 1e-9),
            (Architecture::Pf, 200.0, cap, 1.01 * cap),
            (Architecture::Pf, 1000.0, 0.49 * cap, 0.51 * cap),
            // pp keeps the configured cap at every round trip.
            (Architecture::Pp, 0.0, cap, cap),
            (Architecture::Pp, 1000.0, cap, cap),
        ]
        .into_iter()
        .map(|(a, rt, lo, hi)| (a, DelayControl::Gains, rt, lo, hi))
        .chain([
            // Wave variables, either architecture: the cap, halved at a one-second round trip.
            (Architecture::Pf, DelayControl::Wave, 0.0, cap, cap),
            (Architecture::Pf, DelayControl::Wave, 200.0, cap, cap),
            (
                Architecture::Pf,
                DelayControl::Wave,
                1000.0,
                0.49 * cap,
                0.51 * cap,
            ),
            (Architecture::Pp, DelayControl::Wave, 0.0, cap, cap),
            (
                Architecture::Pp,
                DelayControl::Wave,
                1000.0,
                0.49 * cap,
                0.51 * cap,
            ),
        ]) {
            let cfg = TeleopConfig {
                architecture: arch,
                delay_control: dc,
                ..always()
            };
            let imp = Impairment {
                delay_ms: rt_ms / 2.0,
                ..Impairment::default()
            };
            let (l, f) = pair(imp, imp, 9);
            let mut p = (
                Coupling::new(Role::Leader, &cfg, l, DT),
                Coupling::new(Role::Follower, &cfg, f, DT),
            );
            run(&mut p, 0, 4000, input(0.0, [0.0; 3]), input(0.0, [0.0; 3]));
            let c = p.0.damping_cap();
            assert!(
                (lo..=hi).contains(&c),
                "{arch:?} {dc:?} at {rt_ms} ms: cap {c}"
            );
        }
    }

    #[test]
    fn with_operator_button1_the_pair_follows_only_while_it_is_held() {
        let cfg = TeleopConfig {
            operator: Operator::Button1,
            ramp_s: 0.0,
            ..TeleopConfig::default()
        };
        let mut p = sides(&cfg);
        let away = input(0.0, [0.0; 3]);
        run(
            &mut p,
            0,
            20,
            SideInput {
                tip_mm: V3::new(5.0, 0.0, 0.0),
                ..away
            },
            away,
        );
        assert_eq!(p.0.state(), TeleopState::Waiting);
        let (_, ff) = run(&mut p, 20, 3, away, away);
        assert!(ff.norm() < 1e-9, "followed without the operator: {ff:?}");
        let held = SideInput {
            buttons: [true, false],
            ..away
        };
        run(&mut p, 23, 5, held, away);
        assert_eq!(p.0.state(), TeleopState::Engaged);
        run(&mut p, 28, 5, away, away);
        assert_eq!(p.0.state(), TeleopState::Waiting);
    }

    /// Two point masses (0.1 kg, 1 N·s/m of friction each) coupled over a channel of
    /// `delay_ms` each way and `loss` (seeded): the hand (500 N/m, 5 N·s/m) pulls the leader
    /// toward `hand(t)` (mm, y only); the follower meets a floor `wall` N/mm at −10 mm. Returns
    /// the largest |y| of each arm over the run's last half, and the lowest the channel's
    /// energy went: what the two ports took in from the arms less what they put out, J, by
    /// an independent account here of each tick's force times velocity.
    fn wave_pair(
        cfg: &TeleopConfig,
        delay_ms: f64,
        loss: f64,
        wall: f64,
        secs: f64,
        hand: impl Fn(f64) -> f64,
    ) -> (f64, f64, f64) {
        let imp = Impairment {
            delay_ms,
            jitter_ms: 0.0,
            loss,
        };
        let (l, f) = pair(imp, imp, 7);
        let mut lead = Coupling::new(Role::Leader, cfg, l, DT);
        let mut follow = Coupling::new(Role::Follower, cfg, f, DT);
        let (m, fric) = (0.1, 1.0);
        let (mut yl, mut vl, mut yf, mut vf) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        let (mut energy, mut lowest) = (0.0f64, 0.0f64);
        let (mut max_l, mut max_f) = (0.0f64, 0.0f64);
        let n = (secs / DT) as usize;
        for k in 0..n {
            let t = k as f64 * DT;
            let side = |y: f64, v: f64| SideInput {
                vel_mm_s: V3::new(0.0, v * 1e3, 0.0),
                ..input(t, [0.0, y * 1e3, 0.0])
            };
            let fl = lead.step(&side(yl, vl))[1];
            let ff = follow.step(&side(yf, vf))[1];
            // The channel's energy: what the arms pushed into it less what it put into them.
            energy -= (fl * vl + ff * vf) * DT;
            lowest = lowest.min(energy);
            let hand_f = 500.0 * (hand(t) * 1e-3 - yl) - 5.0 * vl;
            let wall_f = if yf < -0.010 {
                -wall * 1e3 * (yf + 0.010) - 5.0 * vf.min(0.0)
            } else {
                0.0
            };
            vl += (fl + hand_f - fric * vl) / m * DT;
            vf += (ff + wall_f - fric * vf) / m * DT;
            yl += vl * DT;
            yf += vf * DT;
            assert!(yl.is_finite() && yf.is_finite());
            if k >= n / 2 {
                max_l = max_l.max(yl.abs() * 1e3);
                max_f = max_f.max(yf.abs() * 1e3);
            }
        }
        (max_l, max_f, lowest)
    }

    fn wave() -> TeleopConfig {
        TeleopConfig {
            delay_control: DelayControl::Wave,
            passivity: true,
            ..always()
        }
    }

    #[test]
    fn wave_variables_hold_a_stiff_wall_bounded_at_a_one_second_round_trip_and_half_loss() {
        // The hand pushes 30 mm past a 2 N/mm floor that stands 10 mm down: without control
        // the delayed pair would ring; with waves it presses and stays bounded.
        for loss in [0.0, 0.5] {
            let (l, f, _) = wave_pair(&wave(), 500.0, loss, 2.0, 20.0, |_| -30.0);
            assert!(l <= 31.0, "loss {loss}: leader reached {l} mm");
            assert!(f <= 12.0, "loss {loss}: follower reached {f} mm");
            // Against it, the same pair with full-stiffness springs and no wave or ports
            // (the control is what holds it): a real oscillation, not a slow press.
            let bare = TeleopConfig {
                delay_gain_ms: 0.0,
                passivity: false,
                ..always()
            };
            let (lb, _, _) = wave_pair(&bare, 500.0, loss, 2.0, 20.0, |_| -30.0);
            assert!(
                lb > l + 5.0,
                "loss {loss}: without control the leader reached {lb} mm, with waves {l}"
            );
        }
    }

    #[test]
    fn the_wave_channel_puts_out_no_more_than_it_took_in_under_delay_and_loss() {
        // The hand moves the leader back and forth into the floor. Without the drift
        // compensation the wave channel is passive at every delay and loss: its energy,
        // tallied here from each tick's forces and velocities, never falls below −1 mJ. The
        // drift compensation pulls the follower onto the leader's position and that pull is
        // not passive: what it makes stays bounded (measured −0.10 J at 250 ms over 12 s of
        // this motion) and the pair stays bounded (docs/TELEOP.md §5).
        let hand = |t: f64| -15.0 + 12.0 * (std::f64::consts::TAU * 0.7 * t).sin();
        for (delay_ms, loss) in [(0.0, 0.0), (50.0, 0.0), (250.0, 0.1), (500.0, 0.5)] {
            let passive = TeleopConfig {
                wave_drift_hz: 0.0,
                ..wave()
            };
            let (_, _, lowest) = wave_pair(&passive, delay_ms, loss, 1.0, 12.0, hand);
            assert!(
                lowest >= -1e-3,
                "{delay_ms} ms, loss {loss}: energy went to {lowest} J"
            );
            let (l, f, lowest) = wave_pair(&wave(), delay_ms, loss, 1.0, 12.0, hand);
            assert!(
                lowest >= -0.25,
                "{delay_ms} ms, loss {loss}, drift compensation: energy went to {lowest} J"
            );
            assert!(l < 40.0 && f < 40.0, "{delay_ms} ms: {l} / {f} mm");
        }
    }
}

//! The run summary (docs/DESIGN.md §2.3): accumulated in the loop without allocation (`RunStats`),
//! turned into JSON and a human printout at the end.

use super::timing::{Percentiles, TickTiming};
use serde::{Deserialize, Serialize};

/// Running sums for the summary, updated every tick.
#[derive(Debug, Clone, Default)]
pub struct RunStats {
    /// Ticks run so far.
    pub ticks: u64,
    pub(crate) first_t: Option<f64>,
    pub(crate) last_t: f64,
    tracked: u64,
    track_sq: [f64; 3],
    track_max: [f64; 3],
    torque_n: u64,
    torque_sq: [f64; 3],
    torque_tv: [f64; 3],
    last_tau: Option<[f64; 3]>,
    /// The identifier's τ̂ against the torque that acted.
    pub(crate) identifier: ErrorBins,
    /// The plant's exact model against the same torque (simulator only).
    pub(crate) oracle: ErrorBins,
    oracle_seen: bool,
    pub(crate) clamped_ticks: u64,
    /// Ticks the tip force was held to the peak or continuous force.
    pub(crate) force_limited_ticks: u64,
    /// Ticks a hot motor was held to its continuous torque.
    pub(crate) thermal_ticks: u64,
    /// The haptic modes' figures (free, servo_cf).
    pub(crate) haptic: HapticStats,
}

const SLOTS: usize = crate::haptics::effects::MAX_EFFECTS;

/// Running sums of the haptic modes (free, servo_cf): the force commanded at the tip, the
/// simulated hand's, and how deep the tip went into each slot's wall. Fixed size.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct HapticStats {
    ticks: u64,
    force_sq: f64,
    force_peak: f64,
    hand_ticks: u64,
    hand_sq: f64,
    hand_peak: f64,
    /// Per slot: the last effect kind seen there, and its deepest depth, m (None: no wall).
    slots: [Option<(&'static str, Option<f64>)>; SLOTS],
}

impl HapticStats {
    /// One haptic tick: the tip force `force` (N), the hand's `hand` (N; None without one or
    /// not finite), each slot's kind and depth.
    pub(crate) fn record(
        &mut self,
        force: &[f64; 3],
        hand: Option<[f64; 3]>,
        depths: &[Option<(&'static str, Option<f64>)>; SLOTS],
    ) {
        let norm = |v: &[f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        let f = norm(force);
        if f.is_finite() {
            self.ticks += 1;
            self.force_sq += f * f;
            self.force_peak = self.force_peak.max(f);
        }
        if let Some(h) = hand.map(|h| norm(&h)).filter(|h| h.is_finite()) {
            self.hand_ticks += 1;
            self.hand_sq += h * h;
            self.hand_peak = self.hand_peak.max(h);
        }
        for (acc, now) in self.slots.iter_mut().zip(depths) {
            if let Some((kind, depth)) = *now {
                let deepest = match (*acc, depth) {
                    (Some((k, Some(d0))), Some(d)) if k == kind => Some(d0.max(d)),
                    (Some((k, Some(d0))), None) if k == kind => Some(d0),
                    (_, d) => d,
                };
                *acc = Some((kind, deepest));
            }
        }
    }
}

impl RunStats {
    /// Become a copy of `other` without allocating (the error bins are reused).
    pub(crate) fn copy_from(&mut self, other: &RunStats) {
        let RunStats {
            ticks,
            first_t,
            last_t,
            tracked,
            track_sq,
            track_max,
            torque_n,
            torque_sq,
            torque_tv,
            last_tau,
            identifier,
            oracle,
            oracle_seen,
            clamped_ticks,
            force_limited_ticks,
            thermal_ticks,
            haptic,
        } = other;
        (self.ticks, self.first_t, self.last_t) = (*ticks, *first_t, *last_t);
        (self.tracked, self.track_sq, self.track_max) = (*tracked, *track_sq, *track_max);
        (self.torque_n, self.torque_sq, self.torque_tv) = (*torque_n, *torque_sq, *torque_tv);
        self.last_tau = *last_tau;
        self.identifier.copy_from(identifier);
        self.oracle.copy_from(oracle);
        self.oracle_seen = *oracle_seen;
        self.clamped_ticks = *clamped_ticks;
        self.force_limited_ticks = *force_limited_ticks;
        self.thermal_ticks = *thermal_ticks;
        self.haptic = *haptic;
    }

    pub(crate) fn record_time(&mut self, t: f64) {
        self.ticks += 1;
        self.first_t.get_or_insert(t);
        self.last_t = t;
    }

    pub(crate) fn record_tracking(&mut self, error: &[f64; 3]) {
        self.tracked += 1;
        for j in 0..3 {
            self.track_sq[j] += error[j] * error[j];
            self.track_max[j] = self.track_max[j].max(error[j].abs());
        }
    }

    pub(crate) fn record_torque(&mut self, tau: &[f64; 3]) {
        self.torque_n += 1;
        for j in 0..3 {
            self.torque_sq[j] += tau[j] * tau[j];
            if let Some(last) = self.last_tau {
                self.torque_tv[j] += (tau[j] - last[j]).abs();
            }
        }
        self.last_tau = Some(*tau);
    }

    /// The plant's exact model against the torque that acted (simulator only).
    pub(crate) fn record_oracle(&mut self, tau: &[f64; 3], tau_model: &[f64; 3]) {
        self.oracle_seen = true;
        self.oracle.record(tau, tau_model);
    }

    /// Tracking error RMS per joint, rad, over the ticks that tracked a reference (none yet: None).
    pub fn tracking_rms(&self) -> Option<[f64; 3]> {
        (self.tracked > 0).then(|| self.track_sq.map(|s| (s / self.tracked as f64).sqrt()))
    }

    pub(crate) fn tracking_max(&self) -> Option<[f64; 3]> {
        (self.tracked > 0).then_some(self.track_max)
    }

    pub(crate) fn torque_rms(&self) -> Option<[f64; 3]> {
        (self.torque_n > 0).then(|| self.torque_sq.map(|s| (s / self.torque_n as f64).sqrt()))
    }

    pub(crate) fn torque_total_variation(&self) -> [f64; 3] {
        self.torque_tv
    }

    pub(crate) fn oracle_nrmse(&self) -> Option<[f64; 3]> {
        if self.oracle_seen {
            self.oracle.nrmse()
        } else {
            None
        }
    }

    pub(crate) fn oracle_nrmse_last_20pct(&self) -> Option<[f64; 3]> {
        if self.oracle_seen {
            self.oracle.nrmse_last_20pct()
        } else {
            None
        }
    }
}

/// Bins of the identifier's squared errors over time: enough to give the NRMSE of the whole
/// run and of its last 20 % without storing every tick or knowing the length in advance.
/// When the bins fill up, neighbours merge and each bin covers twice as many ticks.
#[derive(Debug, Clone)]
pub(crate) struct ErrorBins {
    err_sq: Vec<[f64; 3]>,
    ref_sq: Vec<[f64; 3]>,
    used: usize,
    ticks_per_bin: u64,
    in_bin: u64,
}

const ERROR_BINS: usize = 1000;

impl Default for ErrorBins {
    fn default() -> Self {
        ErrorBins {
            err_sq: vec![[0.0; 3]; ERROR_BINS],
            ref_sq: vec![[0.0; 3]; ERROR_BINS],
            used: 0,
            ticks_per_bin: 1,
            in_bin: 0,
        }
    }
}

impl ErrorBins {
    /// Become a copy of `other` without allocating.
    pub(crate) fn copy_from(&mut self, other: &ErrorBins) {
        self.err_sq.clone_from(&other.err_sq);
        self.ref_sq.clone_from(&other.ref_sq);
        self.used = other.used;
        self.ticks_per_bin = other.ticks_per_bin;
        self.in_bin = other.in_bin;
    }

    /// Add one tick: `reference` the measured torque, `estimate` the prediction.
    pub fn record(&mut self, reference: &[f64; 3], estimate: &[f64; 3]) {
        if self.in_bin == self.ticks_per_bin {
            self.used += 1;
            self.in_bin = 0;
        }
        if self.used == ERROR_BINS {
            for i in 0..ERROR_BINS / 2 {
                for j in 0..3 {
                    self.err_sq[i][j] = self.err_sq[2 * i][j] + self.err_sq[2 * i + 1][j];
                    self.ref_sq[i][j] = self.ref_sq[2 * i][j] + self.ref_sq[2 * i + 1][j];
                }
            }
            for i in ERROR_BINS / 2..ERROR_BINS {
                self.err_sq[i] = [0.0; 3];
                self.ref_sq[i] = [0.0; 3];
            }
            self.used = ERROR_BINS / 2;
            self.ticks_per_bin *= 2;
        }
        let b = self.used;
        for j in 0..3 {
            self.err_sq[b][j] += (reference[j] - estimate[j]).powi(2);
            self.ref_sq[b][j] += reference[j] * reference[j];
        }
        self.in_bin += 1;
    }

    fn nrmse_from(&self, first_bin: usize) -> Option<[f64; 3]> {
        let last = if self.in_bin > 0 {
            self.used + 1
        } else {
            self.used
        };
        if first_bin >= last {
            return None;
        }
        let mut r = [0.0; 3];
        for j in 0..3 {
            let e: f64 = self.err_sq[first_bin..last].iter().map(|b| b[j]).sum();
            let t: f64 = self.ref_sq[first_bin..last].iter().map(|b| b[j]).sum();
            // A joint whose measured torque is zero throughout (a recording without torque,
            // e.g. a converted hand-guided log) has nothing to normalise by: no NRMSE.
            if t <= 0.0 {
                return None;
            }
            r[j] = (e / t).sqrt();
        }
        Some(r)
    }

    /// RMS(error) / RMS(reference) per joint over the whole run.
    pub fn nrmse(&self) -> Option<[f64; 3]> {
        self.nrmse_from(0)
    }

    /// The same over the last 20 % of the run (to the resolution of one bin).
    pub fn nrmse_last_20pct(&self) -> Option<[f64; 3]> {
        let bins = if self.in_bin > 0 {
            self.used + 1
        } else {
            self.used
        };
        self.nrmse_from((bins as f64 * 0.8).round() as usize)
    }
}

/// How well the identifier predicted the torque that acted (summary JSON `identifier`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct IdentifierSummary {
    /// NRMSE of τ̂ against the torque that acted, per joint, over the whole run.
    pub nrmse: Option<[f64; 3]>,
    /// The same over the last 20 % of the run (after learning).
    pub nrmse_last_20pct: Option<[f64; 3]>,
    /// The exact model's NRMSE over the whole run (simulator only).
    pub nrmse_oracle: Option<[f64; 3]>,
    /// The exact model's NRMSE over the last 20 % (simulator only).
    pub nrmse_oracle_last_20pct: Option<[f64; 3]>,
    /// Weights the run started from: "fresh", "shipped", or a file path.
    pub weights: Option<String>,
    /// Whether the identifier learned online during the run.
    pub adapt: bool,
    /// Why the identifier stopped adapting, if it did (NNIDC then ran on PD).
    pub fault: Option<String>,
}

/// Tick timing percentiles, µs (summary JSON `timing_us`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TimingSummary {
    /// Time between successive samples arriving.
    pub period: Option<Percentiles>,
    /// Null for unpaced (`--fast`) runs, where lateness has no meaning.
    pub lateness: Option<Percentiles>,
    /// Time from a sample's arrival to its command being ready.
    pub compute: Option<Percentiles>,
    /// Ticks whose lateness plus compute exceeded the device's step.
    pub overruns: u64,
}

impl TimingSummary {
    pub(crate) fn from_timing(t: &TickTiming) -> Self {
        TimingSummary {
            period: t.period.percentiles_us(),
            lateness: t.lateness.percentiles_us(),
            compute: t.compute.percentiles_us(),
            overruns: t.overruns,
        }
    }
}

/// The haptic modes' figures (summary JSON `haptics`; null when the arm never ran free or
/// servo_cf).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct HapticSummary {
    /// Ticks in a haptic mode.
    pub ticks: u64,
    /// RMS of the tip force commanded (effects and a client's force, after the limits), N.
    pub force_rms_n: f64,
    /// Its largest magnitude, N.
    pub force_peak_n: f64,
    /// RMS of the simulated hand's force on the tip, N (null without a hand).
    pub hand_rms_n: Option<f64>,
    /// Its largest magnitude, N.
    pub hand_peak_n: Option<f64>,
    /// Each slot with an effect: its kind and how deep the tip went into its wall.
    pub effects: Vec<EffectDepth>,
}

/// One effect of a haptic run (summary JSON `haptics.effects`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EffectDepth {
    /// The slot (0–7; a scene file's effects fill slots from 0, in order).
    pub slot: usize,
    /// Its `type`.
    pub kind: String,
    /// The deepest the tip went into its wall, mm (0: never in it; null: no wall).
    pub depth_max_mm: Option<f64>,
}

impl HapticSummary {
    pub(crate) fn from_stats(h: &HapticStats) -> Option<HapticSummary> {
        (h.ticks > 0).then(|| HapticSummary {
            ticks: h.ticks,
            force_rms_n: (h.force_sq / h.ticks as f64).sqrt(),
            force_peak_n: h.force_peak,
            hand_rms_n: (h.hand_ticks > 0).then(|| (h.hand_sq / h.hand_ticks as f64).sqrt()),
            hand_peak_n: (h.hand_ticks > 0).then_some(h.hand_peak),
            effects: h
                .slots
                .iter()
                .enumerate()
                .filter_map(|(slot, s)| {
                    s.map(|(kind, d)| EffectDepth {
                        slot,
                        kind: kind.to_string(),
                        depth_max_mm: d.map(|d| d * 1e3),
                    })
                })
                .collect(),
        })
    }
}

/// One fault of a run (summary JSON `faults`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FaultEntry {
    /// The tick it happened on.
    pub tick: u64,
    /// Device time it happened at, s.
    pub t: f64,
    /// What kind: `device-fault` or `safety-fault`.
    pub class: String,
    /// What went wrong, for the operator.
    pub message: String,
}

/// The summary of a run: printed for people ([`RunSummary::human`]) and written as the
/// summary JSON (`--summary-json`, docs/DESIGN.md §2.3).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// The device backend: `sim`, `usb`, `firewire` or `replay`.
    pub device: String,
    /// The controller that ran.
    pub controller: String,
    /// The reference trajectory it tracked.
    pub trajectory: String,
    /// Ticks run.
    pub ticks: u64,
    /// Device time from the first tick to the last, s.
    pub duration_s: f64,
    /// RMS tracking error per joint, rad (null if nothing was tracked).
    pub tracking_rms_rad: Option<[f64; 3]>,
    /// Largest tracking error per joint, rad.
    pub tracking_max_rad: Option<[f64; 3]>,
    /// The oracle's RMS tracking error on the same reference, rad: computed torque with the
    /// simulator's exact model and its friction, run in a second `--fast` pass after an NNIDC
    /// run on the simulator (`omnid run` only; null otherwise). The summary prints NNIDC's
    /// ratio to it (docs/IDENTIFIER.md).
    #[serde(default)]
    pub oracle_tracking_rms_rad: Option<[f64; 3]>,
    /// RMS commanded torque per joint, N·m.
    pub torque_rms_nm: Option<[f64; 3]>,
    /// Sum of tick-to-tick torque changes per joint, N·m (how much the command chattered).
    pub torque_total_variation_nm: [f64; 3],
    /// How well the identifier predicted the torque.
    pub identifier: IdentifierSummary,
    /// Tick timing.
    pub timing_us: TimingSummary,
    /// Faults, in order.
    pub faults: Vec<FaultEntry>,
    /// Log rows dropped because the writer fell behind.
    pub telemetry_dropped: u64,
    /// How the run ended: completed, end-of-data, operator-stop, device-fault, safety-fault.
    pub end: String,
    /// Packets lost or corrupt.
    pub missed_packets: u64,
    /// Ticks on which the safety layer limited the torque.
    pub clamped_ticks: u64,
    /// Ticks on which the tip force was held to `haptics.max_force_n` or the continuous force.
    #[serde(default)]
    pub force_limited_ticks: u64,
    /// Ticks on which a hot motor was held to its continuous torque.
    #[serde(default)]
    pub thermal_ticks: u64,
    /// The haptic modes' figures (null when none ran).
    #[serde(default)]
    pub haptics: Option<HapticSummary>,
    /// The log written, if any.
    pub log_path: Option<String>,
    /// Rows that reached the log file.
    pub log_rows: u64,
    /// Whether every row reached the log (null without a log); if not, `log_error` says how
    /// many were lost and why (a full disk, rows dropped by a writer that fell behind).
    #[serde(default)]
    pub log_complete: Option<bool>,
    /// Why rows were lost, if any were.
    #[serde(default)]
    pub log_error: Option<String>,
    /// The simulator's random seed.
    pub seed: u64,
    /// Whether the run was unpaced (`--fast`).
    pub fast: bool,
    /// The realtime steps that took effect (null for `--fast` runs, which skip them).
    pub realtime: Option<crate::servo::realtime::RealtimeReport>,
    /// Host time from the first sample to the last command, s, and device time over it: 1 on
    /// a paced run, the speed-up of a `--fast` one.
    #[serde(default)]
    pub wall_s: Option<f64>,
    /// Device time over host time (see `wall_s`).
    #[serde(default)]
    pub realtime_factor: Option<f64>,
    /// Times the Kalman filter restarted across a gap in the device time (longer than
    /// `estimate::kalman::RESTART_GAP_S`), and the longest such gap, s.
    #[serde(default)]
    pub estimator_restarts: u64,
    /// The longest gap in device time the filter restarted across, s.
    #[serde(default)]
    pub longest_gap_s: f64,
    /// Things that did not stop the run but must not go unseen (faults scheduled past its
    /// end, rows skipped with `--lenient`, …).
    #[serde(default)]
    pub warnings: Vec<String>,
}

fn triple(v: Option<[f64; 3]>, scale: f64, unit: &str) -> String {
    match v {
        Some(v) => format!(
            "{:.2} / {:.2} / {:.2} {unit}",
            v[0] * scale,
            v[1] * scale,
            v[2] * scale
        ),
        None => "n/a".to_string(),
    }
}

fn pct(p: &Option<Percentiles>) -> String {
    match p {
        Some(p) => format!(
            "p50 {:.1}  p99 {:.1}  p99.9 {:.1}  max {:.1} µs",
            p.p50, p.p99, p.p999, p.max
        ),
        None => "n/a".to_string(),
    }
}

impl HapticSummary {
    /// Its lines of the printout.
    fn human(&self) -> String {
        let mut s = format!(
            "  tip force       RMS {:.2} N  peak {:.2} N   (rendered: effects and client force, \
             after the limits; {} ticks in a haptic mode)\n",
            self.force_rms_n, self.force_peak_n, self.ticks
        );
        if let (Some(rms), Some(peak)) = (self.hand_rms_n, self.hand_peak_n) {
            s += &format!(
                "  hand force      RMS {rms:.2} N  peak {peak:.2} N   (the simulated hand on the \
                 stylus)\n"
            );
        }
        if self.effects.is_empty() {
            s += "  effects         none\n";
        }
        for e in &self.effects {
            let depth = match e.depth_max_mm {
                Some(d) if d > 0.0 => format!("deepest {d:.2} mm into its wall"),
                Some(_) => "the tip never went into its wall".to_string(),
                None => "no wall".to_string(),
            };
            s += &format!("  effect {}        {}: {depth}\n", e.slot, e.kind);
        }
        s
    }
}

/// What names a run in its summary.
pub struct SummaryLabels<'a> {
    /// The device, as the summary names it.
    pub device: &'a str,
    /// The controller, as the summary names it.
    pub controller: &'a str,
    /// The reference the run followed, as the summary names it.
    pub trajectory: String,
    /// Weights the identifier started from.
    pub weights: String,
    /// The simulator's seed.
    pub seed: u64,
    /// Whether the run went as fast as it could (`--fast`).
    pub fast: bool,
}

/// The identifier's state at the time of the summary.
pub struct IdentifierState {
    /// Whether the identifier was learning at the end.
    pub adapt: bool,
    /// Why the identifier stopped, if it did.
    pub fault: Option<crate::identifier::Fault>,
}

/// How a run ended, as a sentence's end (the JSON's `end` keeps the short names).
fn end_for_people(end: &str) -> &str {
    match end {
        "end-of-data" => "at the end of the recording",
        "operator-stop" => "stopped by the operator",
        "device-fault" => "by a device fault",
        "safety-fault" => "by a safety fault",
        other => other,
    }
}

impl RunSummary {
    /// The summary of the loop's results so far. How the run ended, its faults, log and
    /// realtime report are the caller's to fill in (`end` is "running" until then).
    pub fn from_results(
        labels: &SummaryLabels,
        stats: &RunStats,
        timing: &TickTiming,
        identifier: IdentifierState,
        telemetry_dropped: u64,
        missed_packets: u64,
    ) -> RunSummary {
        let duration_s = stats.first_t.map(|t0| stats.last_t - t0).unwrap_or(0.0);
        let wall_s = timing.wall_s();
        RunSummary {
            device: labels.device.to_string(),
            controller: labels.controller.to_string(),
            trajectory: labels.trajectory.clone(),
            ticks: stats.ticks,
            duration_s,
            tracking_rms_rad: stats.tracking_rms(),
            tracking_max_rad: stats.tracking_max(),
            oracle_tracking_rms_rad: None,
            torque_rms_nm: stats.torque_rms(),
            torque_total_variation_nm: stats.torque_total_variation(),
            identifier: IdentifierSummary {
                nrmse: stats.identifier.nrmse(),
                nrmse_last_20pct: stats.identifier.nrmse_last_20pct(),
                nrmse_oracle: stats.oracle_nrmse(),
                nrmse_oracle_last_20pct: stats.oracle_nrmse_last_20pct(),
                weights: Some(labels.weights.clone()),
                adapt: identifier.adapt,
                fault: identifier.fault.map(|f| f.to_string()),
            },
            timing_us: TimingSummary::from_timing(timing),
            faults: Vec::new(),
            telemetry_dropped,
            end: "running".to_string(),
            missed_packets,
            clamped_ticks: stats.clamped_ticks,
            force_limited_ticks: stats.force_limited_ticks,
            thermal_ticks: stats.thermal_ticks,
            haptics: HapticSummary::from_stats(&stats.haptic),
            log_path: None,
            log_rows: 0,
            log_complete: None,
            log_error: None,
            seed: labels.seed,
            fast: labels.fast,
            realtime: None,
            wall_s,
            realtime_factor: wall_s.filter(|&w| w > 0.0).map(|w| duration_s / w),
            estimator_restarts: 0,
            longest_gap_s: 0.0,
            warnings: Vec::new(),
        }
    }

    /// The printout at the end of a run: one block after another, one line per figure, in
    /// the order they are printed.
    pub fn human(&self) -> String {
        let mut s = self.headline();
        // A run that only rendered forces tracked nothing: its figures are the forces. A run
        // that followed nothing (`--controller off`) has no tracking to report.
        let haptic_only = self.tracking_rms_rad.is_none() && self.haptics.is_some();
        if !haptic_only && self.trajectory != "none" {
            s += &self.tracking_block();
        }
        if let Some(h) = &self.haptics {
            s += &h.human();
        }
        s += &self.torque_block();
        s += &self.model_block();
        s += &self.timing_block();
        s += &self.counters_block();
        s += &self.faults_and_log_block();
        s
    }

    /// What ran, on what, following what, and how it ended.
    fn headline(&self) -> String {
        // A daemon's session follows whatever its clients asked for.
        let what = match self.trajectory.as_str() {
            "serve" => format!("omnid serve: {} ticks", self.ticks),
            _ => format!("omnid run: {} ticks", self.ticks),
        };
        let controller = match self.controller.as_str() {
            "off" => "the controller off".to_string(),
            c => c.to_string(),
        };
        format!(
            "{what} ({:.3} s device time) on {} with {controller}{}{}; ended: {}\n",
            self.duration_s,
            self.device,
            match self.trajectory.as_str() {
                "serve" => " at the start, then as its clients asked".to_string(),
                "free" => " in free mode (compensation and effects)".to_string(),
                "none" => String::new(),
                t => format!(" following {t}"),
            },
            if self.fast { " (--fast)" } else { "" },
            end_for_people(&self.end)
        )
    }

    /// Tracking RMS and max, and against the oracle when it ran.
    fn tracking_block(&self) -> String {
        let mut s = format!(
            "  tracking RMS    {}   (joints 1/2/3, after the start-up blend)\n",
            triple(self.tracking_rms_rad, 1e3, "mrad")
        );
        s += &format!(
            "  tracking max    {}\n",
            triple(self.tracking_max_rad, 1e3, "mrad")
        );
        if let (Some(own), Some(oracle)) = (self.tracking_rms_rad, self.oracle_tracking_rms_rad) {
            let ratio = [0, 1, 2].map(|j| own[j] / oracle[j]);
            s += &format!(
                "  vs oracle       {}   (tracking RMS ÷ ct with the exact model and friction: {})\n",
                triple(Some(ratio), 1.0, "×"),
                triple(Some(oracle), 1e3, "mrad")
            );
        }
        s
    }

    /// Torque RMS and total variation.
    fn torque_block(&self) -> String {
        format!(
            "  torque RMS      {}\n  torque TV       {}   (total variation: chattering)\n",
            triple(self.torque_rms_nm, 1e3, "mN·m"),
            triple(Some(self.torque_total_variation_nm), 1.0, "N·m")
        )
    }

    /// The identifier's fit and whether it stopped; the estimator's restarts.
    fn model_block(&self) -> String {
        let mut s = String::new();
        if self.identifier.nrmse.is_some() || self.identifier.nrmse_oracle.is_some() {
            s += &format!(
                "  ident NRMSE     {}   (last 20 %: {}; exact model: {})\n",
                triple(self.identifier.nrmse, 1.0, ""),
                triple(self.identifier.nrmse_last_20pct, 1.0, ""),
                triple(self.identifier.nrmse_oracle, 1.0, "")
            );
        }
        if let Some(fault) = &self.identifier.fault {
            s += &format!(
                "  identifier      STOPPED: {fault}; its last good weights kept, nnidc ran on PD \
                 from then on (flag 256 in the log)\n"
            );
        }
        if self.estimator_restarts > 0 {
            s += &format!(
                "  estimator       restarted {} time(s) across gaps in the device time (longest \
                 {:.3} s)\n",
                self.estimator_restarts, self.longest_gap_s
            );
        }
        s
    }

    /// The tick's period, lateness and compute time; the wall clock.
    fn timing_block(&self) -> String {
        let mut s = format!("  period          {}\n", pct(&self.timing_us.period));
        s += &format!("  lateness        {}\n", pct(&self.timing_us.lateness));
        s += &format!(
            "  compute         {}   overruns {}\n",
            pct(&self.timing_us.compute),
            self.timing_us.overruns
        );
        if let (Some(w), Some(f)) = (self.wall_s, self.realtime_factor) {
            s += &format!("  wall clock      {w:.3} s   ({f:.0}× real time)\n");
        }
        s
    }

    /// Missed packets, clamped and force-held ticks, dropped telemetry; the real-time setup.
    fn counters_block(&self) -> String {
        let mut s = format!(
            "  packets missed {}  clamped ticks {}  telemetry dropped {}\n",
            self.missed_packets, self.clamped_ticks, self.telemetry_dropped
        );
        if self.force_limited_ticks > 0 || self.thermal_ticks > 0 {
            s += &format!(
                "  force held      {} ticks at the force limit, {} ticks at a hot motor's \
                 continuous torque\n",
                self.force_limited_ticks, self.thermal_ticks
            );
        }
        if let Some(rt) = &self.realtime {
            s += &format!(
                "  realtime        SCHED_FIFO {}  memory locked {}  cpu {}  signals blocked {}\n",
                rt.fifo_priority.map_or("no".to_string(), |p| p.to_string()),
                if rt.memory_locked { "yes" } else { "no" },
                rt.cpu.map_or("any".to_string(), |c| c.to_string()),
                if rt.signals_blocked { "yes" } else { "no" },
            );
        }
        s
    }

    /// Each fault, then the log written.
    fn faults_and_log_block(&self) -> String {
        let mut s = String::new();
        for f in &self.faults {
            s += &format!(
                "  FAULT at tick {} (t = {:.3} s): {}: {}\n",
                f.tick, f.t, f.class, f.message
            );
        }
        if let Some(p) = &self.log_path {
            match &self.log_error {
                Some(why) => {
                    s += &format!("  log: {p} ({} rows; INCOMPLETE: {why})\n", self.log_rows)
                }
                None => s += &format!("  log: {p} ({} rows)\n", self.log_rows),
            }
        }
        s
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_printed_summary_says_when_the_identifier_stopped_and_the_estimator_restarted() {
        let mut s = RunSummary::from_results(
            &SummaryLabels {
                device: "sim",
                controller: "nnidc",
                trajectory: "sine".into(),
                weights: "shipped".into(),
                seed: 1,
                fast: true,
            },
            &RunStats::default(),
            &TickTiming::new(1_000_000),
            IdentifierState {
                adapt: true,
                fault: Some(crate::identifier::Fault::NonFiniteUpdate),
            },
            0,
            0,
        );
        s.estimator_restarts = 2;
        s.longest_gap_s = 0.25;
        let text = s.human();
        assert!(
            text.contains("identifier      STOPPED: identifier: non-finite weight update"),
            "{text}"
        );
        assert!(text.contains("nnidc ran on PD"), "{text}");
        assert!(
            text.contains("restarted 2 time(s)") && text.contains("0.250 s"),
            "{text}"
        );
    }

    use super::*;

    #[test]
    fn error_bins_match_a_direct_computation_across_merges() {
        // 5003 ticks: bins merge twice; the whole-run NRMSE is exact, the last 20 % is
        // exact to one bin.
        let mut b = ErrorBins::default();
        let (mut e, mut t, mut e_late, mut t_late) = (0.0, 0.0, 0.0, 0.0);
        let n = 5003;
        for k in 0..n {
            let tau = [(k as f64 * 0.01).sin(), 1.0, 0.5];
            let err = if k > n / 2 { 0.1 } else { 0.3 };
            let est = [tau[0] + err, 1.0, 0.5];
            b.record(&tau, &est);
            e += err * err;
            t += tau[0] * tau[0];
            if k >= (n as f64 * 0.8) as usize {
                e_late += err * err;
                t_late += tau[0] * tau[0];
            }
        }
        assert!((b.nrmse().unwrap()[0] - (e / t).sqrt()).abs() < 1e-12);
        assert_eq!(b.nrmse().unwrap()[1], 0.0);
        let late = b.nrmse_last_20pct().unwrap()[0];
        assert!(
            (late - (e_late / t_late).sqrt()).abs() < 0.02 * late,
            "{late}"
        );
        assert!(ErrorBins::default().nrmse().is_none());

        // No measured torque on a joint: undefined, not a huge number.
        let mut z = ErrorBins::default();
        for _ in 0..100 {
            z.record(&[0.1, 0.0, 0.2], &[0.1, 1e-3, 0.2]);
        }
        assert!(z.nrmse().is_none() && z.nrmse_last_20pct().is_none());
    }

    #[test]
    fn stats_match_a_direct_computation() {
        let mut st = RunStats::default();
        let taus = [[0.1, -0.2, 0.0], [0.3, 0.2, 0.0], [-0.1, 0.0, 0.05]];
        for t in &taus {
            st.record_torque(t);
            st.record_tracking(t);
        }
        let rms0 = ((0.01 + 0.09 + 0.01) / 3.0f64).sqrt();
        assert!((st.torque_rms().unwrap()[0] - rms0).abs() < 1e-15);
        assert!((st.torque_total_variation()[0] - (0.2 + 0.4)).abs() < 1e-15);
        assert_eq!(st.tracking_max().unwrap()[1], 0.2);
        assert!(RunStats::default().tracking_rms().is_none());
    }
}

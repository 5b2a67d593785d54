//! `omnid experiment haptics --out DIR` (docs/HAPTICS.md §9): on the simulator with the
//! simulated hand, (1) transparency: the hand traces a 3-D path at 0.1 m/s in free mode with
//! no compensation, the lab's parametric model, the learned model, and the plant's exact
//! model; (2) walls: the hand pushes with 1 N into a wall on each axis, at the vendor's
//! stiffness with and without the passivity controller, then stiffer until it no longer
//! holds; (3) force accuracy: a held stylus under a constant commanded force. Writes
//! `report.md`, `results.json`, the logs and figures.

use super::{ExperimentError, ExperimentReport};
use crate::cmd::run::{execute, RunOptions};
use crate::config::Config;
use crate::control::{ControllerKind, Trajectory};
use crate::haptics::{Effect, HandPattern, HapticRun};
use crate::omni::{jacobian, tip_position_mm, Joint3};
use crate::plot::figures::Role;
use crate::plot::render::{Figure, Line, Panel};
use crate::telemetry::reader::{ColumnReader, ReadError, Row};
use serde_json::{json, Value};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// The vendor's nominal stiffness per axis, N/mm (docs/HAPTICS.md §2).
pub const NOMINAL_STIFFNESS: [f64; 3] = [1.26, 2.31, 1.02];
/// Stiffer walls tried with the passivity controller, N/mm.
const SWEEP: [f64; 7] = [3.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0];
/// How far from the workspace centre each wall stands, mm, and which way the hand pushes.
const WALL_GAP_MM: f64 = 10.0;
const PUSH: [(usize, f64); 3] = [(0, 1.0), (1, -1.0), (2, -1.0)];
const AXES: [&str; 3] = ["x", "y", "z"];
/// A wall holds when the tip's peak-to-peak motion along the normal over the last second is
/// at most this (about two encoder counts at the tip) ...
const STABLE_PP_MM: f64 = 0.15;
/// ... and the hand still pushes on it with most of its force (not bouncing off).
const STABLE_FORCE_FRACTION: f64 = 0.8;

/// The columns the haptics analyses read (a log without some of them simply lacks them).
const LOG_COLUMNS: [&str; 13] = [
    "t", "q1", "q2", "q3", "tip1", "tip2", "tip3", "fhand1", "fhand2", "fhand3", "fcmd1", "fcmd2",
    "fcmd3",
];

/// The [`LOG_COLUMNS`] of one log, by name, every row but the last (the final stop packet).
struct Log {
    columns: Vec<(&'static str, Vec<f64>)>,
}

impl Log {
    /// Read `path` through the crate's log reader; a field that is not a number is NaN.
    fn read(path: &Path) -> Result<Log, ExperimentError> {
        let bad = |e: ReadError| ExperimentError::ReadLog {
            path: path.to_path_buf(),
            why: e.to_string(),
        };
        let mut reader = ColumnReader::open(path, &["t"], false, None).map_err(bad)?;
        let mut wanted = Vec::new();
        let mut columns = Vec::new();
        for name in LOG_COLUMNS {
            if let Some(i) = reader.header().iter().position(|h| h == name) {
                wanted.push(i);
                columns.push((name, Vec::new()));
            }
        }
        let mut take = |row: &Row<'_>| {
            for (&i, (_, values)) in wanted.iter().zip(columns.iter_mut()) {
                let v = std::str::from_utf8(row.field(i))
                    .ok()
                    .and_then(|s| s.parse().ok());
                values.push(v.unwrap_or(f64::NAN));
            }
            Ok(())
        };
        while reader.next_with(&mut take).map_err(bad)?.is_some() {}
        // Every row but the final stop packet.
        for (_, values) in &mut columns {
            values.pop();
        }
        Ok(Log { columns })
    }

    fn col(&self, name: &str) -> Result<Vec<f64>, ExperimentError> {
        self.columns
            .iter()
            .find(|(n, _)| *n == name)
            .map(|(_, values)| values.clone())
            .ok_or_else(|| ExperimentError::Internal(format!("log has no column `{name}`")))
    }

    fn group(&self, prefix: &str) -> Result<[Vec<f64>; 3], ExperimentError> {
        Ok([
            self.col(&format!("{prefix}1"))?,
            self.col(&format!("{prefix}2"))?,
            self.col(&format!("{prefix}3"))?,
        ])
    }
}

/// The workspace centre's tip position, mm.
fn centre_mm(cfg: &Config) -> [f64; 3] {
    tip_position_mm(&cfg.geometry, &cfg.reference.center.into()).into()
}

/// The experiment's base configuration: the arm starts at the centre of the workspace.
fn base_config() -> Config {
    let mut cfg = Config::default();
    cfg.sim.start_pose = cfg.reference.center;
    cfg.safety.persist_heat = false;
    cfg
}

/// One `--fast` simulator run into `dir/log.csv`; a fault is an error.
fn run(
    name: &str,
    cfg: &Config,
    controller: ControllerKind,
    secs: f64,
    dir: &Path,
    haptics: HapticRun,
) -> Result<Log, ExperimentError> {
    super::make_dir(dir)?;
    let log = dir.join("log.csv");
    let opts = RunOptions {
        controller,
        trajectory: Trajectory::Hold,
        duration_s: secs,
        log: Some(log.clone()),
        fast: true,
        haptics,
        ..RunOptions::default()
    };
    let out = execute(&opts, cfg, Arc::new(AtomicBool::new(false))).map_err(|source| {
        ExperimentError::Run {
            name: name.to_string(),
            source: Box::new(source),
        }
    })?;
    if let Some(f) = out.summary.faults.first() {
        return Err(ExperimentError::RunFailed {
            name: name.to_string(),
            why: format!("{} at t = {:.3} s: {}", f.class, f.t, f.message),
        });
    }
    Log::read(&log)
}

fn rms_norm(v: &[Vec<f64>; 3], from: usize) -> f64 {
    let n = v[0].len().saturating_sub(from).max(1) as f64;
    let s: f64 = (from..v[0].len())
        .map(|k| v.iter().map(|c| c[k] * c[k]).sum::<f64>())
        .sum();
    (s / n).sqrt()
}

/// One line of a figure: its label, role and points.
type Series = (&'static str, Role, Vec<(f64, f64)>);

/// Draw `series` (label, role, points) as one figure `name` in `dir`.
fn figure(
    dir: &Path,
    name: &str,
    title: &'static str,
    y_desc: &'static str,
    panels: Vec<(&'static str, Vec<Series>)>,
    files: &mut Vec<PathBuf>,
) -> Result<(), ExperimentError> {
    let mut legend = Vec::new();
    let mut x_max: f64 = 0.0;
    let panels = panels
        .into_iter()
        .map(|(title, lines)| Panel {
            title,
            lines: lines
                .into_iter()
                .map(|(label, role, points)| {
                    if !legend.iter().any(|(l, _)| *l == label) {
                        legend.push((label, role));
                    }
                    x_max = points.iter().fold(x_max, |m, p| m.max(p.0));
                    Line { points, role }
                })
                .collect(),
        })
        .collect();
    let fig = Figure {
        size: (crate::plot::render::WIDTH, crate::plot::render::HEIGHT),
        font_scale: 1.0,
        title,
        y_desc,
        x_range: (0.0, x_max.max(1e-3)),
        shade_until: None,
        zero_line: true,
        legend,
        panels,
    };
    super::write_figure(&fig, dir, name, files)
}

fn series(t: &[f64], y: &[f64], scale: f64) -> Vec<(f64, f64)> {
    t.iter().zip(y).map(|(t, y)| (*t, y * scale)).collect()
}

// ---------------------------------------------------------------------------------------------
// transparency

/// The compensations: name, controller, the config change it needs, what it is. The rows
/// named `…_inertia` add the default partial inertia compensation (`[haptics]
/// inertia_compensation`, docs/HAPTICS.md §3); the others compensate no inertia.
const TRANSPARENCY: [(&str, ControllerKind, &str); 6] = [
    ("none", ControllerKind::Off, "no compensation"),
    (
        "ct",
        ControllerKind::Ct,
        "the lab's parametric model (nominal parameters, no friction model)",
    ),
    (
        "nnidc",
        ControllerKind::Nnidc,
        "the learned model (shipped weights, learned online on the simulator)",
    ),
    (
        "exact",
        ControllerKind::Ct,
        "the plant's exact model with its friction (the oracle)",
    ),
    (
        "nnidc_inertia",
        ControllerKind::Nnidc,
        "the learned model, and β·M̂·q̈ (partial inertia compensation, the default)",
    ),
    (
        "exact_inertia",
        ControllerKind::Ct,
        "the exact model, and β·M·q̈ (partial inertia compensation, the default)",
    ),
];

/// The hand traces the path, then lets go 2 s before the end: how far the tip moves over
/// the last second, mm (the arm must stay stable without the hand).
fn let_go(out: &Path, secs: f64) -> Result<f64, ExperimentError> {
    let mut cfg = base_config();
    cfg.haptics.hand.pattern = HandPattern::Path;
    cfg.haptics.hand.release_s = secs - 2.0;
    let log = run(
        "free-nnidc-let-go",
        &cfg,
        ControllerKind::Nnidc,
        secs,
        &out.join("free-nnidc-let-go"),
        HapticRun {
            free: true,
            effects: Vec::new(),
        },
    )?;
    let t = log.col("t")?;
    let tip = log.group("tip")?;
    let from = t.iter().position(|&x| x >= secs - 1.0).unwrap_or(0);
    let last = t.len() - 1;
    let drift = ((0..3)
        .map(|i| (tip[i][last] - tip[i][from]).powi(2))
        .sum::<f64>())
    .sqrt();

    Ok(drift)
}

struct Transparency {
    rms: Vec<(&'static str, f64)>,
    let_go_drift_mm: f64,
}

fn transparency(
    out: &Path,
    quick: bool,
    md: &mut String,
    files: &mut Vec<PathBuf>,
) -> Result<Transparency, ExperimentError> {
    let secs = if quick { 4.0 } else { 12.0 };
    // The hand reaches the centre after 1 s and its full speed after 2 s: measure from 3 s.
    let from_s: f64 = 3.0;
    let mut rms = Vec::new();
    let mut lines = Vec::new();
    for (name, controller, _) in TRANSPARENCY {
        let mut cfg = base_config();
        cfg.haptics.hand.pattern = HandPattern::Path;
        cfg.control.ct_friction = name.starts_with("exact");
        if !name.ends_with("_inertia") {
            cfg.haptics.inertia_compensation = 0.0;
        }
        let log = run(
            &format!("free-{name}"),
            &cfg,
            controller,
            secs,
            &out.join(format!("free-{name}")),
            HapticRun {
                free: true,
                effects: Vec::new(),
            },
        )?;
        let t = log.col("t")?;
        let from = t
            .iter()
            .position(|&x| x >= from_s.min(secs / 2.0))
            .unwrap_or(0);
        let hand = log.group("fhand")?;
        rms.push((name, rms_norm(&hand, from)));
        let norm: Vec<f64> = (0..t.len())
            .map(|k| (hand[0][k].powi(2) + hand[1][k].powi(2) + hand[2][k].powi(2)).sqrt())
            .collect();
        let role = match name {
            "none" => Role::Target,
            "ct" => Role::Estimate,
            "nnidc" => Role::Measured,
            _ => Role::Error,
        };
        // The figure shows the four model compensations (no inertia).
        if !name.ends_with("_inertia") {
            lines.push((name, role, series(&t, &norm, 1.0)));
        }
    }
    figure(
        out,
        "transparency",
        "Force the hand feels tracing the path at 0.1 m/s in free mode",
        "‖hand force‖ (N)",
        vec![("none, ct, nnidc, exact", lines)],
        files,
    )?;
    let drift = let_go(out, secs)?;
    let none = rms[0].1;
    let _ = write!(md, "## Transparency\n\nThe simulated hand (grip 500 N/m, 5 N·s/m) traces a closed 3-D path around the workspace centre at 0.1 m/s in free mode; the table gives the RMS of the force in the grip from 3 s on (what the user would feel). The rows `…_inertia` add the partial inertia compensation at its default β = {} (`[haptics] inertia_compensation`); the others compensate no inertia.\n\n", base_config().haptics.inertia_compensation);
    md.push_str("| compensation | what | hand force RMS (N) | × none |\n|---|---|---:|---:|\n");
    for ((name, r), (_, _, what)) in rms.iter().zip(TRANSPARENCY) {
        let _ = writeln!(md, "| {name} | {what} | {r:.4} | {:.3} |", r / none);
    }
    let _ = writeln!(
        md,
        "\nLet go (nnidc, with the default inertia compensation): the hand releases the stylus at {:.0} s; over the last second the tip moved {drift:.3} mm.\n\n![Hand force in free mode](transparency.png) ([SVG](transparency.svg))\n",
        secs - 2.0
    );
    Ok(Transparency {
        rms,
        let_go_drift_mm: drift,
    })
}

// ---------------------------------------------------------------------------------------------
// walls

struct Wall {
    /// The kick limit was raised (the diagnostic runs).
    kick_raised: bool,
    axis: usize,
    stiffness: f64,
    passivity: bool,
    stable: bool,
    max_penetration_mm: f64,
    pp_mm: f64,
    hand_force_n: f64,
    energy_mj: f64,
}

/// The hand pushes into a wall across `axis` of `stiffness` N/mm.
fn wall_run(
    out: &Path,
    quick: bool,
    axis: usize,
    stiffness: f64,
    passivity: bool,
    kick_scale: f64,
) -> Result<(Wall, Log), ExperimentError> {
    let (_, sign) = PUSH[axis];
    let mut cfg = base_config();
    for r in &mut cfg.safety.max_torque_rate_nm_s {
        *r *= kick_scale;
    }
    cfg.haptics.hand.pattern = HandPattern::Push { axis, sign };
    cfg.haptics.passivity = passivity;
    let mut point = centre_mm(&cfg);
    point[axis] += sign * WALL_GAP_MM;
    let mut normal = [0.0; 3];
    normal[axis] = -sign;
    let wall = Effect::Plane {
        point_mm: point,
        normal,
        stiffness_n_per_mm: stiffness,
        damping_n_s_per_m: 0.0,
    };
    let secs = if quick { 3.0 } else { 4.0 };
    let name = format!(
        "wall-{}-{stiffness}-{}{}",
        AXES[axis],
        if passivity { "pc" } else { "open" },
        if kick_scale != 1.0 { "-kick" } else { "" }
    );
    let log = run(
        &name,
        &cfg,
        ControllerKind::Nnidc,
        secs,
        &out.join("walls").join(&name),
        HapticRun {
            free: true,
            effects: vec![wall],
        },
    )?;
    let t = log.col("t")?;
    let tip = log.col(&format!("tip{}", axis + 1))?;
    let force = log.col(&format!("fcmd{}", axis + 1))?;
    let hand = log.col(&format!("fhand{}", axis + 1))?;
    let depth: Vec<f64> = tip.iter().map(|p| (p - point[axis]) * sign).collect();
    let last = t.iter().position(|&x| x >= secs - 1.0).unwrap_or(0);
    let window = &depth[last..];
    let pp = window.iter().cloned().fold(f64::MIN, f64::max)
        - window.iter().cloned().fold(f64::MAX, f64::min);
    let pushing = hand[last..].iter().map(|f| f * sign).sum::<f64>() / window.len() as f64;
    // Work the wall did on the hand over the last second, mJ (F of the tick before times the
    // tip's displacement): bounded near zero when the wall holds still.
    let energy: f64 = (last.max(1)..t.len())
        .map(|k| force[k - 1] * (tip[k] - tip[k - 1]))
        .sum();
    let target = cfg.haptics.hand.push_force_n;
    let w = Wall {
        kick_raised: kick_scale != 1.0,
        axis,
        stiffness,
        passivity,
        stable: pp <= STABLE_PP_MM && pushing >= STABLE_FORCE_FRACTION * target,
        max_penetration_mm: depth.iter().cloned().fold(0.0, f64::max),
        pp_mm: pp,
        hand_force_n: pushing,
        energy_mj: energy,
    };
    Ok((w, log))
}

/// The stiffest wall that held on one axis: (without, with) the passivity controller, N/mm.
type AxisStiffest = (Option<f64>, Option<f64>);
/// The same per axis.
type Stiffest = [AxisStiffest; 3];

/// One axis: the vendor's stiffness first, then stiffer until neither variant holds (a wall
/// counts only when every softer one held too). Its walls, the figure's lines (the vendor's
/// stiffness), and the stiffest that held.
fn sweep_axis(
    out: &Path,
    quick: bool,
    axis: usize,
    all: &mut Vec<Wall>,
) -> Result<(Vec<Series>, AxisStiffest), ExperimentError> {
    let mut stiffest = (None, None);
    let mut lines = Vec::new();
    let sweep: &[f64] = if quick { &SWEEP[..2] } else { &SWEEP };
    let ks = std::iter::once(NOMINAL_STIFFNESS[axis]).chain(
        sweep
            .iter()
            .copied()
            .filter(|&k| k > NOMINAL_STIFFNESS[axis]),
    );
    let mut holding = (true, true);
    for k in ks {
        let (open, log_open) = wall_run(out, quick, axis, k, false, 1.0)?;
        let (pc, log_pc) = wall_run(out, quick, axis, k, true, 1.0)?;
        if k == NOMINAL_STIFFNESS[axis] {
            let mut t_end: f64 = 0.0;
            for (log, label, role) in [
                (&log_open, "passivity control off", Role::Target),
                (&log_pc, "passivity control on", Role::Measured),
            ] {
                let t = log.col("t")?;
                t_end = t.iter().fold(t_end, |m, &x| m.max(x));
                let tip = log.col(&format!("tip{}", axis + 1))?;
                lines.push((label, role, series(&t, &tip, 1.0)));
            }
            // The wall's surface, under the tip's lines.
            let (_, sign) = PUSH[axis];
            let surface = centre_mm(&base_config())[axis] + sign * WALL_GAP_MM;
            lines.insert(
                0,
                (
                    "the wall's surface",
                    Role::Wall,
                    vec![(0.0, surface), (t_end, surface)],
                ),
            );
        }
        holding = (holding.0 && open.stable, holding.1 && pc.stable);
        if holding.0 {
            stiffest.0 = Some(k);
        }
        if holding.1 {
            stiffest.1 = Some(k);
        }
        all.push(open);
        all.push(pc);
        if !holding.0 && !holding.1 {
            break;
        }
    }
    Ok((lines, stiffest))
}

fn walls(
    out: &Path,
    quick: bool,
    md: &mut String,
    files: &mut Vec<PathBuf>,
) -> Result<(Vec<Wall>, Stiffest), ExperimentError> {
    let mut all = Vec::new();
    let mut stiffest: Stiffest = [(None, None); 3];
    let mut panels = Vec::new();
    for axis in 0..3 {
        let (lines, s) = sweep_axis(out, quick, axis, &mut all)?;
        stiffest[axis] = s;
        panels.push((["x axis", "y axis", "z axis"][axis], lines));
    }
    // What limits the stiffness: the same y walls with the kick limit ten times higher.
    let diag: &[f64] = if quick { &[30.0] } else { &[20.0, 30.0, 40.0] };
    for &k in diag {
        for pc in [false, true] {
            all.push(wall_run(out, quick, 1, k, pc, 10.0)?.0);
        }
    }
    figure(
        out,
        "walls",
        "Tip while the hand pushes with 1 N into a wall at the vendor's stiffness (grey: the wall)",
        "tip (mm)",
        panels,
        files,
    )?;
    walls_markdown(md, &all, &stiffest);
    Ok((all, stiffest))
}

/// The walls' tables.
fn walls_markdown(md: &mut String, all: &[Wall], stiffest: &Stiffest) {
    md.push_str("## Walls\n\nThe hand moves from the centre towards a wall 10 mm away (x: to the right, y: down onto a floor, z: away from the user) at 0.1 m/s and settles pushing with 1 N. A wall *holds* when over the last second the tip moves at most 0.15 mm peak to peak (about two encoder counts at the tip) and the hand still pushes with at least 0.8 N (it is not bouncing off). The nnidc compensation is active.\n\n*Passivity control* off (the logs named `-open` in `walls/`: the wall's force as computed, nothing watching its energy) or on (`-pc`: the passivity observer sums the energy the wall has put into the hand, and when it would give out more than it took in, the controller adds damping to take the excess back; docs/HAPTICS.md §6). *Max penetration* is how deep the tip went past the surface; *peak-to-peak* how much it still moves over the last second (smaller is steadier); *hand force* the hand's push over the last second (1 N when it rests on the wall). *Wall's work on the hand* is the work the wall's force did on the moving tip over the last second (the force of each tick times the tip's displacement): positive means the wall gave the hand more energy than it took from it in that second. A passive wall can give back only what the push stored in it, so over a second in which the tip holds still the work is near zero either way; a wall that keeps giving energy is pumping it into the hand, which is what makes a wall buzz. Closer to zero is better. But read it with the peak-to-peak column: the sum uses each tick's force times the next displacement, and a tip that dithers by one encoder count (about 0.06 mm at the tip) against a wall whose force steps with that count adds about k·(0.06 mm)² to it per back-and-forth (0.01 mJ at 3 N/mm), a few mJ over a second of such dither, without the hand feeling any bounce. That is why it can be larger with passivity control on (its damping acts on the velocity estimated from the same encoder steps, so its force moves with every step too) while the wall holds just as still: a wall that really pumps energy shows it as a growing peak-to-peak and a hand force below 1 N, and then `holds` says no.\n\n| axis | stiffness (N/mm) | passivity control | holds | max penetration (mm) | peak-to-peak, last s (mm) | hand force (N) | wall's work on the hand, last s (mJ) |\n|---|---:|---|---|---:|---:|---:|---:|\n");
    for w in all.iter().filter(|w| !w.kick_raised) {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {} | {:.3} | {:.3} | {:.3} | {:.3} |",
            AXES[w.axis],
            w.stiffness,
            if w.passivity { "on" } else { "off" },
            if w.stable { "yes" } else { "no" },
            w.max_penetration_mm,
            w.pp_mm,
            w.hand_force_n,
            w.energy_mj
        );
    }
    let show = |k: Option<f64>| k.map_or("none".to_string(), |k| format!("{k} N/mm"));
    md.push_str("\nStiffest wall that holds (of those tried; every softer one held too):\n\n| axis | vendor | without passivity control | with passivity control |\n|---|---:|---:|---:|\n");
    for axis in 0..3 {
        let _ = writeln!(
            md,
            "| {} | {} N/mm | {} | {} |",
            AXES[axis],
            NOMINAL_STIFFNESS[axis],
            show(stiffest[axis].0),
            show(stiffest[axis].1)
        );
    }
    md.push_str("\nWhat limits it: the safety layer's kick limit (`safety.max_torque_rate_nm_s`, 50 N·m/s: about 0.35 N per tick at the tip) delays the wall's force when the tip strikes it, and the tip bounces. The same y walls with that limit ten times higher (a diagnostic, not the default):\n\n| stiffness (N/mm) | passivity control | holds | peak-to-peak, last s (mm) | hand force (N) |\n|---:|---|---|---:|---:|\n");
    for w in all.iter().filter(|w| w.kick_raised) {
        let _ = writeln!(
            md,
            "| {} | {} | {} | {:.3} | {:.3} |",
            w.stiffness,
            if w.passivity { "on" } else { "off" },
            if w.stable { "yes" } else { "no" },
            w.pp_mm,
            w.hand_force_n
        );
    }
    md.push_str("\n![Walls](walls.png) ([SVG](walls.svg))\n\nIn the figure the grey line is the wall's surface; where the two tip lines lie on top of each other, the passivity controller found no energy to take back at the vendor's stiffness and changed nothing.\n\n");
}

// ---------------------------------------------------------------------------------------------
// force accuracy

/// The largest error (N) a half DAC count on each joint can make in the tip force at `q`:
/// ‖J⁻ᵀ δτ‖ maximised over the signs of δτ.
fn dac_bound(cfg: &Config, q: &Joint3) -> f64 {
    let jt_inv = match jacobian(&cfg.geometry, q).transpose().try_inverse() {
        Some(m) => m,
        None => return f64::INFINITY,
    };
    let half = Joint3::from(cfg.device.nm_per_count) * 0.5;
    let mut worst: f64 = 0.0;
    for signs in 0..8 {
        let d = Joint3::from_fn(|j, _| half[j] * if signs >> j & 1 == 1 { -1.0 } else { 1.0 });
        worst = worst.max((jt_inv * d).amax());
    }
    worst
}

struct Accuracy {
    max_error_n: f64,
    bound_n: f64,
}

fn force_accuracy(out: &Path, md: &mut String) -> Result<Accuracy, ExperimentError> {
    let mut cfg = base_config();
    cfg.sim.torque_noise_nm = 0.0;
    cfg.control.ct_friction = true;
    cfg.haptics.hand.pattern = HandPattern::Hold;
    let mut max_error: f64 = 0.0;
    let mut bound: f64 = 0.0;
    md.push_str("## Force accuracy\n\nThe hand holds the stylus still at the centre (grip 500 N/m) while the scene commands a constant force; the exact model compensates gravity, so at rest the hand must hold exactly the commanded force. Mean over the last 0.5 s of 3 s.\n\n| commanded (N) | hand holds (N) | error, largest component (N) | DAC bound (N) |\n|---|---|---:|---:|\n");
    for (k, f) in [[0.5, 0.0, 0.0], [0.0, -1.0, 0.0], [0.3, 0.6, -0.9]]
        .into_iter()
        .enumerate()
    {
        let log = run(
            "force",
            &cfg,
            ControllerKind::Ct,
            3.0,
            &out.join(format!("force-{k}")),
            HapticRun {
                free: true,
                effects: vec![Effect::Constant { force_n: f }],
            },
        )?;
        let t = log.col("t")?;
        let from = t.iter().position(|&x| x >= 2.5).unwrap_or(0);
        let hand = log.group("fhand")?;
        let n = (t.len() - from) as f64;
        let mean: [f64; 3] = std::array::from_fn(|i| hand[i][from..].iter().sum::<f64>() / n);
        // The hand holds against the device: its force is the commanded one reversed.
        let err = (0..3).map(|i| (mean[i] + f[i]).abs()).fold(0.0, f64::max);
        let q = log.group("q")?;
        let last = t.len() - 1;
        let b = dac_bound(&cfg, &Joint3::new(q[0][last], q[1][last], q[2][last]));
        max_error = max_error.max(err);
        bound = bound.max(b);
        let _ = writeln!(
            md,
            "| {f:?} | [{:.4}, {:.4}, {:.4}] | {err:.5} | {b:.5} |",
            -mean[0], -mean[1], -mean[2]
        );
    }
    md.push('\n');
    Ok(Accuracy {
        max_error_n: max_error,
        bound_n: bound,
    })
}

/// Run the whole experiment into `out`.
pub fn run_haptics(out: &Path, quick: bool) -> Result<ExperimentReport, ExperimentError> {
    crate::output::check_dir(out).map_err(ExperimentError::OutDir)?;
    for f in ["report.md", "results.json"] {
        crate::output::check_file(&out.join(f))?;
    }
    let mut figures = Vec::new();
    let mut md = String::from("# Haptics on the simulated Omni\n\nFree mode, walls and force accuracy measured with the simulated hand (docs/HAPTICS.md). Every run: `--fast` on the simulator, starting at the centre of the workspace; logs and figures beside this report.\n\n");
    if quick {
        md.push_str(
            "*`--quick`: shortened runs and sweep; the numbers are not the full experiment's.*\n\n",
        );
    }
    let tr = transparency(out, quick, &mut md, &mut figures)?;
    let (walls, stiffest) = walls(out, quick, &mut md, &mut figures)?;
    let acc = force_accuracy(out, &mut md)?;
    let mut transparency = serde_json::Map::new();
    for (name, r) in &tr.rms {
        transparency.insert(name.to_string(), json!({ "hand_force_rms_n": r }));
    }
    let results: Value = json!({
        "transparency": transparency,
        "let_go_drift_mm": tr.let_go_drift_mm,
        "walls": walls.iter().filter(|w| !w.kick_raised).map(|w| json!({
            "axis": AXES[w.axis],
            "stiffness_n_per_mm": w.stiffness,
            "passivity_control": w.passivity,
            "stable": w.stable,
            "max_penetration_mm": w.max_penetration_mm,
            "peak_to_peak_last_s_mm": w.pp_mm,
            "hand_force_n": w.hand_force_n,
            "wall_work_on_hand_last_s_mj": w.energy_mj,
        })).collect::<Vec<_>>(),
        "stiffest_stable_n_per_mm": AXES.iter().zip(stiffest).map(|(a, (open, pc))| json!({
            "axis": a, "without_passivity_control": open, "with_passivity_control": pc,
        })).collect::<Vec<_>>(),
        "walls_kick_limit_x10": walls.iter().filter(|w| w.kick_raised).map(|w| json!({
            "axis": AXES[w.axis],
            "stiffness_n_per_mm": w.stiffness,
            "passivity_control": w.passivity,
            "stable": w.stable,
            "peak_to_peak_last_s_mm": w.pp_mm,
        })).collect::<Vec<_>>(),
        "force_accuracy": { "max_error_n": acc.max_error_n, "dac_bound_n": acc.bound_n },
        "quick": quick,
    });
    let text = serde_json::to_string_pretty(&results)
        .map_err(|e| ExperimentError::Internal(e.to_string()))?;
    crate::output::write_bytes(&out.join("results.json"), text.as_bytes())?;
    let report = out.join("report.md");
    crate::output::write_bytes(&report, md.as_bytes())?;
    Ok(ExperimentReport {
        report,
        figures,
        markdown: md,
    })
}

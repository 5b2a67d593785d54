//! `omnid plot`: figures like the paper's from a log, as PNG and SVG.
//!
//! [`plot_log`] reads the header, plans which figures the log's columns can feed
//! (`figures`), streams the rows once through the crate's log reader into a min/max decimator
//! (`read`, `decimate`) and draws each figure (`render`). Figures whose columns are missing are skipped and
//! reported, so a seven-column log from another tool still gets its angle and torque plots.

pub(crate) mod decimate;
pub(crate) mod figures;
pub(crate) mod read;
pub(crate) mod render;

pub use figures::Skipped;
pub use render::RenderError;

use crate::output::OutputError;
use crate::telemetry::reader::ReadError;
use figures::PlannedFigure;
use read::LogReader;
use std::fmt;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Buckets kept by the decimator: at least this many, at most twice as many, each giving
/// a min and a max. The plot area is ~1100 px wide, so this is about one point per pixel.
const BUCKETS: usize = 1024;

/// Logs at least this big get a progress bar (about 10 s of a full log; smaller ones are
/// read before a bar would be worth drawing).
const PROGRESS_MIN_BYTES: u64 = 16 << 20;

/// Why `omnid plot` drew nothing, or not everything.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// The log could not be read, or a row of it is bad.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The log's columns feed no figure at all.
    #[error("{}: nothing to plot: {}", path.display(), reasons(skipped))]
    NothingToPlot {
        /// The log.
        path: PathBuf,
        /// Every figure, and what the log lacks for it.
        skipped: Vec<Skipped>,
    },
    /// The output directory cannot be made or used.
    #[error("--out: output directory: {0}")]
    OutDir(OutputError),
    /// A figure's file cannot be written there (checked before the log is read).
    #[error("--out: {0}")]
    Output(#[from] OutputError),
    /// `--from`/`--to` leave no row of the log.
    #[error("--from {from} --to {to}: no row of the log in that window (its rows span {first} to {last} s)")]
    EmptyWindow {
        /// The window asked for, s.
        from: f64,
        /// Its end, s.
        to: f64,
        /// The log's first time, s.
        first: f64,
        /// Its last time, s.
        last: f64,
    },
    /// A window whose end is not after its start, or not a number.
    #[error("--from {from} --to {to}: the window must have --from before --to")]
    BadWindow {
        /// Start asked for, s.
        from: f64,
        /// End asked for, s.
        to: f64,
    },
    /// A figure size or font scale outside what can be drawn.
    #[error("{what}: {why}")]
    BadStyle {
        /// The option.
        what: &'static str,
        /// What is wrong with it.
        why: String,
    },
    /// A figure could not be drawn or written.
    #[error("writing {}: {source}", file.display())]
    Render {
        /// The figure's file.
        file: PathBuf,
        /// Why.
        source: RenderError,
    },
}

impl PlotError {
    /// The user's input is at fault (a bad or unusable log, an output directory that cannot be
    /// made), not the program.
    pub fn is_bad_input(&self) -> bool {
        !matches!(self, PlotError::Render { .. })
    }

    /// The operator stopped it while the log was read.
    pub fn is_stopped(&self) -> bool {
        matches!(self, PlotError::Read(ReadError::Stopped { .. }))
    }
}

/// The file of one figure in one format.
fn figure_file(out_dir: &Path, name: &str, format: render::Format) -> PathBuf {
    out_dir.join(format!("{name}.{}", format.extension()))
}

fn reasons(skipped: &[Skipped]) -> String {
    skipped
        .iter()
        .map(|s| format!("{}: {}", s.figure, s.reason))
        .collect::<Vec<_>>()
        .join("; ")
}

/// What [`plot_log`] did.
#[derive(Debug, Clone)]
pub struct PlotReport {
    /// Data rows read.
    pub rows: u64,
    /// Figures drawn (file stems), in order.
    pub figures: Vec<&'static str>,
    /// Every file written (a PNG and an SVG per figure).
    pub files: Vec<PathBuf>,
    /// Figures not drawn, and why.
    pub skipped: Vec<Skipped>,
    /// Figures drawn without one of their optional lines, and why.
    pub notes: Vec<String>,
}

impl fmt::Display for PlotReport {
    /// The human summary `omnid plot` prints.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "omnid plot: {} rows, {} figures ({} files)",
            self.rows,
            self.figures.len(),
            self.files.len()
        )?;
        for file in &self.files {
            writeln!(f, "  wrote   {}", file.display())?;
        }
        for note in &self.notes {
            writeln!(f, "  note    {note}")?;
        }
        for s in &self.skipped {
            writeln!(f, "  skipped {}: {}", s.figure, s.reason)?;
        }
        Ok(())
    }
}

/// How the figures are drawn: which part of the log, how large, with what text size.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlotOptions {
    /// Only rows from this time on, s (the log's own `t`).
    pub from_s: Option<f64>,
    /// Only rows up to this time, s.
    pub to_s: Option<f64>,
    /// Figure size, px (the SVG's user units too).
    pub width: u32,
    /// Figure height, px.
    pub height: u32,
    /// Text size relative to the default (1.0).
    pub font_scale: f64,
}

impl Default for PlotOptions {
    fn default() -> Self {
        PlotOptions {
            from_s: None,
            to_s: None,
            width: render::WIDTH,
            height: render::HEIGHT,
            font_scale: 1.0,
        }
    }
}

impl PlotOptions {
    /// Sizes and windows that can be drawn, or the option that cannot.
    pub fn check(&self) -> Result<(), PlotError> {
        let bad = |what, why: String| Err(PlotError::BadStyle { what, why });
        for (what, v, lo) in [("--width", self.width, 400), ("--height", self.height, 300)] {
            if !(lo..=render::MAX_SIDE).contains(&v) {
                return bad(
                    what,
                    format!("{v} px is outside {lo}..={} px", render::MAX_SIDE),
                );
            }
        }
        if !(0.5..=3.0).contains(&self.font_scale) {
            return bad(
                "--font-scale",
                format!(
                    "{} is outside 0.5..=3 (the text must fit the panels)",
                    self.font_scale
                ),
            );
        }
        let (from, to) = self.window();
        if from.is_nan() || to.is_nan() || from >= to {
            return Err(PlotError::BadWindow { from, to });
        }
        Ok(())
    }

    fn window(&self) -> (f64, f64) {
        (
            self.from_s.unwrap_or(f64::NEG_INFINITY),
            self.to_s.unwrap_or(f64::INFINITY),
        )
    }
}

/// Draw every figure `log` can feed into `out_dir` (created if needed) as `<name>.png` and
/// `<name>.svg`. The output paths are checked before the rows are read. `stop` (the
/// operator's) ends the reading (see [`crate::input::open`]).
pub fn plot_log(
    log: &Path,
    out_dir: &Path,
    scene: &[crate::haptics::Effect],
    options: &PlotOptions,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<PlotReport, PlotError> {
    options.check()?;
    let (from, to) = options.window();
    let reader = LogReader::open(log, stop)?.window(from, to);
    let plan = figures::plan(reader.header());
    if plan.figures.is_empty() {
        return Err(PlotError::NothingToPlot {
            path: log.to_path_buf(),
            skipped: plan.skipped,
        });
    }

    // Before the work: every file this plot will write. A directory made for this check is
    // removed again if the plot then fails (an empty one; nothing else is touched).
    let made_dir = !out_dir.exists();
    crate::output::check_dir(out_dir).map_err(PlotError::OutDir)?;
    let result = draw(out_dir, reader, plan, scene, options);
    if result.is_err() && made_dir {
        let _ = std::fs::remove_dir(out_dir);
    }
    result
}

/// Check the figure files, read the rows once and draw every planned figure.
fn draw(
    out_dir: &Path,
    reader: LogReader,
    mut plan: figures::Plan,
    scene: &[crate::haptics::Effect],
    options: &PlotOptions,
) -> Result<PlotReport, PlotError> {
    for planned in &plan.figures {
        for format in render::FORMATS {
            crate::output::check_file(&figure_file(out_dir, planned.def.name, format))?;
        }
    }

    let bar = if reader.bytes() >= PROGRESS_MIN_BYTES {
        crate::progress::bytes(reader.bytes(), "reading log")
    } else {
        indicatif::ProgressBar::hidden()
    };
    let data = reader.decimate(&plan.formulas, BUCKETS, |pos| bar.set_position(pos))?;
    bar.finish_and_clear();
    if data.decimated.rows == 0 {
        let (from, to) = options.window();
        return Err(PlotError::EmptyWindow {
            from,
            to,
            first: data.seen.0,
            last: data.seen.1,
        });
    }

    // A figure for another kind of run is left out: tracking errors mean nothing where
    // nothing tracked (free mode), and a tracking run has no tip forces to show.
    let not_for = |shows: figures::Shows| match (shows, data.modes) {
        (figures::Shows::Tracking, Some((0, haptic))) if haptic > 0 => {
            Some("a haptic run: no row follows a reference (mode free or servo_cf)")
        }
        (figures::Shows::Haptic, None | Some((_, 0))) => {
            Some("no row in a haptic mode (free, servo_cf)")
        }
        _ => None,
    };
    let (drawn, left): (Vec<_>, Vec<_>) = std::mem::take(&mut plan.figures)
        .into_iter()
        .partition(|f| not_for(f.def.shows).is_none());
    // A run that is not haptic is not told about the haptic figures it has no use for (its
    // report stays as it was); a haptic run is told why its tracking figure is missing.
    let haptic_run = data.modes.is_some_and(|(_, h)| h > 0);
    let is_haptic = |name: &str| {
        figures::FIGURES
            .iter()
            .any(|d| d.name == name && d.shows == figures::Shows::Haptic)
    };
    if !haptic_run {
        plan.skipped.retain(|s| !is_haptic(s.figure));
        plan.notes.retain(|n| {
            !figures::FIGURES.iter().any(|d| {
                d.shows == figures::Shows::Haptic && n.starts_with(&format!("{}:", d.name))
            })
        });
    }
    for f in left
        .into_iter()
        .filter(|f| haptic_run || f.def.shows != figures::Shows::Haptic)
    {
        plan.skipped.push(Skipped {
            figure: f.def.name,
            reason: not_for(f.def.shows).unwrap_or_default().to_string(),
        });
    }
    plan.figures = drawn;
    let walls = walls(scene);

    let mut files = Vec::new();
    for planned in &plan.figures {
        let mut figure = assemble(planned, &data.decimated, data.blend_end);
        figure.size = (options.width, options.height);
        figure.font_scale = options.font_scale;
        if planned.def.name == "tip_path" {
            add_walls(&mut figure, &walls);
        }
        for format in render::FORMATS {
            let file = figure_file(out_dir, planned.def.name, format);
            render::write(&figure, format, &file).map_err(|source| PlotError::Render {
                file: file.clone(),
                source,
            })?;
            files.push(file);
        }
    }
    Ok(PlotReport {
        rows: data.decimated.rows,
        figures: plan.figures.iter().map(|f| f.def.name).collect(),
        files,
        skipped: plan.skipped,
        notes: plan.notes,
    })
}

/// The walls of `scene` the tip path's panels can show, per axis (mm): an axis-aligned
/// plane's surface, a box's two faces on every axis. A tilted plane is not one line on any
/// axis, and springs, dampers and constant forces have no wall.
fn walls(scene: &[crate::haptics::Effect]) -> [Vec<f64>; 3] {
    use crate::haptics::Effect;
    let mut walls: [Vec<f64>; 3] = Default::default();
    for e in scene {
        match *e {
            Effect::Plane {
                point_mm, normal, ..
            } => {
                let axes: Vec<usize> = (0..3).filter(|&a| normal[a] != 0.0).collect();
                if let [a] = axes[..] {
                    walls[a].push(point_mm[a]);
                }
            }
            Effect::Box { min_mm, max_mm, .. } => {
                for a in 0..3 {
                    walls[a].extend([min_mm[a], max_mm[a]]);
                }
            }
            _ => {}
        }
    }
    walls
}

/// Draw `walls` (per panel, mm) across the figure's time range, under the tip.
fn add_walls(figure: &mut render::Figure, walls: &[Vec<f64>; 3]) {
    if walls.iter().all(Vec::is_empty) {
        return;
    }
    let (t0, t1) = figure.x_range;
    for (panel, ys) in figure.panels.iter_mut().zip(walls) {
        for &y in ys {
            panel.lines.insert(
                0,
                render::Line {
                    points: vec![(t0, y), (t1, y)],
                    role: figures::Role::Wall,
                },
            );
        }
    }
    figure
        .legend
        .insert(0, ("wall of an effect (the scene)", figures::Role::Wall));
}

/// The drawable figure: the planned lines' decimated points, scaled to plotted units.
fn assemble(
    planned: &PlannedFigure,
    data: &decimate::Decimated,
    blend_end: Option<f64>,
) -> render::Figure {
    let def = planned.def;
    let panels = (0..3)
        .map(|j| render::Panel {
            title: def.panels[j],
            lines: planned
                .lines
                .iter()
                .map(|line| render::Line {
                    points: data.channels[line.channels[j]]
                        .iter()
                        .map(|&(t, v)| (t, v * def.scale))
                        .collect(),
                    role: line.def.role,
                })
                .collect(),
        })
        .collect();
    render::Figure {
        title: def.title,
        y_desc: def.y_desc,
        x_range: data.t_range,
        // Shaded so the start-up transient is not mistaken for tracking behaviour.
        shade_until: blend_end.filter(|&b| b > data.t_range.0),
        zero_line: def.zero_line,
        size: (render::WIDTH, render::HEIGHT),
        font_scale: 1.0,
        legend: planned
            .lines
            .iter()
            .map(|l| (l.def.label, l.def.role))
            .collect(),
        panels,
    }
}

//! Which figures exist, what each draws, and which of them a given log can feed. Planning only
//! looks at the header, so a figure's absence is known (and reported) before any row is read.

use super::read::{Formula, Header};

/// A quantity logged per joint as `{prefix}1`, `{prefix}2`, `{prefix}3`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Signal {
    /// Measured joint angle, rad.
    Q,
    /// Reference joint angle, rad.
    Ref,
    /// Torque applied to the motors (after the safety layer), N·m.
    Tau,
    /// The controller's output before the safety layer, N·m.
    TauCmd,
    /// The identifier's estimate of `tau`, N·m.
    TauHat,
    /// The stylus tip, mm (OpenHaptics frame; per axis, not per joint).
    Tip,
    /// The tip force commanded (effects, a client's force), N, per axis.
    Fcmd,
    /// The simulated hand's force on the tip, N, per axis.
    Fhand,
    /// The outside's force on the tip estimated from the motors and the model, N, per axis
    /// (docs/TELEOP.md §2).
    Fext,
}

impl Signal {
    pub fn prefix(self) -> &'static str {
        match self {
            Signal::Q => "q",
            Signal::Ref => "ref",
            Signal::Tau => "tau",
            Signal::TauCmd => "tau_cmd",
            Signal::TauHat => "tau_hat",
            Signal::Tip => "tip",
            Signal::Fcmd => "fcmd",
            Signal::Fhand => "fhand",
            Signal::Fext => "fext",
        }
    }

    fn meaning(self) -> &'static str {
        match self {
            Signal::Q => "the measured angles",
            Signal::Ref => "the reference",
            Signal::Tau => "the applied torque",
            Signal::TauCmd => "the controller's output",
            Signal::TauHat => "the identifier's torque estimate",
            Signal::Tip => "the stylus tip",
            Signal::Fcmd => "the tip force commanded",
            Signal::Fhand => "the simulated hand's force",
            Signal::Fext => "the estimated outside force",
        }
    }
}

/// What one line of a figure shows.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Quantity {
    Of(Signal),
    /// The first minus the second.
    Difference(Signal, Signal),
}

/// How a line is drawn; the renderer maps roles to colours and widths so that every figure
/// reads the same way (the target wide and pale underneath, the measurement on top).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// What the measurement is compared against (reference, controller output).
    Target,
    /// The measured signal.
    Measured,
    /// A model's estimate.
    Estimate,
    /// An error signal.
    Error,
    /// An effect's wall (a scene's geometry, drawn where the tip would meet it).
    Wall,
}

/// Which runs a figure is for: decided once the rows are read (the `mode` column).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Shows {
    /// Every log that has its columns.
    Always,
    /// Logs with rows that track a reference (`blend`, `track`), or without a `mode` column.
    Tracking,
    /// Logs with rows in a haptic mode (`free`, `servo_cf`).
    Haptic,
}

/// One line of a figure, as defined: what it shows and how it is drawn.
#[derive(Debug)]
pub struct LineDef {
    /// Legend text.
    pub label: &'static str,
    /// What is plotted, per joint.
    pub quantity: Quantity,
    /// Its pen.
    pub role: Role,
    /// Without it the figure is skipped; without an optional line it is drawn without it.
    pub required: bool,
}

/// One figure, as defined: three panels (one per joint) with the same lines.
#[derive(Debug)]
pub struct FigureDef {
    /// File stem: `<name>.png`, `<name>.svg`.
    pub name: &'static str,
    /// Heading drawn above the panels.
    pub title: &'static str,
    /// Y-axis description, with its unit.
    pub y_desc: &'static str,
    /// Log units (SI) to plotted units.
    pub scale: f64,
    /// Draw y = 0 (error signals).
    pub zero_line: bool,
    /// Drawn in this order: later lines on top.
    pub lines: &'static [LineDef],
    /// The three panels' titles, top to bottom.
    pub panels: &'static [&'static str; 3],
    /// Which runs it is for.
    pub shows: Shows,
}

/// Every figure `omnid plot` can draw, in report order.
pub const FIGURES: &[FigureDef] = &[
    FigureDef {
        name: "angles",
        title: "Joint angles",
        y_desc: "angle (rad)",
        scale: 1.0,
        zero_line: false,
        panels: &JOINTS,
        shows: Shows::Always,
        lines: &[
            LineDef {
                label: "reference (ref)",
                quantity: Quantity::Of(Signal::Ref),
                role: Role::Target,
                required: false,
            },
            LineDef {
                label: "measured (q)",
                quantity: Quantity::Of(Signal::Q),
                role: Role::Measured,
                required: true,
            },
        ],
    },
    FigureDef {
        name: "torque_identification",
        title: "Measured torque and the identifier's estimate (paper Fig. 4)",
        y_desc: "torque (N·m)",
        scale: 1.0,
        zero_line: false,
        panels: &JOINTS,
        shows: Shows::Always,
        lines: &[
            LineDef {
                label: "measured (tau)",
                quantity: Quantity::Of(Signal::Tau),
                role: Role::Measured,
                required: true,
            },
            LineDef {
                label: "identifier estimate (tau_hat)",
                quantity: Quantity::Of(Signal::TauHat),
                role: Role::Estimate,
                required: true,
            },
        ],
    },
    FigureDef {
        name: "identification_error",
        title: "Identification error: tau − tau_hat",
        y_desc: "error (N·m)",
        scale: 1.0,
        zero_line: true,
        panels: &JOINTS,
        shows: Shows::Always,
        lines: &[LineDef {
            label: "tau − tau_hat",
            quantity: Quantity::Difference(Signal::Tau, Signal::TauHat),
            role: Role::Error,
            required: true,
        }],
    },
    FigureDef {
        name: "control_effort",
        title: "Control effort",
        y_desc: "torque (N·m)",
        scale: 1.0,
        zero_line: true,
        panels: &JOINTS,
        shows: Shows::Always,
        lines: &[
            LineDef {
                label: "controller output (tau_cmd)",
                quantity: Quantity::Of(Signal::TauCmd),
                role: Role::Target,
                required: false,
            },
            LineDef {
                label: "applied, after safety limits (tau)",
                quantity: Quantity::Of(Signal::Tau),
                role: Role::Measured,
                required: true,
            },
        ],
    },
    FigureDef {
        name: "tracking_error",
        title: "Tracking error: ref − q",
        // Errors are a few mrad on a 0.5 rad motion: in rad the ticks would be all zeros.
        y_desc: "error (mrad)",
        scale: 1e3,
        zero_line: true,
        panels: &JOINTS,
        shows: Shows::Tracking,
        lines: &[LineDef {
            label: "ref − q",
            quantity: Quantity::Difference(Signal::Ref, Signal::Q),
            role: Role::Error,
            required: true,
        }],
    },
    FigureDef {
        name: "tip_path",
        title: "Tip path, with the scene's walls (omnid plot --scene)",
        y_desc: "position (mm)",
        scale: 1.0,
        zero_line: false,
        panels: &AXES,
        shows: Shows::Haptic,
        lines: &[LineDef {
            label: "tip",
            quantity: Quantity::Of(Signal::Tip),
            role: Role::Measured,
            required: true,
        }],
    },
    FigureDef {
        name: "tip_force",
        title: "Force on the tip: rendered by omnid, the hand's push, the estimate",
        y_desc: "force (N)",
        scale: 1.0,
        zero_line: true,
        panels: &AXES,
        shows: Shows::Haptic,
        lines: &[
            LineDef {
                label: "hand's push (fhand, simulator)",
                quantity: Quantity::Of(Signal::Fhand),
                role: Role::Target,
                required: false,
            },
            LineDef {
                label: "rendered (fcmd: effects, client force, after limits)",
                quantity: Quantity::Of(Signal::Fcmd),
                role: Role::Measured,
                required: true,
            },
            LineDef {
                label: "outside force estimated from the motors (fext)",
                quantity: Quantity::Of(Signal::Fext),
                role: Role::Estimate,
                required: false,
            },
        ],
    },
];

/// Axis names for the tip's panels (OpenHaptics frame).
pub const AXES: [&str; 3] = ["x (right)", "y (up)", "z (toward the user)"];

/// Joint names for panel titles (OpenHaptics convention).
pub const JOINTS: [&str; 3] = [
    "joint 1 (base yaw)",
    "joint 2 (upper arm)",
    "joint 3 (lower arm)",
];

/// A figure that will be drawn, with the lines the log can feed.
/// A figure this log can feed, with the lines it has the columns for.
#[derive(Debug)]
pub struct PlannedFigure {
    /// Its definition.
    pub def: &'static FigureDef,
    /// The lines to draw, in drawing order.
    pub lines: Vec<PlannedLine>,
}

/// A line this log can feed.
#[derive(Debug)]
pub struct PlannedLine {
    /// Its definition.
    pub def: &'static LineDef,
    /// Per joint: index into [`Plan::formulas`] (and so into the decimated channels).
    pub channels: [usize; 3],
}

/// A figure not drawn, and why.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Skipped {
    /// The figure's file stem (`tracking_error`, …).
    pub figure: &'static str,
    /// What the log lacks for it (`no ref1..3 columns`, …).
    pub reason: String,
}

/// What one log can be drawn as, decided from its header alone.
#[derive(Debug)]
pub struct Plan {
    /// Figures to draw, in report order.
    pub figures: Vec<PlannedFigure>,
    /// Figures not drawn, and why.
    pub skipped: Vec<Skipped>,
    /// Figures drawn without an optional line, and why.
    pub notes: Vec<String>,
    /// What to compute per row; shared between figures.
    pub formulas: Vec<Formula>,
}

/// The three columns of a signal, or why the log does not have them.
fn columns(header: &Header, signal: Signal) -> Result<[usize; 3], String> {
    let found = [1, 2, 3].map(|j| header.find(&format!("{}{j}", signal.prefix())));
    match found {
        [Some(a), Some(b), Some(c)] => Ok([a, b, c]),
        [None, None, None] => Err(format!(
            "no {p}1..3 columns ({m})",
            p = signal.prefix(),
            m = signal.meaning()
        )),
        partial => {
            let missing: Vec<String> = (1..=3)
                .zip(partial)
                .filter(|(_, f)| f.is_none())
                .map(|(j, _)| format!("{}{j}", signal.prefix()))
                .collect();
            Err(format!(
                "{} missing ({})",
                missing.join(", "),
                signal.meaning()
            ))
        }
    }
}

/// Per joint, how to compute `q` from a row, or why the log cannot.
fn resolve(header: &Header, q: Quantity) -> Result<[Formula; 3], String> {
    match q {
        Quantity::Of(s) => columns(header, s).map(|c| c.map(Formula::Column)),
        Quantity::Difference(a, b) => match (columns(header, a), columns(header, b)) {
            (Ok(a), Ok(b)) => Ok([0, 1, 2].map(|j| Formula::Difference(a[j], b[j]))),
            (Err(why), Ok(_)) | (Ok(_), Err(why)) => Err(why),
            (Err(x), Err(y)) => Err(format!("{x}; {y}")),
        },
    }
}

/// Decide from the header which figures and lines can be drawn, and what each row must give.
pub fn plan(header: &Header) -> Plan {
    let mut plan = Plan {
        figures: Vec::new(),
        skipped: Vec::new(),
        notes: Vec::new(),
        formulas: Vec::new(),
    };
    for def in FIGURES {
        let mut lines = Vec::new();
        let mut missing_required = Vec::new();
        let mut missing_optional: Vec<(&LineDef, String)> = Vec::new();
        for line in def.lines {
            let formulas = resolve(header, line.quantity);
            match formulas {
                Ok(f) => lines.push((line, f)),
                Err(why) if line.required => missing_required.push(why),
                Err(why) => missing_optional.push((line, why)),
            }
        }
        if !missing_required.is_empty() {
            missing_required.dedup();
            plan.skipped.push(Skipped {
                figure: def.name,
                reason: missing_required.join("; "),
            });
            continue;
        }
        for (line, why) in missing_optional {
            plan.notes.push(format!(
                "{}: drawn without \"{}\": {why}",
                def.name, line.label
            ));
        }
        let lines = lines
            .into_iter()
            .map(|(line, f)| PlannedLine {
                def: line,
                channels: f.map(|f| intern(&mut plan.formulas, f)),
            })
            .collect();
        plan.figures.push(PlannedFigure { def, lines });
    }
    plan
}

/// Index of `f` in `formulas`, added if new.
fn intern(formulas: &mut Vec<Formula>, f: Formula) -> usize {
    formulas.iter().position(|&g| g == f).unwrap_or_else(|| {
        formulas.push(f);
        formulas.len() - 1
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(cols: &str) -> Header {
        Header::new(cols.split(',').map(String::from).collect())
    }

    fn names(plan: &Plan) -> Vec<&str> {
        plan.figures.iter().map(|f| f.def.name).collect()
    }

    #[test]
    fn seven_column_log_gets_angles_and_effort() {
        let p = plan(&header("t,q1,q2,q3,tau1,tau2,tau3"));
        assert_eq!(names(&p), ["angles", "control_effort"]);
        let skipped: Vec<&str> = p.skipped.iter().map(|s| s.figure).collect();
        assert_eq!(
            skipped,
            [
                "torque_identification",
                "identification_error",
                "tracking_error",
                "tip_path",
                "tip_force"
            ]
        );
        assert!(
            p.skipped[0].reason.contains("tau_hat1..3"),
            "{:?}",
            p.skipped
        );
        assert!(p.skipped[2].reason.contains("ref1..3"), "{:?}", p.skipped);
        assert_eq!(p.notes.len(), 2, "{:?}", p.notes);
        // q1..3 and tau1..3, each parsed once.
        assert_eq!(p.formulas.len(), 6);
    }

    #[test]
    fn full_log_gets_every_figure_and_shares_columns() {
        let mut cols = vec!["t".to_string()];
        for g in [
            "q", "tau", "ref", "tau_cmd", "tau_hat", "tip", "fcmd", "fhand", "fext",
        ] {
            cols.extend((1..=3).map(|j| format!("{g}{j}")));
        }
        let p = plan(&Header::new(cols));
        assert_eq!(p.figures.len(), FIGURES.len());
        assert!(p.skipped.is_empty() && p.notes.is_empty());
        // 9 signals × 3 joints or axes + 2 differences × 3 joints.
        assert_eq!(p.formulas.len(), 33);
    }

    #[test]
    fn partial_groups_are_named() {
        let p = plan(&header("t,q1,q2,q3,tau1,tau2,tau3,ref1,tau_hat2"));
        let track = p
            .skipped
            .iter()
            .find(|s| s.figure == "tracking_error")
            .unwrap();
        assert!(track.reason.contains("ref2, ref3 missing"), "{track:?}");
        let ident = p
            .skipped
            .iter()
            .find(|s| s.figure == "torque_identification")
            .unwrap();
        assert!(
            ident.reason.contains("tau_hat1, tau_hat3 missing"),
            "{ident:?}"
        );
    }

    #[test]
    fn time_only_log_plans_nothing() {
        let p = plan(&header("t"));
        assert!(p.figures.is_empty());
        assert_eq!(p.skipped.len(), FIGURES.len());
    }
}

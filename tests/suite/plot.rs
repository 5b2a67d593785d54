//! `omnid plot` end to end: on a simulator log, on a seven-column log from another tool, on a
//! log with the identifier's estimate, and on logs it must refuse.

use crate::common;
use common::{omnid, run_ok, Log};
use std::fs::File;
use std::path::Path;

/// The measured-signal colour of the figures: its presence shows a line was drawn.
const MEASURED_RGB: [u8; 3] = [0, 90, 181];

/// Check that `dir/<name>.png` is a real 1200×900 PNG with a measured line in it, and that
/// `dir/<name>.svg` is a whole SVG document.
fn assert_figure(dir: &Path, name: &str) {
    let png_path = dir.join(format!("{name}.png"));
    let bytes = std::fs::read(&png_path).unwrap_or_else(|e| panic!("{}: {e}", png_path.display()));
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n", "{name}.png signature");
    let decoder = png::Decoder::new(std::io::BufReader::new(File::open(&png_path).unwrap()));
    let mut reader = decoder.read_info().expect("PNG header decodes");
    let (w, h) = (reader.info().width, reader.info().height);
    assert_eq!((w, h), (1200, 900), "{name}.png size");
    let mut pixels = vec![0; reader.output_buffer_size().expect("size fits")];
    let frame = reader.next_frame(&mut pixels).expect("PNG data decodes");
    assert_eq!(frame.color_type, png::ColorType::Rgb);
    let rgb = &pixels[..frame.buffer_size()];
    let white = rgb
        .chunks_exact(3)
        .filter(|p| p == &[255, 255, 255])
        .count();
    assert!(white < (w * h) as usize, "{name}.png is blank");
    let measured = rgb.chunks_exact(3).filter(|p| p == &MEASURED_RGB).count();
    let error = rgb.chunks_exact(3).filter(|p| p == &[0, 130, 100]).count();
    assert!(
        measured + error > 1000,
        "{name}.png: only {measured} measured and {error} error-line pixels"
    );

    let svg_path = dir.join(format!("{name}.svg"));
    let svg = std::fs::read_to_string(&svg_path)
        .unwrap_or_else(|e| panic!("{}: {e}", svg_path.display()));
    assert!(
        svg.starts_with("<svg"),
        "{name}.svg starts with {:?}",
        &svg[..20]
    );
    assert!(
        svg.trim_end().ends_with("</svg>"),
        "{name}.svg is not closed"
    );
    assert!(svg.contains("<polyline"), "{name}.svg has no lines");
    assert!(
        svg.contains("time (s)"),
        "{name}.svg has no time axis label"
    );
}

fn plot(log: &Path, out: &Path) -> (String, String) {
    let o = run_ok(&[
        "plot",
        log.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr).into_owned();
    // Not a terminal: the progress bar must stay silent.
    assert!(
        !stderr.contains('\x1b'),
        "control codes on stderr: {stderr:?}"
    );
    (String::from_utf8_lossy(&o.stdout).into_owned(), stderr)
}

fn assert_skipped(stdout: &str, figure: &str, because: &str) {
    let line = stdout
        .lines()
        .find(|l| l.trim_start().starts_with(&format!("skipped {figure}:")))
        .unwrap_or_else(|| panic!("{figure} not reported as skipped:\n{stdout}"));
    assert!(line.contains(because), "{line}");
}

fn pngs_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".png"))
        .collect();
    names.sort();
    names
}

#[test]
fn plots_a_simulator_run() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("run.csv");
    run_ok(&[
        "run",
        "--fast",
        "--duration",
        "3",
        "--log",
        log.to_str().unwrap(),
    ]);
    let out = dir.path().join("figures");
    let (stdout, _) = plot(&log, &out);

    for name in ["angles", "control_effort", "tracking_error"] {
        assert_figure(&out, name);
    }
    // The identifier's estimate is logged by newer builds; until then its figures are skipped.
    let has_estimate = Log::read(&log).header.iter().any(|h| h == "tau_hat1");
    for name in ["torque_identification", "identification_error"] {
        if has_estimate {
            assert_figure(&out, name);
        } else {
            assert_skipped(&stdout, name, "tau_hat1..3");
            assert!(!out.join(format!("{name}.png")).exists());
        }
    }
    assert!(stdout.contains("3001 rows"), "{stdout}");
    // The log's `mode` column marks the start-up blend, which is shaded and labelled.
    let svg = std::fs::read_to_string(out.join("tracking_error.svg")).unwrap();
    assert!(svg.contains("start-up blend"), "no blend shading legend");
}

#[test]
fn plots_a_seven_column_log_and_says_what_it_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("other-tool.csv");
    let mut csv = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
    for i in 0..2000 {
        let t = i as f64 * 1e-3;
        let s = (std::f64::consts::TAU * 0.5 * t).sin();
        csv += &format!(
            "{t},{},{},{},{},{},{}\n",
            0.4 * s,
            0.6 + 0.3 * s,
            0.2 * s,
            0.02 * s,
            -0.01 + 0.01 * s,
            -0.03 * s
        );
    }
    std::fs::write(&log, csv).unwrap();
    let out = dir.path().join("figs");
    let (stdout, _) = plot(&log, &out);

    assert_eq!(pngs_in(&out), ["angles.png", "control_effort.png"]);
    assert_figure(&out, "angles");
    assert_figure(&out, "control_effort");
    assert_skipped(&stdout, "tracking_error", "no ref1..3 columns");
    assert_skipped(&stdout, "torque_identification", "no tau_hat1..3 columns");
    assert_skipped(&stdout, "identification_error", "no tau_hat1..3 columns");
    assert!(stdout.contains("2000 rows"), "{stdout}");
    let svg = std::fs::read_to_string(out.join("angles.svg")).unwrap();
    assert!(
        !svg.contains("start-up blend"),
        "no mode column, nothing to shade"
    );

    // The same file replayed through omnid (identification pass): its log has every figure.
    let replayed = dir.path().join("replayed.csv");
    let device = format!("--device=replay:{}", log.display());
    run_ok(&[
        "run",
        &device,
        "--controller",
        "off",
        "--fast",
        "--log",
        replayed.to_str().unwrap(),
    ]);
    let out2 = dir.path().join("figs-replayed");
    plot(&replayed, &out2);
    for name in [
        "angles",
        "control_effort",
        "torque_identification",
        "identification_error",
    ] {
        assert_figure(&out2, name);
    }
}

#[test]
fn plots_the_identifier_figures_when_the_estimate_is_logged() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("ident.csv");
    let mut csv =
        String::from("t,q1,q2,q3,tau1,tau2,tau3,ref1,ref2,ref3,tau_hat1,tau_hat2,tau_hat3,mode\n");
    for i in 0..3000 {
        let t = i as f64 * 1e-3;
        let s = (std::f64::consts::TAU * 0.5 * t).sin();
        // The estimate converges onto the torque: its error decays.
        let e = 0.01 * (-t).exp();
        csv += &format!(
            "{t},{q1},{q2},{q3},{a},{b},{c},{r1},{r2},{r3},{ha},{hb},{hc},track\n",
            q1 = 0.4 * s,
            q2 = 0.6 + 0.3 * s,
            q3 = 0.2 * s,
            a = 0.02 * s,
            b = -0.01,
            c = -0.03 * s,
            r1 = 0.41 * s,
            r2 = 0.6 + 0.31 * s,
            r3 = 0.21 * s,
            ha = 0.02 * s + e,
            hb = -0.01 - e,
            hc = -0.03 * s + e,
        );
    }
    std::fs::write(&log, csv).unwrap();
    let out = dir.path().join("figs");
    let (stdout, _) = plot(&log, &out);
    for name in [
        "angles",
        "torque_identification",
        "identification_error",
        "control_effort",
        "tracking_error",
    ] {
        assert_figure(&out, name);
    }
    assert!(!stdout.contains("skipped"), "{stdout}");
    // Only tau_cmd is missing: the effort figure says it is drawn without it.
    assert!(stdout.contains("control_effort: drawn without"), "{stdout}");
}

fn plot_fails(csv: &str) -> (i32, String) {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("bad.csv");
    std::fs::write(&log, csv).unwrap();
    let out = omnid()
        .args(["plot", log.to_str().unwrap(), "--out"])
        .arg(dir.path().join("figs"))
        .output()
        .expect("omnid starts");
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(!stderr.contains("panicked"), "{stderr}");
    (out.status.code().unwrap_or(-1), stderr)
}

#[test]
fn a_non_numeric_value_is_refused_with_its_line_and_column() {
    let (code, stderr) =
        plot_fails("t,q1,q2,q3,tau1,tau2,tau3\n0,0,0,0,0,0,0\n0.001,0,0,zero,0,0,0\n");
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("bad.csv"), "{stderr}");
    assert!(stderr.contains("line 3"), "{stderr}");
    assert!(stderr.contains("column 4 (`q3`)"), "{stderr}");
    assert!(stderr.contains("\"zero\""), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "one message: {stderr}");
}

#[test]
fn logs_it_cannot_use_are_bad_input() {
    let (code, stderr) = plot_fails("time,q1,q2,q3\n0,0,0,0\n");
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("line 1: no `t` column"), "{stderr}");

    let (code, stderr) = plot_fails("t,q1,q2,q3\n0,0,0,0\n0.001,0,0\n");
    assert_eq!(code, 2, "{stderr}");
    assert!(
        stderr.contains("line 3: 3 fields, but the header has 4"),
        "{stderr}"
    );

    let (code, stderr) = plot_fails("t,amps\n0,1\n");
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("nothing to plot"), "{stderr}");

    let (code, stderr) = plot_fails("");
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("empty"), "{stderr}");

    let out = omnid()
        .args(["plot", "/nonexistent/log.csv", "--out", "/tmp/never"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("/nonexistent/log.csv"));
}

#[test]
fn extreme_values_are_drawn_without_failing() {
    // Values near f64::MAX, infinities, gaps and NaN: garbage, but no reason to crash.
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("wild.csv");
    std::fs::write(
        &log,
        "t,q1,q2,q3,tau1,tau2,tau3\n0,1e308,-1e308,0,1,1,1\n1,-1e308,1e308,NaN,inf,,-inf\n",
    )
    .unwrap();
    let out = dir.path().join("figs");
    let (stdout, _) = plot(&log, &out);
    assert!(stdout.contains("2 rows"), "{stdout}");
    assert_eq!(pngs_in(&out), ["angles.png", "control_effort.png"]);
}

/// A free-mode log is drawn as a haptic run (issue 33, item 7): the tip path with the scene's
/// wall and the forces, no tracking error; a tracking log keeps its figures and gets none of
/// the haptic ones.
#[test]
fn a_haptic_run_is_drawn_as_one() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("floor.toml");
    std::fs::write(
        &scene,
        "[[effect]]\ntype = \"plane\"\npoint_mm = [0, -33.3, 0]\nnormal = [0, 1, 0]\n\
         stiffness_n_per_mm = 2.31\n",
    )
    .unwrap();
    let log = dir.path().join("free.csv");
    let s = |p: &Path| p.to_str().unwrap().to_string();
    run_ok(&[
        "run",
        "--fast",
        "--mode",
        "free",
        "--hand",
        "push-y",
        "--duration",
        "2",
        "--scene",
        &s(&scene),
        "--log",
        &s(&log),
    ]);
    let out = dir.path().join("figures");
    let o = run_ok(&["plot", &s(&log), "--out", &s(&out), "--scene", &s(&scene)]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    for name in ["tip_path", "tip_force"] {
        assert_figure(&out, name);
    }
    assert_skipped(&stdout, "tracking_error", "a haptic run");
    assert!(!out.join("tracking_error.png").exists());
    // The floor is drawn on the y panel, in the wall's pen, and named in the legend.
    let svg = std::fs::read_to_string(out.join("tip_path.svg")).unwrap();
    assert!(svg.contains("#6E6E6E"), "no wall line");
    assert!(svg.contains("wall of an effect"), "no wall in the legend");
    assert!(svg.contains("y (up)"), "panels are not the tip's axes");
    let force = std::fs::read_to_string(out.join("tip_force.svg")).unwrap();
    assert!(force.contains("(fhand, simulator)") && force.contains("rendered (fcmd"));
    assert!(
        force.contains("estimated from the motors (fext)"),
        "no force estimate"
    );

    // A tracking run: today's figures, no haptic ones.
    let track = dir.path().join("track.csv");
    run_ok(&["run", "--fast", "--duration", "1", "--log", &s(&track)]);
    let out = dir.path().join("tracking");
    let (stdout, _) = plot(&track, &out);
    assert_figure(&out, "tracking_error");
    assert!(
        !stdout.contains("tip_"),
        "haptic figures told to a tracking run:\n{stdout}"
    );
    assert!(!out.join("tip_path.png").exists());
}

/// The numbers printed on the axes of an SVG figure, in document order.
fn svg_numbers(svg: &str) -> Vec<f64> {
    svg.split("<text")
        .skip(1)
        .filter_map(|t| {
            let inner = t.split('>').nth(1)?.split('<').next()?;
            inner.trim().parse::<f64>().ok()
        })
        .collect()
}

#[test]
fn a_window_a_size_and_a_text_scale_make_a_publishable_figure() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("run.csv");
    run_ok(&[
        "run",
        "--fast",
        "--duration",
        "6",
        "--log",
        log.to_str().unwrap(),
    ]);
    let out = dir.path().join("figures");
    let o = run_ok(&[
        "plot",
        log.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--from",
        "3",
        "--to",
        "5",
        "--width",
        "800",
        "--height",
        "600",
        "--font-scale",
        "1.5",
    ]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    // 3.000 s to 5.000 s at 1 kHz, both ends in.
    assert!(stdout.contains("2001 rows"), "{stdout}");
    let png = png::Decoder::new(std::io::BufReader::new(
        File::open(out.join("angles.png")).unwrap(),
    ))
    .read_info()
    .unwrap();
    assert_eq!((png.info().width, png.info().height), (800, 600));
    let svg = std::fs::read_to_string(out.join("tracking_error.svg")).unwrap();
    assert!(svg.contains("width=\"800\""), "the SVG's size");
    // The time axis shows only the window.
    let numbers = svg_numbers(&svg);
    for t in [3.0, 4.0, 5.0] {
        assert!(numbers.contains(&t), "no time label {t}: {numbers:?}");
    }
    let last = numbers.iter().cloned().fold(f64::MIN, f64::max);
    assert!(last <= 5.0, "a label past the window: {numbers:?}");

    // A window with no row, and one backwards: refused, naming the options.
    for (from, to, says) in [
        ("50", "60", "no row of the log"),
        ("5", "3", "--from before --to"),
    ] {
        let o = omnid()
            .args(["plot", log.to_str().unwrap(), "--out"])
            .arg(dir.path().join("none"))
            .args(["--from", from, "--to", to])
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(2));
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(err.contains(says), "{err}");
    }
    let o = omnid()
        .args(["plot", log.to_str().unwrap(), "--out"])
        .arg(dir.path().join("none"))
        .args(["--width", "100000"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--width"));
}

/// Tick labels are read back from the figures: each printed value is the tick plotters drew,
/// so consecutive labels on one axis are evenly spaced and none repeats (a label printed with
/// fewer decimals than its step repeats or skews: `0.1, 0.0, 0.0, -0.1`). The tracking error's
/// scale is the steady error, not the start-up blend's transient.
#[test]
fn tick_labels_read_back_are_the_ticks_and_errors_are_scaled_to_the_steady_state() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("run.csv");
    run_ok(&[
        "run",
        "--fast",
        "--duration",
        "6",
        "--log",
        log.to_str().unwrap(),
    ]);
    let out = dir.path().join("figures");
    plot(&log, &out);
    for name in [
        "control_effort",
        "identification_error",
        "tracking_error",
        "angles",
    ] {
        let svg = std::fs::read_to_string(out.join(format!("{name}.svg"))).unwrap();
        let numbers = svg_numbers(&svg);
        assert!(numbers.len() > 20, "{name}: {numbers:?}");
        // Runs of labels with a constant step: every axis is such a run; a repeat inside one
        // is a bug. One axis may end on the value the next begins with (an error axis ending at
        // 0 before a time axis starting at 0): there the steps on either side differ.
        for i in 0..numbers.len() - 1 {
            if numbers[i] != numbers[i + 1] {
                continue;
            }
            let before = (i > 0).then(|| numbers[i] - numbers[i - 1]);
            let after = numbers.get(i + 2).map(|v| v - numbers[i + 1]);
            let between_axes = matches!((before, after), (Some(b), Some(a))
                if (a - b).abs() > 1e-9 * a.abs().max(b.abs()));
            assert!(
                between_axes,
                "{name}: a repeated tick label {} in {numbers:?}",
                numbers[i]
            );
        }
        let steps: Vec<f64> = numbers.windows(2).map(|w| w[1] - w[0]).collect();
        let mut uneven = 0;
        for w in steps.windows(2) {
            let same_axis = w[0].signum() == w[1].signum();
            if same_axis && (w[0] - w[1]).abs() > 1e-9 * w[0].abs().max(1.0) {
                uneven += 1;
            }
        }
        // Between axes the step changes once per axis (3 panels × 2 axes).
        assert!(uneven <= 6, "{name}: uneven tick labels {numbers:?}");
    }
    let svg = std::fs::read_to_string(out.join("tracking_error.svg")).unwrap();
    // Time labels are 0 to 6 s; the error labels are mrad.
    let biggest = svg_numbers(&svg)
        .into_iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let log = Log::read(&log);
    let mode = log.col("mode");
    let steady: Vec<f64> = ["ref1", "ref2", "ref3"]
        .iter()
        .zip(["q1", "q2", "q3"])
        .flat_map(|(r, q)| {
            let (r, q) = (log.col(r), log.col(q));
            log.rows
                .iter()
                .filter(|row| row[mode] == "track")
                .map(move |row| {
                    (row[r].parse::<f64>().unwrap() - row[q].parse::<f64>().unwrap()).abs() * 1e3
                })
        })
        .collect();
    let steady_max = steady.iter().cloned().fold(0.0, f64::max);
    assert!(
        biggest < 3.0 * steady_max.max(6.0),
        "the error axis reaches {biggest} mrad for a steady error of {steady_max} mrad"
    );
}

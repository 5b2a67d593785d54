//! pyOpenHaptics 1.0.1 from PyPI, unmodified, in a virtual environment, on our libHD
//! (LD_LIBRARY_PATH) against `omnid serve --device sim`: it reads the stylus and renders a
//! spring (clients/hdapi/tests/pyopenhaptics_spring.py). Skipped, loudly, only when the
//! package registry cannot be reached.

use crate::common;
use crate::hd;

use crate::common::Served;
use hd::{wait_output, HD};
use omnid::omni::kinematics::{tip_position_mm, Geometry};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

const PACKAGE: &str = "pyopenhaptics==1.0.1";

/// A venv with pyOpenHaptics under target/ (kept between runs); None when PyPI is out of
/// reach.
fn venv() -> Option<PathBuf> {
    common::venv("hdapi-venv", &[PACKAGE], "pyOpenHaptics")
}

#[test]
#[ignore = "paced"]
fn pyopenhaptics_from_pypi_reads_the_stylus_and_renders_a_spring() {
    let Some(python) = venv() else {
        eprintln!(
            "\n\n*** SKIPPED: PyPI is unreachable, so {PACKAGE} could not be installed: the \
             pyOpenHaptics test did not run. ***\n\n"
        );
        return;
    };
    let hd = HD::get();
    let daemon = Served::sim(&[], None);
    let script =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/hdapi/tests/pyopenhaptics_spring.py");
    let child = Command::new(python)
        .arg(script)
        .env("LD_LIBRARY_PATH", hd.prefix.join("lib"))
        .env("OMNID_SOCKET", &daemon.sock)
        .env("PYTHONDONTWRITEBYTECODE", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python starts");
    let out = wait_output(child, Duration::from_secs(90));
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "pyOpenHaptics spring failed ({}):\n{stdout}\n{stderr}",
        out.status
    );
    assert!(
        stdout.contains("Intialized device! SensAble Technologies/PHANTOM Omni"),
        "{stdout}"
    );
    let line = stdout
        .lines()
        .find(|l| l.starts_with("sample pos "))
        .expect("a sample");
    let w: Vec<f64> = line
        .split_whitespace()
        .filter_map(|x| x.parse().ok())
        .collect();
    // pos (3), q (3), tr (3), g (3), buttons.
    let (pos, q, g) = (&w[0..3], &w[3..6], &w[9..12]);
    let fk = tip_position_mm(&Geometry::default(), &[q[0], q[1], q[2]].into());
    for j in 0..3 {
        assert!((pos[j] - fk[j]).abs() < 1e-6, "{line}");
        assert_eq!(g[j], 0.0, "{line}");
    }
    assert_eq!(w[12], 0.0, "no button: {line}");
    assert!(stdout.contains("spring reached"), "{stdout}");
}

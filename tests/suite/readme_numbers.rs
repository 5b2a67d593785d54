//! The numbers the README prints come from the code: each is re-made here by the run it
//! describes (`--fast` runs are deterministic, and give the rows a paced run gives) and compared
//! with the README's text. A change that moves them fails here until the README says the new ones.

use crate::common;
use std::path::Path;

fn readme() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap()
}

fn squeeze(s: &str) -> String {
    s.split_whitespace().collect::<Vec<_>>().join(" ")
}

/// `omnid run --fast --duration 10` plus `args`, in a scratch directory: its stdout and summary.
fn run(args: &[&str]) -> (String, serde_json::Value) {
    let dir = tempfile::tempdir().unwrap();
    let summary = dir.path().join("s.json");
    let log = dir.path().join("run.csv");
    let mut all = vec![
        "run",
        "--fast",
        "--duration",
        "10",
        "--summary-json",
        summary.to_str().unwrap(),
        "--log",
        log.to_str().unwrap(),
    ];
    all.extend_from_slice(args);
    let out = common::omnid()
        .args(&all)
        .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")))
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let json = serde_json::from_str(&std::fs::read_to_string(&summary).unwrap()).unwrap();
    (String::from_utf8(out.stdout).unwrap(), json)
}

#[test]
fn what_omnid_run_prints_shows_the_numbers_of_the_run_it_names() {
    let readme = readme();
    let section = readme
        .split("## What `omnid run` prints")
        .nth(1)
        .expect("the section");
    let block = section.split("```").nth(1).expect("its sample output");
    let (printed, _) = run(&[]);
    let labels = [
        "tracking RMS",
        "tracking max",
        "vs oracle",
        "torque RMS",
        "torque TV",
        "ident NRMSE",
    ];
    for label in labels {
        let line = |text: &str| {
            text.lines()
                .find(|l| l.trim_start().starts_with(label))
                .map(squeeze)
                .unwrap_or_else(|| panic!("no `{label}` line in {text}"))
        };
        assert_eq!(
            line(block),
            line(&printed),
            "the README's `{label}` line is not what `omnid run` prints now"
        );
    }
}

/// Millimetre-radians as the README writes them: three significant figures.
fn mrad(v: &serde_json::Value) -> String {
    let three: Vec<String> = v
        .as_array()
        .unwrap()
        .iter()
        .map(|x| {
            let m = x.as_f64().unwrap() * 1000.0;
            if m >= 10.0 {
                format!("{m:.1}")
            } else {
                format!("{m:.2}")
            }
        })
        .collect();
    three.join(" / ")
}

#[test]
fn the_controllers_compared_on_the_simulator_are_the_runs_measured_now() {
    let readme = squeeze(&readme());
    let runs = [
        run(&["--controller", "pd"]).1,
        run(&["--controller", "ct"]).1,
        run(&[]).1,
    ];
    let [pd, ct, nnidc] = runs.each_ref().map(|r| mrad(&r["tracking_rms_rad"]));
    let [pd_tv, ct_tv, nnidc_tv] = runs.each_ref().map(|r| {
        let v: Vec<String> = r["torque_total_variation_nm"]
            .as_array()
            .unwrap()
            .iter()
            .map(|x| format!("{:.2}", x.as_f64().unwrap()))
            .collect();
        v.join(" / ")
    });
    let sentence = format!(
        "On the simulator (10 s sine, tracking RMS after 2 s, mrad): PD {pd}, CT {ct}, NNIDC \
         {nnidc}; torque total variation (N·m, how much it chatters) PD {pd_tv}, CT {ct_tv}, \
         NNIDC {nnidc_tv}"
    );
    assert!(
        readme.contains(&sentence),
        "the README should say: {sentence}"
    );
    let three_nets = mrad(
        &run(&[
            "--weights",
            "mock/nnidc-pretuned-3net.json",
            "--config",
            "mock/nnidc-3net.toml",
        ])
        .1["tracking_rms_rad"],
    );
    let aside = format!(
        "`--weights mock/nnidc-pretuned-3net.json --config mock/nnidc-3net.toml`: {three_nets})"
    );
    assert!(readme.contains(&aside), "the README should say: {aside}");
}

//! What a person sees from `omnid ctl status` and `omnid watch` (issue 33, item 5): readable
//! forms by default, the daemon's JSON with `--json`.

use crate::common;

use common::Served;
use std::io::BufRead;
use std::process::Stdio;
use std::time::{Duration, Instant};

fn stdout(out: &std::process::Output) -> String {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
#[ignore = "paced"]
fn ctl_status_is_a_readable_block_and_json_on_request() {
    let d = Served::start(&["--device", "sim"], None, &["sim"]);
    stdout(&d.omnid(&["ctl", "mode", "hold"]));
    // The servo applies the mode at its next tick, and its timing has lines once it has
    // ticked: ask until it says so (a loaded machine can start the loop late).
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    let text = loop {
        let text = stdout(&d.omnid(&["ctl", "status"]));
        if text.contains("hold (holding the pose)") || std::time::Instant::now() > deadline {
            break text;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    assert!(!text.contains('{'), "JSON where a person reads:\n{text}");
    assert!(text.starts_with("arm sim (sim) on "), "{text}");
    for label in [
        "mode",
        "controller",
        "lease",
        "clients",
        "faults",
        "tracking",
        "period",
        "compute",
        "recording",
    ] {
        assert!(
            text.lines()
                .any(|l| l.trim_start().starts_with(&format!("{label} "))),
            "no `{label}` line in\n{text}"
        );
    }
    assert!(text.contains("hold (holding the pose)"), "{text}");
    assert!(text.contains("faults      none"), "{text}");
    // Other commands answer in words too.
    assert_eq!(
        stdout(&d.omnid(&["ctl", "controller", "pd"])).trim(),
        "controller pd"
    );
    // --json, before or after the command: the summary's keys, as programs read them.
    for args in [["ctl", "--json", "status"], ["ctl", "status", "--json"]] {
        let v: serde_json::Value = serde_json::from_str(&stdout(&d.omnid(&args))).unwrap();
        assert_eq!(v["arm"], "sim");
        assert_eq!(v["mode"], "hold");
        assert!(v["timing_us"]["period"]["p50"].is_number(), "{v}");
    }
}

/// `omnid watch` (with `--json` or not) against `d`, its stdout lines over a channel; the
/// child is killed on drop.
struct Watch {
    child: std::process::Child,
    lines: std::sync::mpsc::Receiver<String>,
}

impl Watch {
    fn start(d: &Served, json: bool) -> Watch {
        let mut cmd = common::omnid();
        cmd.args(["watch", "--rate", "10"])
            .env("XDG_RUNTIME_DIR", d.dir.path())
            .env_remove("RUNTIME_DIRECTORY")
            .env_remove("OMNID_SOCKET")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped());
        if json {
            cmd.arg("--json");
        }
        let mut child = cmd.spawn().unwrap();
        let out = child.stdout.take().unwrap();
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Watch { child, lines }
    }

    /// Lines until one matches `want` (all of them, that one last); fails after 20 s.
    fn until(&self, want: impl Fn(&str) -> bool) -> Vec<String> {
        let deadline = Instant::now() + Duration::from_secs(20);
        let mut seen = Vec::new();
        while let Some(left) = deadline.checked_duration_since(Instant::now()) {
            match self.lines.recv_timeout(left) {
                Ok(l) => {
                    let done = want(&l);
                    seen.push(l);
                    if done {
                        return seen;
                    }
                }
                Err(_) => break,
            }
        }
        panic!("not seen; the watch printed:\n{}", seen.join("\n"));
    }
}

impl Drop for Watch {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
#[ignore = "paced"]
fn watch_tells_events_in_sentences_and_json_on_request() {
    let d = Served::start(&["--device", "sim"], None, &["sim"]);
    let human = Watch::start(&d, false);
    let json = Watch::start(&d, true);
    // Both are streaming before anything happens.
    human.until(|l| l.contains(" idle ") && l.contains("rad"));
    json.until(|l| l.contains(r#""type":"state""#));
    stdout(&d.omnid(&["ctl", "mode", "hold"]));
    let seen = human.until(|l| l.contains("mode is now hold"));
    let lease = seen
        .iter()
        .find(|l| l.contains("lease: "))
        .unwrap_or_else(|| panic!("no lease sentence in\n{}", seen.join("\n")));
    assert!(
        lease.contains("`omnid ctl` holds the command lease"),
        "{lease}"
    );
    for l in &seen {
        assert!(!l.contains('{'), "JSON where a person reads: {l}");
    }
    let seen = json.until(|l| l.contains(r#""event":"mode""#));
    let event: serde_json::Value = serde_json::from_str(seen.last().unwrap()).unwrap();
    assert_eq!(event["type"], "event");
    assert_eq!(event["mode"], "hold");
}

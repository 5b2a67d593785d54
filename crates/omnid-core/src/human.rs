//! What `omnid ctl status` and `omnid watch` print for people (their `--json` prints the
//! daemon's messages as they came, docs/PROTOCOL.md): a short block for the status, one
//! sentence a line for events. Built from the messages' JSON, so a key this version of the
//! CLI does not know is left out rather than refused.

use serde_json::Value;

fn f(v: &Value) -> Option<f64> {
    v.as_f64()
}

fn triple(v: &Value, scale: f64, unit: &str) -> Option<String> {
    let a = v.as_array()?;
    let x: Vec<f64> = a.iter().filter_map(|x| x.as_f64()).collect();
    (x.len() == 3).then(|| {
        format!(
            "{:.2} / {:.2} / {:.2} {unit}",
            x[0] * scale,
            x[1] * scale,
            x[2] * scale
        )
    })
}

fn text(v: &Value) -> Option<String> {
    v.as_str().map(crate::text::printable)
}

fn percentiles(p: &Value) -> Option<String> {
    Some(format!(
        "p50 {:.1}  p99 {:.1}  max {:.1} µs",
        f(&p["p50"])?,
        f(&p["p99"])?,
        f(&p["max"])?
    ))
}

/// The labelled lines one part of the status gives (none, one or several).
type Block = fn(&Value) -> Vec<(&'static str, String)>;

/// `omnid ctl status` for people: the arm, mode, controller, lease, clients, faults, tracking,
/// timing and recording of a `status` reply's `status` object.
pub fn status_block(s: &Value) -> String {
    let arm = text(&s["arm"]).unwrap_or_else(|| "?".into());
    let device = text(&s["device"]).unwrap_or_else(|| "?".into());
    let mut out = format!("arm {arm} ({device})");
    if let Some(socket) = text(&s["socket"]) {
        out += &format!(" on {socket}");
    }
    out.push('\n');
    let blocks: [Block; 9] = [
        mode_line,
        controller_line,
        lease_line,
        run_lines,
        tracking_line,
        timing_lines,
        teleop_lines,
        recording_line,
        zenoh_line,
    ];
    for (label, value) in blocks.iter().flat_map(|block| block(s)) {
        out += &format!("  {label:<11} {value}\n");
    }
    out
}

fn mode_line(s: &Value) -> Vec<(&'static str, String)> {
    let mode = text(&s["mode"]).unwrap_or_else(|| "not started".into());
    let words = match mode.as_str() {
        "idle" => "idle (no torque, amplifiers off)".to_string(),
        "hold" => "hold (holding the pose)".to_string(),
        "blend" | "track" => format!("{mode} (following a trajectory)"),
        "free" => "free (compensation and effects only)".to_string(),
        m if m.starts_with("servo_") => format!("{m} (a client streams commands)"),
        m => m.to_string(),
    };
    vec![("mode", words)]
}

fn controller_line(s: &Value) -> Vec<(&'static str, String)> {
    let mut controller = text(&s["controller"]).unwrap_or_else(|| "?".into());
    let ident = &s["identifier"];
    if let Some(fault) = text(&ident["fault"]) {
        controller += &format!(" (identifier STOPPED: {fault}; running on PD)");
    } else if ident["adapt"] == Value::Bool(true) {
        controller += " (identifier learning)";
    } else if ident["adapt"] == Value::Bool(false) {
        controller += " (identifier frozen)";
    }
    if let Some(w) = text(&ident["weights"]) {
        controller += &format!(", weights {w}");
    }
    vec![("controller", controller)]
}

fn lease_line(s: &Value) -> Vec<(&'static str, String)> {
    let lease = &s["lease"];
    let holder = if lease.is_null() {
        "free (the next command takes it)".to_string()
    } else {
        let name = text(&lease["name"]).unwrap_or_default();
        // A session over the network has no process or user on this PC.
        let whose = if lease["pid"] == 0 && lease["uid"] == u32::MAX {
            "over the network".to_string()
        } else {
            format!("pid {}, uid {}", lease["pid"], lease["uid"])
        };
        format!("client {} `{name}` ({whose})", lease["client"])
    };
    vec![("lease", holder)]
}

/// Clients, time up, faults and limits.
fn run_lines(s: &Value) -> Vec<(&'static str, String)> {
    let mut lines = Vec::new();
    if let Some(n) = s["clients"].as_u64() {
        lines.push(("clients", format!("{n} connected, this one included")));
    }
    if let (Some(t), Some(ticks)) = (f(&s["duration_s"]), s["ticks"].as_u64()) {
        lines.push(("up", format!("{t:.1} s device time ({ticks} ticks)")));
    }
    let faults = s["faults"].as_array().cloned().unwrap_or_default();
    let faults = match faults.last() {
        None => "none".to_string(),
        Some(last) => format!(
            "{} (last at {:.3} s: {})",
            faults.len(),
            f(&last["t"]).unwrap_or(0.0),
            text(&last["message"]).unwrap_or_default()
        ),
    };
    lines.push(("faults", faults));
    let (clamped, limited, hot) = (
        s["clamped_ticks"].as_u64().unwrap_or(0),
        s["force_limited_ticks"].as_u64().unwrap_or(0),
        s["thermal_ticks"].as_u64().unwrap_or(0),
    );
    if clamped + limited + hot > 0 {
        lines.push((
            "limits",
            format!(
                "torque clamped {clamped} ticks, tip force held {limited}, hot motor held {hot}"
            ),
        ));
    }
    lines
}

fn tracking_line(s: &Value) -> Vec<(&'static str, String)> {
    let tracking = match triple(&s["tracking_rms_rad"], 1e3, "mrad") {
        Some(rms) => format!(
            "RMS {rms}, max {} (joints 1/2/3)",
            triple(&s["tracking_max_rad"], 1e3, "mrad").unwrap_or_else(|| "n/a".into())
        ),
        None => "nothing tracked yet (mode track follows a trajectory)".to_string(),
    };
    vec![("tracking", tracking)]
}

/// The loop's period and compute time, and the motors' heat.
fn timing_lines(s: &Value) -> Vec<(&'static str, String)> {
    let mut lines = Vec::new();
    let timing = &s["timing_us"];
    if let Some(p) = percentiles(&timing["period"]) {
        lines.push(("period", p));
    }
    if let Some(p) = percentiles(&timing["compute"]) {
        let overruns = timing["overruns"].as_u64().unwrap_or(0);
        lines.push(("compute", format!("{p}, {overruns} overruns")));
    }
    if let Some(h) = triple(&s["heat"], 1.0, "") {
        let h = h.trim_end();
        lines.push((
            "heat",
            format!("{h} (1 = a motor at its continuous torque)"),
        ));
    }
    lines
}

fn teleop_lines(s: &Value) -> Vec<(&'static str, String)> {
    let t = &s["teleop"];
    if t.is_null() {
        return Vec::new();
    }
    let mut lines = vec![(
        "teleop",
        format!(
            "{}{} of {} ({}, motion ×{}, force ×{}, operator {}, passivity {}{}){}",
            text(&t["state"])
                .map(|s| format!("{s}: "))
                .unwrap_or_default(),
            text(&t["role"]).unwrap_or_default(),
            text(&t["peer"]).unwrap_or_default(),
            text(&t["architecture"]).unwrap_or_default(),
            t["motion_scale"],
            t["force_scale"],
            text(&t["operator"]).unwrap_or_default(),
            if t["passivity"] == true { "on" } else { "off" },
            text(&t["delay_control"])
                .map(|d| format!(", delay control {d}"))
                .unwrap_or_default(),
            t["round_trip_ms"]
                .as_f64()
                .map(|ms| format!("; round trip {ms:.1} ms"))
                .unwrap_or_default()
        ),
    )];
    let net = &t["network"];
    if !net.is_null() {
        lines.push((
            "teleop net",
            format!(
                "zenoh, peer session {}; frames sent {}, received {}, refused {}{}",
                text(&net["peer_session"]).unwrap_or_else(|| "not heard yet".into()),
                net["sent"],
                net["received"],
                net["refused"],
                text(&net["last_refusal"])
                    .map(|w| format!(" (last: {w})"))
                    .unwrap_or_default()
            ),
        ));
    }
    lines
}

fn recording_line(s: &Value) -> Vec<(&'static str, String)> {
    let rec = &s["recording"];
    let recording = if rec.is_null() {
        "no (`omnid ctl record start` starts one)".to_string()
    } else {
        let dropped = rec["dropped"].as_u64().unwrap_or(0);
        format!(
            "to {}{}",
            text(&rec["path"]).unwrap_or_default(),
            if dropped > 0 {
                format!(" ({dropped} rows dropped: the disk fell behind)")
            } else {
                String::new()
            }
        )
    };
    vec![("recording", recording)]
}

fn zenoh_line(s: &Value) -> Vec<(&'static str, String)> {
    let z = &s["zenoh"];
    if !z.is_object() {
        return Vec::new();
    }
    let n = |k: &str| z[k].as_u64().unwrap_or(0);
    vec![(
        "zenoh",
        format!(
            "{} samples published, {} received ({} refused, {} dropped on a full inbox)",
            n("published"),
            n("received"),
            n("refused"),
            n("dropped_in")
        ),
    )]
}

/// One line for a message of the daemon other than a state (an event, `lost`, `bye`, …)
/// for people: when it happened (device time, where the message has it) and what happened, in
/// a sentence. None for messages a person watching has no use for (`reply`).
pub fn event_line(v: &Value) -> Option<String> {
    let when = match f(&v["t"]) {
        Some(t) => format!("{t:>9.3} s"),
        None => format!("{:>11}", ""),
    };
    let message = text(&v["message"]);
    let sentence = match v["type"].as_str() {
        Some("event") => {
            let event = text(&v["event"]).unwrap_or_else(|| "?".into());
            match event.as_str() {
                "mode" => format!(
                    "mode is now {}",
                    text(&v["mode"]).unwrap_or_else(|| "?".into())
                ),
                "controller" => format!(
                    "controller is now {}",
                    text(&v["controller"]).unwrap_or_else(|| "off".into())
                ),
                "lease" => format!(
                    "lease: {}",
                    message.unwrap_or_else(|| match v["holder"].as_u64() {
                        Some(h) => format!("held by client {h}"),
                        None => "free".into(),
                    })
                ),
                "stopped" => format!("stopped: {}", message.unwrap_or_default()),
                "stream-stale" => format!("stream went stale: {}", message.unwrap_or_default()),
                "stream-ended" => format!("stream ended: {}", message.unwrap_or_default()),
                "safety-trip" => format!(
                    "SAFETY TRIP: {} (latched: the arm stays idle until a client asks for a mode)",
                    message.unwrap_or_default()
                ),
                "limit" => format!("limit: {}", message.unwrap_or_default()),
                "weights" => format!("weights: {}", message.unwrap_or_default()),
                "identifier-fault" => {
                    format!("IDENTIFIER STOPPED: {}", message.unwrap_or_default())
                }
                "recording-failed" => {
                    format!("RECORDING FAILED: {}", message.unwrap_or_default())
                }
                other => match message {
                    Some(m) => format!("{other}: {m}"),
                    None => format!("{other}: {}", crate::text::cut(&v.to_string())),
                },
            }
        }
        Some("lost") => format!(
            "{} samples lost: this reader fell behind ({} in all; a lower --rate keeps up)",
            v["count"], v["total"]
        ),
        Some("bye") => format!(
            "the daemon is stopping{}",
            message.map(|m| format!(": {m}")).unwrap_or_default()
        ),
        Some("error") => format!("error: {}", message.unwrap_or_default()),
        Some("reply") | Some("hello") => return None,
        _ => crate::text::cut(&v.to_string()),
    };
    let seq = v["seq"].as_u64().map(|s| s.to_string()).unwrap_or_default();
    Some(format!("{seq:>8} {when}  {sentence}"))
}

/// `omnid ctl`'s answer to a command other than `status`, for people: what the daemon did.
pub fn reply_line(r: &Value) -> String {
    let op = r["op"].as_str().unwrap_or("");
    let path = text(&r["path"]).unwrap_or_default();
    match op {
        "mode" | "hold" | "free" => format!("mode {}", text(&r["mode"]).unwrap_or_default()),
        "controller" => format!("controller {}", text(&r["controller"]).unwrap_or_default()),
        "adapt" => match r["adapt"].as_bool() {
            Some(true) => "the identifier learns".to_string(),
            _ => "the identifier is frozen".to_string(),
        },
        "record_start" => format!("recording to {path}"),
        "record_stop" => format!(
            "recording stopped: {} rows in {path}{}",
            r["rows"],
            match text(&r["error"]) {
                Some(e) => format!(" (INCOMPLETE: {e})"),
                None => String::new(),
            }
        ),
        "weights_save" => format!("weights saved to {path}"),
        "weights_load" => format!("weights loaded from {path}"),
        "weights_reset" => format!(
            "the identifier is back on the shipped weights ({}); {}",
            text(&r["weights"]).unwrap_or_default(),
            match text(&r["removed"]) {
                Some(p) => format!("what the arm had learned ({p}) is removed"),
                None => "the arm had no saved weights".to_string(),
            }
        ),
        "shutdown" => "the daemon is stopping".to_string(),
        "teleop_stop" => "uncoupled: the arm holds".to_string(),
        "teleop_scale" => format!("motion scale {}", r["motion_scale"]),
        "stylus" => match (
            text(&r["stylus"]).unwrap_or_default().as_str(),
            r["button"].as_u64(),
        ) {
            (action, Some(b)) => format!("simulated hand: button {b} {action}"),
            (action, None) => format!("simulated hand: stylus {action}"),
        },
        _ => {
            let mut r = r.clone();
            if let Some(o) = r.as_object_mut() {
                o.remove("type");
                o.remove("id");
            }
            crate::text::cut(&r.to_string())
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn stylus_replies_and_zenoh_counters_read_as_sentences() {
        let r = json!({"type": "reply", "op": "stylus", "stylus": "click", "button": 1});
        assert_eq!(reply_line(&r), "simulated hand: button 1 click");
        let r = json!({"type": "reply", "op": "stylus", "stylus": "undock", "button": null});
        assert_eq!(reply_line(&r), "simulated hand: stylus undock");
        let s = json!({"zenoh": {"published": 5, "received": 3, "refused": 2, "dropped_in": 0}});
        assert!(status_block(&s)
            .contains("5 samples published, 3 received (2 refused, 0 dropped on a full inbox)"));
    }

    #[test]
    fn a_lease_held_over_the_network_names_no_local_process() {
        let s = json!({"lease": {"client": 7, "name": "lab-pc (zenoh)", "pid": 0, "uid": 4294967295u64}});
        let b = status_block(&s);
        assert!(
            b.contains("lease       client 7 `lab-pc (zenoh)` (over the network)"),
            "{b}"
        );
        assert!(!b.contains("4294967295"), "{b}");
    }

    #[test]
    fn a_status_reads_as_a_block_with_every_part_named() {
        let s = json!({
            "arm": "sim", "device": "sim", "socket": "/run/omnid/sim.sock", "mode": "hold",
            "controller": "nnidc", "identifier": {"adapt": true, "weights": "shipped", "fault": null},
            "lease": {"client": 3, "name": "omnid ctl", "pid": 42, "uid": 1000},
            "clients": 2, "duration_s": 12.5, "ticks": 12500,
            "faults": [{"tick": 5, "t": 0.005, "class": "safety-fault", "message": "safety: joint 2 too fast"}],
            "tracking_rms_rad": null, "tracking_max_rad": null,
            "timing_us": {"period": {"p50": 1000.0, "p99": 1010.0, "p999": 1020.0, "max": 1100.0},
                          "compute": {"p50": 12.0, "p99": 30.0, "p999": 40.0, "max": 50.0}, "overruns": 0},
            "heat": [0.1, 0.2, 0.3], "recording": null
        });
        let b = status_block(&s);
        for want in [
            "arm sim (sim) on /run/omnid/sim.sock",
            "mode        hold (holding the pose)",
            "controller  nnidc (identifier learning), weights shipped",
            "lease       client 3 `omnid ctl` (pid 42, uid 1000)",
            "clients     2 connected",
            "faults      1 (last at 0.005 s: safety: joint 2 too fast)",
            "tracking    nothing tracked yet",
            "period      p50 1000.0  p99 1010.0  max 1100.0 µs",
            "compute     p50 12.0  p99 30.0  max 50.0 µs, 0 overruns",
            "recording   no",
        ] {
            assert!(b.contains(want), "{want:?} not in\n{b}");
        }
        assert!(!b.contains('{'), "{b}");
    }

    #[test]
    fn events_read_as_sentences() {
        let l = event_line(
            &json!({"type": "event", "event": "mode", "mode": "hold", "seq": 3, "t": 1.5}),
        )
        .unwrap();
        assert!(l.ends_with("1.500 s  mode is now hold"), "{l}");
        let l = event_line(
            &json!({"type": "event", "event": "safety-trip", "mode": "idle",
            "message": "safety: joint 1 too fast; zero torque"}),
        )
        .unwrap();
        assert!(l.contains("SAFETY TRIP: safety: joint 1 too fast"), "{l}");
        let l = event_line(&json!({"type": "lost", "count": 4, "total": 9})).unwrap();
        assert!(l.contains("4 samples lost"), "{l}");
        assert_eq!(event_line(&json!({"type": "reply", "op": "stream"})), None);
        // An event this version does not know is still shown.
        let l =
            event_line(&json!({"type": "event", "event": "new-thing", "message": "hi"})).unwrap();
        assert!(l.contains("new-thing: hi"), "{l}");
    }
}

//! The operator's console for a pair in a running daemon (`omnid ctl teleop start`,
//! docs/TELEOP.md §8): it takes each arm's side up on that arm's own socket (so each side
//! passes its arm's lease and checks like any client's command), watches both arms, says
//! what the pair is doing once a second, and ends the pair when asked, when either arm leaves
//! `teleop` (a trip, someone's `mode idle`) or when the daemon goes. The pair belongs to the
//! console's sessions: if the console dies, the daemon ends it as for any lease holder that
//! leaves (the follower holds, the leader's force fades).

use omnid_client::client::{Client, ClientError, Message};
use omnid_client::protocol::State;
use serde_json::{json, Value};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

/// The changes to `[teleop]` asked for on the command line (both sides get the same).
#[derive(Debug, Clone, Default)]
pub struct PairSettings {
    /// pp or pf.
    pub architecture: Option<String>,
    /// Follower mm per leader mm.
    pub motion_scale: Option<f64>,
    /// Leader force per coupling force.
    pub force_scale: Option<f64>,
    /// button1 or always.
    pub operator: Option<String>,
    /// Time-domain passivity on or off.
    pub passivity: Option<bool>,
}

/// How a console ended.
#[derive(Debug, Clone, PartialEq)]
pub enum ConsoleEnd {
    /// The operator stopped it (Ctrl-C, SIGTERM).
    Stopped,
    /// The time asked for ran out.
    Elapsed,
    /// An arm left `teleop`: its name and mode.
    ArmLeft {
        /// The arm.
        arm: String,
        /// The mode it went to.
        mode: String,
    },
    /// An arm's daemon closed the connection.
    Gone(String),
}

/// Rate of each arm's state stream while the console watches, Hz.
const WATCH_HZ: f64 = 50.0;
/// How long an arm may take to show `teleop` after its side was started, s (its servo takes
/// the command at its next tick; this is slack for a loaded machine).
const ENTER_S: f64 = 2.0;

/// The `teleop` request for one side.
pub fn side_request(role: &str, peer: &str, s: &PairSettings) -> Value {
    let mut r = json!({"op": "teleop", "role": role, "peer": peer});
    let fields: [(&str, Option<Value>); 5] = [
        ("architecture", s.architecture.as_ref().map(|v| json!(v))),
        ("motion_scale", s.motion_scale.map(|v| json!(v))),
        ("force_scale", s.force_scale.map(|v| json!(v))),
        ("operator", s.operator.as_ref().map(|v| json!(v))),
        ("passivity", s.passivity.map(|v| json!(v))),
    ];
    for (k, v) in fields {
        if let Some(v) = v {
            r[k] = v;
        }
    }
    r
}

/// Start both sides, watch until the end, stop both sides. `say` gets the human lines.
pub fn run(
    leader: &mut Client,
    follower: &mut Client,
    settings: &PairSettings,
    seconds: Option<f64>,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<ConsoleEnd, ClientError> {
    let (l_name, f_name) = (leader.hello().arm.clone(), follower.hello().arm.clone());
    if l_name == f_name {
        return Err(ClientError::Refused(format!(
            "the leader and the follower are the same arm `{l_name}`"
        )));
    }
    let reply = leader.request(side_request("leader", &f_name, settings))?;
    if let Err(e) = follower.request(side_request("follower", &l_name, settings)) {
        let _ = leader.request(json!({"op": "teleop_stop"}));
        return Err(e);
    }
    let t = &reply["teleop"];
    say(&format!(
        "teleop: {l_name} leads, {f_name} follows ({}, motion ×{}, force ×{}, operator {}, \
         passivity {}); Ctrl-C ends the pair",
        t["architecture"].as_str().unwrap_or("?"),
        t["motion_scale"],
        t["force_scale"],
        t["operator"].as_str().unwrap_or("?"),
        if t["passivity"] == json!(true) {
            "on"
        } else {
            "off"
        }
    ));
    if t["operator"] == "button1" {
        say(&format!(
            "teleop: hold {l_name}'s button 1 to follow; button 2 is the clutch"
        ));
    }
    let end = watch(leader, follower, seconds, stop, say);
    for c in [&mut *leader, &mut *follower] {
        let _ = c.request(json!({"op": "teleop_stop"}));
    }
    end
}

/// Both arms' latest states, a line a second, until an end.
fn watch(
    leader: &mut Client,
    follower: &mut Client,
    seconds: Option<f64>,
    stop: &AtomicBool,
    say: &mut dyn FnMut(&str),
) -> Result<ConsoleEnd, ClientError> {
    for c in [&mut *leader, &mut *follower] {
        c.request(json!({"op": "stream", "rate_hz": WATCH_HZ}))?;
    }
    let start = Instant::now();
    let mut next_line = start + Duration::from_secs(1);
    let mut latest: [Option<State>; 2] = [None, None];
    loop {
        if stop.load(Ordering::SeqCst) {
            return Ok(ConsoleEnd::Stopped);
        }
        if seconds.is_some_and(|s| start.elapsed().as_secs_f64() >= s) {
            return Ok(ConsoleEnd::Elapsed);
        }
        for (k, c) in [&mut *leader, &mut *follower].into_iter().enumerate() {
            match c.recv(10) {
                Ok(Message::State(s)) => latest[k] = Some(s),
                Ok(Message::Other(v)) if v["type"] == "bye" => {
                    return Ok(ConsoleEnd::Gone(c.hello().arm.clone()))
                }
                Ok(Message::Other(v)) => {
                    if let Some(line) = crate::human::event_line(&v) {
                        say(&format!("{}: {}", c.hello().arm, line.trim_start()));
                    }
                }
                Err(ClientError::Timeout(_)) => {}
                Err(ClientError::Closed) => return Ok(ConsoleEnd::Gone(c.hello().arm.clone())),
                Err(e) => return Err(e),
            }
        }
        // An arm that has left `teleop` ends the pair (the servo has already disabled it).
        if start.elapsed().as_secs_f64() > ENTER_S {
            for (k, c) in [&*leader, &*follower].into_iter().enumerate() {
                if let Some(s) = &latest[k] {
                    if s.mode != "teleop" {
                        return Ok(ConsoleEnd::ArmLeft {
                            arm: c.hello().arm.clone(),
                            mode: s.mode.clone(),
                        });
                    }
                }
            }
        }
        if Instant::now() >= next_line {
            next_line += Duration::from_secs(1);
            if let [Some(l), Some(f)] = &latest {
                say(&status_line(l, f));
            }
        }
    }
}

/// One line on the pair: each side's state, the follower's contact force, the leader's tip.
pub fn status_line(leader: &State, follower: &State) -> String {
    let norm = |v: &[f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    format!(
        "{:>8.1} s  leader {:<9}  follower {:<9}  follower contact {:>5.2} N  leader tip \
         {:>6.1} {:>6.1} {:>6.1} mm  follower tip {:>6.1} {:>6.1} {:>6.1} mm",
        leader.t,
        leader.teleop.as_deref().unwrap_or(&leader.mode),
        follower.teleop.as_deref().unwrap_or(&follower.mode),
        norm(&follower.fext),
        leader.tip_mm[0],
        leader.tip_mm[1],
        leader.tip_mm[2],
        follower.tip_mm[0],
        follower.tip_mm[1],
        follower.tip_mm[2],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_side_asks_only_for_the_changes_given() {
        let none = side_request("leader", "right", &PairSettings::default());
        assert_eq!(
            none,
            json!({"op": "teleop", "role": "leader", "peer": "right"})
        );
        let some = side_request(
            "follower",
            "left",
            &PairSettings {
                architecture: Some("pf".into()),
                motion_scale: Some(0.5),
                passivity: Some(false),
                ..PairSettings::default()
            },
        );
        assert_eq!(
            some,
            json!({"op": "teleop", "role": "follower", "peer": "left", "architecture": "pf",
                   "motion_scale": 0.5, "passivity": false})
        );
    }
}

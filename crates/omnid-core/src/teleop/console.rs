//! The operator's console for a pair in a running daemon (`omnid ctl teleop start`,
//! docs/TELEOP.md §8): it takes each arm's side up on that arm's own socket (so each side
//! passes its arm's lease and checks like any client's command), watches both arms, says
//! what the pair is doing once a second, and ends the pair when asked, when either arm leaves
//! `teleop` (a trip, someone's `mode idle`) or when the daemon goes. The pair belongs to the
//! console's sessions: if the console dies, the daemon ends it as for any lease holder that
//! leaves (the follower holds, the leader's force fades).
//!
//! When one arm is served on another PC (two daemons over zenoh, docs/TELEOP.md §9), the
//! console takes up only the side whose arm is here; the same command on the other PC takes
//! up the other.

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
    /// Before coupling, bring the follower to the leader's pose (`--align`): a `servo_jp` ramp
    /// of at most [`ALIGN_RAD_S`] on each joint (both arms must be served here).
    pub align: bool,
}

/// `--align`: the follower's setpoint moves toward the leader's joint angles at most this
/// fast, rad/s (about 60 mm/s at the tip).
pub const ALIGN_RAD_S: f64 = 0.5;
/// `--align` is done when the follower is this close to the leader on every joint, rad.
const ALIGN_TOLERANCE_RAD: f64 = 0.01;
/// `--align` gives up after this long, s.
const ALIGN_MAX_S: f64 = 20.0;

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
    /// The other side, served by another daemon, is down (it ended or faulted): this side's
    /// arm showed `down` (docs/TELEOP.md §4).
    PeerDown {
        /// The arm served here.
        arm: String,
        /// The other daemon's arm.
        peer: String,
    },
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

/// The pair's two arms, each reached here on its socket or served by another daemon.
pub enum Side<'a> {
    /// Served on this PC: its side is taken up on this client.
    Here(&'a mut Client),
    /// Served by another daemon (over zenoh): its name; its side is taken up there.
    Elsewhere(String),
}

impl Side<'_> {
    fn name(&self) -> String {
        match self {
            Side::Here(c) => c.hello().arm.clone(),
            Side::Elsewhere(n) => n.clone(),
        }
    }
}

/// How the console speaks: to people, or a JSON object a line (`{"type":"note","text"}` for
/// what it says, `{"type":"pair","sides":[{"arm","state"}…]}` once a second).
pub struct Say<'a> {
    /// JSON lines.
    pub json: bool,
    /// Where each line goes.
    pub out: &'a mut dyn FnMut(&str),
}

impl Say<'_> {
    fn note(&mut self, text: &str) {
        if self.json {
            (self.out)(&json!({"type": "note", "text": text}).to_string())
        } else {
            (self.out)(text)
        }
    }

    /// Each watched arm's latest state.
    fn pair(&mut self, sides: &[&mut Client], latest: &[Option<State>]) {
        if self.json {
            let sides: Vec<Value> = sides
                .iter()
                .zip(latest)
                .map(|(c, s)| json!({"arm": c.hello().arm, "state": s}))
                .collect();
            (self.out)(&json!({"type": "pair", "sides": sides}).to_string());
            return;
        }
        match latest {
            [Some(l), Some(f)] => (self.out)(&status_line(l, f)),
            [Some(s)] => (self.out)(&side_line(s)),
            _ => {}
        }
    }
}

/// Start the sides served here, watch until the end, stop them.
pub fn run(
    leader: Side<'_>,
    follower: Side<'_>,
    settings: &PairSettings,
    seconds: Option<f64>,
    stop: &AtomicBool,
    say: &mut Say<'_>,
) -> Result<ConsoleEnd, ClientError> {
    let (l_name, f_name) = (leader.name(), follower.name());
    if l_name == f_name {
        return Err(ClientError::Refused(format!(
            "the leader and the follower are the same arm `{l_name}`"
        )));
    }
    // The sides served here, with the role each takes and its peer.
    let mut here: Vec<(&mut Client, &str, &str)> = Vec::new();
    if let Side::Here(c) = leader {
        here.push((c, "leader", &f_name));
    }
    if let Side::Here(c) = follower {
        here.push((c, "follower", &l_name));
    }
    if here.is_empty() {
        return Err(ClientError::Refused(format!(
            "neither `{l_name}` nor `{f_name}` is served on this PC"
        )));
    }
    if settings.align {
        match here.as_mut_slice() {
            [(l, _, _), (f, _, _)] => align(l, f, stop, say)?,
            _ => {
                return Err(ClientError::Refused(format!(
                    "--align moves the follower to the leader's pose, which only a console with \
                     both arms on its PC knows (`{l_name}` and `{f_name}` are on two daemons)"
                )))
            }
        }
    }
    let mut reply = Value::Null;
    for k in 0..here.len() {
        let (c, role, peer) = &mut here[k];
        match c.request(side_request(role, peer, settings)) {
            Ok(r) => {
                if k == 0 {
                    reply = r;
                }
            }
            Err(e) => {
                for (c, _, _) in here.iter_mut().take(k) {
                    let _ = c.request(json!({"op": "teleop_stop"}));
                }
                return Err(e);
            }
        }
    }
    let t = &reply["teleop"];
    say.note(&format!(
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
    if here.len() == 1 {
        let (c, role, peer) = &here[0];
        say.note(&format!(
            "teleop: `{peer}` is not served on this PC: {} is the {role} of a pair with another \
             daemon's arm (over zenoh); start the other side on its PC with the same command",
            c.hello().arm
        ));
    }
    if t["operator"] == "button1" {
        say.note(&format!(
            "teleop: hold {l_name}'s button 1 to follow; button 2 is the clutch"
        ));
    }
    // With the other side on another daemon, its end shows here only as this side's `down`.
    let alone = (here.len() == 1).then(|| here[0].2.to_string());
    let mut clients: Vec<&mut Client> = here.into_iter().map(|(c, _, _)| c).collect();
    let end = watch(&mut clients, alone.as_deref(), seconds, stop, say);
    for c in clients {
        let _ = c.request(json!({"op": "teleop_stop"}));
    }
    end
}

/// Bring the follower to the leader's joint angles (read again every step: the leader may be
/// moving) by a `servo_jp` ramp of at most [`ALIGN_RAD_S`] per joint, until it is within
/// [`ALIGN_TOLERANCE_RAD`] on every joint. The follower holds there (the stream's fallback)
/// until its side is taken up.
fn align(
    leader: &mut Client,
    follower: &mut Client,
    stop: &AtomicBool,
    say: &mut Say<'_>,
) -> Result<(), ClientError> {
    const STEP_S: f64 = 0.01;
    for c in [&mut *leader, &mut *follower] {
        c.request(json!({"op": "stream", "rate_hz": 100}))?;
    }
    let newest = |c: &mut Client| -> Result<State, ClientError> {
        let mut s = c.next_state(1000)?;
        while let Ok(n) = c.next_state(0) {
            s = n;
        }
        Ok(s)
    };
    let start = Instant::now();
    let mut setpoint = newest(follower)?.q;
    say.note(&format!(
        "teleop: aligning {} to {}'s pose (at most {ALIGN_RAD_S} rad/s a joint)",
        follower.hello().arm,
        leader.hello().arm
    ));
    for seq in 1u64.. {
        if stop.load(Ordering::SeqCst) {
            let _ = follower.request(json!({"op": "mode", "mode": "hold"}));
            return Err(ClientError::Refused("stopped while aligning".into()));
        }
        if start.elapsed().as_secs_f64() > ALIGN_MAX_S {
            let _ = follower.request(json!({"op": "mode", "mode": "hold"}));
            return Err(ClientError::Refused(format!(
                "the follower did not reach the leader's pose within {ALIGN_MAX_S} s"
            )));
        }
        let (l, f) = (newest(leader)?, newest(follower)?);
        let mut done = true;
        for j in 0..3 {
            let step = ALIGN_RAD_S * STEP_S;
            setpoint[j] += (l.q[j] - setpoint[j]).clamp(-step, step);
            done &= (f.q[j] - l.q[j]).abs() <= ALIGN_TOLERANCE_RAD;
        }
        if done {
            return Ok(());
        }
        follower.send(&json!({"op": "servo_jp", "seq": seq, "q": setpoint, "ttl_ms": 200}))?;
        std::thread::sleep(Duration::from_secs_f64(STEP_S));
    }
    Ok(())
}

/// The latest states of the arms served here, a line a second, until an end.
fn watch(
    sides: &mut [&mut Client],
    elsewhere: Option<&str>,
    seconds: Option<f64>,
    stop: &AtomicBool,
    say: &mut Say<'_>,
) -> Result<ConsoleEnd, ClientError> {
    for c in sides.iter_mut() {
        c.request(json!({"op": "stream", "rate_hz": WATCH_HZ}))?;
    }
    let start = Instant::now();
    let mut next_line = start + Duration::from_secs(1);
    let mut latest: Vec<Option<State>> = vec![None; sides.len()];
    loop {
        if stop.load(Ordering::SeqCst) {
            return Ok(ConsoleEnd::Stopped);
        }
        if seconds.is_some_and(|s| start.elapsed().as_secs_f64() >= s) {
            return Ok(ConsoleEnd::Elapsed);
        }
        for (k, c) in sides.iter_mut().enumerate() {
            match c.recv(10) {
                Ok(Message::State(s)) => latest[k] = Some(s),
                Ok(Message::Other(v)) if v["type"] == "bye" => {
                    return Ok(ConsoleEnd::Gone(c.hello().arm.clone()))
                }
                Ok(Message::Other(v)) => {
                    if let Some(line) = crate::human::event_line(&v) {
                        say.note(&format!("{}: {}", c.hello().arm, line.trim_start()));
                    }
                }
                Err(ClientError::Timeout(_)) => {}
                Err(ClientError::Closed) => return Ok(ConsoleEnd::Gone(c.hello().arm.clone())),
                Err(e) => return Err(e),
            }
        }
        // An arm that has left `teleop` ends the pair (the servo has already disabled it).
        if start.elapsed().as_secs_f64() > ENTER_S {
            for (k, c) in sides.iter().enumerate() {
                if let Some(s) = &latest[k] {
                    if s.mode != "teleop" {
                        return Ok(ConsoleEnd::ArmLeft {
                            arm: c.hello().arm.clone(),
                            mode: s.mode.clone(),
                        });
                    }
                    if let Some(peer) = elsewhere.filter(|_| s.teleop.as_deref() == Some("down")) {
                        return Ok(ConsoleEnd::PeerDown {
                            arm: c.hello().arm.clone(),
                            peer: peer.to_string(),
                        });
                    }
                }
            }
        }
        if Instant::now() >= next_line {
            next_line += Duration::from_secs(1);
            say.pair(sides, &latest);
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

/// One line on the side served here (its peer is another daemon's): its state, its tip, and
/// the round trip is in `status`.
pub fn side_line(s: &State) -> String {
    format!(
        "{:>8.1} s  {:<9}  contact {:>5.2} N  tip {:>6.1} {:>6.1} {:>6.1} mm",
        s.t,
        s.teleop.as_deref().unwrap_or(&s.mode),
        (s.fext[0] * s.fext[0] + s.fext[1] * s.fext[1] + s.fext[2] * s.fext[2]).sqrt(),
        s.tip_mm[0],
        s.tip_mm[1],
        s.tip_mm[2],
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

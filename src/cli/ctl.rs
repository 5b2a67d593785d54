//! `omnid ctl`: commands to a running daemon, teleoperation among them.

use crate::{
    absolute, connect, stop_on_signal, EXIT_BAD_INPUT, EXIT_DEVICE_FAULT, EXIT_OPERATOR_STOP,
    EXIT_REFUSED,
};
use clap::Subcommand;
use omnid::transport::client::{Client, ClientError};
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct CtlArgs {
    /// The daemon's socket [default: $OMNID_SOCKET, else the one in the default directory].
    #[arg(long)]
    socket: Option<PathBuf>,
    /// The arm, by name or alias (its socket `<name>.sock` in the default directories).
    #[arg(long, value_name = "NAME", conflicts_with = "socket")]
    arm: Option<String>,
    /// Print the daemon's reply as JSON (for programs; `status`: the keys of
    /// docs/DESIGN.md §2.3) instead of the readable form; `teleop start`: a JSON object a line
    /// (`note`s, and each second a `pair` with each arm's latest state).
    #[arg(long, global = true)]
    json: bool,
    #[command(subcommand)]
    command: CtlCommand,
}

#[derive(Subcommand)]
pub(crate) enum CtlCommand {
    /// The mode, controller, lease, clients, faults, tracking, timing and recording (`--json`:
    /// the run summary so far with them).
    Status,
    /// idle, hold, track or free (track follows --trajectory).
    Mode {
        mode: String,
        #[arg(long, default_value = "sine")]
        trajectory: String,
    },
    /// Switch the control law (bumpless): pd, ct, nnidc, off.
    Controller { controller: String },
    /// Start or stop recording every tick to a log (CSV, as `omnid run` writes).
    Record {
        /// start or stop
        action: String,
        path: Option<PathBuf>,
    },
    /// Save the identifier's weights to a file, load them from one, or reset them to the
    /// shipped ones (what the arm learned is forgotten: its saved weights are removed).
    Weights {
        /// save, load or reset
        action: String,
        /// The file (save and load).
        path: Option<PathBuf>,
    },
    /// Freeze the identifier's online adaptation.
    Freeze,
    /// Resume the identifier's online adaptation.
    Adapt,
    /// Stop the daemon (zero torque, amplifiers off).
    Shutdown,
    /// Simulator: the hand presses, releases or clicks (press, then release 0.1 s later) a
    /// stylus button, 1 or 2.
    Button {
        /// 1 or 2
        button: u64,
        /// press, release or click
        action: String,
    },
    /// Simulator: the hand puts the stylus in its inkwell.
    Dock,
    /// Simulator: the hand takes the stylus out of its inkwell and holds it lightly.
    Undock,
    /// Teleoperation between two arms of the daemon (docs/TELEOP.md): `start` couples them
    /// and watches until Ctrl-C, which uncouples them (both hold).
    Teleop {
        #[command(subcommand)]
        action: TeleopAction,
    },
}

#[derive(Subcommand)]
pub(crate) enum TeleopAction {
    /// Couple a leader arm (a person moves it) and a follower arm (it copies the leader),
    /// with `[teleop]`'s settings and the changes given; runs until Ctrl-C or --seconds.
    Start {
        /// The leader arm, by name or alias.
        #[arg(long, value_name = "ARM")]
        leader: String,
        /// The follower arm, by name or alias.
        #[arg(long, value_name = "ARM")]
        follower: String,
        /// pp (position–position) or pf (position–force, from the follower's estimate).
        #[arg(long)]
        architecture: Option<String>,
        /// Follower mm per leader mm.
        #[arg(long)]
        motion_scale: Option<f64>,
        /// The leader feels this times the force.
        #[arg(long)]
        force_scale: Option<f64>,
        /// When the operator counts as present: button1 (held) or always.
        #[arg(long)]
        operator: Option<String>,
        /// Time-domain passivity off (on by default).
        #[arg(long)]
        no_passivity: bool,
        /// Before coupling, bring the follower to the leader's pose (a servo_jp ramp of at
        /// most 0.5 rad/s a joint; both arms served on this PC).
        #[arg(long)]
        align: bool,
        /// Uncouple after this many seconds.
        #[arg(long)]
        seconds: Option<f64>,
    },
}

pub(crate) fn ctl_cmd(args: CtlArgs) -> Result<u8, anyhow::Error> {
    use serde_json::json;
    if let CtlCommand::Teleop { action } = args.command {
        return teleop_console(action, args.json);
    }
    let Some(mut request) = request_for(&args.command) else {
        return Ok(EXIT_BAD_INPUT);
    };
    // Paths are the daemon's to open: make relative ones relative to where ctl runs.
    if let Some(p) = request
        .get("path")
        .and_then(|p| p.as_str())
        .map(String::from)
    {
        request["path"] = json!(absolute(std::path::Path::new(&p)));
    }
    let mut client = match connect(args.socket, args.arm.as_deref(), "omnid ctl") {
        Ok(c) => c,
        Err(code) => return Ok(code),
    };
    match client.request(request) {
        Ok(reply) => {
            let text = reply_text(&args.command, args.json, &reply)?;
            omnid::outln!("{text}");
            Ok(0)
        }
        Err(e) => {
            omnid::errln!("omnid ctl: {e}");
            Ok(EXIT_REFUSED)
        }
    }
}

/// The request a command sends; `None` once a bad argument has been said (the exit is
/// `EXIT_BAD_INPUT`).
fn request_for(command: &CtlCommand) -> Option<serde_json::Value> {
    use serde_json::json;
    Some(match command {
        CtlCommand::Status => json!({ "op": "status" }),
        CtlCommand::Mode { mode, trajectory } => {
            json!({ "op": "mode", "mode": mode, "trajectory": trajectory })
        }
        CtlCommand::Controller { controller } => {
            json!({ "op": "controller", "controller": controller })
        }
        CtlCommand::Record { action, path } => match action.as_str() {
            "start" => json!({ "op": "record_start", "path": path }),
            "stop" => json!({ "op": "record_stop" }),
            other => {
                omnid::errln!("omnid ctl: record {other}: expected start or stop");
                return None;
            }
        },
        CtlCommand::Weights { action, path } => return weights_request(action, path.as_deref()),
        CtlCommand::Freeze => json!({ "op": "adapt", "on": false }),
        CtlCommand::Adapt => json!({ "op": "adapt", "on": true }),
        CtlCommand::Shutdown => json!({ "op": "shutdown" }),
        CtlCommand::Button { button, action } => match action.as_str() {
            "press" | "release" | "click" => {
                json!({ "op": "stylus", "action": action, "button": button })
            }
            other => {
                omnid::errln!(
                    "omnid ctl: button {button} {}: expected press, release or click",
                    omnid::text::cut(other)
                );
                return None;
            }
        },
        CtlCommand::Dock => json!({ "op": "stylus", "action": "dock" }),
        CtlCommand::Undock => json!({ "op": "stylus", "action": "undock" }),
        CtlCommand::Teleop { .. } => unreachable!("handled by teleop_console"),
    })
}

/// `weights save|load PATH`, `weights reset`; `None` once a bad argument has been said.
fn weights_request(action: &str, path: Option<&std::path::Path>) -> Option<serde_json::Value> {
    use serde_json::json;
    match (action, path) {
        ("save", Some(path)) => Some(json!({ "op": "weights_save", "path": absolute(path) })),
        ("load", Some(path)) => Some(json!({ "op": "weights_load", "path": absolute(path) })),
        ("reset", None) => Some(json!({ "op": "weights_reset" })),
        ("save" | "load", None) => {
            omnid::errln!(
                "omnid ctl: weights {action}: which file? (omnid ctl weights {action} PATH)"
            );
            None
        }
        ("reset", Some(_)) => {
            omnid::errln!(
                "omnid ctl: weights reset takes no file (it puts the shipped weights back)"
            );
            None
        }
        (other, _) => {
            omnid::errln!(
                "omnid ctl: weights {}: expected save, load or reset",
                omnid::text::cut(other)
            );
            None
        }
    }
}

/// The daemon's reply as printed: `status` as its block (or pretty JSON), others as a line
/// (or the reply's JSON without its envelope).
fn reply_text(
    command: &CtlCommand,
    json: bool,
    reply: &serde_json::Value,
) -> Result<String, anyhow::Error> {
    Ok(match command {
        CtlCommand::Status if json => serde_json::to_string_pretty(&reply["status"])?,
        CtlCommand::Status => omnid::human::status_block(&reply["status"])
            .trim_end()
            .to_string(),
        _ if !json => omnid::human::reply_line(reply),
        _ => {
            let mut r = reply.clone();
            if let Some(o) = r.as_object_mut() {
                o.remove("type");
                o.remove("id");
            }
            r.to_string()
        }
    })
}

/// `omnid ctl teleop start`: the pair's console, until Ctrl-C, SIGTERM or --seconds.
pub(crate) fn teleop_console(action: TeleopAction, json: bool) -> Result<u8, anyhow::Error> {
    use omnid::teleop::console::{self, PairSettings};
    let TeleopAction::Start {
        leader,
        follower,
        architecture,
        motion_scale,
        force_scale,
        operator,
        no_passivity,
        align,
        seconds,
    } = action;
    if seconds.is_some_and(|s| !(s.is_finite() && s > 0.0)) {
        omnid::errln!("omnid ctl teleop: --seconds must be a number > 0");
        return Ok(EXIT_BAD_INPUT);
    }
    let stop = stop_on_signal()?;
    let (mut l_client, mut f_client) = match connect_pair(&leader, &follower) {
        Ok(clients) => clients,
        Err(code) => return Ok(code),
    };
    let settings = PairSettings {
        architecture,
        motion_scale,
        force_scale,
        operator,
        passivity: no_passivity.then_some(false),
        align,
    };
    let mut out = |line: &str| omnid::outln!("{line}");
    let mut say = console::Say {
        json,
        out: &mut out,
    };
    let end = console::run(
        side(l_client.as_mut(), &leader),
        side(f_client.as_mut(), &follower),
        &settings,
        seconds,
        &stop,
        &mut say,
    );
    Ok(say_console_end(end, &leader, &follower, seconds))
}

/// A client on each arm served on this PC (`None`: served by another daemon, its side started
/// there); `Err`: the exit, once the reason is said.
fn connect_pair(leader: &str, follower: &str) -> Result<(Option<Client>, Option<Client>), u8> {
    let found = [leader, follower].map(omnid::transport::find_arm_socket);
    if let [Err(a), Err(b)] = &found {
        omnid::errln!("omnid: {a}");
        omnid::errln!("omnid: {b}");
        return Err(EXIT_DEVICE_FAULT);
    }
    let mut clients = Vec::new();
    for (p, who) in found.iter().zip(["leader", "follower"]) {
        clients.push(match p {
            Ok(p) => {
                let name = format!("omnid ctl teleop ({who})");
                match Client::connect(p, &name) {
                    Ok(c) => Some(c),
                    Err(e) => {
                        omnid::errln!("omnid: {e}");
                        return Err(match e {
                            ClientError::Refused(_) => EXIT_REFUSED,
                            _ => EXIT_DEVICE_FAULT,
                        });
                    }
                }
            }
            Err(_) => None,
        });
    }
    let f_client = clients.pop().flatten();
    let l_client = clients.pop().flatten();
    Ok((l_client, f_client))
}

/// An arm's side for the console: its client here, or its name.
fn side<'a>(c: Option<&'a mut Client>, name: &str) -> omnid::teleop::console::Side<'a> {
    use omnid::teleop::console::Side;
    match c {
        Some(c) => Side::Here(c),
        None => Side::Elsewhere(name.to_string()),
    }
}

/// How the console ended, said; the exit.
fn say_console_end(
    end: Result<omnid::teleop::console::ConsoleEnd, ClientError>,
    leader: &str,
    follower: &str,
    seconds: Option<f64>,
) -> u8 {
    use omnid::teleop::console::ConsoleEnd;
    match end {
        Ok(ConsoleEnd::Elapsed) => {
            omnid::outln!(
                "teleop: uncoupled after {} s; both arms hold",
                seconds.unwrap_or(0.0)
            );
            0
        }
        Ok(ConsoleEnd::Stopped) => {
            omnid::errln!(
                "omnid ctl teleop: stopped by the operator; both arms uncoupled, holding"
            );
            EXIT_OPERATOR_STOP
        }
        Ok(ConsoleEnd::ArmLeft { arm, mode }) => {
            // What each side does now: the one that left is in its new mode.
            let follower_now = if arm == follower {
                format!("the follower is {mode}")
            } else {
                "the follower holds".to_string()
            };
            let leader_now = if arm == leader {
                format!("the leader is {mode}")
            } else {
                "the leader's force faded".to_string()
            };
            omnid::errln!(
                "omnid ctl teleop: {arm} left teleop (now {mode}): the pair is uncoupled \
                 ({follower_now}, {leader_now}); `omnid ctl --arm {arm} status` says why"
            );
            EXIT_DEVICE_FAULT
        }
        Ok(ConsoleEnd::PeerDown { arm, peer }) => {
            omnid::errln!(
                "omnid ctl teleop: {peer}'s side is down (it ended or faulted on its daemon): the \
                 pair is uncoupled, {arm} holds"
            );
            EXIT_DEVICE_FAULT
        }
        Ok(ConsoleEnd::Gone(arm)) => {
            omnid::errln!("omnid ctl teleop: {arm}'s daemon closed the connection");
            EXIT_DEVICE_FAULT
        }
        Err(e) => {
            omnid::errln!("omnid ctl teleop: {e}");
            EXIT_REFUSED
        }
    }
}

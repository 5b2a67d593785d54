//! `omnid watch`: live state from a running daemon.

use crate::{connect, EXIT_BAD_INPUT, EXIT_INTERNAL, EXIT_REFUSED};
use std::path::PathBuf;

#[derive(clap::Args)]
pub(crate) struct WatchArgs {
    /// The daemon's socket [default: $OMNID_SOCKET, else the one in the default directory].
    #[arg(long)]
    socket: Option<PathBuf>,
    /// The arm, by name or alias (its socket `<name>.sock` in the default directories).
    #[arg(long, value_name = "NAME", conflicts_with = "socket")]
    arm: Option<String>,
    /// Stop after this many samples.
    #[arg(long)]
    count: Option<u64>,
    /// Samples per second (up to the device's rate).
    #[arg(long, default_value_t = 10.0)]
    rate: f64,
    /// One JSON object per line, for programs: each sample, and each event as the daemon
    /// sent it (without it: readable lines, events as sentences).
    #[arg(long)]
    json: bool,
}

pub(crate) fn watch_cmd(args: WatchArgs) -> Result<u8, anyhow::Error> {
    use omnid::transport::client::Message;
    use std::io::Write;
    if !(args.rate.is_finite() && args.rate > 0.0) {
        omnid::errln!("omnid watch: --rate {} must be a number > 0", args.rate);
        return Ok(EXIT_BAD_INPUT);
    }
    let mut client = match connect(args.socket, args.arm.as_deref(), "omnid watch") {
        Ok(c) => c,
        Err(code) => return Ok(code),
    };
    if let Err(e) = client.request(serde_json::json!({ "op": "stream", "rate_hz": args.rate })) {
        omnid::errln!("omnid watch: {e}");
        return Ok(EXIT_REFUSED);
    }
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    if !args.json {
        // What each column is, above the first line (the widths are the lines' own).
        let header = format!(
            "{:>8} {:>11}  {:<8} {:<5}  {:<29}  {:<30}  {:<10}  {}",
            "sample",
            "time",
            "mode",
            "ctrl",
            "q: joints 1, 2, 3",
            "tip: x, y, z",
            "buttons",
            "tau: joints 1, 2, 3"
        );
        if let Err(e) = writeln!(out, "{header}") {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                return Ok(0);
            }
            omnid::errln!("omnid watch: cannot write to stdout: {e}; stopped");
            return Ok(EXIT_INTERNAL);
        }
    }
    let mut seen = 0u64;
    while args.count.is_none_or(|n| seen < n) {
        let line = match client.recv(-1) {
            Ok(Message::State(s)) => {
                seen += 1;
                if args.json {
                    let mut v = serde_json::to_value(&s)?;
                    v["type"] = serde_json::json!("state");
                    v.to_string()
                } else {
                    format!(
                        "{:>8} {:>9.3} s  {:<8} {:<5}  q {:>7.4} {:>7.4} {:>7.4} rad  tip {:>7.1} {:>7.1} {:>7.1} mm  buttons {}{}  tau {:>6.1} {:>6.1} {:>6.1} mN·m{}",
                        s.seq, s.t, s.mode, s.controller, s.q[0], s.q[1], s.q[2],
                        s.tip_mm[0], s.tip_mm[1], s.tip_mm[2],
                        u8::from(s.buttons[0]), u8::from(s.buttons[1]),
                        s.tau[0] * 1e3, s.tau[1] * 1e3, s.tau[2] * 1e3,
                        if s.flags != 0 { format!("  flags {}", s.flags) } else { String::new() }
                    )
                }
            }
            Ok(Message::Other(v)) if v["type"] == "bye" => {
                omnid::errln!("omnid watch: the daemon is stopping");
                return Ok(0);
            }
            Ok(Message::Other(v)) => {
                if args.json {
                    v.to_string()
                } else {
                    match omnid::human::event_line(&v) {
                        Some(line) => line,
                        None => continue,
                    }
                }
            }
            Err(omnid::transport::client::ClientError::Closed) => {
                omnid::errln!("omnid watch: the daemon closed the connection");
                return Ok(0);
            }
            Err(e) => {
                omnid::errln!("omnid watch: {e}");
                return Ok(EXIT_INTERNAL);
            }
        };
        // A closed stdout (`| head`) ends the watch quietly; any other failure (a full disk
        // under `> file`) is an error: the data did not arrive.
        if let Err(e) = writeln!(out, "{line}").and_then(|()| out.flush()) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                return Ok(0);
            }
            omnid::errln!("omnid watch: cannot write to stdout: {e}; stopped");
            return Ok(EXIT_INTERNAL);
        }
    }
    Ok(0)
}

//! What the live view costs the servo loop: `omnid serve` on the simulator for SECONDS with
//! no live view, with a viewer that reads everything, and with a viewer that subscribed to
//! everything and never reads; rounds interleaved; the servo's lateness percentiles from the
//! daemon's own summary, then the median over rounds.
//! `cargo bench --bench live_view -- [SECONDS] [ROUNDS]` (default 20 s, 2 rounds).
//!
//! The viewers are a few lines of WebSocket by hand (handshake, one masked text frame to
//! subscribe): a test client, not a protocol omnid speaks.

mod support;

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::Duration;

/// Read one server frame (unmasked): (opcode, payload).
fn frame(s: &mut impl Read) -> std::io::Result<(u8, Vec<u8>)> {
    let mut h = [0u8; 2];
    s.read_exact(&mut h)?;
    let mut len = (h[1] & 0x7f) as u64;
    if len == 126 {
        let mut b = [0u8; 2];
        s.read_exact(&mut b)?;
        len = u16::from_be_bytes(b) as u64;
    } else if len == 127 {
        let mut b = [0u8; 8];
        s.read_exact(&mut b)?;
        len = u64::from_be_bytes(b);
    }
    let mut payload = vec![0; len as usize];
    s.read_exact(&mut payload)?;
    Ok((h[0] & 0x0f, payload))
}

/// Connect, subscribe to every advertised channel; the stream, ready to be read or not.
fn viewer(addr: SocketAddr) -> TcpStream {
    let mut s = TcpStream::connect(addr).expect("live view reachable");
    write!(
        s,
        "GET / HTTP/1.1\r\nHost: {addr}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
         Sec-WebSocket-Key: b21uaWQtYmVuY2gtdmlldw==\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    )
    .unwrap();
    let mut r = BufReader::new(s.try_clone().unwrap());
    let mut line = String::new();
    r.read_line(&mut line).unwrap();
    assert!(line.contains("101"), "handshake: {line}");
    while {
        line.clear();
        r.read_line(&mut line).unwrap();
        line != "\r\n"
    } {}
    let channels = loop {
        let (op, payload) = frame(&mut r).unwrap();
        if op != 1 {
            continue;
        }
        let j: serde_json::Value = serde_json::from_slice(&payload).unwrap();
        if j["op"] == "advertise" {
            break j["channels"].as_array().unwrap().clone();
        }
    };
    let subs: Vec<_> = channels
        .iter()
        .enumerate()
        .map(|(i, c)| serde_json::json!({"id": i + 1, "channelId": c["id"]}))
        .collect();
    let text = serde_json::json!({"op": "subscribe", "subscriptions": subs}).to_string();
    let mut f = vec![0x81u8];
    let n = text.len();
    if n < 126 {
        f.push(0x80 | n as u8);
    } else {
        f.push(0x80 | 126);
        f.extend_from_slice(&(n as u16).to_be_bytes());
    }
    let mask = [1u8, 2, 3, 4];
    f.extend_from_slice(&mask);
    f.extend(text.bytes().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    s.write_all(&f).unwrap();
    s
}

fn main() {
    let (secs, rounds) = support::seconds_and_rounds(20.0, 2);
    let cases = ["no view", "reading viewer", "stuck viewer"];
    let mut p99s: Vec<Vec<f64>> = vec![Vec::new(); cases.len()];
    for round in 0..rounds {
        for (k, case) in cases.iter().enumerate() {
            // A free port for the view (taken and let go: the daemon binds it next).
            let port = std::net::TcpListener::bind("127.0.0.1:0")
                .unwrap()
                .local_addr()
                .unwrap();
            let daemon =
                support::SimServe::start(|_, opts| opts.foxglove = (k > 0).then_some(port));
            let mut keep = None;
            if k > 0 {
                let deadline = std::time::Instant::now() + Duration::from_secs(30);
                while TcpStream::connect(port).is_err() {
                    assert!(std::time::Instant::now() < deadline, "no live view");
                    std::thread::sleep(Duration::from_millis(20));
                }
                let s = viewer(port);
                if k == 1 {
                    let mut r = s.try_clone().unwrap();
                    std::thread::spawn(move || {
                        let mut sink = [0u8; 1 << 16];
                        while matches!(r.read(&mut sink), Ok(n) if n > 0) {}
                    });
                }
                keep = Some(s);
            }
            std::thread::sleep(Duration::from_secs_f64(secs));
            let outcome = daemon.finish();
            drop(keep);
            let t = &outcome.arms[0].summary.timing_us;
            let late = t.lateness.expect("paced");
            println!(
                "round {round} {case:14}: lateness p50 {:.1} p99 {:.1} p99.9 {:.1} max {:.0} µs, \
                 compute p99 {:.1} µs, overruns {}",
                late.p50,
                late.p99,
                late.p999,
                late.max,
                t.compute.map_or(f64::NAN, |c| c.p99),
                t.overruns
            );
            p99s[k].push(late.p99);
        }
    }
    for (k, case) in cases.iter().enumerate() {
        println!(
            "median {case:14}: lateness p99 {:.1} µs",
            support::median(&p99s[k])
        );
    }
    let base = support::median(&p99s[0]);
    println!(
        "lateness p99 / no view: reading {:.3}, stuck {:.3}",
        support::median(&p99s[1]) / base,
        support::median(&p99s[2]) / base
    );
}

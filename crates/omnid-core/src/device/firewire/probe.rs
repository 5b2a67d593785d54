//! `omnid probe`: first contact with a FireWire Omni, for a lab that has one (docs/BRINGUP.md).
//!
//! 1. Identify (vendor and serial registers) and dump the registers omnid knows, reading only.
//! 2. Start streaming with zero torque and the amplifiers off; measure the packet rate from
//!    the bus timestamps; then capture every packet to a file while telling the operator what
//!    to do ("dock the stylus", "press button 1", "turn the base to your left") and what the
//!    device reports: switches, packet period, counter behaviour, each joint's direction
//!    against `firewire.encoder_sign`.
//! 3. With `--outputs` only, and only with the operator's yes before each step, torques far
//!    below normal: the lamp bits with the motors off (a lamp that changes proves the device
//!    takes our packets), the amplifiers on at zero torque, then a few DAC counts each way on
//!    one motor at a time to find its sign, printed as the `dac_sign` line to write. Any "no",
//!    a stylus button, a joint moving further than a small pulse can move it, a disagreement
//!    between the operator and the encoders, or a device error ends the step at zero torque
//!    with the amplifiers off, and the device is stopped.
//!
//! The steps run over any `FireWireBus` (`device::firewire`), so the whole kit is tested on the
//! fake bus; the operator is a trait so tests can answer (or refuse) in scripts.

use super::capture::CaptureWriter;
use super::rate::RateMeasurement;
use super::{FireWireBus, FireWireOmni};
use crate::device::codec::{decode_state, MotorCommand, DAC_ZERO};
use crate::device::{DeviceError, EncoderUnwrap};
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use thiserror::Error;

/// Largest DAC offset `--outputs` will send (about 44 mN·m at the default 2.2e-4 N·m per
/// count: a tenth of the Omni's peak).
pub const MAX_PULSE_COUNTS: u16 = 200;
/// Encoder counts a joint must move for the probe to call it a direction (≈ 0.08 rad).
pub(crate) const MOVE_COUNTS: i64 = 200;
/// Encoder counts a sign pulse may move a joint before it is a surprise (≈ 0.35 rad).
pub(crate) const SURPRISE_COUNTS: i64 = 850;
/// Encoder counts of motion that count as "the motor moved the joint" in a sign pulse.
pub(crate) const PULSE_MOTION_COUNTS: i64 = 10;

/// What the probe does.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ProbeOptions {
    /// Packets to capture with the amplifiers off (`--seconds` × rate).
    pub capture_packets: usize,
    /// The configured packet rate (reported against the measured one).
    pub rate_hz: f64,
    /// Run the output steps.
    pub outputs: bool,
    /// DAC counts of the sign pulses (1..=[`MAX_PULSE_COUNTS`]).
    pub pulse_counts: u16,
    /// For messages: N·m per DAC count.
    pub nm_per_count: [f64; 3],
    /// The encoder signs in use (the backend applies them; the probe checks them).
    pub encoder_sign: [i8; 3],
}

/// The operator at the device.
pub trait Operator {
    /// Tell the operator something (one or more lines).
    fn say(&mut self, text: &str);
    /// Ask; `choices` are (key, meaning). `None`: no answer (end of input), which stops.
    fn ask(&mut self, question: &str, choices: &[(char, &str)]) -> Option<char>;
    /// Go on or stop; anything but yes is stop.
    fn confirm(&mut self, question: &str) -> bool {
        self.ask(question, &[('y', "yes, go on"), ('n', "no, stop here")]) == Some('y')
    }
    /// A yes/no question about what the operator saw; `None`: no answer.
    fn yes_no(&mut self, question: &str) -> Option<bool> {
        match self.ask(question, &[('y', "yes"), ('n', "no")]) {
            Some('y') => Some(true),
            Some('n') => Some(false),
            _ => None,
        }
    }
}

/// What stopped the probe early.
#[derive(Debug, Error)]
pub enum ProbeError {
    /// A plan that cannot work with this configuration; the message says why.
    #[error("{0}")]
    BadInput(String),
    /// The device failed or could not be opened.
    #[error(transparent)]
    Device(#[from] DeviceError),
    /// The capture file could not be written.
    #[error("writing the capture {path}: {source}")]
    Capture {
        /// The capture file.
        path: String,
        /// What the write said.
        source: std::io::Error,
    },
}

/// The probe's findings.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ProbeReport {
    /// The device's serial number, if it gave one.
    pub serial: Option<String>,
    /// The measured packet rate, if enough packets came to measure it.
    pub rate: Option<RateMeasurement>,
    /// Packets written to the capture.
    pub captured: u64,
    /// Capture checklist: (what, seen).
    pub checks: Vec<(String, bool)>,
    /// Encoder signs the operator's motions say (None: that joint was not moved).
    pub encoder_sign_seen: [Option<i8>; 3],
    /// The DAC signs found (0: not found), when the output steps ran to the end.
    pub dac_sign: Option<[i8; 3]>,
    /// Why the output steps stopped early, if they did.
    pub aborted: Option<String>,
    /// Whether every packet after the abort (or the end) carried zero torque, amplifiers off.
    pub ended_safe: bool,
}

/// Capture plus the state shared by the steps.
struct Session<'a, B: FireWireBus, W: Write> {
    omni: FireWireOmni<B>,
    stop: &'a AtomicBool,
    capture: &'a mut CaptureWriter<W>,
    capture_path: &'a str,
    op: &'a mut dyn Operator,
    opts: ProbeOptions,
    unwrap: EncoderUnwrap,
    /// Continuous OpenHaptics-signed counts of the last sample.
    counts: [i64; 3],
    switches: Option<u8>,
    packets: u64,
    /// What the received packets did since the last report.
    window: Window,
}

/// Received packets between two live reports.
#[derive(Default)]
struct Window {
    last: Option<(u32, u16, u8)>,
    pairs: u64,
    cycles: u64,
    counter_other: u64,
    byte18_other: u64,
}

impl Window {
    fn add(&mut self, counter: u32, timestamp: u16, byte18: u8) {
        if let Some((c, t, b)) = self.last {
            self.pairs += 1;
            self.cycles += u64::from(super::rate::cycles_between(t, timestamp).unwrap_or(0));
            if counter.wrapping_sub(c) != 1 {
                self.counter_other += 1;
            }
            if byte18.wrapping_sub(b) != 1 {
                self.byte18_other += 1;
            }
        }
        self.last = Some((counter, timestamp, byte18));
    }

    /// One line, and a fresh window (keeping the last packet to measure from).
    fn report(&mut self) -> String {
        let period = if self.pairs > 0 {
            format!(
                "period {:.3} ms",
                self.cycles as f64 / self.pairs as f64 / 8.0
            )
        } else {
            "no period".to_string()
        };
        let line = format!(
            "{period}; counter (bytes 32..35) +1 on {} of {} steps, byte 18 +1 on {}",
            self.pairs - self.counter_other,
            self.pairs,
            self.pairs - self.byte18_other
        );
        *self = Window {
            last: self.last,
            ..Window::default()
        };
        line
    }
}

const JOINT_PLUS: [&str; 3] = [
    "turn the base to your LEFT (seen from above: counter-clockwise)",
    "RAISE the upper arm",
    "swing the lower arm so the stylus end moves TOWARD you",
];

impl<B: FireWireBus, W: Write> Session<'_, B, W> {
    fn flush(&mut self) -> Result<(), ProbeError> {
        for t in self.omni.take_tapped() {
            if let (Some(info), true) = (t.received, t.bytes.len() >= crate::device::STATE_LEN) {
                self.window.add(
                    crate::device::stream::packet_counter(&t.bytes),
                    info.timestamp,
                    t.bytes[18],
                );
            }
            self.capture
                .packet(&t)
                .map_err(|source| ProbeError::Capture {
                    path: self.capture_path.to_string(),
                    source,
                })?;
        }
        Ok(())
    }

    fn note(&mut self, text: &str) -> Result<(), ProbeError> {
        self.flush()?;
        self.capture
            .comment(text)
            .map_err(|source| ProbeError::Capture {
                path: self.capture_path.to_string(),
                source,
            })
    }

    /// Tell the operator and note it in the capture.
    fn say(&mut self, text: &str) -> Result<(), ProbeError> {
        self.op.say(text);
        self.note(text)
    }

    /// One exchange with `cmd` (no DAC signs); `Ok(None)` for a missed packet.
    fn step(&mut self, cmd: MotorCommand) -> Result<Option<u8>, ProbeError> {
        let r = self.omni.exchange_raw(cmd);
        self.flush()?;
        match r {
            Ok(sample) => {
                self.packets += 1;
                let Ok(p) = decode_state(sample.packet()) else {
                    return Ok(None);
                };
                self.counts = self.unwrap.update(p.encoder);
                let sw = sample.packet()[crate::device::codec::STATE_LAYOUT.status];
                self.switches = Some(sw);
                Ok(Some(sw))
            }
            Err(DeviceError::Missed(_)) | Err(DeviceError::Malformed(_)) => Ok(None),
            Err(e) => Err(e.into()),
        }
    }

    fn safe(&mut self) -> Result<Option<u8>, ProbeError> {
        self.step(MotorCommand::safe(0))
    }

    fn per_second(&self) -> usize {
        self.opts.rate_hz.round().max(1.0) as usize
    }
}

fn bits(sw: u8) -> (bool, bool, bool) {
    // Active-low: docs/FIREWIRE.md §4.
    (sw & 1 == 0, sw & 2 == 0, sw & 4 == 0)
}

/// The whole probe on an identified-or-not Omni. The device is stopped (zero torque,
/// amplifiers off, stream bit cleared) on every way out.
/// `stop` (Ctrl-C) ends the capture, or stops an output step, at the next packet.
pub fn probe<B: FireWireBus, W: Write>(
    omni: FireWireOmni<B>,
    opts: ProbeOptions,
    op: &mut dyn Operator,
    capture: &mut CaptureWriter<W>,
    capture_path: &str,
    stop: &AtomicBool,
) -> Result<ProbeReport, ProbeError> {
    let mut s = Session {
        omni,
        stop,
        capture,
        capture_path,
        op,
        opts,
        unwrap: EncoderUnwrap::new(),
        counts: [0; 3],
        switches: None,
        packets: 0,
        window: Window::default(),
    };
    let mut report = ProbeReport::default();
    let result = run(&mut s, &mut report);
    // Every way out: zero torque, amplifiers off, the stop sequence.
    let closed = crate::device::Device::close(&mut s.omni);
    s.flush()?;
    let _ = s.capture.flush();
    report.captured = s.capture.packets();
    result?;
    closed?;
    Ok(report)
}

fn run<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    report: &mut ProbeReport,
) -> Result<(), ProbeError> {
    // 1. Identity and registers, reads only.
    let serial = s.omni.identify()?;
    report.serial = Some(serial.clone());
    let quadlet = s.omni.serial_quadlet().unwrap_or(0);
    s.say(&format!(
        "serial {serial} (label form; quadlet {quadlet:#010x})"
    ))?;
    let regs = s.omni.read_registers();
    let mut dump = String::from("registers (read only):");
    for r in &regs {
        let v = match &r.value {
            Ok(v) if r.width == 4 => format!("{v:#010x}"),
            Ok(v) => format!("{v:#04x}"),
            Err(e) => format!("({e})"),
        };
        dump.push_str(&format!("\n  {:#010x} = {v}  {}", r.offset, r.name));
    }
    s.say(&dump)?;

    // 2. Stream with the amplifiers off: rate, then the guided capture.
    s.omni.set_tap(true);
    s.omni.start()?;
    if s.omni.stale_stream_cleared() {
        s.say("the stream bit (0x1087 bit 3) was set by an earlier run; cleared before starting")?;
    }
    let m = s.omni.measure_rate(super::rate::MEASURE_PACKETS)?;
    report.rate = Some(m);
    let verdict = m
        .mismatch(s.opts.rate_hz)
        .unwrap_or_else(|| format!("matches device.rate_hz = {}", s.opts.rate_hz));
    s.say(&format!(
        "packet period {:.3} ms ({:.1} Hz) from the bus timestamps of {} packets; counter +{} \
         per packet; {verdict}",
        m.period_s * 1e3,
        m.rate_hz(),
        m.packets,
        m.counter_step
    ))?;
    capture_phase(s, report)?;

    // 3. Outputs, only when asked for and confirmed step by step.
    if s.opts.outputs && !s.stop.load(Ordering::Relaxed) {
        match outputs(s) {
            Ok(signs) => {
                report.dac_sign = Some(signs);
                let line = format!(
                    "[firewire]\ndac_sign = [{}, {}, {}]",
                    signs[0], signs[1], signs[2]
                );
                if signs.contains(&0) {
                    s.say(&format!(
                        "signs found (0 = not found; run again with more --counts):\n{line}"
                    ))?;
                } else {
                    s.say(&format!(
                        "all three signs found. Put these lines in your omnid configuration:\n{line}"
                    ))?;
                }
            }
            Err(Stop::Abort(why)) => {
                s.say(&format!("stopped: {why}. Zero torque, amplifiers off."))?;
                report.aborted = Some(why);
            }
            Err(Stop::Error(e)) => return Err(e),
        }
    }
    // End on safe packets, and say so.
    for _ in 0..(s.per_second() / 10).max(3) {
        s.safe()?;
    }
    report.ended_safe = true;
    Ok(())
}

/// A step of the capture: what the operator is asked to do.
#[derive(Clone, Copy, PartialEq)]
enum Want {
    Docked,
    Undocked,
    Button(usize),
    Joint(usize),
}

/// The capture's steps, in the order they are asked.
fn capture_steps() -> Vec<(Want, String)> {
    let mut todo: Vec<(Want, String)> = vec![
        (Want::Docked, "put the stylus in the inkwell".into()),
        (Want::Undocked, "take the stylus out of the inkwell".into()),
        (Want::Button(0), "press and release stylus button 1".into()),
        (Want::Button(1), "press and release stylus button 2".into()),
    ];
    for j in 0..3 {
        todo.push((
            Want::Joint(j),
            format!("joint {}: {}", j + 1, JOINT_PLUS[j]),
        ));
    }
    todo
}

/// The capture with the amplifiers off, guided: the operator's script (prompt, wait, record,
/// check), each step asked in turn until every one was seen or the packets are all in.
fn capture_phase<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    report: &mut ProbeReport,
) -> Result<(), ProbeError> {
    let mut todo = capture_steps();
    let total = todo.len();
    s.say(&format!(
        "capturing {} packets with the amplifiers off. Do what it asks, one at a time \
         (no keys needed):",
        s.opts.capture_packets
    ))?;
    s.say(&format!("  now: {}", todo[0].1))?;
    let mut done = 0usize;
    let mut last_sw: Option<u8> = None;
    let mut joint_from: Option<[i64; 3]> = None;
    let per_second = s.per_second();
    let (mut since, mut missed) = (0usize, 0usize);
    for k in 0..s.opts.capture_packets {
        if s.stop.load(Ordering::Relaxed) {
            s.say("capture stopped by the operator")?;
            break;
        }
        let Some(sw) = s.safe()? else {
            missed += 1;
            continue;
        };
        since += 1;
        if last_sw != Some(sw) {
            if let Some(prev) = last_sw {
                s.say(&switch_change(prev, sw))?;
            }
            last_sw = Some(sw);
        }
        // The current instruction.
        if let Some((want, text)) = todo.first().cloned() {
            if step_seen(s, report, want, sw, &mut joint_from)? {
                done += 1;
                todo.remove(0);
                report.checks.push((text, true));
                match todo.first() {
                    Some((_, next)) => {
                        let next = next.clone();
                        s.say(&format!("  done. now: {next}"))?;
                    }
                    None => s.say("  done: every step seen.")?,
                }
            }
        }
        if since >= per_second {
            say_second(s, k, missed, last_sw)?;
            since = 0;
        }
        if todo.is_empty() && k + 1 >= per_second {
            break;
        }
    }
    for (_, text) in todo {
        report.checks.push((text, false));
    }
    s.say(&format!(
        "capture: {done} of {total} steps seen; {} packets",
        s.packets
    ))?;
    Ok(())
}

/// What changed from switch byte `prev` to `sw`, as the operator would say it.
fn switch_change(prev: u8, sw: u8) -> String {
    let (b1, b2, docked) = bits(sw);
    let (p1, p2, pd) = bits(prev);
    let mut what = Vec::new();
    if docked != pd {
        what.push(if docked {
            "stylus docked"
        } else {
            "stylus out of the inkwell"
        });
    }
    if b1 != p1 {
        what.push(if b1 {
            "button 1 pressed"
        } else {
            "button 1 released"
        });
    }
    if b2 != p2 {
        what.push(if b2 {
            "button 2 pressed"
        } else {
            "button 2 released"
        });
    }
    if sw & 0xF8 != prev & 0xF8 {
        what.push("bits 3..7 of byte 19 changed");
    }
    format!(
        "switch byte 19: {prev:#04x} -> {sw:#04x}: {}",
        what.join(", ")
    )
}

/// Whether this packet (switch byte `sw`) shows the step `want` done.
fn step_seen<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    report: &mut ProbeReport,
    want: Want,
    sw: u8,
    joint_from: &mut Option<[i64; 3]>,
) -> Result<bool, ProbeError> {
    let (b1, b2, docked) = bits(sw);
    Ok(match want {
        Want::Docked => docked,
        Want::Undocked => !docked,
        Want::Button(0) => b1,
        Want::Button(_) => b2,
        Want::Joint(j) => joint_moved(s, report, j, joint_from)?,
    })
}

/// A joint's step: seen once joint `j` moved [`MOVE_COUNTS`] from where the step began; its
/// direction is checked against `firewire.encoder_sign` and said.
fn joint_moved<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    report: &mut ProbeReport,
    j: usize,
    joint_from: &mut Option<[i64; 3]>,
) -> Result<bool, ProbeError> {
    let from = *joint_from.get_or_insert(s.counts);
    let d = s.counts[j] - from[j];
    if d.abs() < MOVE_COUNTS {
        return Ok(false);
    }
    let sign: i8 = if d > 0 { 1 } else { -1 };
    report.encoder_sign_seen[j] = Some(sign);
    let msg = if sign > 0 {
        format!(
            "joint {} counts up as it should (encoder_sign[{j}] = {} is right)",
            j + 1,
            s.opts.encoder_sign[j]
        )
    } else {
        format!(
            "joint {} counts DOWN: firewire.encoder_sign[{j}] should be {}, \
             not {} (docs/FIREWIRE.md §6); please report this",
            j + 1,
            -s.opts.encoder_sign[j],
            s.opts.encoder_sign[j]
        )
    };
    s.say(&msg)?;
    *joint_from = None;
    Ok(true)
}

/// The capture's progress, once a second: packets, misses, the rate window, the switches.
fn say_second<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    k: usize,
    missed: usize,
    last_sw: Option<u8>,
) -> Result<(), ProbeError> {
    let window = s.window.report();
    s.say(&format!(
        "{:.0} s: {} packets, {} missed, {} lost by the counter; {window}; switches \
         {:#04x}",
        (k + 1) as f64 / s.opts.rate_hz,
        s.packets,
        missed,
        s.omni.stats().lost,
        last_sw.unwrap_or(0)
    ))
}

/// Why the output steps stopped.
enum Stop {
    Abort(String),
    Error(ProbeError),
}

impl From<ProbeError> for Stop {
    fn from(e: ProbeError) -> Self {
        Stop::Error(e)
    }
}

/// Packets of `cmd`, watching for a stylus button (abort) and for motion beyond `limit`
/// counts from where it started (abort). Returns the motion of each joint at the end.
fn hold<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    cmd: MotorCommand,
    packets: usize,
    limit: i64,
) -> Result<[i64; 3], Stop> {
    let from = s.counts;
    for _ in 0..packets {
        if s.stop.load(Ordering::Relaxed) {
            return Err(Stop::Abort("stopped by the operator (Ctrl-C)".into()));
        }
        let sw = match s.step(cmd) {
            Ok(sw) => sw,
            Err(ProbeError::Device(e)) => {
                return Err(Stop::Abort(format!("the device failed: {e}")))
            }
            Err(e) => return Err(Stop::Error(e)),
        };
        if let Some(sw) = sw {
            let (b1, b2, _) = bits(sw);
            if b1 || b2 {
                return Err(Stop::Abort("a stylus button was pressed".into()));
            }
        }
        for j in 0..3 {
            let d = s.counts[j] - from[j];
            if d.abs() > limit {
                return Err(Stop::Abort(format!(
                    "joint {} moved {d} counts ({:.2} rad), more than the {limit} this step allows",
                    j + 1,
                    d as f64 * std::f64::consts::TAU / 15000.0
                )));
            }
        }
    }
    let mut moved = [0; 3];
    for j in 0..3 {
        moved[j] = s.counts[j] - from[j];
    }
    Ok(moved)
}

/// The output steps; on any stop the caller sends safe packets and closes. Each step is
/// confirmed by the operator before any torque, in the order they are asked.
fn outputs<B: FireWireBus, W: Write>(s: &mut Session<'_, B, W>) -> Result<[i8; 3], Stop> {
    let per_second = s.per_second();
    let safe = MotorCommand::safe(0);
    s.say(
        "output steps: each asks first. Press a stylus button at any time to stop (zero \
         torque, amplifiers off).",
    )?;
    lamp_step(s, safe)?;
    let amps = amplifier_step(s, safe)?;
    // Step 3: one motor at a time, + then - counts.
    let mut signs = [0i8; 3];
    for (j, sign) in signs.iter_mut().enumerate() {
        *sign = motor_step(s, j, amps)?;
    }
    hold(s, safe, per_second / 10, SURPRISE_COUNTS)?;
    Ok(signs)
}

/// Step 1: the lamp, motors off; the operator says whether it changed.
fn lamp_step<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    safe: MotorCommand,
) -> Result<(), Stop> {
    let per_second = s.per_second();
    if !s.op.confirm(
        "step 1 of 3: set the inkwell lamp bits for 2 s with the motors OFF (no torque). Go on?",
    ) {
        return Err(Stop::Abort("step 1 (lamp) not confirmed".into()));
    }
    s.note("step 1: lamp bits 0b11 for 1 s, then 0b01 for 1 s, amplifiers off")?;
    hold(
        s,
        MotorCommand { lamp: 0b11, ..safe },
        per_second,
        SURPRISE_COUNTS,
    )?;
    hold(
        s,
        MotorCommand { lamp: 0b01, ..safe },
        per_second,
        SURPRISE_COUNTS,
    )?;
    hold(s, safe, per_second / 10, SURPRISE_COUNTS)?;
    if s.op
        .yes_no("did the inkwell lamp change (on, then flashing)?")
        != Some(true)
    {
        return Err(Stop::Abort(
            "the lamp did not change: the device may not act on omnid's packets; send the \
             capture back (docs/BRINGUP.md)"
                .into(),
        ));
    }
    Ok(())
}

/// Step 2: amplifiers on at zero torque; the operator says nothing unexpected happened.
/// Returns that command (the motor steps add their DAC words to it).
fn amplifier_step<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    safe: MotorCommand,
) -> Result<MotorCommand, Stop> {
    let per_second = s.per_second();
    if !s.op.confirm(
        "step 2 of 3: amplifiers ON at zero torque for 1 s. Hold the stylus lightly. Go on?",
    ) {
        return Err(Stop::Abort(
            "step 2 (amplifiers at zero torque) not confirmed".into(),
        ));
    }
    s.note("step 2: amplifiers on, DAC words 0x07ff")?;
    let amps = MotorCommand {
        amps_on: true,
        ..safe
    };
    hold(s, amps, per_second, MOVE_COUNTS)?;
    hold(s, safe, per_second / 10, SURPRISE_COUNTS)?;
    if s.op
        .yes_no("did anything move, click or hum more than you expected?")
        != Some(false)
    {
        return Err(Stop::Abort(
            "the operator saw something unexpected at zero torque (or did not answer)".into(),
        ));
    }
    Ok(amps)
}

/// Step 3.`j+1`: motor `j` pulsed + then -, its sign read from the encoder and checked
/// against what the operator saw. Returns the sign (0: no motion at this size).
fn motor_step<B: FireWireBus, W: Write>(
    s: &mut Session<'_, B, W>,
    j: usize,
    amps: MotorCommand,
) -> Result<i8, Stop> {
    let per_second = s.per_second();
    let counts = s.opts.pulse_counts.clamp(1, MAX_PULSE_COUNTS);
    let safe = MotorCommand::safe(0);
    let pulse = per_second / 2;
    let mnm = f64::from(counts) * s.opts.nm_per_count[j] * 1e3;
    if !s.op.confirm(&format!(
        "step 3.{} of 3: motor {}: +{counts} DAC counts (about {mnm:.0} mN·m) for 0.5 s, \
         zero, then -{counts} for 0.5 s, zero. Hold the stylus lightly so joint {} can \
         move a little. Go on?",
        j + 1,
        j + 1,
        j + 1
    )) {
        return Err(Stop::Abort(format!("step 3.{} not confirmed", j + 1)));
    }
    // One pulse of motor j at DAC `value`, then zero for `rest` ticks: what the pulse moved.
    let mut pulse_at = |value, rest| {
        let mut dac = [DAC_ZERO; 3];
        dac[j] = value;
        s.note(&format!(
            "step 3.{}: motor {} at {value:#06x}",
            j + 1,
            j + 1
        ))?;
        let moved = hold(s, MotorCommand { dac, ..amps }, pulse, SURPRISE_COUNTS)?;
        hold(s, amps, rest, SURPRISE_COUNTS)?;
        Ok::<_, Stop>(moved)
    };
    let plus = pulse_at(DAC_ZERO + counts, pulse)?;
    let minus = pulse_at(DAC_ZERO - counts, pulse / 2)?;
    // Amplifiers off while the operator answers.
    hold(s, safe, per_second / 10, SURPRISE_COUNTS)?;
    let (p, m) = (plus[j], minus[j]);
    let seen = match (p.signum(), m.signum()) {
        _ if p.abs() < PULSE_MOTION_COUNTS && m.abs() < PULSE_MOTION_COUNTS => 0,
        (a, b) if a != 0 && a == -b => a as i8,
        _ => {
            return Err(Stop::Abort(format!(
                "motor {}: +{counts} moved joint {} by {p} counts and -{counts} by {m}: not \
                 opposite directions",
                j + 1,
                j + 1
            )))
        }
    };
    let said = operator_saw(s, j)?;
    if said != seen {
        return Err(Stop::Abort(format!(
            "joint {}: you saw {} but the encoder counted {p} counts (OpenHaptics-signed): \
             check firewire.encoder_sign first (the capture step checks it)",
            j + 1,
            match said {
                1 => "+",
                -1 => "-",
                _ => "no motion",
            }
        )));
    }
    s.say(&format!(
        "motor {}: {}",
        j + 1,
        match seen {
            0 => "no motion at this size: its sign stays unknown (0)".to_string(),
            v => format!(
                "a positive DAC word turns joint {} {}: dac_sign[{j}] = {v}",
                j + 1,
                if v > 0 { "positive" } else { "negative" }
            ),
        }
    ))?;
    Ok(seen)
}

/// Which way the operator saw joint `j` go on the + pulse: 1, -1 or 0 (no motion).
fn operator_saw<B: FireWireBus, W: Write>(s: &mut Session<'_, B, W>, j: usize) -> Result<i8, Stop> {
    let answer = s.op.ask(
        &format!("which way did joint {} go on the first (+) pulse?", j + 1),
        &[
            ('+', JOINT_PLUS[j]),
            ('-', "the other way"),
            ('0', "it did not move"),
        ],
    );
    match answer {
        Some('+') => Ok(1),
        Some('-') => Ok(-1),
        Some('0') => Ok(0),
        _ => Err(Stop::Abort(format!("no answer at step 3.{}", j + 1))),
    }
}

/// What `omnid probe` was asked to do.
#[derive(Debug, Clone, PartialEq)]
pub struct ProbePlan {
    /// The capture file to write (replayable after `omnid convert --from capture`).
    pub capture: std::path::PathBuf,
    /// How long to capture with the amplifiers off, s (ends early once every step was seen).
    pub seconds: f64,
    /// Also run the guided lamp, amplifier and motor-sign steps (`--outputs`).
    pub outputs: bool,
    /// DAC counts of the sign pulses (1..=200).
    pub counts: u16,
    /// The arm to lock once the Omni is found (`None`: the caller holds it already), so a
    /// daemon or a run on it refuses to start, and this probe refuses while one of them has it.
    pub lock: Option<String>,
}

/// The sections of the configuration a probe reads (a `&Config` gives them).
#[derive(Debug, Clone, Copy)]
pub struct ProbeSetup<'a> {
    /// Encoder resolution and servo rate.
    pub device: &'a crate::device::DeviceConfig,
    /// The FireWire device's ids, timing and DAC signs.
    pub firewire: &'a super::FirewireConfig,
}

impl ProbePlan {
    /// What is wrong with the plan for this configuration, if anything (before any device or
    /// lock is touched).
    pub fn check<'a>(&self, cfg: impl Into<ProbeSetup<'a>>) -> Result<(), ProbeError> {
        self.options(cfg).map(|_| ())
    }

    /// The probe's options for this configuration, or what is wrong with the plan.
    pub(crate) fn options<'a>(
        &self,
        cfg: impl Into<ProbeSetup<'a>>,
    ) -> Result<ProbeOptions, ProbeError> {
        let cfg = cfg.into();
        if !(self.seconds.is_finite() && self.seconds > 0.0 && self.seconds <= 3600.0) {
            return Err(ProbeError::BadInput(format!(
                "--seconds {} is out of range: allowed 0 < seconds <= 3600",
                self.seconds
            )));
        }
        if !(1..=MAX_PULSE_COUNTS).contains(&self.counts) {
            return Err(ProbeError::BadInput(format!(
                "--counts {} is out of range: allowed 1 ..= {MAX_PULSE_COUNTS} DAC counts (a \
                 tenth of the Omni's peak torque at most)",
                self.counts
            )));
        }
        Ok(ProbeOptions {
            capture_packets: (self.seconds * cfg.device.rate_hz).round().max(1.0) as usize,
            rate_hz: cfg.device.rate_hz,
            outputs: self.outputs,
            pulse_counts: self.counts,
            nm_per_count: cfg.device.nm_per_count,
            encoder_sign: cfg.firewire.encoder_sign,
        })
    }
}

/// The capture's header lines for this configuration (the converter reads `kind`,
/// `encoder_sign`, `counts_per_rev` and `rate_hz`).
pub(crate) fn capture_header<'a>(cfg: impl Into<ProbeSetup<'a>>, kind: &str) -> String {
    let cfg = cfg.into();
    let s = cfg.firewire.encoder_sign;
    format!(
        "kind {kind}\nomnid {}\nrate_hz {}\nencoder_sign {} {} {}\ncounts_per_rev {}\n\
         command_byte7 {}",
        env!("CARGO_PKG_VERSION"),
        cfg.device.rate_hz,
        s[0],
        s[1],
        s[2],
        cfg.device.counts_per_rev,
        cfg.firewire.command_byte7
    )
}

/// `omnid probe` on the configured FireWire Omni: find it (reads only), open the capture,
/// then [`probe`].
pub fn probe_firewire<'a>(
    cfg: impl Into<ProbeSetup<'a>>,
    plan: &ProbePlan,
    op: &mut dyn Operator,
    stop: &AtomicBool,
) -> Result<ProbeReport, ProbeError> {
    let cfg = cfg.into();
    let opts = plan.options(cfg)?;
    let omni = super::find_firewire(cfg.firewire, cfg.device.rate_hz)?;
    let _lock = plan
        .lock
        .as_deref()
        .map(crate::arm::ArmLock::acquire)
        .transpose()
        .map_err(ProbeError::BadInput)?;
    let path = plan.capture.display().to_string();
    let cap = |source| ProbeError::Capture {
        path: path.clone(),
        source,
    };
    if let Some(dir) = plan.capture.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(cap)?;
    }
    let file = std::fs::File::create(&plan.capture).map_err(cap)?;
    let mut w = CaptureWriter::new(std::io::BufWriter::new(file)).map_err(cap)?;
    let node = omni.name().to_string();
    let rom = super::cdev::read_rom(std::path::Path::new(&node))
        .map(|q| {
            q.iter()
                .map(|v| format!("{v:08x}"))
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_else(|e| format!("(unreadable: {e})"));
    let head = format!(
        "{}\nnode {node}\nconfig_rom {rom}",
        capture_header(cfg, "firewire")
    );
    w.comment(&head).map_err(cap)?;
    op.say(&format!(
        "FireWire Omni at {node}; config ROM {rom}\ncapture: {path}"
    ));
    probe(omni, opts, op, &mut w, &path, stop)
}

/// The operator at a terminal: prompts on stderr, answers from stdin (one line each).
/// Waiting for an answer gives up when `stop` is set (Ctrl-C).
pub struct TerminalOperator<'a> {
    /// The operator's stop flag (set by Ctrl-C).
    pub stop: &'a AtomicBool,
}

impl Operator for TerminalOperator<'_> {
    fn say(&mut self, text: &str) {
        for line in text.lines() {
            crate::errln!("probe: {line}");
        }
    }

    fn ask(&mut self, question: &str, choices: &[(char, &str)]) -> Option<char> {
        loop {
            crate::errln!("probe: {question}");
            for (k, meaning) in choices {
                crate::errln!("         [{k}] {meaning}");
            }
            crate::errln!("probe: answer and press Enter:");
            let line = read_line_unless(self.stop)?;
            let answer = line.trim().chars().next().map(|c| c.to_ascii_lowercase());
            match answer {
                Some(c) if choices.iter().any(|(k, _)| *k == c) => return Some(c),
                _ => crate::errln!("probe: please answer with one of the keys shown"),
            }
        }
    }
}

/// One line from stdin; `None` at end of input or when `stop` is set while waiting.
fn read_line_unless(stop: &AtomicBool) -> Option<String> {
    use std::io::BufRead;
    loop {
        if stop.load(Ordering::Relaxed) {
            return None;
        }
        let mut p = libc::pollfd {
            fd: 0,
            events: libc::POLLIN,
            revents: 0,
        };
        // SAFETY: one valid pollfd for the process's stdin.
        let r = unsafe { libc::poll(&mut p, 1, 200) };
        if r < 0 {
            let e = std::io::Error::last_os_error();
            if e.kind() == std::io::ErrorKind::Interrupted {
                continue;
            }
            return None;
        }
        if r == 0 {
            continue;
        }
        let mut line = String::new();
        return match std::io::stdin().lock().read_line(&mut line) {
            Ok(0) | Err(_) => None,
            Ok(_) => Some(line),
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::firewire::capture::CaptureReader;
    use crate::device::firewire::fake::{ArmState, FakeBus, Op, WireCommand};
    use crate::device::firewire::FireWireOptions;
    use std::collections::VecDeque;
    use std::time::Duration;

    /// Answers from a script; `None` in the script (or its end) is end of input. `on_ask`
    /// runs before the answer to the question with that index (0-based).
    struct Script {
        answers: VecDeque<Option<char>>,
        said: Vec<String>,
        asked: Vec<String>,
        on_ask: Option<(usize, Box<dyn FnMut()>)>,
    }

    impl Script {
        fn new(answers: &str) -> Self {
            Script {
                answers: answers.chars().map(Some).collect(),
                said: Vec::new(),
                asked: Vec::new(),
                on_ask: None,
            }
        }
        fn text(&self) -> String {
            self.said.join("\n")
        }
    }

    impl Operator for Script {
        fn say(&mut self, text: &str) {
            self.said.push(text.to_string());
        }
        fn ask(&mut self, question: &str, _: &[(char, &str)]) -> Option<char> {
            if let Some((k, f)) = self.on_ask.as_mut() {
                if *k == self.asked.len() {
                    f();
                }
            }
            self.asked.push(question.to_string());
            self.answers.pop_front().flatten()
        }
    }

    fn opts(capture_packets: usize, outputs: bool, counts: u16) -> ProbeOptions {
        ProbeOptions {
            capture_packets,
            rate_hz: 1000.0,
            outputs,
            pulse_counts: counts,
            nm_per_count: [2.2e-4; 3],
            encoder_sign: crate::device::firewire::OPENHAPTICS_ENCODER_SIGN,
        }
    }

    /// The fake arm's physics for the output steps: motor j moves encoder j by
    /// (word − 0x7FF) × gain / 8 counts a packet. With the encoder signs [-1, -1, 1] these
    /// gains make the DAC signs [-1, 1, -1].
    const GAIN: [i32; 3] = [1, -1, -1];
    const SIGNS: [i8; 3] = [-1, 1, -1];

    fn bus() -> FakeBus {
        FakeBus::with(|n| n.motor_gain = GAIN)
    }

    /// Run the probe; the capture text comes back beside the result.
    fn run_probe(
        bus: &FakeBus,
        o: ProbeOptions,
        op: &mut Script,
    ) -> (Result<ProbeReport, ProbeError>, String) {
        let omni = FireWireOmni::with_options(
            bus.clone(),
            "fake-fw1".into(),
            FireWireOptions {
                busy_retry: Duration::from_millis(1),
                ..FireWireOptions::new(Duration::from_millis(10), 1000.0)
            },
        );
        let mut w = CaptureWriter::new(Vec::new()).unwrap();
        w.comment(&capture_header(
            &crate::config::Config::default(),
            "firewire",
        ))
        .unwrap();
        let stop = AtomicBool::new(false);
        let r = probe(omni, o, op, &mut w, "capture.txt", &stop);
        (r, String::from_utf8(w.into_inner()).unwrap())
    }

    /// Every way out: the last packets zero torque with the amplifiers off, the stream bit
    /// cleared, the stream stopped, the channels freed. Returns the commands sent.
    fn assert_ends_safe(bus: &FakeBus) -> Vec<WireCommand> {
        let n = bus.node();
        let sent = n.sent_wire();
        let tail = sent.iter().rev().take_while(|c| c.is_safe()).count();
        assert!(tail >= 3, "only {tail} safe packets at the end");
        assert_eq!(sent.last().map(|c| c.lamp), Some(0));
        assert!(!n.streaming());
        let stop = n
            .ops
            .iter()
            .rposition(|o| *o == Op::WriteByte(0x1087, 0x00));
        let last_send = n.ops.iter().rposition(|o| matches!(o, Op::Send(_)));
        assert!(
            stop > last_send,
            "the stream bit was not cleared after the last packet"
        );
        assert!(n.ops.iter().any(|o| matches!(o, Op::Free(_))));
        sent
    }

    /// A schedule of what the operator does during the capture, by packets delivered.
    fn guided_arm() -> VecDeque<(usize, ArmState)> {
        let mut arm = ArmState::default();
        let mut v = VecDeque::new();
        let mut at = |k: usize, f: &dyn Fn(&mut ArmState)| {
            f(&mut arm);
            v.push_back((k, arm));
        };
        at(100, &|a| a.docked = true);
        at(150, &|a| a.docked = false);
        at(200, &|a| a.buttons[0] = true);
        at(220, &|a| a.buttons[0] = false);
        at(240, &|a| a.buttons[1] = true);
        at(260, &|a| a.buttons[1] = false);
        // OpenHaptics + on each joint, 300 counts at a hand's pace (2 counts a packet):
        // device counts down on x and y, up on z (docs/FIREWIRE.md §6).
        for (j, start, step) in [(0, 300, -2i16), (1, 500, -2), (2, 700, 2)] {
            for k in 0..150 {
                at(start + k, &|a| {
                    a.encoder[j] = a.encoder[j].wrapping_add(step as u16)
                });
            }
        }
        v
    }

    #[test]
    fn the_whole_kit_end_to_end_capture_outputs_convert_replay() {
        let bus = bus();
        bus.node().arm_at = guided_arm();
        // Lamp yes, lamp changed yes, amplifiers yes, nothing unexpected, then per motor:
        // go on, and the direction the operator saw (the fake's truth, SIGNS).
        let mut op = Script::new("yyynY-Y+Y-".to_lowercase().as_str());
        let (r, text) = run_probe(&bus, opts(3000, true, 8), &mut op);
        let report = r.unwrap_or_else(|e| panic!("{e}\n{}", op.text()));
        assert_eq!(report.aborted, None, "{}", op.text());
        assert_eq!(report.dac_sign, Some(SIGNS), "{}", op.text());
        assert_eq!(report.encoder_sign_seen, [Some(1); 3]);
        assert_eq!(report.checks.len(), 7);
        assert!(
            report.checks.iter().all(|(_, seen)| *seen),
            "{:?}",
            report.checks
        );
        assert!(report.ended_safe);
        let said = op.text();
        for want in [
            "serial 10203400567",
            "0x1006000c = 0x000b9900",
            "0x00001002 = 0x00",
            "packet period 1.000 ms (1000.0 Hz)",
            // The first second also holds the 64 packets of the rate measurement.
            "period 1.000 ms; counter (bytes 32..35) +1 on 1063 of 1063 steps, byte 18 +1 on 1063",
            "counter +1 per packet",
            "stylus docked",
            "button 1 pressed",
            "button 2 released",
            "joint 3 counts up as it should",
            "every step seen",
            "dac_sign = [-1, 1, -1]",
        ] {
            assert!(said.contains(want), "missing {want:?} in:\n{said}");
        }
        // Ten questions, each before its step; the amplifiers were on only after step 2's yes.
        assert_eq!(op.asked.len(), 10);
        let sent = assert_ends_safe(&bus);
        assert!(sent.iter().any(|c| c.motors_on && c.force[1] == 0x07FF + 8));
        assert!(sent
            .iter()
            .all(|c| c.force.iter().all(|&f| f.abs_diff(0x07FF) <= 8)));

        // The capture: header, notes, both directions; converted it replays through the servo.
        assert!(text.starts_with("# omnid capture 1\n# kind firewire\n"));
        assert!(text.contains("# note switch byte 19: 0x97 -> 0x93: stylus docked"));
        let dir = tempfile::tempdir().unwrap();
        let cap = dir.path().join("capture.txt");
        std::fs::write(&cap, &text).unwrap();
        let mut reader = CaptureReader::new(text.as_bytes(), "capture.txt").unwrap();
        let (mut rx, mut tx) = (0, 0);
        while let Some(p) = reader.next_packet().unwrap() {
            match p.received {
                Some(Some(_)) => rx += 1,
                Some(None) => panic!("the fake bus gives receive timestamps"),
                None => tx += 1,
            }
        }
        assert!(rx > 1000 && tx > 1000, "{rx} received, {tx} sent");
        assert_eq!(report.captured, (rx + tx) as u64);
        let log = dir.path().join("capture-log.csv");
        let conv = crate::convert::convert(
            crate::convert::SourceFormat::Capture,
            &cap,
            &log,
            false,
            None,
        )
        .unwrap();
        assert_eq!(conv.rows, rx as u64);
        let out = dir.path().join("replayed.csv");
        let run = crate::cmd::run::RunOptions {
            device: crate::cmd::run::DeviceSpec::Replay(log.clone()),
            controller: crate::control::ControllerKind::Off,
            trajectory: crate::control::Trajectory::Hold,
            duration_s: f64::INFINITY,
            log: Some(out.clone()),
            fast: true,
            ..crate::cmd::run::RunOptions::default()
        };
        let outcome = crate::cmd::run::execute(
            &run,
            &crate::config::Config::default(),
            std::sync::Arc::new(AtomicBool::new(false)),
        )
        .unwrap();
        assert_eq!(outcome.end, crate::servo::EndReason::EndOfData);
        assert_eq!(outcome.summary.ticks, conv.rows);
        // The replay saw the operator's motions: joint 1 moved +300 counts in the capture.
        let converted = std::fs::read_to_string(&log).unwrap();
        let enc1: Vec<i64> = converted
            .lines()
            .skip(1)
            .map(|l| l.split(',').nth(7).unwrap().parse().unwrap())
            .collect();
        assert!(enc1.iter().any(|&c| c - enc1[0] >= 300), "{:?}", &enc1[..5]);
    }

    #[test]
    fn output_steps_refuse_to_go_on_without_confirmation() {
        for answers in ["n", "", "x"] {
            let bus = bus();
            let mut op = Script::new(answers);
            let (r, _) = run_probe(&bus, opts(50, true, 8), &mut op);
            let report = r.unwrap();
            let why = report.aborted.expect("went on without a yes");
            assert!(why.contains("step 1"), "{why}");
            assert_eq!(op.asked.len(), 1);
            let sent = assert_ends_safe(&bus);
            // Nothing but zero torque, amplifiers off, lamp off was ever sent.
            assert!(
                sent.iter().all(|c| c.is_safe() && c.lamp == 0),
                "{answers:?}"
            );
            assert!(report.dac_sign.is_none());
        }
    }

    #[test]
    fn a_lamp_that_did_not_change_stops_before_the_amplifiers() {
        let bus = bus();
        let mut op = Script::new("yn");
        let (r, _) = run_probe(&bus, opts(50, true, 8), &mut op);
        let why = r.unwrap().aborted.unwrap();
        assert!(why.contains("lamp did not change"), "{why}");
        let sent = assert_ends_safe(&bus);
        assert!(sent.iter().any(|c| c.lamp == 0b11));
        assert!(sent.iter().all(|c| !c.motors_on));
    }

    #[test]
    fn every_abort_in_the_sign_steps_ends_at_zero_torque_amplifiers_off() {
        // (answers, counts, what happens, the reason's words)
        type Setup = fn(&FakeBus, &mut Script);
        let none: Setup = |_, _| {};
        let press: Setup = |bus, op| {
            // The operator presses button 1 while reading step 3.2's question.
            let b = bus.clone();
            op.on_ask = Some((6, Box::new(move || b.node().arm.buttons[0] = true)));
        };
        let cases: [(&str, u16, Setup, &str); 6] = [
            ("yyyny-n", 8, none, "step 3.2 not confirmed"),
            ("yyyny-y", 8, press, "a stylus button was pressed"),
            ("yyyny+", 8, none, "you saw +"),
            ("yyyny", 8, none, "no answer at step 3.1"),
            ("yyyny", 40, none, "moved"),
            ("yyyy", 8, none, "something unexpected at zero torque"),
        ];
        for (answers, counts, setup, says) in cases {
            let bus = bus();
            let mut op = Script::new(answers);
            setup(&bus, &mut op);
            let (r, _) = run_probe(&bus, opts(50, true, counts), &mut op);
            let report = r.unwrap();
            let why = report.aborted.clone().unwrap_or_default();
            assert!(
                why.contains(says),
                "{answers}/{counts}: {why}\n{}",
                op.text()
            );
            assert!(report.dac_sign.is_none());
            assert!(report.ended_safe);
            assert_ends_safe(&bus);
            assert!(op.text().contains("Zero torque, amplifiers off"));
        }
    }

    #[test]
    fn a_device_at_another_rate_is_reported_and_the_capture_goes_on() {
        let bus = FakeBus::with(|n| {
            n.rate_hz = 500.0;
            n.regs.insert(crate::device::firewire::reg::CONTROL, 0x08);
        });
        let mut op = Script::new("");
        let (r, text) = run_probe(&bus, opts(100, false, 8), &mut op);
        let report = r.unwrap();
        let said = op.text();
        assert!(
            said.contains("500.0 Hz") && said.contains("device.rate_hz = 1000"),
            "{said}"
        );
        assert!(said.contains("stream bit (0x1087 bit 3) was set"), "{said}");
        assert!((report.rate.unwrap().rate_hz() - 500.0).abs() < 1.0);
        assert!(op.asked.is_empty(), "no output steps without --outputs");
        assert!(text.contains("rx,"));
        let sent = assert_ends_safe(&bus);
        assert!(sent.iter().all(|c| c.is_safe() && c.lamp == 0));
    }

    #[test]
    fn plans_are_checked() {
        let cfg = crate::config::Config::default();
        let plan = |seconds: f64, counts: u16| ProbePlan {
            capture: "c.txt".into(),
            seconds,
            outputs: true,
            counts,
            lock: None,
        };
        assert_eq!(plan(2.0, 40).options(&cfg).unwrap().capture_packets, 2000);
        for (p, says) in [
            (plan(0.0, 40), "--seconds 0"),
            (plan(f64::NAN, 40), "--seconds NaN"),
            (plan(2.0, 0), "--counts 0"),
            (plan(2.0, 201), "--counts 201"),
        ] {
            let e = p.options(&cfg).unwrap_err().to_string();
            assert!(e.contains(says), "{e}");
        }
    }
}

//! `omnid convert`: turn a recording into a replayable log (docs/DESIGN.md §2.2: `t, q1..3,
//! tau1..3` first).
//!
//! Sources:
//! - `ros-touch`: the ROS Geomagic/Phantom driver's joint states as in
//!   `data/touch-2016-joint-and-tip.csv`: `t, waist, shoulder, elbow` (any order) in the
//!   ROS convention (waist = −j1, shoulder = j2, elbow = j3 − j2), mapped to OpenHaptics joints
//!   with [`crate::omni::kinematics::from_ros`]. No torque was recorded, so `tau = 0`. Every
//!   other column (`x_mm, y_mm, z_mm`, the gimbal angles, …) is kept, unchanged, after them.
//! - `omnid`: an omnid log reduced to what replay reads: `t, q1..3, tau1..3`, then `enc1..3` and
//!   `mode` when present. Numbers are written as the log writer writes them (shortest
//!   round-trip form), so the kept columns are bit-for-bit the original's. Used for the compact
//!   recorded sessions in `mock/`.
//! - `capture`: an `omnid probe` capture (docs/BRINGUP.md): every received state packet
//!   becomes a row. `t` from the bus's receive timestamps (else the host's clock), `q` from the
//!   encoder counts turned by the capture's `encoder_sign` and unwrapped as the servo does,
//!   `tau = 0` (the motors' signs are unknown when a probe runs), `enc1..3`, then the packet's
//!   `counter`, switch byte `switches`, and the last command's `dac1..3` and `amps`.
//!
//! The input is read with the log reader's checks (strict, or `lenient`: skip damaged rows).
//! The output is checked before the input is read and written whole ([`crate::output`]): a
//! failed conversion never leaves a half-written log that would replay, nor a temporary file,
//! and only a regular file or a new path is written.

use crate::omni::kinematics::from_ros;
use crate::output::OutputError;
use crate::telemetry::reader::{ColumnReader, LogReader, ReadError, SkipReport, REQUIRED_COLUMNS};
use std::io::{self, Write};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// Formats `omnid convert --from` understands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SourceFormat {
    /// ROS driver joint states: t, waist, shoulder, elbow (ROS joint convention).
    RosTouch,
    /// An omnid log, reduced to the columns replay reads (t, q, tau, enc, mode).
    Omnid,
    /// An `omnid probe` capture (raw packets): one row per received state packet.
    Capture,
    /// An omnid log whole, CSV or MCAP, to the format `--out`'s extension names (`.mcap`:
    /// MCAP, else CSV); every column kept.
    Log,
}

/// The ROS driver's columns (the first is the time).
pub(crate) const ROS_TOUCH_COLUMNS: [&str; 4] = ["t", "waist", "shoulder", "elbow"];

/// Why a conversion failed.
#[derive(Debug, Error)]
pub enum ConvertError {
    /// The input could not be read, or a row of it is bad.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// Writing the output failed part-way (the partial file is removed).
    #[error("cannot write {path}: {source}")]
    Write {
        /// The output file.
        path: String,
        /// What the operating system said.
        source: io::Error,
    },
    /// An input column has the name of a column the output writes itself.
    #[error("{path}: line 1: column `{column}` would clash with the output column of that name")]
    ColumnClash {
        /// The input file.
        path: String,
        /// The clashing name.
        column: String,
    },
    /// Nothing left to write (every row skipped, or none at all).
    #[error("{path}: no data rows to convert{}", if skipped.count > 0 { format!(" ({skipped})") } else { String::new() })]
    NoRows {
        /// The input file.
        path: String,
        /// What lenient reading skipped.
        skipped: SkipReport,
    },
    /// `--out` names the input file itself.
    #[error("the output {0} is the input")]
    SameFile(String),
    /// The output file cannot be created there.
    #[error("--out: {0}")]
    Output(#[from] OutputError),
    /// A probe capture (`--from capture`) could not be read.
    #[error(transparent)]
    Capture(#[from] crate::device::firewire::capture::CaptureError),
}

impl ConvertError {
    /// The user's input is at fault (exit code 2), not a write that failed part-way.
    pub fn is_bad_input(&self) -> bool {
        match self {
            ConvertError::Write { .. } => false,
            ConvertError::Output(e) => e.is_bad_input(),
            _ => true,
        }
    }
}

impl ConvertError {
    /// The operator stopped it while the input was read.
    pub fn is_stopped(&self) -> bool {
        matches!(self, ConvertError::Read(ReadError::Stopped { .. }))
    }
}

/// What a conversion did.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvertReport {
    /// Data rows written.
    pub rows: u64,
    /// The output's header, in order.
    pub columns: Vec<String>,
    /// Rows skipped in lenient mode.
    pub skipped: SkipReport,
}

/// Convert `input` (in format `from`) into a replayable log at `out`. `stop` (the operator's)
/// ends the reading (see [`crate::input::open`]); nothing is left at `out` then.
pub fn convert(
    from: SourceFormat,
    input: &Path,
    out: &Path,
    lenient: bool,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<ConvertReport, ConvertError> {
    if crate::output::same_file(input, out) {
        return Err(ConvertError::SameFile(out.display().to_string()));
    }
    crate::output::check_file(out)?;
    if from == SourceFormat::Log {
        return crate::output::write_with(out, |file| whole_log(input, file, out, lenient, stop));
    }
    crate::output::write_with(out, |file| {
        let mut w = csv::WriterBuilder::new().from_writer(file);
        let report = match from {
            SourceFormat::RosTouch => ros_touch(input, &mut w, lenient, out, stop)?,
            SourceFormat::Omnid => omnid(input, &mut w, lenient, out, stop)?,
            SourceFormat::Capture => capture(input, &mut w, out)?,
            SourceFormat::Log => unreachable!("converted above"),
        };
        w.flush().map_err(|source| ConvertError::Write {
            path: out.display().to_string(),
            source,
        })?;
        Ok(report)
    })
}

fn write_err(out: &Path) -> impl Fn(csv::Error) -> ConvertError + '_ {
    move |e| ConvertError::Write {
        path: out.display().to_string(),
        source: match e.into_kind() {
            csv::ErrorKind::Io(e) => e,
            other => io::Error::other(format!("{other:?}")),
        },
    }
}

/// Formats numbers as the log writer does (shortest round-trip floats, ryu; integers, itoa).
struct NumBuf {
    f: ryu::Buffer,
    i: itoa::Buffer,
}

impl NumBuf {
    fn new() -> Self {
        NumBuf {
            f: ryu::Buffer::new(),
            i: itoa::Buffer::new(),
        }
    }
    fn f64(&mut self, v: f64) -> &[u8] {
        self.f.format(v).as_bytes()
    }
    fn i64(&mut self, v: i64) -> &[u8] {
        self.i.format(v).as_bytes()
    }
}

fn ros_touch<W: Write>(
    input: &Path,
    w: &mut csv::Writer<W>,
    lenient: bool,
    out: &Path,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<ConvertReport, ConvertError> {
    let mut reader = ColumnReader::open(input, &ROS_TOUCH_COLUMNS, lenient, stop)?;
    let idx: Vec<usize> = ROS_TOUCH_COLUMNS
        .iter()
        .map(|c| reader.require(c, &ROS_TOUCH_COLUMNS))
        .collect::<Result<_, _>>()?;
    let (waist, shoulder, elbow) = (idx[1], idx[2], idx[3]);
    let extras: Vec<usize> = (0..reader.header().len())
        .filter(|i| !idx.contains(i))
        .collect();
    let mut columns: Vec<String> = REQUIRED_COLUMNS.iter().map(|c| c.to_string()).collect();
    for &i in &extras {
        let name = &reader.header()[i];
        if columns.contains(name) {
            return Err(ConvertError::ColumnClash {
                path: reader.path().to_string(),
                column: name.clone(),
            });
        }
        columns.push(name.clone());
    }
    let werr = write_err(out);
    w.write_record(&columns).map_err(&werr)?;
    let mut num = NumBuf::new();
    let mut extra_values: Vec<Vec<u8>> = vec![Vec::new(); extras.len()];
    let mut rows = 0u64;
    loop {
        let row = reader.next_with(|r| {
            let q = from_ros(r.f64(waist)?, r.f64(shoulder)?, r.f64(elbow)?);
            for (k, &i) in extras.iter().enumerate() {
                extra_values[k].clear();
                extra_values[k].extend_from_slice(r.field(i));
            }
            Ok((r.t, q))
        })?;
        let Some((t, q)) = row else { break };
        w.write_field(num.f64(t)).map_err(&werr)?;
        for j in 0..3 {
            w.write_field(num.f64(q[j])).map_err(&werr)?;
        }
        for _ in 0..3 {
            w.write_field(num.f64(0.0)).map_err(&werr)?;
        }
        for v in &extra_values {
            w.write_field(v).map_err(&werr)?;
        }
        w.write_record(None::<&[u8]>).map_err(&werr)?;
        rows += 1;
    }
    finish(rows, columns, reader.skipped().clone(), reader.path())
}

fn omnid<W: Write>(
    input: &Path,
    w: &mut csv::Writer<W>,
    lenient: bool,
    out: &Path,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<ConvertReport, ConvertError> {
    let mut reader = LogReader::open(input, lenient, stop)?;
    let has_enc = reader.columns().enc.is_some();
    let has_mode = reader.columns().mode.is_some();
    let mut columns: Vec<String> = REQUIRED_COLUMNS.iter().map(|c| c.to_string()).collect();
    if has_enc {
        columns.extend(["enc1", "enc2", "enc3"].map(String::from));
    }
    if has_mode {
        columns.push("mode".into());
    }
    let werr = write_err(out);
    w.write_record(&columns).map_err(&werr)?;
    let mut num = NumBuf::new();
    let mut rows = 0u64;
    while let Some(row) = reader.next_row()? {
        w.write_field(num.f64(row.t)).map_err(&werr)?;
        for v in row.q.iter().chain(&row.tau) {
            w.write_field(num.f64(*v)).map_err(&werr)?;
        }
        if let Some(enc) = row.enc {
            for c in enc {
                w.write_field(num.i64(c)).map_err(&werr)?;
            }
        }
        if has_mode {
            w.write_field(row.mode.map(|m| m.as_str()).unwrap_or(""))
                .map_err(&werr)?;
        }
        w.write_record(None::<&[u8]>).map_err(&werr)?;
        rows += 1;
    }
    finish(rows, columns, reader.skipped().clone(), reader.path())
}

/// A whole omnid log (CSV or MCAP, read through the one log reader) to `out` in the format its
/// extension names. Every value passes as its exact bits (shortest round-trip text in CSV,
/// binary in MCAP), so CSV → MCAP → CSV gives the same file back.
fn whole_log<W: Write>(
    input: &Path,
    file: &mut W,
    out: &Path,
    lenient: bool,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<ConvertReport, ConvertError> {
    use crate::telemetry::mcap_log::LogFormat;
    let mut reader = ColumnReader::open(input, &["t"], lenient, stop)?;
    let (schema, at) = LogColumns::locate(&reader)?;
    let format = LogFormat::for_path(out, crate::omni::kinematics::Geometry::default());
    let mut rec = crate::telemetry::writer::recorder(schema, format);
    let werr = |source: io::Error| ConvertError::Write {
        path: out.display().to_string(),
        source,
    };
    let mut bytes = Vec::with_capacity(1 << 16);
    rec.header(&mut bytes).map_err(werr)?;
    let mut rows = 0u64;
    while let Some(r) = reader.next_with(|row| at.record(row))? {
        rec.row(&r, &mut bytes).map_err(werr)?;
        rows += 1;
        if bytes.len() >= 1 << 16 {
            file.write_all(&bytes).map_err(werr)?;
            bytes.clear();
        }
    }
    rec.finish_rows(&mut bytes).map_err(werr)?;
    rec.footer(&mut bytes).map_err(werr)?;
    file.write_all(&bytes).map_err(werr)?;
    finish(
        rows,
        schema.columns(),
        reader.skipped().clone(),
        reader.path(),
    )
}

/// Where each of an omnid log's columns is in the file being converted (its header may order
/// them otherwise, or hold more).
struct LogColumns {
    q: [usize; 3],
    tau: [usize; 3],
    qf: [usize; 3],
    qd: [usize; 3],
    qdd: [usize; 3],
    reference: [usize; 3],
    tau_cmd: [usize; 3],
    tau_hat: [usize; 3],
    tip: [usize; 3],
    fcmd: [usize; 3],
    enc: [usize; 3],
    /// `tau_model` and `fhand`, in logs of the simulator.
    model: Option<([usize; 3], [usize; 3])>,
    /// `tau_ext` and `fext`, in logs written since the force estimate was logged.
    external: Option<([usize; 3], [usize; 3])>,
    amps: usize,
    mode: usize,
    flags: usize,
    /// The buttons and the inkwell, in logs written since they were logged.
    stylus: Option<[usize; 3]>,
}

impl LogColumns {
    /// The log's schema as its header shows it, and where its columns are; a column the schema
    /// needs and the header lacks is refused, named.
    fn locate<R: io::Read>(
        reader: &ColumnReader<R>,
    ) -> Result<(crate::telemetry::record::LogSchema, LogColumns), ConvertError> {
        // An optional group is there when any of its columns is (a partial group is then a
        // missing column, named); logs written before the force estimate was logged have none
        // of `tau_ext`/`fext` and convert without them.
        let any = |names: &[&str]| reader.header().iter().any(|h| names.contains(&h.as_str()));
        let schema = crate::telemetry::record::LogSchema {
            model: any(&["tau_model1"]),
            external: any(&[
                "tau_ext1", "tau_ext2", "tau_ext3", "fext1", "fext2", "fext3",
            ]),
            buttons: any(&crate::telemetry::record::STYLUS_COLUMNS),
        };
        let columns = schema.columns();
        let names: Vec<&str> = columns.iter().map(String::as_str).collect();
        let idx: Vec<usize> = names
            .iter()
            .map(|c| reader.require(c, &names))
            .collect::<Result<_, _>>()?;
        let col = |name: &str| idx[names.iter().position(|n| *n == name).expect("a log column")];
        let three = |group: &str| [1, 2, 3].map(|j| col(&format!("{group}{j}")));
        let at = LogColumns {
            q: three("q"),
            tau: three("tau"),
            qf: three("qf"),
            qd: three("qd"),
            qdd: three("qdd"),
            reference: three("ref"),
            tau_cmd: three("tau_cmd"),
            tau_hat: three("tau_hat"),
            tip: three("tip"),
            fcmd: three("fcmd"),
            enc: three("enc"),
            model: schema.model.then(|| (three("tau_model"), three("fhand"))),
            external: schema.external.then(|| (three("tau_ext"), three("fext"))),
            amps: col("amps"),
            mode: col("mode"),
            flags: col("flags"),
            stylus: schema
                .buttons
                .then(|| crate::telemetry::record::STYLUS_COLUMNS.map(col)),
        };
        Ok((schema, at))
    }

    /// One row as the tick it records (a group the log lacks reads NaN, or released buttons).
    fn record(
        &self,
        row: &crate::telemetry::reader::Row<'_>,
    ) -> Result<crate::telemetry::record::TickRecord, crate::telemetry::reader::RowFault> {
        use crate::telemetry::reader::RowFault;
        use crate::telemetry::record::{HapticRecord, Live, Mode, TickRecord};
        let nums = |c: [usize; 3]| -> Result<[f64; 3], RowFault> {
            Ok([
                row.number_or_gap(c[0])?,
                row.number_or_gap(c[1])?,
                row.number_or_gap(c[2])?,
            ])
        };
        let pair = |group: Option<([usize; 3], [usize; 3])>| match group {
            Some((a, b)) => Ok((nums(a)?, nums(b)?)),
            None => Ok(([f64::NAN; 3], [f64::NAN; 3])),
        };
        let mode = std::str::from_utf8(row.field(self.mode))
            .ok()
            .and_then(Mode::parse)
            .ok_or(RowFault::UnknownMode { col: self.mode })?;
        let (tau_model, hand) = pair(self.model)?;
        let (tau_ext, fext) = pair(self.external)?;
        let mut live = Live::default();
        if let Some(s) = self.stylus {
            live.buttons = [row.i64(s[0])? != 0, row.i64(s[1])? != 0];
            live.inkwell = row.i64(s[2])? != 0;
        }
        let enc = self.enc;
        Ok(TickRecord {
            t: row.t,
            q: nums(self.q)?,
            tau: nums(self.tau)?,
            qf: nums(self.qf)?,
            qd: nums(self.qd)?,
            qdd: nums(self.qdd)?,
            reference: nums(self.reference)?,
            tau_cmd: nums(self.tau_cmd)?,
            tau_hat: nums(self.tau_hat)?,
            tau_model,
            tau_ext,
            enc: [row.i64(enc[0])?, row.i64(enc[1])?, row.i64(enc[2])?],
            amps: row.i64(self.amps)? != 0,
            mode,
            flags: u32::try_from(row.i64(self.flags)?)
                .map_err(|_| RowFault::NotAnInteger { col: self.flags })?,
            haptic: HapticRecord {
                tip_mm: nums(self.tip)?,
                force: nums(self.fcmd)?,
                hand,
                fext,
            },
            live,
        })
    }
}

fn capture<W: Write>(
    input: &Path,
    w: &mut csv::Writer<W>,
    out: &Path,
) -> Result<ConvertReport, ConvertError> {
    use crate::device::codec::{decode_command, decode_state, STATE_LAYOUT, STATE_LEN};
    use crate::device::firewire::capture::{CaptureError, CaptureReader};
    use crate::device::EncoderUnwrap;
    let path = input.display().to_string();
    let file = std::fs::File::open(input).map_err(|source| CaptureError::Io {
        path: path.clone(),
        source,
    })?;
    let mut reader = CaptureReader::new(io::BufReader::new(file), &path)?;
    let header = reader.header().clone();
    let rad = std::f64::consts::TAU / header.counts_per_rev;
    let columns: Vec<String> = REQUIRED_COLUMNS
        .iter()
        .map(|c| c.to_string())
        .chain(
            [
                "enc1", "enc2", "enc3", "counter", "switches", "dac1", "dac2", "dac3", "amps",
            ]
            .map(String::from),
        )
        .collect();
    let werr = write_err(out);
    w.write_record(&columns).map_err(&werr)?;
    let mut num = NumBuf::new();
    let mut unwrap = EncoderUnwrap::new();
    let mut last_cmd = None;
    let mut clock = CaptureClock::default();
    let mut last_t: Option<f64> = None;
    let mut rows = 0u64;
    while let Some(p) = reader.next_packet()? {
        let Some(info) = p.received else {
            last_cmd = decode_command(&p.bytes).ok();
            continue;
        };
        if p.bytes.len() < STATE_LEN {
            continue;
        }
        let Ok(state) = decode_state(&p.bytes[..STATE_LEN]) else {
            continue;
        };
        let t = clock.time(info.map(|i| i.timestamp), p.host_ns);
        if last_t.is_some_and(|l| t <= l) {
            // Two packets in one bus cycle cannot both be the device's: keep the first.
            continue;
        }
        last_t = Some(t);
        let mut raw = state.encoder;
        for j in 0..3 {
            if header.encoder_sign[j] < 0 {
                raw[j] = raw[j].wrapping_neg();
            }
        }
        let enc = unwrap.update(raw);
        let (dac, amps) = last_cmd
            .map_or(([0x07FFu16; 3], false), |c: crate::device::MotorCommand| {
                (c.dac, c.amps_on)
            });
        let row = CaptureRow {
            t,
            enc,
            rad,
            counter: state.counter,
            switches: p.bytes[STATE_LAYOUT.status],
            dac,
            amps,
        };
        row.write(w, &mut num).map_err(&werr)?;
        rows += 1;
    }
    finish(rows, columns, SkipReport::default(), &path)
}

/// A capture's time base: the receive timestamps' bus cycles, unwrapped, when the capture has
/// them; else the host's clock from the first packet.
#[derive(Default)]
struct CaptureClock {
    first_ns: Option<u64>,
    last_ts: Option<u16>,
    cycles: u64,
}

impl CaptureClock {
    /// Seconds since the capture's start of a packet with bus timestamp `ts` (if any),
    /// received at `host_ns`.
    fn time(&mut self, ts: Option<u16>, host_ns: u64) -> f64 {
        use crate::device::firewire::rate::{cycles_between, CYCLES_PER_S};
        match ts {
            Some(ts) => {
                if let Some(prev) = self.last_ts {
                    self.cycles += u64::from(cycles_between(prev, ts).unwrap_or(0));
                }
                self.last_ts = Some(ts);
                self.cycles as f64 / f64::from(CYCLES_PER_S)
            }
            None => {
                let first = *self.first_ns.get_or_insert(host_ns);
                host_ns.saturating_sub(first) as f64 * 1e-9
            }
        }
    }
}

/// One converted capture row: `t, q1..3, tau1..3 (zero), enc1..3, counter, switches,
/// dac1..3, amps`.
struct CaptureRow {
    t: f64,
    enc: [i64; 3],
    rad: f64,
    counter: u32,
    switches: u8,
    dac: [u16; 3],
    amps: bool,
}

impl CaptureRow {
    fn write<W: Write>(&self, w: &mut csv::Writer<W>, num: &mut NumBuf) -> csv::Result<()> {
        w.write_field(num.f64(self.t))?;
        for c in self.enc {
            w.write_field(num.f64(c as f64 * self.rad))?;
        }
        for _ in 0..3 {
            w.write_field(num.f64(0.0))?;
        }
        for c in self.enc {
            w.write_field(num.i64(c))?;
        }
        w.write_field(num.i64(i64::from(self.counter)))?;
        w.write_field(num.i64(i64::from(self.switches)))?;
        for d in self.dac {
            w.write_field(num.i64(i64::from(d)))?;
        }
        w.write_field(num.i64(i64::from(self.amps)))?;
        w.write_record(None::<&[u8]>)
    }
}

fn finish(
    rows: u64,
    columns: Vec<String>,
    skipped: SkipReport,
    path: &str,
) -> Result<ConvertReport, ConvertError> {
    if rows == 0 {
        return Err(ConvertError::NoRows {
            path: path.to_string(),
            skipped,
        });
    }
    Ok(ConvertReport {
        rows,
        columns,
        skipped,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ros_rows_map_to_openhaptics_joints_and_keep_extras() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.csv");
        let out = dir.path().join("out/replay.csv");
        std::fs::write(
            &input,
            "t,waist,shoulder,elbow,x_mm\n0.0,0.1,0.2,0.3,1.5\n0.01,-0.1,0.25,-0.5,\"2,5\"\n",
        )
        .unwrap();
        let rep = convert(SourceFormat::RosTouch, &input, &out, false, None).unwrap();
        assert_eq!(rep.rows, 2);
        let text = std::fs::read_to_string(&out).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines[0], "t,q1,q2,q3,tau1,tau2,tau3,x_mm");
        let q = from_ros(0.1, 0.2, 0.3);
        let f: Vec<f64> = lines[1].split(',').map(|v| v.parse().unwrap()).collect();
        assert_eq!(f, [0.0, q[0], q[1], q[2], 0.0, 0.0, 0.0, 1.5]);
        assert!(lines[2].ends_with(",0.0,0.0,0.0,\"2,5\""), "{}", lines[2]);
        assert_eq!(
            std::fs::read_dir(dir.path().join("out")).unwrap().count(),
            1
        );
    }

    #[test]
    fn a_failed_conversion_leaves_no_output() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.csv");
        let out = dir.path().join("out.csv");
        std::fs::write(&input, "t,waist,shoulder,elbow\n0,0,0,0\n0.01,0,zero,0\n").unwrap();
        let e = convert(SourceFormat::RosTouch, &input, &out, false, None).unwrap_err();
        assert!(
            e.to_string().contains("line 3") && e.to_string().contains("`shoulder`"),
            "{e}"
        );
        assert!(!out.exists());
        assert_eq!(
            std::fs::read_dir(dir.path()).unwrap().count(),
            1,
            "only the input"
        );
        let rep = convert(SourceFormat::RosTouch, &input, &out, true, None).unwrap();
        assert_eq!((rep.rows, rep.skipped.count), (1, 1));
        assert!(convert(SourceFormat::RosTouch, &out, &out, false, None).is_err());
    }

    /// A whole log of `schema` (three rows, the last `stop`), written by the CSV recorder, with
    /// a force estimate of `fext` N on every row (the middle row's differs).
    fn log_text(schema: crate::telemetry::LogSchema, fext: [f64; 3]) -> Vec<u8> {
        use crate::telemetry::record::{Mode, TickRecord};
        let mut text = schema.columns().join(",").into_bytes();
        text.push(b'\n');
        for (k, mode) in [Mode::Hold, Mode::Hold, Mode::Stop].into_iter().enumerate() {
            let mut r = TickRecord::at(k as u64, mode);
            r.q = [0.1, -0.2, 1.0 / 3.0];
            r.tau_model = [f64::NAN; 3];
            r.haptic.hand = [f64::NAN; 3];
            r.tau_ext = [0.01 * k as f64, -0.02, 1e-17];
            r.haptic.fext = fext.map(|v| v * (1 + k % 2) as f64);
            crate::telemetry::recorder::format_row(&mut text, &r, &schema);
        }
        text
    }

    fn ticks(
        mcap: &Path,
    ) -> (
        crate::telemetry::LogSchema,
        Vec<crate::telemetry::TickRecord>,
    ) {
        let mut t = crate::telemetry::mcap_log::read::McapTicks::new(
            std::fs::File::open(mcap).unwrap(),
            false,
        );
        let rows = std::iter::from_fn(|| t.next_tick().unwrap()).collect();
        (t.schema(), rows)
    }

    #[test]
    fn the_force_estimate_passes_csv_to_mcap_to_csv_and_older_logs_convert_without_it() {
        use crate::telemetry::LogSchema;
        let dir = tempfile::tempdir().unwrap();
        let p = |n: &str| dir.path().join(n);
        let log = |from: &Path, to: &Path| convert(SourceFormat::Log, from, to, false, None);
        // Today's log: its estimate comes back from the MCAP value for value, then as the
        // same CSV bytes.
        let now = log_text(LogSchema::new(true), [0.25, -1.5, 0.0]);
        std::fs::write(p("now.csv"), &now).unwrap();
        let rep = log(&p("now.csv"), &p("now.mcap")).unwrap();
        assert!(
            rep.columns.iter().any(|c| c == "fext3"),
            "{:?}",
            rep.columns
        );
        let (schema, rows) = ticks(&p("now.mcap"));
        assert_eq!(schema, LogSchema::new(true));
        assert_eq!(rows.len(), 3);
        assert_eq!(rows[1].haptic.fext, [0.5, -3.0, 0.0]);
        assert_eq!(rows[2].tau_ext, [0.02, -0.02, 1e-17]);
        log(&p("now.mcap"), &p("again.csv")).unwrap();
        assert_eq!(std::fs::read(p("again.csv")).unwrap(), now);

        // A log from before the estimate was logged: no `tau_ext`, no `fext`, no channels for
        // them; it converts both ways unchanged, the estimate absent (not made up as zeros).
        let old_schema = LogSchema {
            model: true,
            external: false,
            buttons: false,
        };
        let old = log_text(old_schema, [9.0; 3]);
        let header = String::from_utf8_lossy(&old[..old.iter().position(|b| *b == b'\n').unwrap()])
            .to_string();
        assert!(
            !header.contains("fext") && !header.contains("tau_ext") && header.contains("fhand1")
        );
        std::fs::write(p("old.csv"), &old).unwrap();
        log(&p("old.csv"), &p("old.mcap")).unwrap();
        let (schema, rows) = ticks(&p("old.mcap"));
        assert_eq!(schema, old_schema);
        assert!(rows
            .iter()
            .all(|r| r.haptic.fext.iter().all(|v| v.is_nan())));
        log(&p("old.mcap"), &p("old-again.csv")).unwrap();
        assert_eq!(std::fs::read(p("old-again.csv")).unwrap(), old);

        // Half a group is a broken header, named, not an absent group.
        let cut = String::from_utf8(now.clone())
            .unwrap()
            .replacen("fext2", "fextra", 1);
        std::fs::write(p("cut.csv"), cut).unwrap();
        let e = log(&p("cut.csv"), &p("cut.mcap")).unwrap_err().to_string();
        assert!(e.contains("line 1") && e.contains("`fext2`"), "{e}");
        assert!(!p("cut.mcap").exists());
    }

    #[test]
    fn omnid_compact_keeps_the_replay_columns_verbatim() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.csv");
        let out = dir.path().join("out.csv");
        std::fs::write(
            &input,
            "t,q1,q2,q3,tau1,tau2,tau3,qf1,enc1,enc2,enc3,amps,mode,flags\n\
             0,0.5,0,0,0.0022,0,-0.45,9,1,0,0,1,blend,0\n\
             0.001,0.5,0,0,0,0,0,9,1,0,0,0,stop,0\n",
        )
        .unwrap();
        convert(SourceFormat::Omnid, &input, &out, false, None).unwrap();
        let text = std::fs::read_to_string(&out).unwrap();
        assert_eq!(
            text,
            "t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3,mode\n\
             0.0,0.5,0.0,0.0,0.0022,0.0,-0.45,1,0,0,blend\n\
             0.001,0.5,0.0,0.0,0.0,0.0,0.0,1,0,0,stop\n"
        );
    }

    #[test]
    fn captures_become_rows_with_bus_time_signed_encoders_and_the_last_command() {
        use crate::device::codec::{encode_command, encode_state, MotorCommand, StatePacket};
        let hex = |b: &[u8]| b.iter().map(|x| format!("{x:02x}")).collect::<String>();
        let state = |enc: [u16; 3], counter: u32| {
            hex(&encode_state(&StatePacket {
                encoder: enc,
                counter,
                ..Default::default()
            }))
        };
        let amps = hex(&encode_command(&MotorCommand {
            dac: [0x0800, 0x07FF, 0x07FE],
            amps_on: true,
            lamp: 0,
            watchdog: 0x53,
        }));
        // Timestamps 7 s 7996 → 0 s 4 (8 cycles, across the 8 s wrap), then a repeat.
        let text = format!(
            "# omnid capture 1\n# kind firewire\n# encoder_sign -1 1 1\n\
             dir,host_ns,iso_header,timestamp,counter,bytes\n\
             rx,10,0x002c00a0,{:#06x},5,{}\ntx,11,,,,{amps}\n# note hello\n\
             rx,12,0x002c00a0,0x0004,6,{}\nrx,13,0x002c00a0,0x0004,6,{}\nrx,14,0x00040000,0x0005,,00\n",
            (7 << 13) | 7996,
            state([1, 2, 3], 5),
            state([0xFFFF, 2, 3], 6),
            state([0xFFFF, 2, 3], 6),
        );
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("c.txt");
        let out = dir.path().join("c.csv");
        std::fs::write(&input, text).unwrap();
        let rep = convert(SourceFormat::Capture, &input, &out, false, None).unwrap();
        assert_eq!(rep.rows, 2);
        let csv = std::fs::read_to_string(&out).unwrap();
        let lines: Vec<&str> = csv.lines().collect();
        assert_eq!(
            lines[0],
            "t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3,counter,switches,dac1,dac2,dac3,amps"
        );
        let rad = std::f64::consts::TAU / 15000.0;
        let row: Vec<f64> = lines[2].split(',').map(|v| v.parse().unwrap()).collect();
        assert_eq!(row[0], 0.001);
        // Joint 1's sign is -1: raw 1 reads -1, raw 0xFFFF (one count down) reads +1.
        assert_eq!(&row[7..10], &[1.0, 2.0, 3.0]);
        assert_eq!(row[1], rad);
        assert_eq!(&row[10..], &[6.0, 151.0, 2048.0, 2047.0, 2046.0, 1.0]);
        assert!(
            lines[1].starts_with("0.0,") && lines[1].contains(",-1,2,3,5,151,2047,2047,2047,0")
        );
        // A broken line is named.
        std::fs::write(&input, "# omnid capture 1\nrx,1,0x0,0x0,,zz\n").unwrap();
        let e = convert(SourceFormat::Capture, &input, &out, false, None)
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 2") && e.contains("hex digits"), "{e}");
    }
}

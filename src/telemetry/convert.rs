//! `omnid convert`: turn a recording into a replayable log (DESIGN §2.2: `t, q1..3, tau1..3`
//! first).
//!
//! Sources:
//! - `ros-touch`: the ROS Geomagic/Phantom driver's joint states as in
//!   `shared/data/touch-2016-joint-and-tip.csv`: `t, waist, shoulder, elbow` (any order) in the
//!   ROS convention (waist = −j1, shoulder = j2, elbow = j3 − j2), mapped to OpenHaptics joints
//!   with [`crate::omni::kinematics::from_ros`]. No torque was recorded, so `tau = 0`. Every
//!   other column (`x_mm, y_mm, z_mm`, the gimbal angles, …) is kept, unchanged, after them.
//! - `omnid`: an omnid log reduced to what replay reads: `t, q1..3, tau1..3`, then `enc1..3` and
//!   `mode` when present. Numbers are written as the log writer writes them (shortest
//!   round-trip form), so the kept columns are bit-for-bit the original's. Used for the compact
//!   recorded sessions in `mock/`.
//!
//! The input is read with the log reader's checks (strict, or `lenient`: skip damaged rows).
//! The output is written beside the target and renamed into place when complete, so a failed
//! conversion never leaves a half-written log that would replay.

use super::reader::{ColumnReader, LogReader, ReadError, SkipReport, REQUIRED_COLUMNS};
use crate::omni::kinematics::from_ros;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
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
}

/// The ROS driver's columns (the first is the time).
pub const ROS_TOUCH_COLUMNS: [&str; 4] = ["t", "waist", "shoulder", "elbow"];

#[derive(Debug, Error)]
pub enum ConvertError {
    #[error(transparent)]
    Read(#[from] ReadError),
    #[error("cannot write {path}: {source}")]
    Write { path: String, source: io::Error },
    #[error("{path}: line 1: column `{column}` would clash with the output column of that name")]
    ColumnClash { path: String, column: String },
    #[error("{path}: no data rows to convert{}", if skipped.count > 0 { format!(" ({skipped})") } else { String::new() })]
    NoRows { path: String, skipped: SkipReport },
    #[error("the output {0} is the input")]
    SameFile(String),
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
    pub rows: u64,
    pub columns: Vec<String>,
    pub skipped: SkipReport,
}

/// Convert `input` (in format `from`) into a replayable log at `out`. `stop` (the operator's)
/// ends the reading (see [`ColumnReader::open`]); nothing is left at `out` then.
pub fn convert(
    from: SourceFormat,
    input: &Path,
    out: &Path,
    lenient: bool,
    stop: Option<&Arc<AtomicBool>>,
) -> Result<ConvertReport, ConvertError> {
    if let (Ok(a), Ok(b)) = (input.canonicalize(), out.canonicalize()) {
        if a == b {
            return Err(ConvertError::SameFile(out.display().to_string()));
        }
    }
    let partial = partial_path(out);
    let werr = |source: io::Error| ConvertError::Write {
        path: out.display().to_string(),
        source,
    };
    let result = (|| {
        if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(werr)?;
        }
        let file = File::create(&partial).map_err(werr)?;
        let mut w = csv::WriterBuilder::new().from_writer(BufWriter::with_capacity(1 << 16, file));
        let report = match from {
            SourceFormat::RosTouch => ros_touch(input, &mut w, lenient, out, stop)?,
            SourceFormat::Omnid => omnid(input, &mut w, lenient, out, stop)?,
        };
        w.flush().map_err(werr)?;
        let file = w
            .into_inner()
            .map_err(|e| werr(io::Error::other(e.to_string())))?
            .into_inner()
            .map_err(|e| werr(e.into_error()))?;
        file.sync_all().map_err(werr)?;
        std::fs::rename(&partial, out).map_err(werr)?;
        Ok(report)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&partial);
    }
    result
}

fn partial_path(out: &Path) -> PathBuf {
    let mut name = out.file_name().unwrap_or_default().to_os_string();
    name.push(".partial");
    out.with_file_name(name)
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
            r.check_time(false)?;
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
        assert!(!partial_path(&out).exists());
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
        assert!(!out.exists() && !partial_path(&out).exists());
        let rep = convert(SourceFormat::RosTouch, &input, &out, true, None).unwrap();
        assert_eq!((rep.rows, rep.skipped.count), (1, 1));
        assert!(convert(SourceFormat::RosTouch, &out, &out, false, None).is_err());
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
}

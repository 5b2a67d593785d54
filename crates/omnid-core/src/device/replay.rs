//! The mock device: replays a recorded log (docs/DESIGN.md §2.1 `--device replay:PATH`).
//!
//! - Each exchange returns the next row as a state packet: the angles go through the encoder
//!   path (the `enc1..3` counts when the log has them, else `round(q / rad_per_count)`), wrapped
//!   to 16 bits and encoded with the packet codec, so the servo decodes and unwraps them exactly
//!   as it would a device's.
//! - `device_time_s` is the row's `t`, untouched: the Kalman filter sees the recording's own
//!   time steps (irregular ones included).
//! - Paced at the log's timestamps with absolute deadlines, or as fast as possible.
//! - [`Device::recorded_torque`] returns the row's `tau`: the torque the recorded plant got.
//! - `mode = stop` rows (omnid's final packet: zero torque, amplifiers off) are never played as
//!   a control tick: the exchange that meets one returns [`DeviceError::EndOfData`], and the
//!   servo's final safe packet (zero torque, amplifiers off) gets that row back as its reply, so
//!   a replayed omnid log ends with the same `stop` row as the original. The same holds for the
//!   first row past a duration limit (as the simulator answers its final packet with the next
//!   sample). A log without a `stop` row answers the final safe packet with its last sample
//!   again (zero torque), so every replayed log still ends with a `stop` row.
//!
//! The log must be a regular file: it is read twice (checked, then played), which a FIFO or
//! pipe cannot give, so one is refused at once rather than waited on. The validation pass reads
//! through [`crate::input`] with the operator's stop flag, and the paced sleeps between rows end
//! on it, so Ctrl-C ends a replay within a fraction of a second however big the file or far
//! apart its timestamps.
//!
//! Opening validates the whole file in one streaming pass (constant memory) before anything
//! runs, so a bad row is a clear error at start, not a fault an hour in. The encoder path is
//! checked there too: the servo takes the first packet's 16-bit count as a signed value and
//! every later one as a step of less than half the 16-bit range, so the first count must lie in
//! −32768..=32767 and no step may reach 32768 counts; when the log has `enc` columns, each `q`
//! must equal `enc · rad_per_count` to within half a count (else the log was recorded with
//! another `device.counts_per_rev`). These checks are errors in lenient mode too: they are not
//! damaged rows but a log this configuration cannot carry.

use super::codec::{decode_command, encode_state, StatePacket};
use super::DeviceConfig;
use super::{Device, DeviceError, RawSample, COMMAND_LEN};
use crate::clock;
use crate::telemetry::reader::{LogReader, LogRow, ReadError, SkipReport};
use crate::telemetry::record::Mode;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// Tolerance of the duration limit, s.
const DURATION_SLACK_S: f64 = 1e-9;

/// Why a log cannot be replayed.
#[derive(Debug, Error)]
pub enum ReplayError {
    /// The log could not be read, or a row of it is bad.
    #[error(transparent)]
    Read(#[from] ReadError),
    /// The log is a pipe, FIFO or device, which cannot be read twice.
    #[error(
        "{path} is {kind}: a replay is checked whole before it plays, so its file is read \
         twice; save the recording to a regular file and replay that"
    )]
    NotRegular {
        /// The log, as given.
        path: String,
        /// What it is instead ("a FIFO", …).
        kind: &'static str,
    },
    /// Nothing to play (every row skipped, or none at all).
    #[error("{path}: no data rows to replay{}", if skipped.count > 0 { format!(" ({skipped})") } else { String::new() })]
    NoRows {
        /// The log, as given.
        path: String,
        /// What lenient reading skipped.
        skipped: SkipReport,
    },
    /// The first row's encoder count does not fit the device's signed 16-bit counter.
    #[error("{path}: line {line}: column `{column}`: the first count {count} is outside \
             -32768..=32767: the servo takes the first packet's 16-bit count as signed, so this \
             log cannot be replayed through the encoder path (device.counts_per_rev = {counts_per_rev})")]
    FirstCountRange {
        /// The log, as given.
        path: String,
        /// The first row's line.
        line: u64,
        /// The `enc` column (or the `q` column counts are made from).
        column: String,
        /// The count, encoder counts.
        count: i64,
        /// The configuration's counts per revolution.
        counts_per_rev: f64,
    },
    /// Two rows' counts differ by more than the 16-bit counter can tell apart.
    #[error(
        "{path}: line {line}: column `{column}`: a step of {step} counts from the previous row \
             (limit ±32767: the 16-bit encoder counter would be ambiguous)"
    )]
    CountJump {
        /// The log, as given.
        path: String,
        /// The later row's line.
        line: u64,
        /// The `enc` column (or the `q` column counts are made from).
        column: String,
        /// The step, encoder counts.
        step: i128,
    },
    /// `enc` and `q` disagree by more than half a count: another `counts_per_rev` made it.
    #[error(
        "{path}: line {line}: column `{column}`: {enc} counts are {expected} rad at \
             device.counts_per_rev = {counts_per_rev}, but `{q_column}` = {q} (more than half a \
             count away): the log was recorded with another counts_per_rev"
    )]
    EncoderMismatch {
        /// The log, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The `enc` column.
        column: String,
        /// The matching `q` column.
        q_column: String,
        /// The count, encoder counts.
        enc: i64,
        /// The angle that count means here, rad.
        expected: f64,
        /// The logged angle, rad.
        q: f64,
        /// The configuration's counts per revolution.
        counts_per_rev: f64,
    },
}

/// What the validation pass found.
#[derive(Debug, Clone, PartialEq)]
pub struct ReplayInfo {
    /// The log, as given.
    pub path: PathBuf,
    /// Rows that will be played (the final `stop` row included).
    pub rows: u64,
    /// The first row's time, s.
    pub first_t: f64,
    /// The last played row's time, s.
    pub last_t: f64,
    /// The log has `enc1..3` (else counts come from `q`).
    pub has_enc: bool,
    /// The log ends with a `mode = stop` row.
    pub has_stop: bool,
    /// Rows skipped in lenient mode.
    pub skipped: SkipReport,
}

/// Turns rows into the continuous counts the device reports, checking that the servo's
/// 16-bit unwrap will give them back.
#[derive(Debug, Clone, Copy)]
struct EncoderPath {
    rad_per_count: f64,
    counts_per_rev: f64,
    last: Option<[i64; 3]>,
}

impl EncoderPath {
    fn new(device: &DeviceConfig) -> Self {
        EncoderPath {
            rad_per_count: device.rad_per_count(),
            counts_per_rev: device.counts_per_rev,
            last: None,
        }
    }

    fn counts(&mut self, row: &LogRow, path: &str) -> Result<[i64; 3], ReplayError> {
        let column = |j: usize| {
            if row.enc.is_some() {
                format!("enc{}", j + 1)
            } else {
                format!("q{}", j + 1)
            }
        };
        let counts = match row.enc {
            Some(enc) => {
                for j in 0..3 {
                    let expected = enc[j] as f64 * self.rad_per_count;
                    if (row.q[j] - expected).abs() > 0.5 * self.rad_per_count {
                        return Err(ReplayError::EncoderMismatch {
                            path: path.to_string(),
                            line: row.line,
                            column: column(j),
                            q_column: format!("q{}", j + 1),
                            enc: enc[j],
                            expected,
                            q: row.q[j],
                            counts_per_rev: self.counts_per_rev,
                        });
                    }
                }
                enc
            }
            // Finite by the reader; `as` saturates, and the range checks below catch that.
            None => row.q.map(|q| (q / self.rad_per_count).round() as i64),
        };
        match self.last {
            None => {
                if let Some(j) = (0..3).find(|&j| i16::try_from(counts[j]).is_err()) {
                    return Err(ReplayError::FirstCountRange {
                        path: path.to_string(),
                        line: row.line,
                        column: column(j),
                        count: counts[j],
                        counts_per_rev: self.counts_per_rev,
                    });
                }
            }
            Some(last) => {
                for j in 0..3 {
                    let step = counts[j] as i128 - last[j] as i128;
                    if step.abs() > i16::MAX as i128 {
                        return Err(ReplayError::CountJump {
                            path: path.to_string(),
                            line: row.line,
                            column: column(j),
                            step,
                        });
                    }
                }
            }
        }
        self.last = Some(counts);
        Ok(counts)
    }
}

/// A recorded log behind the [`Device`] trait.
pub struct ReplayDevice {
    reader: LogReader,
    encoder: EncoderPath,
    info: ReplayInfo,
    paced: bool,
    /// Play rows with `t − first t` below this, s.
    duration_s: f64,
    tick: u64,
    start_ns: u64,
    first_t: f64,
    /// A row that only the final safe packet gets back (a `stop` row, or the first row past the
    /// duration limit).
    held_back: Option<LogRow>,
    /// The row returned last.
    last_row: Option<LogRow>,
    finished: bool,
    torque: Option<[f64; 3]>,
    /// The operator's stop: ends the paced wait for the next row.
    stop: Arc<AtomicBool>,
}

impl ReplayDevice {
    /// Validate the log at `path` for this configuration (one streaming pass) and open it for
    /// playback: `paced` plays it at its own timestamps, else as fast as possible; `lenient`
    /// skips damaged rows instead of refusing the file. `stop` (the operator's) ends the
    /// validation pass ([`ReadError::Stopped`]) and any paced wait.
    pub fn open(
        path: &Path,
        device: &DeviceConfig,
        paced: bool,
        lenient: bool,
        stop: &Arc<AtomicBool>,
    ) -> Result<Self, ReplayError> {
        let info = Self::scan(path, device, lenient, stop)?;
        Ok(ReplayDevice {
            // No stop flag for playback: the servo loop looks at it itself each tick, and a
            // read that failed on it would end the run as a device fault (or spoil the final
            // safe packet). Without one, only a regular file opens, as the scan found it.
            reader: LogReader::open(path, lenient, None)?,
            encoder: EncoderPath::new(device),
            first_t: info.first_t,
            info,
            paced,
            duration_s: f64::INFINITY,
            tick: 0,
            start_ns: 0,
            held_back: None,
            last_row: None,
            finished: false,
            torque: None,
            stop: stop.clone(),
        })
    }

    /// Play only rows less than `seconds` of device time after the first (`None`: all).
    pub(crate) fn with_duration_limit(mut self, seconds: Option<f64>) -> Self {
        self.duration_s = seconds.unwrap_or(f64::INFINITY);
        self
    }

    /// Read the whole file once: every row checked as playback will see it.
    pub(crate) fn scan(
        path: &Path,
        device: &DeviceConfig,
        lenient: bool,
        stop: &Arc<AtomicBool>,
    ) -> Result<ReplayInfo, ReplayError> {
        // Looked at before opening: a FIFO is refused, not waited on.
        if let Some(kind) = std::fs::metadata(path)
            .ok()
            .and_then(|m| crate::input::special_kind(m.file_type()))
        {
            return Err(ReplayError::NotRegular {
                path: path.display().to_string(),
                kind,
            });
        }
        let mut reader = LogReader::open(path, lenient, Some(stop))?;
        let name = reader.path().to_string();
        let mut encoder = EncoderPath::new(device);
        let (mut rows, mut first_t, mut last_t, mut has_stop) = (0u64, 0.0, 0.0, false);
        while let Some(row) = reader.next_row()? {
            encoder.counts(&row, &name)?;
            if rows == 0 {
                first_t = row.t;
            }
            rows += 1;
            last_t = row.t;
            has_stop = row.is_stop();
        }
        if rows == 0 {
            return Err(ReplayError::NoRows {
                path: name,
                skipped: reader.skipped().clone(),
            });
        }
        Ok(ReplayInfo {
            path: path.to_path_buf(),
            rows,
            first_t,
            last_t,
            has_enc: reader.columns().enc.is_some(),
            has_stop,
            skipped: reader.skipped().clone(),
        })
    }

    /// What the validation pass found.
    pub fn info(&self) -> &ReplayInfo {
        &self.info
    }

    /// The next row, or the reason there is none (errors only if the file changed after
    /// validation).
    fn next_row(&mut self) -> Result<Option<LogRow>, DeviceError> {
        self.reader
            .next_row()
            .map_err(|e| DeviceError::Io(format!("the log changed while replaying: {e}")))
    }
}

impl Device for ReplayDevice {
    fn kind(&self) -> &'static str {
        "replay"
    }

    fn exchange(&mut self, command: &[u8; COMMAND_LEN]) -> Result<RawSample, DeviceError> {
        let safe = decode_command(command)?.is_safe();
        self.torque = None;
        if self.finished {
            return Err(DeviceError::EndOfData);
        }
        let row = match self.held_back.take() {
            Some(row) => row,
            None => match (self.next_row()?, self.last_row) {
                (Some(row), _) => row,
                // The file is done, but the final safe packet still gets a reply: the last
                // sample again (the arm is where it was last seen), with nothing applied.
                (None, Some(last)) if safe => {
                    self.finished = true;
                    LogRow {
                        tau: [0.0; 3],
                        mode: Some(Mode::Stop),
                        ..last
                    }
                }
                (None, _) => return Err(DeviceError::EndOfData),
            },
        };
        // To within a nanosecond, so that rounding in `t` never lets one row too many through.
        let since_first = row.t - self.first_t;
        let beyond = self.tick > 0 && since_first >= self.duration_s - DURATION_SLACK_S;
        let last = row.is_stop() || beyond;
        if last && !safe {
            // Only the final safe packet gets this row back; the loop ends here.
            self.held_back = Some(row);
            return Err(DeviceError::EndOfData);
        }
        if last {
            self.finished = true;
        }
        let counts = self
            .encoder
            .counts(&row, self.info.path.to_str().unwrap_or("log"))
            .map_err(|e| DeviceError::Io(format!("the log changed while replaying: {e}")))?;
        if self.tick == 0 {
            self.start_ns = clock::now_ns();
            self.first_t = row.t;
        } else if self.paced {
            let offset_ns = ((row.t - self.first_t) * 1e9).round() as u64;
            // Cut short by a stop: the row is returned at once and the loop ends at its next
            // tick (and the final safe packet's reply is not waited for either).
            clock::sleep_until_ns_or_stop(self.start_ns.saturating_add(offset_ns), &self.stop);
        }
        let state = StatePacket {
            // Counts wrap at 16 bits on the wire; the servo unwraps them.
            encoder: counts.map(|c| c as u16),
            gimbal: [0x8000; 3],
            // What the stylus reported, which the servo acts on (a docked stylus stops the
            // identifier learning): the replay learns where the run learned.
            buttons: row.buttons,
            inkwell: row.inkwell,
            counter: self.tick as u32,
        };
        self.torque = Some(row.tau);
        self.last_row = Some(row);
        self.tick += 1;
        Ok(RawSample::new(encode_state(&state), row.t))
    }

    fn recorded_torque(&self) -> Option<[f64; 3]> {
        self.torque
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use crate::device::codec::{decode_state, encode_command, EncoderUnwrap, MotorCommand};
    use std::io::Write;

    fn write(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(text.as_bytes()).unwrap();
        f
    }

    fn live(k: u8) -> [u8; COMMAND_LEN] {
        let mut c = MotorCommand::safe(k);
        c.amps_on = true;
        encode_command(&c)
    }

    #[test]
    fn counts_round_trip_through_packets_and_unwrap() {
        let cfg = Config::default();
        let rpc = cfg.device.rad_per_count();
        // Joint 1 spins through several 16-bit wraps, joint 2 goes negative, joint 3 starts at
        // the edge of the signed range.
        let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3\n");
        let mut truth = Vec::new();
        for k in 0..2000i64 {
            let enc = [k * 97, -k * 31, 32767 - k * 5];
            truth.push(enc);
            text += &format!(
                "{},{},{},{},0.1,0.2,0.3,{},{},{}\n",
                k as f64 * 1e-3,
                enc[0] as f64 * rpc,
                enc[1] as f64 * rpc,
                enc[2] as f64 * rpc,
                enc[0],
                enc[1],
                enc[2]
            );
        }
        let f = write(&text);
        let mut dev =
            ReplayDevice::open(f.path(), &cfg.device, false, false, &Arc::default()).unwrap();
        assert_eq!(dev.info().rows, 2000);
        let mut unwrap = EncoderUnwrap::new();
        for (k, enc) in truth.iter().enumerate() {
            let raw = dev.exchange(&live(k as u8)).unwrap();
            assert_eq!(raw.device_time_s, k as f64 * 1e-3);
            let p = decode_state(raw.packet()).unwrap();
            assert_eq!(unwrap.update(p.encoder), *enc, "row {k}");
            assert_eq!(dev.recorded_torque(), Some([0.1, 0.2, 0.3]));
        }
        assert!(matches!(
            dev.exchange(&live(0)),
            Err(DeviceError::EndOfData)
        ));
        assert_eq!(dev.recorded_torque(), None);
        // The final safe packet gets the last sample back, with nothing applied; then nothing.
        let safe = encode_command(&MotorCommand::safe(9));
        let raw = dev.exchange(&safe).unwrap();
        assert_eq!(raw.device_time_s, 1999.0 * 1e-3);
        assert_eq!(
            unwrap.update(decode_state(raw.packet()).unwrap().encoder),
            truth[1999]
        );
        assert_eq!(dev.recorded_torque(), Some([0.0; 3]));
        assert!(matches!(dev.exchange(&safe), Err(DeviceError::EndOfData)));
    }

    #[test]
    fn q_only_logs_are_quantised_at_the_configured_resolution() {
        let cfg = Config::default();
        let rpc = cfg.device.rad_per_count();
        let f =
            write("t,q1,q2,q3,tau1,tau2,tau3\n0,0.5,-0.25,1e-5,0,0,0\n0.0137,0.6,-0.3,0,0,0,0\n");
        let mut dev =
            ReplayDevice::open(f.path(), &cfg.device, false, false, &Arc::default()).unwrap();
        let mut unwrap = EncoderUnwrap::new();
        for (t, q) in [(0.0, [0.5, -0.25, 1e-5]), (0.0137, [0.6, -0.3, 0.0])] {
            let raw = dev.exchange(&live(1)).unwrap();
            assert_eq!(
                raw.device_time_s, t,
                "irregular steps flow through as device time"
            );
            let enc = unwrap.update(decode_state(raw.packet()).unwrap().encoder);
            for j in 0..3 {
                assert!((enc[j] as f64 * rpc - q[j]).abs() <= 0.5 * rpc);
            }
        }
    }

    #[test]
    fn first_count_outside_i16_is_refused() {
        let mut cfg = Config::default();
        cfg.device.counts_per_rev = 1e6;
        // 0.5 rad at 1e6 counts/rev is ~79577 counts: not representable as the first packet.
        let f = write("t,q1,q2,q3,tau1,tau2,tau3\n0,0,0.5,0,0,0,0\n");
        let e = ReplayDevice::open(f.path(), &cfg.device, false, false, &Arc::default())
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("line 2") && e.contains("`q2`") && e.contains("-32768"),
            "{e}"
        );
    }

    #[test]
    fn enc_inconsistent_with_q_is_refused() {
        let cfg = Config::default();
        let f = write("t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3\n0,0,0,0.5,0,0,0,0,0,100\n");
        let e = ReplayDevice::open(f.path(), &cfg.device, false, true, &Arc::default())
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.contains("line 2") && e.contains("`enc3`") && e.contains("counts_per_rev"),
            "{e}"
        );
    }

    #[test]
    fn huge_step_is_refused() {
        let cfg = Config::default();
        let f = write("t,q1,q2,q3,tau1,tau2,tau3\n0,0,0,0,0,0,0\n0.001,0,0,20,0,0,0\n");
        let e = ReplayDevice::open(f.path(), &cfg.device, false, false, &Arc::default())
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("line 3") && e.contains("`q3`"), "{e}");
    }

    #[test]
    fn stop_row_answers_only_the_safe_packet() {
        let cfg = Config::default();
        let f = write(
            "t,q1,q2,q3,tau1,tau2,tau3,mode\n0,0,0,0,0.1,0,0,track\n0.001,0,0,0,0.2,0,0,track\n\
             0.002,0,0,0,0,0,0,stop\n",
        );
        let mut dev =
            ReplayDevice::open(f.path(), &cfg.device, false, false, &Arc::default()).unwrap();
        assert!(dev.info().has_stop);
        dev.exchange(&live(1)).unwrap();
        dev.exchange(&live(2)).unwrap();
        assert_eq!(dev.recorded_torque(), Some([0.2, 0.0, 0.0]));
        assert!(matches!(
            dev.exchange(&live(3)),
            Err(DeviceError::EndOfData)
        ));
        let raw = dev
            .exchange(&encode_command(&MotorCommand::safe(4)))
            .unwrap();
        assert_eq!(raw.device_time_s, 0.002);
        assert_eq!(dev.recorded_torque(), Some([0.0; 3]));
        assert!(matches!(
            dev.exchange(&encode_command(&MotorCommand::safe(5))),
            Err(DeviceError::EndOfData)
        ));
    }

    #[test]
    fn duration_limit_counts_device_time() {
        let cfg = Config::default();
        let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
        for k in 0..50 {
            text += &format!("{},0,0,0,0,0,0\n", 10.0 + k as f64 * 0.01);
        }
        let f = write(&text);
        let mut dev = ReplayDevice::open(f.path(), &cfg.device, false, false, &Arc::default())
            .unwrap()
            .with_duration_limit(Some(0.1));
        let mut n = 0;
        while dev.exchange(&live(n as u8)).is_ok() {
            n += 1;
        }
        // 10.00 … 10.09 are within 0.1 s of the first row (100 Hz).
        assert_eq!(n, 10);
        let raw = dev
            .exchange(&encode_command(&MotorCommand::safe(0)))
            .unwrap();
        assert_eq!(raw.device_time_s, 10.0 + 10.0 * 0.01);
    }

    #[test]
    fn a_long_gap_between_rows_ends_on_stop_and_a_fifo_is_refused() {
        let cfg = Config::default();
        // The second row is 50 s after the first (the longest a log may pause is 60 s).
        let f = write("t,q1,q2,q3,tau1,tau2,tau3\n0,0,0,0,0,0,0\n50,0,0,0,0,0,0\n");
        let stop = Arc::new(AtomicBool::new(false));
        let mut dev = ReplayDevice::open(f.path(), &cfg.device, true, false, &stop).unwrap();
        dev.exchange(&live(1)).unwrap();
        let flag = stop.clone();
        let setter = std::thread::spawn(move || {
            std::thread::sleep(std::time::Duration::from_millis(100));
            flag.store(true, std::sync::atomic::Ordering::Relaxed);
        });
        let t0 = std::time::Instant::now();
        let raw = dev.exchange(&live(2)).unwrap();
        setter.join().unwrap();
        assert_eq!(raw.device_time_s, 50.0);
        assert!(t0.elapsed().as_secs_f64() < 2.0, "{:?}", t0.elapsed());

        // A set flag stops the validation pass.
        let e = ReplayDevice::open(f.path(), &cfg.device, false, false, &stop)
            .err()
            .unwrap();
        assert!(
            matches!(e, ReplayError::Read(ReadError::Stopped { .. })),
            "{e}"
        );

        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("fifo");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let e = ReplayDevice::open(&fifo, &cfg.device, true, false, &Arc::default())
            .err()
            .unwrap();
        assert!(
            matches!(e, ReplayError::NotRegular { .. }) && e.to_string().contains("FIFO"),
            "{e}"
        );
    }

    /// The loop ends a run on a stop itself; the device must not turn the stop into a read
    /// error (a device fault mid-run, or a final safe packet that cannot be answered).
    #[test]
    fn playback_reads_on_after_a_stop() {
        let cfg = Config::default();
        let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3\n");
        for k in 0..3000 {
            text += &format!("{},0,0,0,0.001,0,0\n", k as f64 * 1e-3);
        }
        let f = write(&text);
        let stop = Arc::new(AtomicBool::new(false));
        let mut dev = ReplayDevice::open(f.path(), &cfg.device, false, false, &stop).unwrap();
        dev.exchange(&live(0)).unwrap();
        stop.store(true, std::sync::atomic::Ordering::Relaxed);
        // Far past the reader's buffer: it refills from the file several times.
        for k in 1..3000 {
            dev.exchange(&live(k as u8)).unwrap();
        }
        let safe = encode_command(&MotorCommand::safe(1));
        assert_eq!(dev.exchange(&safe).unwrap().device_time_s, 2.999);
    }

    #[test]
    fn header_only_file_has_no_rows() {
        let f = write("t,q1,q2,q3,tau1,tau2,tau3\n");
        let e = ReplayDevice::open(
            f.path(),
            &DeviceConfig::default(),
            false,
            false,
            &Arc::default(),
        )
        .err()
        .unwrap();
        assert!(matches!(e, ReplayError::NoRows { .. }), "{e}");
    }
}

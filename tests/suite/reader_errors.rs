//! Malformed logs: every case is a typed error naming the file, the line and the column, never
//! a panic; `--lenient` skips and counts; random bytes never panic the reader.

use omnid::device::replay::{ReplayDevice, ReplayError};
use omnid::telemetry::reader::{LogReader, ReadError, MAX_ROW_BYTES};
use omnid::telemetry::record::Mode;
use proptest::prelude::*;
use std::io::Read;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

const HEADER: &str = "t,q1,q2,q3,tau1,tau2,tau3\n";

/// A file named after the case, so the message can be checked to name it.
fn file(dir: &tempfile::TempDir, name: &str, text: &str) -> PathBuf {
    let p = dir.path().join(name);
    std::fs::write(&p, text).unwrap();
    p
}

/// Read the whole file strictly; the error it fails with.
fn error_of(name: &str, text: &str) -> (ReadError, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = file(&dir, name, text);
    let result = LogReader::open(&path, false, None).and_then(|r| r.collect::<Result<Vec<_>, _>>());
    let e = result.expect_err("must be refused");
    let msg = e.to_string();
    assert!(msg.contains(name), "message does not name the file: {msg}");
    assert!(!msg.contains('\n'), "one line: {msg}");
    // The replay device refuses it with the same message, before anything runs.
    match ReplayDevice::open(&path, &Default::default(), false, false, &Arc::default()) {
        Err(ReplayError::Read(r)) => assert_eq!(r.to_string(), msg),
        Err(other) => panic!("replay: another error: {other}"),
        Ok(_) => panic!("replay accepted it"),
    }
    (e, msg)
}

fn assert_names(msg: &str, line: u64, column: &str) {
    assert!(
        msg.contains(&format!("line {line}:")),
        "no line {line}: {msg}"
    );
    assert!(
        msg.contains(&format!("`{column}`")),
        "no column {column}: {msg}"
    );
}

#[test]
fn missing_column() {
    let (e, msg) = error_of("missing.csv", "t,q1,q2,q3,tau1,tau3\n0,0,0,0,0,0\n");
    assert!(matches!(e, ReadError::MissingColumn { .. }));
    assert_names(&msg, 1, "tau2");
    assert!(!msg.contains("did you mean"), "{msg}");
}

#[test]
fn misnamed_column_suggests_the_closest() {
    let (e, msg) = error_of(
        "misnamed.csv",
        "t,q1,q2,q3,tau1,Tau_2,tau3\n0,0,0,0,0,0,0\n",
    );
    assert!(matches!(e, ReadError::MissingColumn { .. }));
    assert_names(&msg, 1, "tau2");
    assert!(msg.contains("did you mean `Tau_2`?"), "{msg}");
    let (_, msg) = error_of("time.csv", "time,q1,q2,q3,tau1,tau2,tau3\n0,0,0,0,0,0,0\n");
    assert!(
        msg.contains("`t`") && msg.contains("did you mean `time`?"),
        "{msg}"
    );
}

#[test]
fn duplicated_column() {
    let (e, msg) = error_of("dup.csv", "t,q1,q2,q3,tau1,tau2,tau3,q1\n0,0,0,0,0,0,0,0\n");
    assert!(matches!(e, ReadError::DuplicateColumn { .. }));
    assert_names(&msg, 1, "q1");
}

#[test]
fn non_numeric_value() {
    let text = format!("{HEADER}0,0,0,0,0,0,0\n0.001,0,abc,0,0,0,0\n");
    let (e, msg) = error_of("text.csv", &text);
    assert!(matches!(e, ReadError::NotANumber { line: 3, .. }));
    assert_names(&msg, 3, "q2");
    assert!(msg.contains("\"abc\""), "{msg}");
    let text = format!("{HEADER}0,0,0,0,0,,0\n");
    let (_, msg) = error_of("blank.csv", &text);
    assert_names(&msg, 2, "tau2");
}

#[test]
fn nan_and_infinite_values() {
    for (name, v) in [
        ("nan.csv", "NaN"),
        ("inf.csv", "inf"),
        ("ninf.csv", "-Infinity"),
        ("big.csv", "1e999"),
    ] {
        let text = format!("{HEADER}0,0,0,0,0,0,0\n0.001,0,0,0,{v},0,0\n");
        let (e, msg) = error_of(name, &text);
        assert!(matches!(e, ReadError::NotFinite { line: 3, .. }), "{msg}");
        assert_names(&msg, 3, "tau1");
    }
    let (_, msg) = error_of("nant.csv", &format!("{HEADER}nan,0,0,0,0,0,0\n"));
    assert_names(&msg, 2, "t");
}

#[test]
fn unknown_mode() {
    let text = "t,q1,q2,q3,tau1,tau2,tau3,mode\n0,0,0,0,0,0,0,blend\n0.001,0,0,0,0,0,0,pause\n";
    let (e, msg) = error_of("mode.csv", text);
    assert!(matches!(e, ReadError::UnknownMode { line: 3, .. }), "{msg}");
    assert_names(&msg, 3, "mode");
    assert!(msg.contains("`pause`") && msg.contains("servo_jp"), "{msg}");
}

#[test]
fn time_goes_backwards() {
    let text = format!("{HEADER}0,0,0,0,0,0,0\n0.002,0,0,0,0,0,0\n0.001,0,0,0,0,0,0\n");
    let (e, msg) = error_of("back.csv", &text);
    assert!(matches!(
        e,
        ReadError::TimeBackwards {
            line: 4,
            previous_line: 3,
            ..
        }
    ));
    assert_names(&msg, 4, "t");
    assert!(msg.contains("backwards"), "{msg}");
}

#[test]
fn time_repeats() {
    let text = format!("{HEADER}0,0,0,0,0,0,0\n0.001,0,0,0,0,0,0\n0.001,1,0,0,0,0,0\n");
    let (e, msg) = error_of("repeat.csv", &text);
    assert!(matches!(e, ReadError::TimeRepeats { line: 4, .. }));
    assert_names(&msg, 4, "t");
    assert!(msg.contains("repeats"), "{msg}");
}

#[test]
fn truncated_last_line() {
    let text = format!("{HEADER}0,0,0,0,0,0,0\n0.001,0,0,0,0,0,0\n0.002,0.1,0.2");
    let (e, msg) = error_of("cut.csv", &text);
    assert!(
        matches!(
            e,
            ReadError::Truncated {
                line: 4,
                got: 3,
                ..
            }
        ),
        "{msg}"
    );
    assert_names(&msg, 4, "q3");
    assert!(msg.contains("truncated"), "{msg}");
}

#[test]
fn short_row_in_the_middle() {
    let text = format!("{HEADER}0,0,0,0,0,0,0\n0.001,0,0,0,0\n0.002,0,0,0,0,0,0\n");
    let (e, msg) = error_of("short.csv", &text);
    assert!(
        matches!(
            e,
            ReadError::FieldCount {
                line: 3,
                got: 5,
                expected: 7,
                ..
            }
        ),
        "{msg}"
    );
    assert_names(&msg, 3, "tau2");
    let text = format!("{HEADER}0,0,0,0,0,0,0,9\n");
    let (_, msg) = error_of("long.csv", &text);
    assert_names(&msg, 2, "tau3");
}

#[test]
fn empty_file() {
    for (name, text) in [("empty.csv", ""), ("blank.csv", "\n\n")] {
        let (e, msg) = error_of(name, text);
        assert!(matches!(e, ReadError::Empty { .. }), "{msg}");
        assert!(msg.contains("line 1") && msg.contains("empty"), "{msg}");
        assert!(msg.contains("t, q1, q2, q3, tau1, tau2, tau3"), "{msg}");
    }
}

#[test]
fn header_only_file_has_nothing_to_replay() {
    let dir = tempfile::tempdir().unwrap();
    let path = file(&dir, "header.csv", HEADER);
    let e = ReplayDevice::open(&path, &Default::default(), false, false, &Arc::default())
        .err()
        .unwrap();
    assert!(matches!(e, ReplayError::NoRows { .. }));
    assert!(e.to_string().contains("header.csv"), "{e}");
}

#[test]
fn lenient_counts_skipped_rows_and_where() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3\n");
    let mut bad = Vec::new();
    for k in 0..200u64 {
        let t = k as f64 * 1e-3;
        let line = k + 2;
        if k % 25 == 7 {
            bad.push(line);
            text += &format!("{t},0,0,0,0,0,0,1.5,0,0\n"); // enc not an integer
        } else {
            text += &format!("{t},0,0,0,0,0,0,0,0,0\n");
        }
    }
    text += "0.3,0,0"; // and a cut-off last line
    bad.push(202);
    let path = file(&dir, "damaged.csv", &text);
    assert!(LogReader::open(&path, false, None)
        .unwrap()
        .collect::<Result<Vec<_>, _>>()
        .is_err());
    let dev = ReplayDevice::open(&path, &Default::default(), false, true, &Arc::default()).unwrap();
    let info = dev.info();
    assert_eq!(info.rows, 200 - 8);
    assert_eq!(info.skipped.count, 9);
    assert_eq!(info.skipped.first_lines, bad[..5]);
    let msg = info.skipped.to_string();
    assert!(
        msg.starts_with("skipped 9 bad rows (lines 9, 34, 59, 84, 109, …)"),
        "{msg}"
    );
    assert!(msg.contains("line 9") && msg.contains("`enc1`"), "{msg}");
}

#[test]
fn lenient_with_nothing_good_left_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = file(&dir, "junk.csv", &format!("{HEADER}a,b,c,d,e,f,g\nx\n"));
    let e = ReplayDevice::open(&path, &Default::default(), false, true, &Arc::default())
        .err()
        .unwrap();
    let msg = e.to_string();
    assert!(
        msg.contains("no data rows") && msg.contains("skipped 2 bad rows"),
        "{msg}"
    );
}

fn drain(bytes: &[u8], lenient: bool) {
    if let Ok(reader) = LogReader::new(bytes, "fuzz.csv", lenient) {
        let has_mode = reader.columns().mode.is_some();
        for row in reader {
            match row {
                Ok(r) => {
                    assert!(r.t.is_finite() && r.q.iter().all(|v| v.is_finite()));
                    assert_eq!(r.mode.is_some(), has_mode, "a row without its mode");
                }
                Err(e) => {
                    // Row faults are skipped in lenient mode, so any error ends the file.
                    let _ = e.to_string();
                    break;
                }
            }
        }
    }
}

proptest! {
    #[test]
    fn reader_never_panics_on_random_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..2048)) {
        drain(&bytes, false);
        drain(&bytes, true);
    }

    #[test]
    fn reader_never_panics_on_csv_like_text(
        body in "[0-9eE+\\-.,\\n\\r\" naNiIf]{0,600}",
        header in prop::sample::select(vec![
            "t,q1,q2,q3,tau1,tau2,tau3\n",
            "t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3,mode\n",
            "q1,t,tau3,q2,q3,tau1,tau2,x\n",
        ]),
    ) {
        let text = format!("{header}{body}");
        drain(text.as_bytes(), false);
        drain(text.as_bytes(), true);
    }
}

/// A mode as a log might hold it: one omnid writes (but `stop`, which must be last) or not.
fn mode_text() -> impl Strategy<Value = String> {
    let known: Vec<String> = Mode::ALL
        .iter()
        .filter(|m| **m != Mode::Stop)
        .map(|m| m.as_str().to_string())
        .collect();
    prop_oneof![
        3 => prop::sample::select(known),
        1 => "[A-Za-z_ -]{0,9}".prop_filter("not stop", |s| s.trim() != "stop"),
    ]
}

proptest! {
    /// Every row read carries the mode written in it; the first row whose mode omnid does not
    /// write is refused there (strict) or skipped and reported (lenient).
    #[test]
    fn modes_are_known_or_refused_where_they_are(modes in proptest::collection::vec(mode_text(), 1..40)) {
        let mut text = String::from("t,q1,q2,q3,tau1,tau2,tau3,mode\n");
        for (k, m) in modes.iter().enumerate() {
            text += &format!("{},0,0,0,0,0,0,{m}\n", k as f64 * 1e-3);
        }
        let known: Vec<Option<Mode>> = modes.iter().map(|m| Mode::parse(m.trim())).collect();
        let first_bad = known.iter().position(Option::is_none);
        let mut strict = LogReader::new(text.as_bytes(), "modes.csv", false).unwrap();
        for (k, expected) in known.iter().enumerate() {
            match (strict.next_row(), expected) {
                (Ok(Some(row)), Some(mode)) => prop_assert_eq!(row.mode, Some(*mode)),
                (Err(ReadError::UnknownMode { line, value, .. }), None) => {
                    prop_assert_eq!(line, k as u64 + 2);
                    prop_assert_eq!(value.as_str(), modes[k].trim());
                    break;
                }
                (other, _) => prop_assert!(false, "row {}: {:?}", k, other.map(|r| r.map(|r| r.mode))),
            }
        }
        let lenient: Vec<_> = LogReader::new(text.as_bytes(), "modes.csv", true)
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        let read: Vec<Option<Mode>> = lenient.iter().map(|r| r.mode).collect();
        let good: Vec<Option<Mode>> = known.iter().copied().filter(Option::is_some).collect();
        prop_assert_eq!(read, good);
        prop_assert_eq!(first_bad.is_none(), lenient.len() == modes.len());
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]
    #[test]
    fn replay_open_never_panics(body in "[0-9.,\\n-]{0,400}", lenient in any::<bool>()) {
        let dir = tempfile::tempdir().unwrap();
        let path = file(&dir, "fuzz.csv", &format!("{HEADER}{body}"));
        let _ = ReplayDevice::open(&path, &Default::default(), false, lenient, &Arc::default());
    }
}

/// `prefix`, then `fill` repeated for `len` bytes: a row that never ends, streamed (never held
/// in memory); counts the bytes the reader took.
struct Endless {
    prefix: Vec<u8>,
    fill: Vec<u8>,
    len: u64,
    at: u64,
    taken: Arc<AtomicU64>,
}

impl Endless {
    fn new(prefix: &str, fill: &str, len: u64) -> (Self, Arc<AtomicU64>) {
        let taken = Arc::new(AtomicU64::new(0));
        let e = Endless {
            prefix: prefix.as_bytes().to_vec(),
            fill: fill.as_bytes().to_vec(),
            len: prefix.len() as u64 + len,
            at: 0,
            taken: taken.clone(),
        };
        (e, taken)
    }
}

impl Read for Endless {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let mut n = 0;
        while n < buf.len() && self.at < self.len {
            let p = self.prefix.len() as u64;
            buf[n] = if self.at < p {
                self.prefix[self.at as usize]
            } else {
                self.fill[((self.at - p) % self.fill.len() as u64) as usize]
            };
            n += 1;
            self.at += 1;
        }
        self.taken.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

#[test]
fn a_long_row_under_the_limit_is_read() {
    let extra = "x".repeat(600_000);
    let text =
        format!("t,q1,q2,q3,tau1,tau2,tau3,note\n0,1,2,3,4,5,6,{extra}\n0.1,1,2,3,4,5,6,y\n");
    let rows: Vec<_> = LogReader::new(text.as_bytes(), "long.csv", false)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(rows.len(), 2);
}

#[test]
fn a_header_without_end_is_refused_on_line_1() {
    let (input, taken) = Endless::new("", "t,q1,", 3 * MAX_ROW_BYTES);
    let e = LogReader::new(input, "zeros.csv", false).err().unwrap();
    let msg = e.to_string();
    assert!(
        matches!(e, ReadError::RowTooLong { line: 1, limit, .. } if limit == MAX_ROW_BYTES),
        "{msg}"
    );
    assert!(
        msg.starts_with("zeros.csv: line 1: ") && msg.contains("1048576 bytes"),
        "{msg}"
    );
    assert!(taken.load(Ordering::Relaxed) <= MAX_ROW_BYTES + 65536);
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    /// A row with no end in sight — no line end at all, or a quote that is never closed over
    /// many short lines — is refused at the line where it starts, naming the limit, strict or
    /// lenient, after the reader took at most the limit and a chunk beyond the rows before it.
    #[test]
    fn an_endless_row_is_refused_where_it_starts(
        rows in 0usize..5,
        quoted in any::<bool>(),
        fill in "[0-9a-z,. ]{1,16}",
        beyond in 1u64..3_000_000,
        lenient in any::<bool>(),
    ) {
        let mut prefix = String::from(HEADER);
        for k in 0..rows {
            prefix += &format!("{k},0,0,0,0,0,0\n");
        }
        let fill = if quoted {
            prefix += "0,\"";
            format!("{fill}\n")
        } else {
            fill
        };
        let before = prefix.len() as u64;
        let (input, taken) = Endless::new(&prefix, &fill, MAX_ROW_BYTES + beyond);
        let mut reader = LogReader::new(input, "endless.csv", lenient).unwrap();
        for _ in 0..rows {
            prop_assert!(reader.next_row().unwrap().is_some());
        }
        match reader.next_row() {
            Err(ReadError::RowTooLong { line, limit, .. }) => {
                prop_assert_eq!(line, rows as u64 + 2);
                prop_assert_eq!(limit, MAX_ROW_BYTES);
            }
            other => prop_assert!(false, "{:?}", other.map(|r| r.map(|r| r.line))),
        }
        prop_assert!(taken.load(Ordering::Relaxed) <= before + MAX_ROW_BYTES + 65536);
    }
}

//! The CSV log reader on arbitrary bytes, strict and lenient, reading every row: never a panic,
//! every error names a line, every row it hands out is finite with strictly increasing time and
//! (when the file has a `mode` column) a mode omnid writes, and the strict reader's rows are a
//! prefix of the lenient reader's.
#![no_main]

use libfuzzer_sys::fuzz_target;
use omnid::telemetry::{LogReader, LogRow, ReadError};
use std::io::Cursor;

/// Bounded: a lenient reader that kept failing without moving on would spin here, not hang.
const MAX_CALLS: usize = 100_000;

fn read_all(data: &[u8], lenient: bool) -> (Vec<LogRow>, Option<ReadError>) {
    let mut rows = Vec::new();
    let mut r = match LogReader::new(Cursor::new(data), "fuzz.csv", lenient) {
        Ok(r) => r,
        Err(e) => return (rows, Some(e)),
    };
    let has_mode = r.columns().mode.is_some();
    for _ in 0..MAX_CALLS {
        match r.next_row() {
            Ok(Some(row)) => {
                assert_eq!(row.mode.is_some(), has_mode, "line {}: no mode", row.line);
                rows.push(row)
            }
            Ok(None) => return (rows, None),
            Err(e) => return (rows, Some(e)),
        }
    }
    panic!(
        "reader returned more than {MAX_CALLS} rows from {} bytes",
        data.len()
    );
}

fn check(rows: &[LogRow], err: &Option<ReadError>) {
    if let Some(e) = err {
        assert!(e.line().is_some(), "error without a line: {e}");
        let msg = e.to_string();
        assert!(
            msg.starts_with("fuzz.csv: "),
            "error without the file: {msg}"
        );
    }
    let mut prev: Option<&LogRow> = None;
    for row in rows {
        assert!(row.t.is_finite() && row.q.iter().chain(&row.tau).all(|v| v.is_finite()));
        if let Some(p) = prev {
            assert!(row.line > p.line);
            assert!(
                row.t > p.t || (row.is_stop() && row.t >= p.t),
                "time {} after {} (lines {}, {})",
                row.t,
                p.t,
                p.line,
                row.line
            );
            assert!(!p.is_stop(), "a row after the stop row");
        }
        prev = Some(row);
    }
}

fuzz_target!(|data: &[u8]| {
    let (strict, strict_err) = read_all(data, false);
    check(&strict, &strict_err);
    let (lenient, lenient_err) = read_all(data, true);
    check(&lenient, &lenient_err);
    assert!(
        lenient.len() >= strict.len() && lenient[..strict.len()] == strict[..],
        "strict rows are not a prefix of the lenient rows"
    );
    if strict_err.is_none() {
        assert_eq!(
            strict, lenient,
            "a file the strict reader accepts reads the same leniently"
        );
    }
});

//! Streaming CSV log reader: omnid's own log (docs/DESIGN.md §2.2) or any file with the seven
//! required columns `t, q1, q2, q3, tau1, tau2, tau3` (any order; extra columns ignored;
//! `enc1..3` and `mode` used when present).
//!
//! Two layers:
//! - `ColumnReader`: header → column indices, one reused `ByteRecord`, field-count, number and
//!   time-order checks, strict or lenient. Every problem is a [`ReadError`] naming the file, the
//!   line, the column (its 1-based index and its name) and the offending field. It is the
//!   crate's one CSV log reader: `convert`, `plot` (only `t` required, gaps allowed: see
//!   `Row::number_or_gap`) and `experiment` build on it with their own columns.
//! - [`LogReader`]: the replayable log on top of it, yielding one `Copy` [`LogRow`] per data row.
//!
//! Memory is constant: one record buffer, reused; a row allocates nothing (an error does). A
//! row may take at most [`MAX_ROW_BYTES`]: a file without line ends (`/dev/zero`, one 1 GB
//! line, an unclosed quote) is an error naming the line where that row starts, not a buffer as
//! big as the file. Files are opened through [`crate::input`]: a FIFO or pipe is read only with
//! the operator's stop flag, and every read ends on it ([`ReadError::Stopped`]).
//!
//! Rules (strict, the default):
//! - an empty file, a missing/misnamed/duplicated required column, a row with the wrong number
//!   of fields, a value that is not a number or not finite, a `t` that goes backwards or
//!   repeats: each an error.
//! - a last line cut mid-row (wrong field count, no trailing newline) is reported as truncated.
//!   A complete last line without a trailing newline is accepted (many editors write files so).
//! - `mode = stop` (omnid's final, safe packet) must be the last row; its `t` may equal the
//!   previous row's (the servo logs `max(device time, last t)` there). A `mode` that omnid does
//!   not write (see [`Mode::ALL`]; an empty field included) is an error naming the value.
//!
//! Lenient mode skips bad rows instead (header problems, a row past the size limit, a stop and
//! I/O errors still fail) and keeps a
//! [`SkipReport`]: how many and the first few line numbers. Time order is checked against the
//! last *accepted* row.

use super::mcap_log::read::{is_mcap, mcap_error, McapPrefetch, McapReadError};
use super::record::Mode;
pub use crate::input::MAX_ROW_BYTES;
use crate::input::{self, Input, RowBound};
use std::collections::VecDeque;
use std::fmt;
use std::io::{self, Read};
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use thiserror::Error;

/// The seven columns a replayable file must have.
pub(crate) use super::record::REQUIRED_COLUMNS;

/// How many skipped line numbers a [`SkipReport`] keeps.
pub const SKIP_LINES_KEPT: usize = 5;

/// Longest field text quoted in an error message.
const MAX_QUOTED: usize = 40;

/// A problem reading a log. Every variant names the file; row problems name the line (1 is the
/// header, as a text editor counts) and the column, by its 1-based index (as a spreadsheet
/// counts) and its header name.
#[derive(Debug, Error)]
pub enum ReadError {
    /// The file could not be opened or read.
    #[error("{path}: {source}")]
    Io {
        /// The file, as given.
        path: String,
        /// What the operating system said.
        source: io::Error,
    },
    /// An MCAP log that cannot be read (damaged, cut short, or not omnid's).
    #[error("{path}: {source}")]
    Mcap {
        /// The file, as given.
        path: String,
        /// What is wrong, and in which record.
        source: McapReadError,
    },
    /// The operator's stop flag ended the read.
    #[error("{path}: reading stopped by the operator")]
    Stopped {
        /// The file, as given.
        path: String,
    },
    /// One row is longer than [`MAX_ROW_BYTES`] (no line ends, or an unclosed quote).
    #[error(
        "{path}: line {line}: the row starting here runs past {limit} bytes, the most a row may \
         take (a file without line ends, or a quote that is never closed?)"
    )]
    RowTooLong {
        /// The file, as given.
        path: String,
        /// Where the row starts.
        line: u64,
        /// The limit, bytes.
        limit: u64,
    },
    /// No header row at all.
    #[error(
        "{path}: line 1: the file is empty: expected a header row with the columns {expected}"
    )]
    Empty {
        /// The file, as given.
        path: String,
        /// The required columns, comma-separated.
        expected: String,
    },
    /// A required column is not in the header.
    #[error("{path}: line 1: no `{column}` column (required{}); the header has: {header}",
            suggestion.as_ref().map(|s| format!("; did you mean `{s}`?")).unwrap_or_default())]
    MissingColumn {
        /// The file, as given.
        path: String,
        /// The column looked for.
        column: String,
        /// A header field that is probably that column under another name.
        suggestion: Option<String>,
        /// The header row as read, comma-separated.
        header: String,
    },
    /// A column the reader uses appears more than once in the header.
    #[error("{path}: line 1: column `{}` appears twice (fields {first} and {second})",
            crate::text::cut(.column))]
    DuplicateColumn {
        /// The file, as given.
        path: String,
        /// The repeated name.
        column: String,
        /// 1-based index of its first occurrence.
        first: usize,
        /// 1-based index of its second occurrence.
        second: usize,
    },
    /// A row has more or fewer fields than the header.
    #[error("{path}: line {line}: {got} fields, but the header has {expected} (column `{}` {})",
            crate::text::cut(.column), if got < expected { "is missing" } else { "is the last one" })]
    FieldCount {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The first missing column, or the last column when there are too many fields.
        column: String,
        /// Fields in the row.
        got: usize,
        /// Fields in the header.
        expected: usize,
    },
    /// The file ends mid-row, without a newline, before the row's last field.
    #[error(
        "{path}: line {line}: truncated last line: the file ends mid-row without a newline \
             after {got} of {expected} fields (column `{column}` is missing)"
    )]
    Truncated {
        /// The file, as given.
        path: String,
        /// The cut row's line.
        line: u64,
        /// The first missing column.
        column: String,
        /// Fields in the row.
        got: usize,
        /// Fields in the header.
        expected: usize,
    },
    /// A field that must be a number is not one.
    #[error("{path}: line {line}: column {index} (`{}`): {value:?} is not a number",
            crate::text::cut(.column))]
    NotANumber {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The column's header name.
        column: String,
        /// The column's 1-based index.
        index: usize,
        /// The field, as read (cut to a readable length).
        value: String,
    },
    /// A field that must be an integer (an encoder count) is not one.
    #[error("{path}: line {line}: column {index} (`{}`): {value:?} is not an integer",
            crate::text::cut(.column))]
    NotAnInteger {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The column's header name.
        column: String,
        /// The column's 1-based index.
        index: usize,
        /// The field, as read (cut to a readable length).
        value: String,
    },
    /// A number that must be finite is NaN or infinite.
    #[error("{path}: line {line}: column {index} (`{}`): {value:?} is not finite",
            crate::text::cut(.column))]
    NotFinite {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The column's header name.
        column: String,
        /// The column's 1-based index.
        index: usize,
        /// The field, as read (cut to a readable length).
        value: String,
    },
    /// The time column decreases.
    #[error(
        "{path}: line {line}: column {index} (`{column}`): time goes backwards: {t} after \
         {previous} (line {previous_line})"
    )]
    TimeBackwards {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The time column's header name.
        column: String,
        /// The time column's 1-based index.
        index: usize,
        /// This row's time, s.
        t: f64,
        /// The last accepted row's time, s.
        previous: f64,
        /// The last accepted row's line.
        previous_line: u64,
    },
    /// The time column repeats a value (allowed only for the final `stop` row).
    #[error(
        "{path}: line {line}: column {index} (`{column}`): time repeats: {t} again (line \
         {previous_line})"
    )]
    TimeRepeats {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The time column's header name.
        column: String,
        /// The time column's 1-based index.
        index: usize,
        /// The repeated time, s.
        t: f64,
        /// The line that had it first.
        previous_line: u64,
    },
    /// The time column jumps further than any device pauses.
    #[error(
        "{path}: line {line}: column {index} (`{column}`): time jumps {gap_s} s after line \
         {previous_line} (more than {max_s} s between two rows: no device pauses that long; \
         split the recording there)"
    )]
    TimeGap {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The time column's header name.
        column: String,
        /// The time column's 1-based index.
        index: usize,
        /// The jump, s (as written short: `1e12`).
        gap_s: String,
        /// The longest allowed, s.
        max_s: f64,
        /// The row before it.
        previous_line: u64,
    },
    /// A `mode` field that omnid never writes.
    #[error(
        "{path}: line {line}: column {index} (`{column}`): `{value}` is not a mode omnid writes \
             (allowed: {})", Mode::ALL.map(Mode::as_str).join(", ")
    )]
    UnknownMode {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The mode column's header name.
        column: String,
        /// The mode column's 1-based index.
        index: usize,
        /// The field, as read (cut to a readable length).
        value: String,
    },
    /// A row after the final `mode = stop` row.
    #[error(
        "{path}: line {line}: column {index} (`{column}`): a row after the final `stop` row \
         (line {stop_line}); a `mode = stop` row must be the last"
    )]
    AfterStop {
        /// The file, as given.
        path: String,
        /// The row's line.
        line: u64,
        /// The mode column's header name (the time column's when there is none).
        column: String,
        /// That column's 1-based index.
        index: usize,
        /// The `stop` row's line.
        stop_line: u64,
    },
    /// The CSV parser's own complaint (e.g. invalid quoting).
    #[error("{path}: line {line}: {message}")]
    Csv {
        /// The file, as given.
        path: String,
        /// Where the row starts.
        line: u64,
        /// The parser's description.
        message: String,
    },
    /// A header and no data row (for a reader that needs at least one).
    #[error("{path}: no data rows after the header")]
    NoRows {
        /// The file, as given.
        path: String,
    },
}

impl ReadError {
    /// The line the error is about (1 = the header).
    pub fn line(&self) -> Option<u64> {
        use ReadError::*;
        match self {
            Io { .. } | Mcap { .. } | Stopped { .. } | NoRows { .. } => None,
            Empty { .. } | MissingColumn { .. } | DuplicateColumn { .. } => Some(1),
            FieldCount { line, .. }
            | Truncated { line, .. }
            | NotANumber { line, .. }
            | NotAnInteger { line, .. }
            | NotFinite { line, .. }
            | TimeBackwards { line, .. }
            | TimeRepeats { line, .. }
            | TimeGap { line, .. }
            | UnknownMode { line, .. }
            | RowTooLong { line, .. }
            | AfterStop { line, .. }
            | Csv { line, .. } => Some(*line),
        }
    }
}

/// A problem with one data row, before it becomes a [`ReadError`] (`Copy`, so skipping a row in
/// lenient mode allocates nothing). Columns are field indices.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RowFault {
    /// The row has another number of fields than the header.
    FieldCount {
        /// Fields found.
        got: usize,
    },
    /// A field that should be a number is not.
    NotANumber {
        /// The field's index.
        col: usize,
    },
    /// A field that should be an integer is not.
    NotAnInteger {
        /// The field's index.
        col: usize,
    },
    /// A number is NaN or infinite.
    NotFinite {
        /// The field's index.
        col: usize,
    },
    /// The time went back.
    TimeBackwards {
        /// The time field's index.
        col: usize,
        /// This row's time, s.
        t: f64,
        /// The previous row's time, s.
        previous: f64,
        /// The previous row's line.
        previous_line: u64,
    },
    /// The time did not move.
    TimeRepeats {
        /// The time field's index.
        col: usize,
        /// This row's time, s.
        t: f64,
        /// The previous row's line.
        previous_line: u64,
    },
    /// The time jumped ahead more than a log allows.
    TimeGap {
        /// The time field's index.
        col: usize,
        /// The jump, s.
        gap: f64,
        /// The previous row's line.
        previous_line: u64,
    },
    /// The mode is none omnid writes.
    UnknownMode {
        /// The mode field's index.
        col: usize,
    },
    /// A row after the row that ended the run.
    AfterStop {
        /// The field's index.
        col: usize,
        /// The line of the row that ended the run.
        stop_line: u64,
    },
}

/// Rows skipped in lenient mode.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SkipReport {
    /// How many rows were skipped.
    pub count: u64,
    /// Line numbers of the first [`SKIP_LINES_KEPT`] skipped rows.
    pub first_lines: Vec<u64>,
    /// Why the first one was skipped.
    pub first_reason: Option<String>,
}

impl fmt::Display for SkipReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.count == 0 {
            return write!(f, "no rows skipped");
        }
        let lines: Vec<String> = self.first_lines.iter().map(|l| l.to_string()).collect();
        write!(
            f,
            "skipped {} bad row{} (line{} {}{})",
            self.count,
            if self.count == 1 { "" } else { "s" },
            if self.count == 1 { "" } else { "s" },
            lines.join(", "),
            if self.count > self.first_lines.len() as u64 {
                ", …"
            } else {
                ""
            }
        )?;
        if let Some(r) = &self.first_reason {
            write!(f, "; first: {r}")?;
        }
        Ok(())
    }
}

/// Counts bytes and remembers the last one, so a row cut off at the end of the file can be told
/// from one with a wrong field count. Also notes what the CSV parser's line numbers miss: it
/// ends a row at a lone `\r` too but counts only `\n`s, and a row after a `\r\n` starts, for
/// it, at the `\n`, before that line is counted.
struct Tail<R> {
    inner: RowBound<R>,
    total: u64,
    last: Option<u8>,
    eof: bool,
    /// Byte offsets of lone `\r`s not yet passed by a row (empty, never allocated, in a file
    /// without them).
    lone_cr: VecDeque<u64>,
    /// A `\r` that ended the last chunk: lone unless the next chunk starts with `\n`.
    pending_cr: Option<u64>,
    /// Byte offsets of the `\n`s of `\r\n`s not yet passed by a row (empty in a `\n` file).
    crlf_lf: VecDeque<u64>,
}

impl<R> Tail<R> {
    fn new(inner: R) -> Self {
        Tail {
            inner: RowBound::new(inner),
            total: 0,
            last: None,
            eof: false,
            lone_cr: VecDeque::new(),
            pending_cr: None,
            crlf_lf: VecDeque::new(),
        }
    }
}

impl<R: Read> Read for Tail<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        let n = self.inner.read(buf)?;
        let base = self.total;
        if let Some(at) = self.pending_cr.take() {
            if n > 0 && buf[0] == b'\n' {
                self.crlf_lf.push_back(base);
            } else {
                self.lone_cr.push_back(at);
            }
        }
        if n == 0 {
            self.eof = true;
        } else {
            self.total += n as u64;
            self.last = Some(buf[n - 1]);
            for (i, _) in buf[..n].iter().enumerate().filter(|(_, &b)| b == b'\r') {
                match buf[..n].get(i + 1) {
                    Some(b'\n') => self.crlf_lf.push_back(base + i as u64 + 1),
                    Some(_) => self.lone_cr.push_back(base + i as u64),
                    None => self.pending_cr = Some(base + i as u64),
                }
            }
        }
        Ok(n)
    }
}

/// One data row, borrowed from the reader's buffer.
pub struct Row<'a> {
    record: &'a csv::ByteRecord,
    /// Line number in the file (1 = the header).
    pub line: u64,
    /// The time column's value (already parsed and finite).
    pub t: f64,
    time_col: usize,
    previous: Option<(f64, u64)>,
}

impl Row<'_> {
    /// The field's bytes, ASCII whitespace trimmed.
    pub fn field(&self, col: usize) -> &[u8] {
        self.record.get(col).unwrap_or(b"").trim_ascii()
    }

    /// A finite number.
    pub fn f64(&self, col: usize) -> Result<f64, RowFault> {
        parse_f64(self.field(col), col)
    }

    /// A number, or NaN for an empty field (a gap, as other tools write a missing value). NaN
    /// and infinities written out are accepted too: for a reader that only draws the values
    /// (plot), where a wild value is no reason to refuse the file.
    pub fn number_or_gap(&self, col: usize) -> Result<f64, RowFault> {
        let b = self.field(col);
        if b.is_empty() {
            return Ok(f64::NAN);
        }
        std::str::from_utf8(b)
            .ok()
            .and_then(|s| s.trim().parse::<f64>().ok())
            .ok_or(RowFault::NotANumber { col })
    }

    /// Where the row starts in the file, bytes (for a progress bar).
    pub fn byte(&self) -> u64 {
        self.record.position().map_or(0, |p| p.byte())
    }

    /// An integer (also written as an integral float, e.g. `1234.0`).
    pub fn i64(&self, col: usize) -> Result<i64, RowFault> {
        let b = self.field(col);
        let s = std::str::from_utf8(b).map_err(|_| RowFault::NotAnInteger { col })?;
        if let Ok(v) = s.parse::<i64>() {
            return Ok(v);
        }
        match s.parse::<f64>() {
            Ok(v) if v.is_finite() && v.fract() == 0.0 && v.abs() < 9.007_199_254_740_992e15 => {
                Ok(v as i64)
            }
            _ => Err(RowFault::NotAnInteger { col }),
        }
    }

    /// The checks every reader makes of every row, whatever it reads from it (replay,
    /// identify, convert, plot alike): a `mode` omnid writes; `t` later than the row before
    /// (the same only on the final `stop` row) and not further on than [`MAX_GAP_S`]; `flags`
    /// an integer.
    pub(crate) fn check_common(
        &self,
        mode_col: Option<usize>,
        flags_col: Option<usize>,
    ) -> Result<(), RowFault> {
        let stop = match mode_col {
            Some(m) => {
                let mode = std::str::from_utf8(self.field(m))
                    .ok()
                    .and_then(Mode::parse);
                match mode {
                    Some(mode) => mode == Mode::Stop,
                    // Empty included: omnid writes a mode on every row.
                    None => return Err(RowFault::UnknownMode { col: m }),
                }
            }
            None => false,
        };
        self.check_time(stop)?;
        if let Some((previous, previous_line)) = self.previous {
            let gap = self.t - previous;
            if gap > MAX_GAP_S {
                return Err(RowFault::TimeGap {
                    col: self.time_col,
                    gap,
                    previous_line,
                });
            }
        }
        if let Some(f) = flags_col {
            if !self.field(f).is_empty() {
                self.i64(f)?;
            }
        }
        Ok(())
    }

    /// `t` must be later than the last accepted row's (`allow_equal`: or the same).
    pub fn check_time(&self, allow_equal: bool) -> Result<(), RowFault> {
        let Some((previous, previous_line)) = self.previous else {
            return Ok(());
        };
        if self.t < previous {
            Err(RowFault::TimeBackwards {
                col: self.time_col,
                t: self.t,
                previous,
                previous_line,
            })
        } else if self.t == previous && !allow_equal {
            Err(RowFault::TimeRepeats {
                col: self.time_col,
                t: self.t,
                previous_line,
            })
        } else {
            Ok(())
        }
    }
}

fn parse_f64(b: &[u8], col: usize) -> Result<f64, RowFault> {
    let s = std::str::from_utf8(b).map_err(|_| RowFault::NotANumber { col })?;
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(RowFault::NotFinite { col }),
        Err(_) => Err(RowFault::NotANumber { col }),
    }
}

/// Quote a field for a message: lossy UTF-8, cut to a sane length.
pub(crate) fn quote(b: &[u8]) -> String {
    let s = String::from_utf8_lossy(b);
    let mut out: String = s.chars().take(MAX_QUOTED).collect();
    if s.chars().count() > MAX_QUOTED {
        out.push('…');
    }
    out
}

/// Normalised header name for suggestions: lowercase, without `_ - . [ ] ( )` and spaces.
fn normalise(s: &str) -> String {
    s.chars()
        .filter(|c| !"_-.[]() ".contains(*c))
        .flat_map(char::to_lowercase)
        .collect()
}

fn edit_distance(a: &str, b: &str) -> usize {
    let (a, b): (Vec<char>, Vec<char>) = (a.chars().collect(), b.chars().collect());
    let mut prev: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.iter().enumerate() {
        let mut cur = vec![i + 1; b.len() + 1];
        for (j, cb) in b.iter().enumerate() {
            cur[j + 1] = (prev[j] + usize::from(ca != cb))
                .min(prev[j + 1] + 1)
                .min(cur[j] + 1);
        }
        prev = cur;
    }
    prev[b.len()]
}

/// Names other tools use for the required columns.
fn aliases(column: &str) -> &'static [&'static str] {
    match column {
        "t" => &[
            "time",
            "times",
            "timestamp",
            "stamp",
            "time_s",
            "t_s",
            "sec",
            "seconds",
        ],
        "q1" => &["j1", "joint1", "theta1", "angle1", "pos1", "position1"],
        "q2" => &["j2", "joint2", "theta2", "angle2", "pos2", "position2"],
        "q3" => &["j3", "joint3", "theta3", "angle3", "pos3", "position3"],
        "tau1" => &["torque1", "effort1", "u1", "tau_1"],
        "tau2" => &["torque2", "effort2", "u2", "tau_2"],
        "tau3" => &["torque3", "effort3", "u3", "tau_3"],
        _ => &[],
    }
}

/// The header field most likely meant for `column`, among those no other column claims.
fn suggest(column: &str, candidates: &[&str]) -> Option<String> {
    let want = normalise(column);
    let mut best: Option<(usize, &str)> = None;
    for &h in candidates {
        if h.len() > 64 {
            continue;
        }
        let n = normalise(h);
        let d = if n == want || aliases(column).iter().any(|a| normalise(a) == n) {
            0
        } else {
            edit_distance(&n, &want)
        };
        let limit = if want.len() <= 2 { 1 } else { 2 };
        if d <= limit && best.is_none_or(|(bd, _)| d < bd) {
            best = Some((d, h));
        }
    }
    best.map(|(_, h)| h.to_string())
}

/// Header names omnid writes itself: never offered as a suggestion for another column.
fn is_known_log_column(name: &str) -> bool {
    if matches!(name, "t" | "amps" | "mode" | "flags" | "fault") {
        return true;
    }
    let groups = [
        "q",
        "tau",
        "qf",
        "qd",
        "qdd",
        "ref",
        "tau_cmd",
        "tau_model",
        "tau_hat",
        "enc",
    ];
    groups.iter().any(|g| {
        name.strip_prefix(g)
            .is_some_and(|rest| matches!(rest, "1" | "2" | "3"))
    })
}

/// The longest time between two rows a log may have, s. A device sends every millisecond and
/// faults after 20 missed packets; a replay paced at the log's own time would sit silent through
/// a longer pause (a time of 1e12 s: forever).
pub const MAX_GAP_S: f64 = 60.0;

/// The CSV layer: named columns, one reused record, strict or lenient row checks.
pub struct ColumnReader<R: Read> {
    csv: csv::Reader<Tail<R>>,
    path: String,
    header: Vec<String>,
    record: csv::ByteRecord,
    time_col: usize,
    /// `mode` and `flags`, where the log has them: every reader checks them alike.
    mode_col: Option<usize>,
    flags_col: Option<usize>,
    lenient: bool,
    last: Option<(f64, u64)>,
    /// Lone `\r` line ends before the current row (see [`Tail`]).
    cr_lines: u64,
    /// The parser's line of the next row's start (its position moves on while a row is read).
    next_line: u64,
    skipped: SkipReport,
}

/// A log file as the CSV layer reads it: a CSV file as it is, an omnid MCAP log (known by its
/// first bytes) as the CSV text of the same rows ([`McapPrefetch`]), so every reader and check
/// serves both formats.
pub enum LogInput {
    /// A CSV file (or any text).
    Csv(Sniffed),
    /// An MCAP log, decoded on a thread of its own.
    Mcap(McapPrefetch),
}

impl LogInput {
    /// Open `path` (as [`crate::input::open`]) and look at its first bytes.
    pub fn open(
        path: &Path,
        lenient: bool,
        stop: Option<&Arc<AtomicBool>>,
    ) -> io::Result<LogInput> {
        let mut file = Sniffed {
            head: [0; 8],
            len: 0,
            at: 0,
            inner: input::open(path, stop)?,
        };
        while file.len < file.head.len() {
            match file.inner.read(&mut file.head[file.len..]) {
                Ok(0) => break,
                Ok(n) => file.len += n,
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) => return Err(e),
            }
        }
        Ok(if is_mcap(&file.head[..file.len]) {
            LogInput::Mcap(McapPrefetch::new(file, lenient)?)
        } else {
            LogInput::Csv(file)
        })
    }
}

impl Read for LogInput {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        match self {
            LogInput::Csv(f) => f.read(buf),
            LogInput::Mcap(m) => m.read(buf),
        }
    }
}

/// An input whose first bytes were read to tell its format, and are read again first.
pub struct Sniffed {
    head: [u8; 8],
    len: usize,
    at: usize,
    inner: Input,
}

impl Read for Sniffed {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.at < self.len {
            let n = buf.len().min(self.len - self.at);
            buf[..n].copy_from_slice(&self.head[self.at..self.at + n]);
            self.at += n;
            return Ok(n);
        }
        self.inner.read(buf)
    }
}

impl ColumnReader<LogInput> {
    /// Open a file (CSV or MCAP); `required` columns must all be present (the first is the
    /// time column). `stop`: the operator's stop flag, which ends any read (without one, only
    /// a regular file is accepted: see [`crate::input::open`]).
    pub fn open(
        path: &Path,
        required: &[&str],
        lenient: bool,
        stop: Option<&Arc<AtomicBool>>,
    ) -> Result<Self, ReadError> {
        let name = path.display().to_string();
        let file = LogInput::open(path, lenient, stop).map_err(|source| io_error(source, &name))?;
        Self::new(file, &name, required, lenient)
    }
}

impl<R: Read> ColumnReader<R> {
    /// Read the header from `input`; `path` names the source in messages; the first of
    /// `required` is the time column, which must increase from row to row.
    pub fn new(input: R, path: &str, required: &[&str], lenient: bool) -> Result<Self, ReadError> {
        assert!(!required.is_empty(), "a time column is required");
        let mut csv = csv::ReaderBuilder::new()
            .has_headers(false)
            .flexible(true)
            .from_reader(Tail::new(input));
        let mut record = csv::ByteRecord::new();
        let io_err = |e: csv::Error, path: &str| csv_error(e, path, 1);
        let expected = required.join(", ");
        if !csv
            .read_byte_record(&mut record)
            .map_err(|e| io_err(e, path))?
        {
            return Err(ReadError::Empty {
                path: path.to_string(),
                expected,
            });
        }
        let first_row = csv.position().clone();
        csv.get_mut().inner.row_starts_at(first_row.byte());
        let mut header: Vec<String> = record
            .iter()
            .map(|f| String::from_utf8_lossy(f.trim_ascii()).into_owned())
            .collect();
        if let Some(first) = header.first_mut() {
            if let Some(rest) = first.strip_prefix('\u{feff}') {
                *first = rest.trim().to_string();
            }
        }
        if header.len() == 1 && header[0].is_empty() {
            return Err(ReadError::Empty {
                path: path.to_string(),
                expected,
            });
        }
        let mut reader = ColumnReader {
            csv,
            path: path.to_string(),
            header,
            record,
            time_col: 0,
            lenient,
            mode_col: None,
            flags_col: None,
            last: None,
            cr_lines: 0,
            next_line: first_row.line(),
            skipped: SkipReport {
                first_lines: Vec::with_capacity(SKIP_LINES_KEPT),
                ..SkipReport::default()
            },
        };
        for c in required {
            reader.require(c, required)?;
        }
        reader.time_col = reader.require(required[0], required)?;
        reader.mode_col = reader.optional("mode")?;
        reader.flags_col = reader.optional("flags")?;
        Ok(reader)
    }

    /// The index of a column that must be present (`family`: the set it belongs to, never
    /// suggested for it).
    pub fn require(&self, column: &str, family: &[&str]) -> Result<usize, ReadError> {
        let mut found = self.header.iter().enumerate().filter(|(_, h)| *h == column);
        match (found.next(), found.next()) {
            (Some((first, _)), None) => Ok(first),
            (Some((first, _)), Some((second, _))) => Err(ReadError::DuplicateColumn {
                path: self.path.clone(),
                column: column.to_string(),
                first: first + 1,
                second: second + 1,
            }),
            (None, _) => {
                let candidates: Vec<&str> = self
                    .header
                    .iter()
                    .map(String::as_str)
                    .filter(|h| !family.contains(h) && !is_known_log_column(h))
                    .collect();
                Err(ReadError::MissingColumn {
                    path: self.path.clone(),
                    column: column.to_string(),
                    suggestion: suggest(column, &candidates),
                    header: self.header.join(","),
                })
            }
        }
    }

    /// The index of an optional column (a duplicate is an error).
    pub fn optional(&self, column: &str) -> Result<Option<usize>, ReadError> {
        if self.header.iter().any(|h| h == column) {
            self.require(column, &[]).map(Some)
        } else {
            Ok(None)
        }
    }

    /// The header's column names, in file order (whitespace and a BOM trimmed).
    pub fn header(&self) -> &[String] {
        &self.header
    }

    /// The file, as named in messages.
    pub fn path(&self) -> &str {
        &self.path
    }

    /// Rows skipped so far (lenient mode).
    pub fn skipped(&self) -> &SkipReport {
        &self.skipped
    }

    /// The next good row, turned into `T` by `parse`; `None` at the end of the file. In lenient
    /// mode bad rows are skipped and counted; in strict mode the first one is the error.
    pub fn next_with<T>(
        &mut self,
        mut parse: impl FnMut(&Row<'_>) -> Result<T, RowFault>,
    ) -> Result<Option<T>, ReadError> {
        loop {
            let more = self
                .csv
                .read_byte_record(&mut self.record)
                .map_err(|e| csv_error(e, &self.path, self.next_line + self.cr_lines))?;
            if !more {
                return Ok(None);
            }
            let next_row = self.csv.position().clone();
            self.next_line = next_row.line();
            self.csv.get_mut().inner.row_starts_at(next_row.byte());
            let line = self.line_of_record();
            let result = if self.record.len() != self.header.len() {
                Err(RowFault::FieldCount {
                    got: self.record.len(),
                })
            } else {
                parse_f64(
                    self.record.get(self.time_col).unwrap_or(b"").trim_ascii(),
                    self.time_col,
                )
                .and_then(|t| {
                    let row = Row {
                        record: &self.record,
                        line,
                        t,
                        time_col: self.time_col,
                        previous: self.last,
                    };
                    row.check_common(self.mode_col, self.flags_col)?;
                    parse(&row).map(|v| (v, t))
                })
            };
            match result {
                Ok((value, t)) => {
                    self.last = Some((t, line));
                    return Ok(Some(value));
                }
                Err(fault) if self.lenient => {
                    self.skipped.count += 1;
                    if self.skipped.first_lines.len() < SKIP_LINES_KEPT {
                        self.skipped.first_lines.push(line);
                    }
                    if self.skipped.first_reason.is_none() {
                        self.skipped.first_reason = Some(self.error(fault, line).to_string());
                    }
                }
                Err(fault) => return Err(self.error(fault, line)),
            }
        }
    }

    /// The line the record just read starts on: the parser's count of `\n`s plus the lone `\r`s
    /// before it (a file with `\r` line ends would otherwise put every row on line 1), plus one
    /// when the parser puts its start on the `\n` of a `\r\n` (every row of a `\r\n` file would
    /// otherwise be numbered one line early).
    fn line_of_record(&mut self) -> u64 {
        let Some(pos) = self.record.position() else {
            return 0;
        };
        let tail = self.csv.get_mut();
        while tail.lone_cr.front().is_some_and(|&at| at < pos.byte()) {
            tail.lone_cr.pop_front();
            self.cr_lines += 1;
        }
        while tail.crlf_lf.front().is_some_and(|&at| at < pos.byte()) {
            tail.crlf_lf.pop_front();
        }
        let at_lf = tail.crlf_lf.front() == Some(&pos.byte());
        pos.line() + self.cr_lines + u64::from(at_lf)
    }

    /// The record just read was the file's last and it ends without a newline.
    fn is_truncated_tail(&self, fault: RowFault) -> bool {
        let tail = self.csv.get_ref();
        matches!(fault, RowFault::FieldCount { got } if got < self.header.len())
            && tail.eof
            && !matches!(tail.last, Some(b'\n') | Some(b'\r'))
            && self.csv.position().byte() == tail.total
    }

    fn column_name(&self, col: usize) -> String {
        self.header.get(col).cloned().unwrap_or_default()
    }

    /// A row with `got` fields, not the header's count: cut off at the end of the file
    /// ([`ReadError::Truncated`]) or simply short or long ([`ReadError::FieldCount`]).
    fn field_count_error(&self, got: usize, line: u64) -> ReadError {
        let path = self.path.clone();
        let expected = self.header.len();
        let column = if got < expected {
            self.column_name(got)
        } else {
            self.column_name(expected - 1)
        };
        if self.is_truncated_tail(RowFault::FieldCount { got }) {
            ReadError::Truncated {
                path,
                line,
                column,
                got,
                expected,
            }
        } else {
            ReadError::FieldCount {
                path,
                line,
                column,
                got,
                expected,
            }
        }
    }

    /// Turn a row fault into the full error (the record is still in the buffer).
    fn error(&self, fault: RowFault, line: u64) -> ReadError {
        let path = self.path.clone();
        let value = |col: usize| quote(self.record.get(col).unwrap_or(b"").trim_ascii());
        match fault {
            RowFault::FieldCount { got } => self.field_count_error(got, line),
            RowFault::NotANumber { col } => ReadError::NotANumber {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                value: value(col),
            },
            RowFault::NotAnInteger { col } => ReadError::NotAnInteger {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                value: value(col),
            },
            RowFault::NotFinite { col } => ReadError::NotFinite {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                value: value(col),
            },
            RowFault::TimeBackwards {
                col,
                t,
                previous,
                previous_line,
            } => ReadError::TimeBackwards {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                t,
                previous,
                previous_line,
            },
            RowFault::TimeRepeats {
                col,
                t,
                previous_line,
            } => ReadError::TimeRepeats {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                t,
                previous_line,
            },
            RowFault::TimeGap {
                col,
                gap,
                previous_line,
            } => ReadError::TimeGap {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                gap_s: crate::text::number(&gap.to_string()),
                max_s: MAX_GAP_S,
                previous_line,
            },
            RowFault::UnknownMode { col } => ReadError::UnknownMode {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                value: value(col),
            },
            RowFault::AfterStop { col, stop_line } => ReadError::AfterStop {
                path,
                line,
                column: self.column_name(col),
                index: col + 1,
                stop_line,
            },
        }
    }
}

/// An I/O error as a [`ReadError`]: a stop, or the error itself.
fn io_error(source: io::Error, path: &str) -> ReadError {
    if input::is_stopped(&source) {
        ReadError::Stopped {
            path: path.to_string(),
        }
    } else if mcap_error(&source).is_some() {
        let source = source
            .into_inner()
            .and_then(|e| e.downcast::<McapReadError>().ok())
            .map(|e| *e)
            .expect("checked above");
        ReadError::Mcap {
            path: path.to_string(),
            source,
        }
    } else {
        ReadError::Io {
            path: path.to_string(),
            source,
        }
    }
}

/// `line`: where the row being read starts.
fn csv_error(e: csv::Error, path: &str, line: u64) -> ReadError {
    let line = e.position().map(|p| p.line()).unwrap_or(line);
    match e.into_kind() {
        csv::ErrorKind::Io(source) => match input::row_too_long(&source) {
            Some(limit) => ReadError::RowTooLong {
                path: path.to_string(),
                line,
                limit,
            },
            None => io_error(source, path),
        },
        other => ReadError::Csv {
            path: path.to_string(),
            line,
            message: format!("{other:?}"),
        },
    }
}

/// One data row of a replayable log.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LogRow {
    /// Line number in the file (1 = the header).
    pub line: u64,
    /// Device time, s.
    pub t: f64,
    /// Measured joint angles, rad.
    pub q: [f64; 3],
    /// Applied torque, N·m.
    pub tau: [f64; 3],
    /// Continuous encoder counts, when the file has `enc1..3`.
    pub enc: Option<[i64; 3]>,
    /// The `mode` column, when the file has one.
    pub mode: Option<Mode>,
    /// The stylus buttons pressed (`button1`, `button2`; not pressed when the file has no
    /// such columns).
    pub buttons: [bool; 2],
    /// The stylus in its inkwell (`inkwell`; not when the file has no such column).
    pub inkwell: bool,
}

impl LogRow {
    /// `mode = stop`: omnid's final, safe packet (zero torque, amplifiers off).
    pub fn is_stop(&self) -> bool {
        self.mode == Some(Mode::Stop)
    }
}

/// Where the columns of a replayable log are: 0-based field indices.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LogColumns {
    /// `t`.
    pub t: usize,
    /// `q1..3`.
    pub q: [usize; 3],
    /// `tau1..3`.
    pub tau: [usize; 3],
    /// `enc1..3`, when the log has them.
    pub enc: Option<[usize; 3]>,
    /// `mode`, when the log has it.
    pub mode: Option<usize>,
    /// `button1`, `button2` and `inkwell`, when the log has them.
    pub stylus: Option<[usize; 3]>,
}

/// Streaming reader of a replayable log.
pub struct LogReader<R: Read = LogInput> {
    core: ColumnReader<R>,
    cols: LogColumns,
    stop_line: Option<u64>,
}

impl LogReader<LogInput> {
    /// Open a log file. `stop`: the operator's stop flag, which ends any read (without one,
    /// only a regular file is accepted: see [`crate::input::open`]).
    pub fn open(
        path: &Path,
        lenient: bool,
        stop: Option<&Arc<AtomicBool>>,
    ) -> Result<Self, ReadError> {
        Self::with_core(ColumnReader::open(path, &REQUIRED_COLUMNS, lenient, stop)?)
    }
}

impl<R: Read> LogReader<R> {
    /// Read from any byte stream; `path` names it in messages.
    pub fn new(input: R, path: &str, lenient: bool) -> Result<Self, ReadError> {
        Self::with_core(ColumnReader::new(input, path, &REQUIRED_COLUMNS, lenient)?)
    }

    fn with_core(core: ColumnReader<R>) -> Result<Self, ReadError> {
        let req = |name: &str| core.require(name, &REQUIRED_COLUMNS);
        let t = req("t")?;
        let q = [req("q1")?, req("q2")?, req("q3")?];
        let tau = [req("tau1")?, req("tau2")?, req("tau3")?];
        const ENC: [&str; 3] = ["enc1", "enc2", "enc3"];
        let enc = if ENC.iter().any(|c| core.header().iter().any(|h| h == c)) {
            // A partial set is a broken header, not an absent one.
            Some([
                core.require(ENC[0], &ENC)?,
                core.require(ENC[1], &ENC)?,
                core.require(ENC[2], &ENC)?,
            ])
        } else {
            None
        };
        let mode = core.optional("mode")?;
        const STYLUS: [&str; 3] = super::record::STYLUS_COLUMNS;
        let stylus = if STYLUS.iter().any(|c| core.header().iter().any(|h| h == c)) {
            Some([
                core.require(STYLUS[0], &STYLUS)?,
                core.require(STYLUS[1], &STYLUS)?,
                core.require(STYLUS[2], &STYLUS)?,
            ])
        } else {
            None
        };
        Ok(LogReader {
            core,
            cols: LogColumns {
                t,
                q,
                tau,
                enc,
                mode,
                stylus,
            },
            stop_line: None,
        })
    }

    /// Where the log's columns are.
    pub fn columns(&self) -> &LogColumns {
        &self.cols
    }

    /// The file, as named in messages.
    pub fn path(&self) -> &str {
        self.core.path()
    }

    /// Rows skipped so far (lenient mode).
    pub fn skipped(&self) -> &SkipReport {
        self.core.skipped()
    }

    /// The next good row, `None` at the end. Allocates nothing unless it fails (or, in lenient
    /// mode, on the first skipped row).
    pub fn next_row(&mut self) -> Result<Option<LogRow>, ReadError> {
        let cols = self.cols;
        let stop_line = self.stop_line;
        let row = self.core.next_with(|r| {
            if let Some(stop_line) = stop_line {
                return Err(RowFault::AfterStop {
                    col: cols.mode.unwrap_or(cols.t),
                    stop_line,
                });
            }
            let mode = match cols.mode {
                Some(m) => Some(
                    std::str::from_utf8(r.field(m))
                        .ok()
                        .and_then(Mode::parse)
                        .ok_or(RowFault::UnknownMode { col: m })?,
                ),
                None => None,
            };
            let mut q = [0.0; 3];
            let mut tau = [0.0; 3];
            for j in 0..3 {
                q[j] = r.f64(cols.q[j])?;
            }
            for j in 0..3 {
                tau[j] = r.f64(cols.tau[j])?;
            }
            let enc = match cols.enc {
                Some(e) => Some([r.i64(e[0])?, r.i64(e[1])?, r.i64(e[2])?]),
                None => None,
            };
            let (buttons, inkwell) = match cols.stylus {
                Some(s) => ([r.i64(s[0])? != 0, r.i64(s[1])? != 0], r.i64(s[2])? != 0),
                None => ([false; 2], false),
            };
            Ok(LogRow {
                line: r.line,
                t: r.t,
                q,
                tau,
                enc,
                mode,
                buttons,
                inkwell,
            })
        })?;
        if let Some(r) = &row {
            if r.is_stop() {
                self.stop_line = Some(r.line);
            }
        }
        Ok(row)
    }
}

impl<R: Read> Iterator for LogReader<R> {
    type Item = Result<LogRow, ReadError>;
    fn next(&mut self) -> Option<Self::Item> {
        self.next_row().transpose()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read_all(text: &str, lenient: bool) -> Result<(Vec<LogRow>, SkipReport), ReadError> {
        let mut r = LogReader::new(text.as_bytes(), "mem.csv", lenient)?;
        let mut rows = Vec::new();
        while let Some(row) = r.next_row()? {
            rows.push(row);
        }
        Ok((rows, r.skipped().clone()))
    }

    const H: &str = "t,q1,q2,q3,tau1,tau2,tau3\n";

    #[test]
    fn reads_the_seven_columns_in_any_order_with_extras() {
        let text = "extra,tau3,q2,t,q1,tau1,q3,tau2\nx,6,2,0.5,1,4,3,5\ny,6,2,0.75,1,4,3,5\n";
        let (rows, _) = read_all(text, false).unwrap();
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].line, 2);
        assert_eq!(rows[1].line, 3);
        assert_eq!(rows[0].t, 0.5);
        assert_eq!(rows[0].q, [1.0, 2.0, 3.0]);
        assert_eq!(rows[0].tau, [4.0, 5.0, 6.0]);
        assert_eq!(rows[0].enc, None);
    }

    #[test]
    fn whitespace_bom_and_crlf_are_tolerated() {
        let text = "\u{feff}t , q1,q2,q3,tau1,tau2,tau3\r\n 0 , 1,2,3,4,5,6\r\n0.1,1,2,3,4,5,6";
        let (rows, _) = read_all(text, false).unwrap();
        assert_eq!(
            rows.len(),
            2,
            "a complete last line without newline is accepted"
        );
        assert_eq!(rows[1].t, 0.1);
    }

    /// Found by the `log_reader` fuzz target: with lone `\r` line ends the parser still split the
    /// rows but numbered them all on line 1, and with `\r\n` one line early, so errors and skip
    /// reports named the wrong line.
    #[test]
    fn lone_cr_line_ends_number_lines_like_newlines() {
        let body = ["0,1,2,3,4,5,6", "0.1,1,2,3,4,5,6", "0.2,1,2,3,4,5,6"];
        for (name, text) in [
            ("cr", format!("{}\r{}\r", H.trim_end(), body.join("\r"))),
            (
                "crlf",
                format!("{}\r\n{}\r\n", H.trim_end(), body.join("\r\n")),
            ),
            (
                "mixed",
                format!("{}\r\n{}\r{}\n{}", H.trim_end(), body[0], body[1], body[2]),
            ),
        ] {
            let (rows, _) = read_all(&text, false).unwrap();
            let lines: Vec<u64> = rows.iter().map(|r| r.line).collect();
            assert_eq!(lines, [2, 3, 4], "{name}");
            // One byte per read: a `\r` at the end of a chunk, its `\n` in the next.
            let mut r = LogReader::new(OneByte(text.as_bytes()), "mem.csv", false).unwrap();
            let lines: Vec<u64> = std::iter::from_fn(|| r.next_row().unwrap())
                .map(|row| row.line)
                .collect();
            assert_eq!(lines, [2, 3, 4], "{name}, byte by byte");
        }
        let e = read_all(
            &format!("{}\r0,1,2,3,4,5,6\r0,1,2,3,4,5,6\r", H.trim_end()),
            false,
        )
        .unwrap_err();
        assert_eq!(e.line(), Some(3), "{e}");
        assert!(
            e.to_string().contains("line 3:") && e.to_string().contains("(line 2)"),
            "{e}"
        );
        let (_, skipped) =
            read_all(&format!("{H}0,1,2,3,4,5,6\rx,1,2,3,4,5,6\r0.5,1"), true).unwrap();
        assert_eq!(skipped.first_lines, [3, 4]);
    }

    /// A reader that hands out one byte per call.
    struct OneByte<'a>(&'a [u8]);

    impl Read for OneByte<'_> {
        fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
            match (self.0.split_first(), buf.first_mut()) {
                (Some((&b, rest)), Some(out)) => {
                    *out = b;
                    self.0 = rest;
                    Ok(1)
                }
                _ => Ok(0),
            }
        }
    }

    #[test]
    fn enc_and_stop_rows() {
        let text = "t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3,mode\n\
                    0,0,0,0,0,0,0,1,-2,70000,track\n\
                    0.001,0,0,0,0,0,0,1.0,-2,70001,track\n\
                    0.001,0,0,0,0,0,0,1,-2,70001,stop\n";
        let (rows, _) = read_all(text, false).unwrap();
        assert_eq!(rows[1].enc, Some([1, -2, 70001]));
        assert!(
            !rows[1].is_stop() && rows[2].is_stop(),
            "stop may repeat the last t"
        );
        assert_eq!(rows[0].mode, Some(Mode::Track));
        let after = format!("{text}0.002,0,0,0,0,0,0,1,2,3,track\n");
        let e = read_all(&after, false).unwrap_err();
        assert!(
            matches!(
                e,
                ReadError::AfterStop {
                    line: 5,
                    stop_line: 4,
                    ..
                }
            ),
            "{e}"
        );
        let (rows, skipped) = read_all(&after, true).unwrap();
        assert_eq!((rows.len(), skipped.count), (3, 1));
    }

    #[test]
    fn every_mode_omnid_writes_is_read_and_no_other() {
        let header = "t,q1,q2,q3,tau1,tau2,tau3,mode\n";
        let mut text = header.to_string();
        for (k, m) in Mode::ALL.iter().filter(|m| **m != Mode::Stop).enumerate() {
            text += &format!("{},0,0,0,0,0,0,{}\n", k, m.as_str());
        }
        let (rows, _) = read_all(&text, false).unwrap();
        let modes: Vec<Mode> = rows.iter().map(|r| r.mode.unwrap()).collect();
        assert_eq!(modes.len(), Mode::ALL.len() - 1);
        // Once silently read as "no mode": a value omnid never writes, in any case or form.
        for bad in ["Track", "servo-jp", "", "stopp", " ", "blend;"] {
            let text = format!("{header}0,0,0,0,0,0,0,track\n0.1,0,0,0,0,0,0,{bad}\n");
            let e = read_all(&text, false).unwrap_err();
            let msg = e.to_string();
            assert!(
                matches!(&e, ReadError::UnknownMode { line: 3, column, .. } if column == "mode"),
                "{bad:?}: {msg}"
            );
            assert!(
                msg.contains("line 3:") && msg.contains("servo_jf") && msg.contains("`mode`"),
                "{msg}"
            );
            let (rows, skipped) = read_all(&text, true).unwrap();
            assert_eq!((rows.len(), skipped.first_lines.clone()), (1, vec![3]));
        }
    }

    #[test]
    fn partial_enc_set_is_an_error() {
        let e = read_all("t,q1,q2,q3,tau1,tau2,tau3,enc1,enc3\n", false).unwrap_err();
        assert!(
            matches!(&e, ReadError::MissingColumn { column, .. } if column == "enc2"),
            "{e}"
        );
    }

    #[test]
    fn suggestions() {
        let cands = ["Time", "tau_1", "Q2", "qf3", "x"];
        assert_eq!(suggest("t", &cands).as_deref(), Some("Time"));
        assert_eq!(suggest("tau1", &cands).as_deref(), Some("tau_1"));
        assert_eq!(suggest("q2", &cands).as_deref(), Some("Q2"));
        assert_eq!(suggest("q3", &["banana", "x3y"]), None);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
    }

    #[test]
    fn a_known_log_column_is_not_suggested_for_another() {
        let e = read_all("t,qf1,q2,q3,tau1,tau2,tau3\n", false).unwrap_err();
        match e {
            ReadError::MissingColumn {
                column, suggestion, ..
            } => assert_eq!((column.as_str(), suggestion), ("q1", None)),
            other => panic!("{other}"),
        }
    }

    #[test]
    fn lenient_skips_and_reports() {
        // Line 3 is damaged; line 4 repeats the last accepted time (line 2's).
        let text = format!("{H}0,1,2,3,4,5,6\n0.1,x,2,3,4,5,6\n0,1,2,3,4,5,6\n0.2,1,2,3,4,5,6\n");
        assert!(read_all(&text, false).is_err());
        let (rows, s) = read_all(&text, true).unwrap();
        assert_eq!(rows.iter().map(|r| r.line).collect::<Vec<_>>(), [2, 5]);
        assert_eq!(s.count, 2);
        assert_eq!(s.first_lines, [3, 4]);
        assert!(s.to_string().contains("lines 3, 4"), "{s}");
        assert!(s.first_reason.unwrap().contains("line 3"));
    }

    #[test]
    fn huge_values_are_cut_in_messages() {
        let text = format!("{H}0,{},2,3,4,5,6\n", "z".repeat(10_000));
        let e = read_all(&text, false).unwrap_err().to_string();
        assert!(e.len() < 300, "{e}");
    }
}

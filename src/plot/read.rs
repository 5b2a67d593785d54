//! Reading a log for plotting: the header (which columns exist), then one streaming pass over
//! the rows that feeds the decimator, so a 600 k-row log never sits in memory whole. The rows
//! come through the crate's one log reader, [`ColumnReader`] (only `t` required), so a bad
//! row is the same [`ReadError`] as in replay, convert and identify, naming the line, the
//! column and the field; a row may take at most [`crate::input::MAX_ROW_BYTES`], a pipe is
//! waited on only with the operator's stop flag, and every read ends on it.
//!
//! Plot is more tolerant than replay in one way: a value column may hold a gap (an empty
//! field), NaN or an infinity, which only breaks the drawn line there. `t` must still be a
//! finite number, and a `mode` field, when present and not empty, one omnid writes.

use super::decimate::{Decimated, Decimator};
use crate::telemetry::reader::LogInput;
use crate::telemetry::reader::{ColumnReader, ReadError, Row, RowFault};
use crate::telemetry::record::Mode;
use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// How many rows pass between two progress reports.
const PROGRESS_EVERY_ROWS: u64 = 8192;

/// The header row: column names in file order.
#[derive(Debug, Clone)]
pub(crate) struct Header {
    names: Vec<String>,
}

impl Header {
    /// A header with these column names, in file order.
    pub(crate) fn new(names: Vec<String>) -> Header {
        Header { names }
    }

    /// The index of the first column called `name`.
    pub(crate) fn find(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// How many columns.
    pub(crate) fn len(&self) -> usize {
        self.names.len()
    }
}

/// What one plotted channel is computed from, per row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Formula {
    /// The value of one column.
    Column(usize),
    /// One column minus another (tracking and identification errors).
    Difference(usize, usize),
}

/// What one pass over the rows gives.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LogData {
    /// Every channel's min/max points, and the row count and time range.
    pub(crate) decimated: Decimated,
    /// The last time the `mode` column said `blend` (the start-up blend onto the reference),
    /// if the log has that column and any such row.
    pub(crate) blend_end: Option<f64>,
    /// Rows that track a reference (`blend`, `track`) and rows in a haptic mode (`free`,
    /// `servo_cf`); None without a `mode` column.
    pub(crate) modes: Option<(u64, u64)>,
    /// The first and last time of every row read (drawn or outside the window).
    pub(crate) seen: (f64, f64),
}

/// An open log whose header has been read.
pub(crate) struct LogReader {
    reader: ColumnReader<LogInput>,
    header: Header,
    bytes: u64,
    /// Only rows with `t` in this range are drawn (every row is still read and checked).
    window: (f64, f64),
}

impl LogReader {
    /// Open `path` and read its header, which must have a `t` column. `stop`: the operator's
    /// stop flag, which ends any read (without one, only a regular file is accepted: see
    /// [`crate::input::open`]).
    pub(crate) fn open(
        path: &Path,
        stop: Option<&Arc<AtomicBool>>,
    ) -> Result<LogReader, ReadError> {
        let reader = ColumnReader::open(path, &["t"], false, stop)?;
        // For the progress bar: 0 for a pipe, which then gets none.
        let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
        let header = Header::new(reader.header().to_vec());
        Ok(LogReader {
            reader,
            header,
            bytes,
            window: (f64::NEG_INFINITY, f64::INFINITY),
        })
    }

    /// Draw only the rows with `from <= t <= to` (s, the log's own time).
    pub(crate) fn window(mut self, from: f64, to: f64) -> LogReader {
        self.window = (from, to);
        self
    }

    /// The log's columns.
    pub(crate) fn header(&self) -> &Header {
        &self.header
    }

    /// File size in bytes (for the progress bar).
    pub(crate) fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Read every row, evaluate `formulas` on it and decimate to about `buckets` buckets.
    /// `progress` is called now and then with the byte offset reached. A log without data rows
    /// is [`ReadError::NoRows`].
    pub(crate) fn decimate(
        mut self,
        formulas: &[Formula],
        buckets: usize,
        mut progress: impl FnMut(u64),
    ) -> Result<LogData, ReadError> {
        let mut pass = RowPass::new(formulas, &self.header, buckets);
        pass.window = self.window;
        while let Some(byte) = self.reader.next_with(|row| pass.take(row))? {
            if pass.decimator.rows().is_multiple_of(PROGRESS_EVERY_ROWS) {
                progress(byte);
            }
        }
        // Rows outside the window were read: an empty window is the caller's to explain.
        if pass.decimator.rows() == 0 && pass.seen == (f64::INFINITY, f64::NEG_INFINITY) {
            return Err(ReadError::NoRows {
                path: self.reader.path().to_string(),
            });
        }
        progress(self.bytes);
        Ok(LogData {
            seen: pass.seen,
            decimated: pass.decimator.finish(),
            blend_end: pass.blend_end,
            modes: pass.mode.map(|_| (pass.tracking_rows, pass.haptic_rows)),
        })
    }
}

/// The state of one pass over the rows: the decimator, the blend's end so far, and buffers
/// reused from row to row (a row allocates nothing).
struct RowPass<'f> {
    formulas: &'f [Formula],
    /// The columns the formulas read, each once, ascending.
    needed: Vec<usize>,
    /// The `mode` column, if any.
    mode: Option<usize>,
    /// This row's value of every needed column (by column index; others untouched).
    parsed: Vec<f64>,
    /// This row's value of every formula.
    values: Vec<f64>,
    decimator: Decimator,
    blend_end: Option<f64>,
    tracking_rows: u64,
    haptic_rows: u64,
    /// Rows outside it are checked but not drawn.
    window: (f64, f64),
    /// The first and last time of every row read, drawn or not.
    seen: (f64, f64),
}

impl<'f> RowPass<'f> {
    fn new(formulas: &'f [Formula], header: &Header, buckets: usize) -> RowPass<'f> {
        RowPass {
            formulas,
            needed: needed_columns(formulas),
            mode: header.find("mode"),
            parsed: vec![f64::NAN; header.len()],
            values: vec![0.0; formulas.len()],
            decimator: Decimator::new(formulas.len(), buckets),
            blend_end: None,
            tracking_rows: 0,
            haptic_rows: 0,
            window: (f64::NEG_INFINITY, f64::INFINITY),
            seen: (f64::INFINITY, f64::NEG_INFINITY),
        }
    }

    /// Parse one row, feed it to the decimator and note a `blend` mode; the row's start in
    /// the file, bytes, for the progress report.
    fn take(&mut self, row: &Row<'_>) -> Result<u64, RowFault> {
        // Each needed column is parsed once per row even when several formulas use it.
        for &c in &self.needed {
            self.parsed[c] = row.number_or_gap(c)?;
        }
        if let Some(m) = self.mode {
            self.note_mode(row, m);
        }
        for (v, f) in self.values.iter_mut().zip(self.formulas) {
            *v = match *f {
                Formula::Column(c) => self.parsed[c],
                Formula::Difference(a, b) => self.parsed[a] - self.parsed[b],
            };
        }
        self.seen = (self.seen.0.min(row.t), self.seen.1.max(row.t));
        if (self.window.0..=self.window.1).contains(&row.t) {
            self.decimator.push(row.t, &self.values);
        }
        Ok(row.byte())
    }

    /// Count the row by its `mode` (the column reader has checked it is one omnid writes) and
    /// move the blend's end on to this row when it says `blend`.
    fn note_mode(&mut self, row: &Row<'_>, m: usize) {
        match std::str::from_utf8(row.field(m)).ok().and_then(Mode::parse) {
            Some(Mode::Blend) => {
                self.tracking_rows += 1;
                self.blend_end = Some(self.blend_end.map_or(row.t, |b| b.max(row.t)));
            }
            Some(Mode::Track) => self.tracking_rows += 1,
            Some(Mode::Free | Mode::ServoCf) => self.haptic_rows += 1,
            _ => {}
        }
    }
}

/// The columns `formulas` read, each once, ascending.
fn needed_columns(formulas: &[Formula]) -> Vec<usize> {
    let mut needed: Vec<usize> = formulas
        .iter()
        .flat_map(|f| match *f {
            Formula::Column(c) => [Some(c), None],
            Formula::Difference(a, b) => [Some(a), Some(b)],
        })
        .flatten()
        .collect();
    needed.sort_unstable();
    needed.dedup();
    needed
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn file(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(text.as_bytes()).unwrap();
        f
    }

    #[test]
    fn reads_columns_and_differences() {
        let f = file("t,a,b\n0,1,0.5\n0.001,2,0.5\n0.002,3,\n");
        let r = LogReader::open(f.path(), None).unwrap();
        let (a, b) = (r.header().find("a").unwrap(), r.header().find("b").unwrap());
        let data = r
            .decimate(
                &[Formula::Column(a), Formula::Difference(a, b)],
                100,
                |_| {},
            )
            .unwrap();
        assert_eq!(data.blend_end, None);
        let d = data.decimated;
        assert_eq!(d.rows, 3);
        assert_eq!(d.t_range, (0.0, 0.002));
        assert_eq!(d.channels[0], vec![(0.0, 1.0), (0.001, 2.0), (0.002, 3.0)]);
        // The empty field is a gap, not an error.
        assert_eq!(d.channels[1], vec![(0.0, 0.5), (0.001, 1.5)]);
    }

    #[test]
    fn finds_the_end_of_the_start_up_blend() {
        let f = file("t,q1,mode\n0,1,blend\n0.001,1,blend\n0.002,1,track\n0.003,0,stop\n");
        let data = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap();
        assert_eq!(data.blend_end, Some(0.001));
    }

    #[test]
    fn unknown_mode_names_line_and_column() {
        let f = file("t,q1,mode\n0,1,blend\n0.001,1,servo_jp\n0.002,1,tracking\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(
                e,
                ReadError::UnknownMode {
                    line: 4,
                    index: 3,
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(
            msg.contains("line 4: column 3 (`mode`): `tracking`") && msg.contains("servo_jf"),
            "{msg}"
        );
    }

    #[test]
    fn non_numeric_value_names_line_and_column() {
        let f = file("t,q1\n0,1\n0.001,oops\n");
        let r = LogReader::open(f.path(), None).unwrap();
        let e = r.decimate(&[Formula::Column(1)], 10, |_| {}).unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(
                e,
                ReadError::NotANumber {
                    line: 3,
                    index: 2,
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(msg.contains("line 3: column 2 (`q1`)"), "{msg}");
        assert!(msg.contains("\"oops\""), "{msg}");
    }

    #[test]
    fn missing_time_column_is_refused_at_open() {
        let f = file("time,q1\n0,1\n");
        let e = LogReader::open(f.path(), None).err().unwrap();
        assert!(
            matches!(&e, ReadError::MissingColumn { column, .. } if column == "t"),
            "{e:?}"
        );
        assert!(e.to_string().contains("no `t` column"), "{e}");
    }

    #[test]
    fn ragged_rows_and_bad_time_are_typed() {
        let f = file("t,q1\n0,1\n0.001\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        assert!(matches!(e, ReadError::FieldCount { line: 3, .. }), "{e:?}");

        let f = file("t,q1\n0,1\nNaN,2\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        assert!(
            matches!(&e, ReadError::NotFinite { line: 3, column, .. } if column == "t"),
            "{e:?}"
        );
    }

    #[test]
    fn empty_and_header_only_files() {
        let f = file("");
        assert!(matches!(
            LogReader::open(f.path(), None),
            Err(ReadError::Empty { .. })
        ));
        let f = file("t,q1\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        assert!(matches!(e, ReadError::NoRows { .. }), "{e:?}");
    }

    #[test]
    fn missing_file_names_the_path() {
        let e = LogReader::open(Path::new("/nonexistent/x.csv"), None)
            .err()
            .unwrap();
        assert!(e.to_string().starts_with("/nonexistent/x.csv: "), "{e}");
    }
}

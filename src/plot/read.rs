//! Reading a log for plotting: the header (which columns exist), then one streaming pass over
//! the rows that feeds the decimator, so a 600 k-row log never sits in memory whole. The file
//! is read through [`crate::input`]: a row may take at most [`crate::input::MAX_ROW_BYTES`], a pipe is
//! waited on only with the operator's stop flag, and every read ends on it.

use super::decimate::{Decimated, Decimator};
use crate::input::{self, Input, RowBound};
use crate::telemetry::record::Mode;
use std::io;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

/// Why a log could not be read. Every variant names the file; row errors also the line (as a
/// text editor counts them, the header being line 1) and the column.
#[derive(Debug, thiserror::Error)]
pub enum ReadError {
    #[error("{}: {source}", path.display())]
    Open { path: PathBuf, source: io::Error },
    #[error("{}: reading stopped by the operator", path.display())]
    Stopped { path: PathBuf },
    #[error(
        "{}: line {line}: the row starting here runs past {limit} bytes, the most a row may \
         take (a file without line ends, or a quote that is never closed?)",
        path.display()
    )]
    RowTooLong {
        path: PathBuf,
        line: u64,
        limit: u64,
    },
    #[error("{}: empty file (no header row)", path.display())]
    Empty { path: PathBuf },
    #[error("{}: line 1: no `t` column (the header has: {header})", path.display())]
    NoTime { path: PathBuf, header: String },
    #[error("{}: line {line}: {found} fields, but the header has {expected}", path.display())]
    Ragged {
        path: PathBuf,
        line: u64,
        found: usize,
        expected: usize,
    },
    #[error(
        "{}: line {line}, column {column} (`{name}`): {value:?} is not a number",
        path.display()
    )]
    NotNumber {
        path: PathBuf,
        line: u64,
        /// 1-based, as a spreadsheet counts.
        column: usize,
        name: String,
        value: String,
    },
    #[error(
        "{}: line {line}, column {column} (`mode`): `{value}` is not a mode omnid writes \
         (allowed: {})",
        path.display(), Mode::ALL.map(Mode::as_str).join(", ")
    )]
    NotMode {
        path: PathBuf,
        line: u64,
        /// 1-based, as a spreadsheet counts.
        column: usize,
        value: String,
    },
    #[error("{}: line {line}, column 1 (`t`): time must be a finite number", path.display())]
    BadTime { path: PathBuf, line: u64 },
    #[error("{}: line {line}: {source}", path.display())]
    Csv {
        path: PathBuf,
        line: u64,
        source: csv::Error,
    },
    #[error("{}: no data rows after the header", path.display())]
    NoRows { path: PathBuf },
}

/// The header row: column names in file order.
#[derive(Debug, Clone)]
pub struct Header {
    names: Vec<String>,
}

impl Header {
    pub fn new(names: Vec<String>) -> Header {
        Header { names }
    }

    pub fn find(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    pub fn name(&self, index: usize) -> &str {
        &self.names[index]
    }

    pub fn len(&self) -> usize {
        self.names.len()
    }

    pub fn is_empty(&self) -> bool {
        self.names.is_empty()
    }
}

/// What one plotted channel is computed from, per row.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Formula {
    /// The value of one column.
    Column(usize),
    /// One column minus another (tracking and identification errors).
    Difference(usize, usize),
}

/// What one pass over the rows gives.
#[derive(Debug, Clone, PartialEq)]
pub struct LogData {
    pub decimated: Decimated,
    /// The last time the `mode` column said `blend` (the start-up blend onto the reference),
    /// if the log has that column and any such row.
    pub blend_end: Option<f64>,
}

/// A csv error as ours: a stop, a row over the limit, or the parser's own.
fn csv_error(path: &Path, source: csv::Error, line: u64) -> ReadError {
    let line = source.position().map(|p| p.line()).unwrap_or(line);
    if let csv::ErrorKind::Io(e) = source.kind() {
        if input::is_stopped(e) {
            return ReadError::Stopped {
                path: path.to_path_buf(),
            };
        }
        if let Some(limit) = input::row_too_long(e) {
            return ReadError::RowTooLong {
                path: path.to_path_buf(),
                line,
                limit,
            };
        }
    }
    ReadError::Csv {
        path: path.to_path_buf(),
        line,
        source,
    }
}

/// An open log whose header has been read.
pub struct LogReader {
    path: PathBuf,
    reader: csv::Reader<RowBound<Input>>,
    header: Header,
    t: usize,
    bytes: u64,
    /// The parser's line of the next row's start (its position moves on while a row is read).
    next_line: u64,
}

impl LogReader {
    /// Open `path` and read its header. `stop`: the operator's stop flag, which ends any read
    /// (without one, only a regular file is accepted: see [`crate::input::open`]).
    pub fn open(path: &Path, stop: Option<&Arc<AtomicBool>>) -> Result<LogReader, ReadError> {
        let file = input::open(path, stop).map_err(|source| {
            if input::is_stopped(&source) {
                ReadError::Stopped {
                    path: path.to_path_buf(),
                }
            } else {
                ReadError::Open {
                    path: path.to_path_buf(),
                    source,
                }
            }
        })?;
        // For the progress bar: 0 for a pipe, which then gets none.
        let bytes = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
        // Flexible: a short or long row gets our own message with its line, not csv's.
        let mut reader = csv::ReaderBuilder::new()
            .has_headers(true)
            .flexible(true)
            .from_reader(RowBound::new(file));
        let names: Vec<String> = reader
            .byte_headers()
            .map_err(|source| csv_error(path, source, 1))?
            .iter()
            .map(|f| String::from_utf8_lossy(f).trim().to_string())
            .collect();
        if names.iter().all(|n| n.is_empty()) {
            return Err(ReadError::Empty {
                path: path.to_path_buf(),
            });
        }
        let first_row = reader.position().clone();
        reader.get_mut().row_starts_at(first_row.byte());
        let header = Header::new(names);
        let t = header.find("t").ok_or_else(|| ReadError::NoTime {
            path: path.to_path_buf(),
            header: header.names.join(","),
        })?;
        Ok(LogReader {
            path: path.to_path_buf(),
            reader,
            header,
            t,
            bytes,
            next_line: first_row.line(),
        })
    }

    pub fn header(&self) -> &Header {
        &self.header
    }

    /// File size in bytes (for the progress bar).
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// Read every row, evaluate `formulas` on it and decimate to about `buckets` buckets.
    /// `progress` is called now and then with the byte offset reached.
    pub fn decimate(
        mut self,
        formulas: &[Formula],
        buckets: usize,
        mut progress: impl FnMut(u64),
    ) -> Result<LogData, ReadError> {
        let mode = self.header.find("mode");
        let mut blend_end: Option<f64> = None;
        let mut decimator = Decimator::new(formulas.len(), buckets);
        let mut record = csv::ByteRecord::new();
        let mut values = vec![0.0; formulas.len()];
        // Parse each needed column once per row even when several formulas use it.
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
        let mut parsed = vec![f64::NAN; self.header.len()];
        let width = self.header.len();
        loop {
            let more = self
                .reader
                .read_byte_record(&mut record)
                .map_err(|source| csv_error(&self.path, source, self.next_line))?;
            if !more {
                break;
            }
            let next_row = self.reader.position().clone();
            self.next_line = next_row.line();
            self.reader.get_mut().row_starts_at(next_row.byte());
            let line = record
                .position()
                .map(|p| p.line())
                .unwrap_or(decimator.rows() + 2);
            if record.len() != width {
                return Err(ReadError::Ragged {
                    path: self.path.clone(),
                    line,
                    found: record.len(),
                    expected: width,
                });
            }
            let t = match self.number(&record, self.t, line)? {
                t if t.is_finite() => t,
                _ => {
                    return Err(ReadError::BadTime {
                        path: self.path.clone(),
                        line,
                    })
                }
            };
            for &c in &needed {
                parsed[c] = self.number(&record, c, line)?;
            }
            for (v, f) in values.iter_mut().zip(formulas) {
                *v = match *f {
                    Formula::Column(c) => parsed[c],
                    Formula::Difference(a, b) => parsed[a] - parsed[b],
                };
            }
            decimator.push(t, &values);
            if let Some(m) = mode {
                // An empty field is a gap, as in every other column.
                let value = record[m].trim_ascii();
                match std::str::from_utf8(value).ok().and_then(Mode::parse) {
                    Some(Mode::Blend) => blend_end = Some(blend_end.map_or(t, |b| b.max(t))),
                    Some(_) => {}
                    None if value.is_empty() => {}
                    None => {
                        return Err(ReadError::NotMode {
                            path: self.path.clone(),
                            line,
                            column: m + 1,
                            value: crate::telemetry::reader::quote(value),
                        })
                    }
                }
            }
            if decimator.rows() % 8192 == 0 {
                progress(record.position().map(|p| p.byte()).unwrap_or(0));
            }
        }
        if decimator.rows() == 0 {
            return Err(ReadError::NoRows { path: self.path });
        }
        progress(self.bytes);
        Ok(LogData {
            decimated: decimator.finish(),
            blend_end,
        })
    }

    /// One field as a number. An empty field is a gap (NaN): other tools write missing values
    /// that way, and a gap only breaks the line there.
    fn number(&self, record: &csv::ByteRecord, column: usize, line: u64) -> Result<f64, ReadError> {
        let raw = &record[column];
        let text = std::str::from_utf8(raw).unwrap_or("").trim();
        if text.is_empty() && raw.iter().all(u8::is_ascii_whitespace) {
            return Ok(f64::NAN);
        }
        text.parse::<f64>().map_err(|_| ReadError::NotNumber {
            path: self.path.clone(),
            line,
            column: column + 1,
            name: self.header.name(column).to_string(),
            value: String::from_utf8_lossy(raw).into_owned(),
        })
    }
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
        let f = file("t,q1,mode\n0,1,blend\n0.001,1,\n0.002,1,servo_jp\n0.003,1,tracking\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(
                e,
                ReadError::NotMode {
                    line: 5,
                    column: 3,
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(
            msg.contains("line 5, column 3 (`mode`): `tracking`") && msg.contains("servo_jf"),
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
                ReadError::NotNumber {
                    line: 3,
                    column: 2,
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(msg.contains("line 3, column 2 (`q1`)"), "{msg}");
        assert!(msg.contains("\"oops\""), "{msg}");
    }

    #[test]
    fn missing_time_column_is_refused_at_open() {
        let f = file("time,q1\n0,1\n");
        let e = LogReader::open(f.path(), None).err().unwrap();
        assert!(matches!(e, ReadError::NoTime { .. }), "{e:?}");
        assert!(e.to_string().contains("no `t` column"), "{e}");
    }

    #[test]
    fn ragged_rows_and_bad_time_are_typed() {
        let f = file("t,q1\n0,1\n0.001\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        assert!(matches!(e, ReadError::Ragged { line: 3, .. }), "{e:?}");

        let f = file("t,q1\n0,1\nNaN,2\n");
        let e = LogReader::open(f.path(), None)
            .unwrap()
            .decimate(&[Formula::Column(1)], 10, |_| {})
            .unwrap_err();
        assert!(matches!(e, ReadError::BadTime { line: 3, .. }), "{e:?}");
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

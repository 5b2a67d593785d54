//! The log writer thread: drains the bounded telemetry channel into a buffered CSV file. A
//! write error (disk full) is remembered and reported, but the thread keeps draining so the
//! servo loop never notices.
//!
//! The thread polls the channel (drain, then sleep [`POLL`]) instead of blocking in `recv`:
//! a receiver parked in `recv` must be woken by the sender, which would put a futex
//! syscall into every servo tick.

use super::record::{LogSchema, TickRecord};
use crossbeam_channel::{Receiver, TryRecvError};
use std::collections::VecDeque;
use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;

/// Ticks kept for the fault dump.
pub const DUMP_TICKS: usize = 500;

/// How long the writer sleeps when the channel is empty. At 1 kHz this leaves about one row
/// per wake-up; the channel (8192 rows by default) has seconds of slack.
pub const POLL: std::time::Duration = std::time::Duration::from_millis(1);

/// Hand every item to `each` until the senders are gone, sleeping [`POLL`] whenever the
/// channel is empty (never parked in `recv`, so a send never has to wake this thread).
pub fn for_each_polled<T>(rx: &Receiver<T>, mut each: impl FnMut(T)) {
    loop {
        match rx.try_recv() {
            Ok(item) => each(item),
            Err(TryRecvError::Empty) => std::thread::sleep(POLL),
            Err(TryRecvError::Disconnected) => return,
        }
    }
}

#[derive(Debug)]
pub struct WriterReport {
    pub path: PathBuf,
    pub schema: LogSchema,
    pub rows: u64,
    /// The first write error, if any; rows after it are lost.
    pub error: Option<io::Error>,
    /// The last [`DUMP_TICKS`] records received, oldest first (for the fault dump).
    pub tail: VecDeque<TickRecord>,
}

/// `run.csv` → `run-fault.csv`, beside the log.
pub fn dump_path(log: &Path) -> PathBuf {
    let stem = log
        .file_stem()
        .map(|s| s.to_string_lossy())
        .unwrap_or_default();
    let name = match log.extension() {
        Some(ext) => format!("{stem}-fault.{}", ext.to_string_lossy()),
        None => format!("{stem}-fault"),
    };
    log.with_file_name(name)
}

/// Write the fault dump: the same columns as the log, the last ticks before the fault.
pub fn write_dump(path: &Path, schema: &LogSchema, rows: &VecDeque<TickRecord>) -> io::Result<()> {
    let mut out = BufWriter::new(File::create(path)?);
    writeln!(out, "{}", schema.columns().join(","))?;
    for r in rows {
        write_row(&mut out, r, schema)?;
    }
    out.flush()
}

/// Append one CSV row to `line` (shortest round-trip float formatting, so a parsed log gives
/// back the exact bits the loop had).
fn format_row(line: &mut Vec<u8>, r: &TickRecord, schema: &LogSchema) {
    let mut f = ryu::Buffer::new();
    let mut i = itoa::Buffer::new();
    line.extend_from_slice(f.format(r.t).as_bytes());
    let groups = [
        &r.q,
        &r.tau,
        &r.qf,
        &r.qd,
        &r.qdd,
        &r.reference,
        &r.tau_cmd,
        &r.tau_hat,
    ];
    let model = if schema.model {
        Some(&r.tau_model)
    } else {
        None
    };
    for group in groups.into_iter().chain(model) {
        for v in group {
            line.push(b',');
            line.extend_from_slice(f.format(*v).as_bytes());
        }
    }
    for v in &r.enc {
        line.push(b',');
        line.extend_from_slice(i.format(*v).as_bytes());
    }
    line.push(b',');
    line.push(if r.amps { b'1' } else { b'0' });
    line.push(b',');
    line.extend_from_slice(r.mode.as_str().as_bytes());
    line.push(b',');
    line.extend_from_slice(i.format(r.flags).as_bytes());
    line.push(b'\n');
}

fn write_row(w: &mut impl Write, r: &TickRecord, schema: &LogSchema) -> io::Result<()> {
    let mut line = Vec::with_capacity(512);
    format_row(&mut line, r, schema);
    w.write_all(&line)
}

/// Create `path` as a new, empty file. An old regular file there is unlinked rather than
/// truncated: ext4 flushes a file that was truncated and rewritten when it is closed, and the
/// next file created then waits for those tens of MB to reach the disk (~25 ms at the end of a
/// 60 s `--fast` run). Anything else (a symlink, /dev/null) is opened as `File::create` does.
fn create_replacing(path: &Path) -> io::Result<File> {
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.file_type().is_file()) {
        std::fs::remove_file(path)?;
    }
    File::create(path)
}

/// Create the log file now (so an unwritable path fails before torque is enabled) and start
/// the thread that fills it.
pub fn spawn_writer(
    path: &Path,
    schema: LogSchema,
    rx: Receiver<TickRecord>,
) -> io::Result<JoinHandle<WriterReport>> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    let mut out = BufWriter::with_capacity(1 << 16, create_replacing(path)?);
    writeln!(out, "{}", schema.columns().join(","))?;
    out.flush()?;
    let path = path.to_path_buf();
    std::thread::Builder::new()
        .name("omnid-log".into())
        .spawn(move || {
            let mut report = WriterReport {
                path,
                schema,
                rows: 0,
                error: None,
                tail: VecDeque::with_capacity(DUMP_TICKS),
            };
            let mut line = Vec::with_capacity(512);
            for_each_polled(&rx, |record| {
                if report.tail.len() == DUMP_TICKS {
                    report.tail.pop_front();
                }
                report.tail.push_back(record);
                if report.error.is_some() {
                    return; // keep draining: the loop must never block on us
                }
                line.clear();
                format_row(&mut line, &record, &schema);
                match out.write_all(&line) {
                    Ok(()) => report.rows += 1,
                    Err(e) => report.error = Some(e),
                }
            });
            if let Err(e) = out.flush() {
                report.error.get_or_insert(e);
            }
            report
        })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::telemetry::record::Mode;

    #[test]
    fn an_old_log_is_replaced_by_a_new_file_and_a_symlink_is_followed() {
        use std::os::unix::fs::MetadataExt;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("run.csv");
        std::fs::write(&path, "old contents\n").unwrap();
        let old_inode = std::fs::metadata(&path).unwrap().ino();
        // Hold the old file open so its inode cannot be reused for the new one.
        let _old = File::open(&path).unwrap();
        drop(create_replacing(&path).unwrap());
        let new = std::fs::metadata(&path).unwrap();
        assert_eq!(new.len(), 0);
        assert_ne!(
            new.ino(),
            old_inode,
            "the old file was truncated, not replaced"
        );

        let target = dir.path().join("target.csv");
        std::fs::write(&target, "old contents\n").unwrap();
        let link = dir.path().join("link.csv");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        drop(create_replacing(&link).unwrap());
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::metadata(&target).unwrap().len(), 0);
    }

    #[test]
    fn writes_header_and_rows_that_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("sub/run.csv");
        let (tx, rx) = crossbeam_channel::bounded(4);
        let schema = LogSchema { model: true };
        let handle = spawn_writer(&path, schema, rx).unwrap();
        let rec = TickRecord {
            t: 0.001,
            q: [0.1, 0.2, 1.0 / 3.0],
            tau: [1e-17, -0.0, 0.45],
            qf: [0.0; 3],
            qd: [0.0; 3],
            qdd: [0.0; 3],
            reference: [0.0; 3],
            tau_cmd: [0.0; 3],
            tau_hat: [0.0; 3],
            tau_model: [f64::NAN; 3],
            enc: [-5, 0, 70000],
            amps: true,
            mode: Mode::Track,
            flags: 1,
            live: Default::default(),
        };
        tx.send(rec).unwrap();
        drop(tx);
        let report = handle.join().unwrap();
        assert_eq!(report.rows, 1);
        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines = text.lines();
        let header: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(header.len(), schema.columns().len());
        let row: Vec<&str> = lines.next().unwrap().split(',').collect();
        assert_eq!(row.len(), header.len());
        // Shortest round-trip formatting: parsing gives back the exact bits.
        assert_eq!(row[3].parse::<f64>().unwrap(), 1.0 / 3.0);
        assert_eq!(row[4].parse::<f64>().unwrap(), 1e-17);
        assert_eq!(
            row[header.iter().position(|h| *h == "enc3").unwrap()],
            "70000"
        );
        assert_eq!(row[header.len() - 2], "track");
    }

    #[test]
    fn dump_sits_beside_the_log() {
        assert_eq!(
            dump_path(Path::new("/a/run.csv")),
            Path::new("/a/run-fault.csv")
        );
        assert_eq!(dump_path(Path::new("run")), Path::new("run-fault"));
    }

    #[test]
    fn unwritable_path_fails_before_anything_runs() {
        let (_tx, rx) = crossbeam_channel::bounded(4);
        let err = spawn_writer(
            Path::new("/proc/omnid/run.csv"),
            LogSchema { model: false },
            rx,
        );
        assert!(err.is_err());
    }
}

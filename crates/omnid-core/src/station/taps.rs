//! What every tick record flows to on a station: the fault ring (the last seconds, dumped on a
//! fault), a recording (a writer thread fed through a bounded channel, as `omnid run`'s log),
//! and any [`Tap`] a transport or recorder adds.

use crate::telemetry::mcap_log::LogFormat;
use crate::telemetry::record::{LogSchema, TickRecord};
use crate::telemetry::{
    spawn_writer_with, write_dump, DumpTo, LogError, LogFile, Watch, WriterFault, WriterReport,
};
use crossbeam_channel::Sender;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::thread::JoinHandle;

/// A consumer beside the loop: it sees every tick record and every event of its arm, on the
/// station's thread (never the servo's). It must not block: anything slow goes to a thread of
/// its own through a bounded channel, as `Recording` does.
pub trait Tap: Send {
    /// One tick.
    fn on_tick(&mut self, record: &TickRecord);
    /// An event every session is told about.
    fn on_event(&mut self, _event: &super::Event) {}
    /// The servo has ended: flush, close.
    fn finish(&mut self) {}
    /// Each tick must reach it at once (the servo wakes the station every tick), not in the
    /// batches the station drains on its own schedule: a network feed with latency to keep.
    fn prompt(&self) -> bool {
        false
    }
}

/// The last `cap` ticks, oldest first: what a fault dump writes.
pub(crate) struct FaultRing {
    ticks: VecDeque<TickRecord>,
    cap: usize,
    schema: LogSchema,
    format: LogFormat,
}

impl FaultRing {
    pub(crate) fn new(cap: usize, schema: LogSchema, format: LogFormat) -> FaultRing {
        FaultRing {
            ticks: VecDeque::with_capacity(cap),
            cap,
            schema,
            format,
        }
    }

    pub(crate) fn push(&mut self, r: TickRecord) {
        if self.ticks.len() == self.cap {
            self.ticks.pop_front();
        }
        self.ticks.push_back(r);
    }

    /// Write the ring to a new file `<dir>/faults/omnid-<arm>-<UTC>-<why>-fault.csv` (a new
    /// name for every dump: two faults in one second keep both) and say where; `None` when it
    /// cannot be written (said too).
    pub(crate) fn dump(&self, dir: &Path, arm: &str, why: &str) -> Option<PathBuf> {
        let stem = format!("omnid-{arm}-{}-{why}-fault", super::utc_stamp());
        let faults = dir.join("faults");
        let to = DumpTo::Unique {
            dir: &faults,
            stem: &stem,
        };
        let written = write_dump(to, &self.schema, self.format, &self.ticks);
        match written {
            Ok(path) => {
                crate::errln!(
                    "omnid serve: {arm}: the last ticks before the fault are in {}",
                    path.display()
                );
                Some(path)
            }
            Err(e) => {
                crate::errln!("omnid serve: {arm}: cannot write the fault dump: {e}");
                None
            }
        }
    }
}

/// Keep at most `keep` of arm `arm`'s fault dumps in `<dir>/faults`: the oldest go, so trips
/// that repeat cannot fill the disk.
pub(crate) fn prune_dumps(dir: &Path, arm: &str, keep: usize) {
    let prefix = format!("omnid-{arm}-");
    let mut dumps: Vec<(std::time::SystemTime, PathBuf)> = std::fs::read_dir(dir.join("faults"))
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| {
            let name = e.file_name();
            let name = name.to_string_lossy();
            name.starts_with(&prefix) && name.contains("-fault")
        })
        .filter_map(|e| {
            let m = e.metadata().ok().filter(|m| m.is_file())?;
            Some((m.modified().ok()?, e.path()))
        })
        .collect();
    if dumps.len() <= keep {
        return;
    }
    dumps.sort();
    for (_, path) in &dumps[..dumps.len() - keep] {
        let _ = std::fs::remove_file(path);
    }
}

/// A recording in progress: every tick to a log file on a writer thread.
pub(crate) struct Recording {
    tx: Option<Sender<TickRecord>>,
    writer: JoinHandle<WriterReport>,
    path: PathBuf,
    dropped: u64,
    /// The writer's first error, the moment it happens; `told` once it has been announced.
    fault: WriterFault,
    told: bool,
}

impl Recording {
    /// Start writing to `log` (opened by the caller, with the rights of whoever named it).
    pub(crate) fn start(
        log: LogFile,
        schema: LogSchema,
        format: LogFormat,
    ) -> Result<Recording, LogError> {
        let (tx, rx) = crossbeam_channel::bounded(8192);
        let path = log.path.clone();
        let fault = WriterFault::default();
        let recorder = crate::telemetry::writer::recorder(schema, format);
        let writer = spawn_writer_with(
            log,
            schema,
            recorder,
            rx,
            Watch {
                fault: Some(fault.clone()),
                stop: None,
            },
        )
        .map_err(|source| LogError::Io {
            path: path.clone(),
            source,
        })?;
        Ok(Recording {
            tx: Some(tx),
            writer,
            path,
            dropped: 0,
            fault,
            told: false,
        })
    }

    pub(crate) fn path(&self) -> &Path {
        &self.path
    }

    pub(crate) fn dropped(&self) -> u64 {
        self.dropped
    }

    /// One tick; dropped and counted when the writer has fallen behind.
    pub(crate) fn push(&mut self, r: TickRecord) {
        if let Some(tx) = &self.tx {
            if tx.try_send(r).is_err() {
                self.dropped += 1;
            }
        }
    }

    /// The writer's error, once, when it has just failed (so that it is announced while the
    /// recording runs, not only at `record_stop`).
    pub(crate) fn newly_failed(&mut self) -> Option<String> {
        if self.told {
            return None;
        }
        let why = self.fault.get()?.clone();
        self.told = true;
        Some(why)
    }

    /// End it: (path, rows written, error).
    pub(crate) fn stop(mut self) -> (PathBuf, u64, Option<String>) {
        self.tx = None;
        let report = self.writer.join().ok();
        let rows = report.as_ref().map_or(0, |w| w.rows);
        let mut error = report.and_then(|w| {
            w.error.map(|e| {
                format!(
                    "{} of {} rows did not reach the file: {e}",
                    w.received - w.rows,
                    w.received
                )
            })
        });
        if self.dropped > 0 {
            error.get_or_insert(format!(
                "{} rows dropped (the disk fell behind)",
                self.dropped
            ));
        }
        (self.path, rows, error)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::os::fd::{FromRawFd, OwnedFd};

    /// A recording whose file stops taking rows says so while it runs, once, not only when
    /// it is stopped.
    #[test]
    fn a_recording_that_fails_says_so_at_once() {
        let mut fds = [0; 2];
        // SAFETY: `fds` has room for the two descriptors.
        assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
        // SAFETY: both are new and owned here alone.
        let (reader, writer) =
            unsafe { (OwnedFd::from_raw_fd(fds[0]), OwnedFd::from_raw_fd(fds[1])) };
        let log = LogFile::on("pipe".into(), std::fs::File::from(writer));
        let mut rec = Recording::start(log, LogSchema::new(false), LogFormat::Csv).unwrap();
        // The reader goes away: every write from now on fails (EPIPE).
        drop(reader);
        let mut said = Vec::new();
        for seq in 0..20_000u64 {
            rec.push(TickRecord::at(seq, crate::telemetry::record::Mode::Hold));
            said.extend(rec.newly_failed());
            if !said.is_empty() && seq % 1000 == 0 {
                break;
            }
            std::thread::sleep(std::time::Duration::from_micros(50));
        }
        assert_eq!(said.len(), 1, "{said:?}");
        assert!(said[0].to_lowercase().contains("pipe"), "{said:?}");
        assert_eq!(rec.newly_failed(), None, "said once");
        let (_, _, error) = rec.stop();
        assert!(error.is_some());
    }
}

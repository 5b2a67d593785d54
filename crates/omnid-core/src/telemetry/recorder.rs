//! Recorders: what turns the servo's tick records into a log file's bytes. One trait, and
//! one implementation per format — CSV (docs/DESIGN.md §2.2) in this file, MCAP
//! (docs/MCAP.md) in `mcap_log::write`. The writer thread (`writer::spawn_writer`, for `omnid
//! run`'s log and `omnid serve`'s recordings) and every fault dump (`writer::write_dump`, for
//! both) write through it, so a new format is a new implementation and a new arm of
//! `writer::recorder` (which chooses among them: this file knows none of the others).

use super::record::{LogSchema, TickRecord};
use std::io;

/// A log format. Each call appends bytes to `out` and says how many rows those bytes complete:
/// the writer counts rows as they reach the file and, when a write fails, cuts the file back
/// to the end of the last whole row, so a log cut by a full disk still reads to its end.
pub trait Recorder: Send {
    /// What the file starts with.
    fn header(&mut self, out: &mut Vec<u8>) -> io::Result<()>;
    /// One tick; the rows `out` completes (a format that gathers rows into blocks completes
    /// none until a block closes, then all of its rows).
    fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>) -> io::Result<u64>;
    /// The rows still held back (an open block), after the last tick.
    fn finish_rows(&mut self, _out: &mut Vec<u8>) -> io::Result<u64> {
        Ok(0)
    }
    /// What the file ends with after its rows (indexes, a summary); nothing by default.
    fn footer(&mut self, _out: &mut Vec<u8>) -> io::Result<()> {
        Ok(())
    }
}

/// CSV: the header of `schema`'s columns, one line a tick, floats in their shortest
/// round-trip form.
pub(crate) struct Csv {
    pub(crate) schema: LogSchema,
}

impl Recorder for Csv {
    fn header(&mut self, out: &mut Vec<u8>) -> io::Result<()> {
        out.extend_from_slice(self.schema.columns().join(",").as_bytes());
        out.push(b'\n');
        Ok(())
    }

    fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>) -> io::Result<u64> {
        format_row(out, r, &self.schema);
        Ok(1)
    }
}

/// Append one CSV row to `line` (shortest round-trip float formatting, so a parsed log gives
/// back the exact bits the loop had).
pub(crate) fn format_row(line: &mut Vec<u8>, r: &TickRecord, schema: &LogSchema) {
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
    // docs/DESIGN.md §2.2's order: each optional group beside its kind.
    let rest = [
        schema.model.then_some(&r.tau_model),
        schema.external.then_some(&r.tau_ext),
        Some(&r.haptic.tip_mm),
        Some(&r.haptic.force),
        schema.model.then_some(&r.haptic.hand),
        schema.external.then_some(&r.haptic.fext),
    ];
    for group in groups.into_iter().chain(rest.into_iter().flatten()) {
        for v in group {
            line.push(b',');
            line.extend_from_slice(f.format(*v).as_bytes());
        }
    }
    for v in &r.enc {
        line.push(b',');
        line.extend_from_slice(i.format(*v).as_bytes());
    }
    if schema.buttons {
        for on in [r.live.buttons[0], r.live.buttons[1], r.live.inkwell] {
            line.push(b',');
            line.push(if on { b'1' } else { b'0' });
        }
    }
    line.push(b',');
    line.push(if r.amps { b'1' } else { b'0' });
    line.push(b',');
    line.extend_from_slice(r.mode.as_str().as_bytes());
    line.push(b',');
    line.extend_from_slice(i.format(r.flags).as_bytes());
    line.push(b'\n');
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::telemetry::record::Mode;
    use crate::telemetry::writer::spawn_writer_with;
    use crate::telemetry::LogFile;

    /// A format of its own (a test's): one line per tick, `seq mode` — what a second format
    /// needs is this much, plus its arm in `recorder`.
    struct SeqLines;

    impl Recorder for SeqLines {
        fn header(&mut self, out: &mut Vec<u8>) -> io::Result<()> {
            out.extend_from_slice(b"# seq mode\n");
            Ok(())
        }
        fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>) -> io::Result<u64> {
            out.extend_from_slice(format!("{} {}\n", r.live.seq, r.mode.as_str()).as_bytes());
            Ok(1)
        }
        fn footer(&mut self, out: &mut Vec<u8>) -> io::Result<()> {
            out.extend_from_slice(b"# end\n");
            Ok(())
        }
    }

    #[test]
    fn a_second_format_is_one_recorder_and_the_writer_thread_runs_it() {
        let dir = tempfile::tempdir().unwrap();
        let log = LogFile::create(&dir.path().join("run.seq")).unwrap();
        let (tx, rx) = crossbeam_channel::bounded(16);
        let writer = spawn_writer_with(
            log,
            LogSchema::new(false),
            Box::new(SeqLines),
            rx,
            Default::default(),
        )
        .unwrap();
        for seq in 0..3 {
            let r = TickRecord::at(seq, if seq == 2 { Mode::Stop } else { Mode::Hold });
            tx.send(r).unwrap();
        }
        drop(tx);
        let report = writer.join().unwrap();
        assert_eq!((report.rows, report.received), (3, 3));
        let text = std::fs::read_to_string(dir.path().join("run.seq")).unwrap();
        assert_eq!(text, "# seq mode\n0 hold\n1 hold\n2 stop\n# end\n");
        // CSV, the format every log has: its header is the schema's columns.
        let mut csv = Csv {
            schema: LogSchema::new(false),
        };
        let mut out = Vec::new();
        csv.header(&mut out).unwrap();
        assert!(String::from_utf8(out)
            .unwrap()
            .starts_with("t,q1,q2,q3,tau1"));
    }
}

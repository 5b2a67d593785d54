//! Recorders: what turns the servo's tick records into a log file's bytes. One trait, and
//! one file per format — CSV (docs/DESIGN.md §2.2) is the first, in this file. The writer
//! thread (`writer::spawn_writer`, for `omnid run`'s log and `omnid serve`'s recordings) and
//! every fault dump (`writer::write_dump`, for both) write through it, so a new format is a new
//! implementation here and a new arm of `recorder`.

use super::record::{LogSchema, TickRecord};

/// A log format. Each call appends whole units to `out`: the writer counts a `row` as the unit
/// a failed write takes back, so a log cut by a full disk still ends on a whole row.
pub trait Recorder: Send {
    /// What the file starts with.
    fn header(&mut self, out: &mut Vec<u8>);
    /// One tick.
    fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>);
    /// What the file ends with (indexes, a summary); nothing by default.
    fn footer(&mut self, _out: &mut Vec<u8>) {}
}

/// The recorder for logs of `schema`.
pub(crate) fn recorder(schema: LogSchema) -> Box<dyn Recorder> {
    Box::new(Csv { schema })
}

/// CSV: the header of `schema`'s columns, one line a tick, floats in their shortest
/// round-trip form.
pub(crate) struct Csv {
    schema: LogSchema,
}

impl Recorder for Csv {
    fn header(&mut self, out: &mut Vec<u8>) {
        out.extend_from_slice(self.schema.columns().join(",").as_bytes());
        out.push(b'\n');
    }

    fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>) {
        format_row(out, r, &self.schema);
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
    let model = if schema.model {
        Some(&r.tau_model)
    } else {
        None
    };
    let hand = if schema.model {
        Some(&r.haptic.hand)
    } else {
        None
    };
    let haptic = [&r.haptic.tip_mm, &r.haptic.force];
    for group in groups.into_iter().chain(model).chain(haptic).chain(hand) {
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
        fn header(&mut self, out: &mut Vec<u8>) {
            out.extend_from_slice(b"# seq mode\n");
        }
        fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>) {
            out.extend_from_slice(format!("{} {}\n", r.live.seq, r.mode.as_str()).as_bytes());
        }
        fn footer(&mut self, out: &mut Vec<u8>) {
            out.extend_from_slice(b"# end\n");
        }
    }

    #[test]
    fn a_second_format_is_one_recorder_and_the_writer_thread_runs_it() {
        let dir = tempfile::tempdir().unwrap();
        let log = LogFile::create(&dir.path().join("run.seq")).unwrap();
        let (tx, rx) = crossbeam_channel::bounded(16);
        let writer = spawn_writer_with(
            log,
            LogSchema { model: false },
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
        let mut csv = recorder(LogSchema { model: false });
        let mut out = Vec::new();
        csv.header(&mut out);
        assert!(String::from_utf8(out)
            .unwrap()
            .starts_with("t,q1,q2,q3,tau1"));
    }
}

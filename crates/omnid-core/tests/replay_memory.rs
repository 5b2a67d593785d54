//! The log reader streams: a 1-hour, 1 kHz log (3.6 million rows, generated on the fly, never
//! on disk) goes through it with flat memory, and a 100 MB line without an end is refused after
//! a megabyte. Alone in their test binary and one at a time, so the process's peak RSS is the
//! running test's. The whole pipeline (`omnid run --device replay:… --fast` on such a file)
//! is measured by the command in `mock/README.md`.

use omnid_core::telemetry::reader::{LogReader, ReadError, MAX_ROW_BYTES};
use std::io::Read;
use std::sync::Mutex;

/// The tests measure the process's peak memory: one at a time.
static ALONE: Mutex<()> = Mutex::new(());

/// Peak resident set size of this process, kB (`VmHWM`).
fn peak_rss_kb() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmHWM in /proc/self/status")
}

/// An omnid-style log, generated row by row.
struct Generator {
    rows: u64,
    next: u64,
    buf: Vec<u8>,
    pos: usize,
}

impl Generator {
    fn new(rows: u64) -> Self {
        Generator {
            rows,
            next: 0,
            buf: b"t,q1,q2,q3,tau1,tau2,tau3,enc1,enc2,enc3,mode\n".to_vec(),
            pos: 0,
        }
    }
}

impl Read for Generator {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        use std::io::Write;
        if self.pos == self.buf.len() {
            if self.next == self.rows {
                return Ok(0);
            }
            self.buf.clear();
            self.pos = 0;
            // 64 rows at a time.
            for _ in 0..64.min(self.rows - self.next) {
                let k = self.next;
                let enc = [(k % 4000) as i64 - 2000, 600, -800];
                let rpc = std::f64::consts::TAU / 15000.0;
                writeln!(
                    self.buf,
                    "{},{},{},{},{},-0.0123,0.004,{},{},{},track",
                    k as f64 * 1e-3,
                    enc[0] as f64 * rpc,
                    enc[1] as f64 * rpc,
                    enc[2] as f64 * rpc,
                    (k % 97) as f64 * 2.2e-4,
                    enc[0],
                    enc[1],
                    enc[2]
                )?;
                self.next += 1;
            }
        }
        let n = out.len().min(self.buf.len() - self.pos);
        out[..n].copy_from_slice(&self.buf[self.pos..self.pos + n]);
        self.pos += n;
        Ok(n)
    }
}

#[test]
fn one_hour_at_1khz_streams_in_constant_memory() {
    let _alone = ALONE.lock().unwrap_or_else(|e| e.into_inner());
    const ROWS: u64 = 3_600_000;
    let mut reader = LogReader::new(Generator::new(ROWS), "1h.csv", false).unwrap();
    // Warm up: the record buffer has reached its size.
    for _ in 0..10_000 {
        reader.next_row().unwrap().unwrap();
    }
    let before = peak_rss_kb();
    let mut n = 10_000u64;
    let mut sum = 0.0;
    while let Some(row) = reader.next_row().unwrap() {
        sum += row.tau[0];
        n += 1;
    }
    let after = peak_rss_kb();
    eprintln!(
        "{n} rows; peak RSS {before} kB after warm-up, {after} kB at the end (+{} kB)",
        after - before
    );
    assert_eq!(n, ROWS);
    assert!(sum > 0.0);
    // The rows alone are ~300 MB of text; a reader that kept even 8 bytes per row would grow
    // by ~28 MB.
    assert!(
        after - before < 4 * 1024,
        "peak RSS grew by {} kB",
        after - before
    );
}

/// A header, then `len` bytes of digits and commas without a line end (streamed).
struct OneLine {
    header: &'static [u8],
    left: u64,
    at: usize,
}

impl Read for OneLine {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        if self.at < self.header.len() {
            let n = out.len().min(self.header.len() - self.at);
            out[..n].copy_from_slice(&self.header[self.at..self.at + n]);
            self.at += n;
            return Ok(n);
        }
        let n = out.len().min(self.left as usize);
        for (i, b) in out[..n].iter_mut().enumerate() {
            *b = if i % 8 == 7 { b',' } else { b'1' };
        }
        self.left -= n as u64;
        Ok(n)
    }
}

#[test]
fn a_100_mb_line_without_end_is_refused_in_constant_memory() {
    let _alone = ALONE.lock().unwrap_or_else(|e| e.into_inner());
    let input = OneLine {
        header: b"t,q1,q2,q3,tau1,tau2,tau3\n",
        left: 100 << 20,
        at: 0,
    };
    let before = peak_rss_kb();
    let mut reader = LogReader::new(input, "one-line.csv", false).unwrap();
    let e = reader.next_row().unwrap_err();
    let after = peak_rss_kb();
    eprintln!(
        "peak RSS {before} kB before, {after} kB after (+{} kB)",
        after - before
    );
    assert!(
        matches!(e, ReadError::RowTooLong { line: 2, limit, .. } if limit == MAX_ROW_BYTES),
        "{e}"
    );
    assert!(e.to_string().contains("line 2"), "{e}");
    // Reading the whole line would take 100 MB and more (the buffer doubles as it grows); the
    // limit is 1 MiB.
    assert!(
        after - before < 8 * 1024,
        "peak RSS grew by {} kB",
        after - before
    );
}

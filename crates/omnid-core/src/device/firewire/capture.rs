//! Capture files: the raw packets `omnid probe` saw and sent, so that a lab's first contact
//! with a device can be read by a person, sent back, and turned into a replayable log
//! (`omnid convert --from capture`, then `omnid run --device replay:LOG`).
//!
//! Text, one packet per line, after `#` header lines:
//!
//! ```text
//! # omnid capture 1
//! # kind firewire
//! # encoder_sign -1 -1 1
//! # counts_per_rev 15000
//! # ... (identity, registers, notes: anything after `#` is for people)
//! dir,host_ns,iso_header,timestamp,counter,bytes
//! rx,1234567,0x002c00a0,0x1f40,1000,00001e00....
//! tx,1234890,,,,ff07ff07ff07c053...
//! ```
//!
//! `rx` lines carry the 1394 iso header and receive timestamp (3 bits cycleSeconds, 13 bits
//! cycleCount) when the backend has them, the counter of bytes 32..35, and the payload in
//! hex; `tx` lines the command as it went on the wire. Header lines `# key value` with the keys
//! `kind`, `encoder_sign`, `counts_per_rev` and `rate_hz` are read back by the converter;
//! every other `#` line (and `# note` lines between packets) is commentary.

use super::{PacketInfo, Tapped};
use crate::device::STATE_LEN;
use std::fmt::Write as _;
use std::io::{self, BufRead, Write};
use thiserror::Error;

/// First line of every capture.
pub const MAGIC: &str = "# omnid capture 1";
/// The column header line.
pub const COLUMNS: &str = "dir,host_ns,iso_header,timestamp,counter,bytes";

/// Writes a capture.
pub struct CaptureWriter<W: Write> {
    out: W,
    packets: u64,
    started: bool,
}

impl<W: Write> CaptureWriter<W> {
    /// Start a capture with the magic line.
    pub fn new(mut out: W) -> io::Result<Self> {
        writeln!(out, "{MAGIC}")?;
        Ok(CaptureWriter {
            out,
            packets: 0,
            started: false,
        })
    }

    /// A `# key value` header line (before the first packet) or a `# note` (after).
    pub fn comment(&mut self, text: &str) -> io::Result<()> {
        for line in text.lines() {
            if self.started {
                writeln!(self.out, "# note {line}")?;
            } else {
                writeln!(self.out, "# {line}")?;
            }
        }
        Ok(())
    }

    /// One packet received or sent.
    pub fn packet(&mut self, t: &Tapped) -> io::Result<()> {
        if !self.started {
            writeln!(self.out, "{COLUMNS}")?;
            self.started = true;
        }
        let mut hex = String::with_capacity(t.bytes.len() * 2);
        for b in &t.bytes {
            let _ = write!(hex, "{b:02x}");
        }
        match t.received {
            Some(info) => {
                let counter = if t.bytes.len() >= STATE_LEN {
                    crate::device::stream::packet_counter(&t.bytes).to_string()
                } else {
                    String::new()
                };
                writeln!(
                    self.out,
                    "rx,{},{:#010x},{:#06x},{counter},{hex}",
                    t.host_ns, info.iso_header, info.timestamp
                )?;
            }
            None => writeln!(self.out, "tx,{},,,,{hex}", t.host_ns)?,
        }
        self.packets += 1;
        Ok(())
    }

    /// Packets written so far.
    pub fn packets(&self) -> u64 {
        self.packets
    }

    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }

    pub fn into_inner(self) -> W {
        self.out
    }
}

/// A problem reading a capture: names the line (1-based) and what is wrong.
#[derive(Debug, Error)]
pub enum CaptureError {
    #[error("{path}: {source}")]
    Io { path: String, source: io::Error },
    #[error("{path}: line 1: not an omnid capture (the first line is not `{MAGIC}`)")]
    NotACapture { path: String },
    #[error("{path}: line {line}: {message}")]
    Line {
        path: String,
        line: u64,
        message: String,
    },
}

/// One `rx` or `tx` line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CapturedPacket {
    pub line: u64,
    pub host_ns: u64,
    /// `Some` for packets received (with the receive information when the capture has it).
    pub received: Option<Option<PacketInfo>>,
    pub bytes: Vec<u8>,
}

/// What the header says.
#[derive(Debug, Clone, PartialEq)]
pub struct CaptureHeader {
    pub kind: String,
    pub encoder_sign: [i8; 3],
    pub counts_per_rev: f64,
    pub rate_hz: Option<f64>,
}

impl Default for CaptureHeader {
    fn default() -> Self {
        CaptureHeader {
            kind: String::new(),
            encoder_sign: [1; 3],
            counts_per_rev: 15000.0,
            rate_hz: None,
        }
    }
}

/// Reads a capture line by line.
pub struct CaptureReader<R: BufRead> {
    input: R,
    path: String,
    line: u64,
    header: CaptureHeader,
    buf: String,
    pending: Option<String>,
}

impl<R: BufRead> CaptureReader<R> {
    /// Read the header (up to the column line).
    pub fn new(mut input: R, path: &str) -> Result<Self, CaptureError> {
        let io = |source| CaptureError::Io {
            path: path.to_string(),
            source,
        };
        let mut first = String::new();
        input.read_line(&mut first).map_err(io)?;
        if first.trim_end() != MAGIC {
            return Err(CaptureError::NotACapture {
                path: path.to_string(),
            });
        }
        let mut r = CaptureReader {
            input,
            path: path.to_string(),
            line: 1,
            header: CaptureHeader::default(),
            buf: String::new(),
            pending: None,
        };
        while let Some(text) = r.next_line()? {
            if text == COLUMNS {
                break;
            }
            let Some(rest) = text.strip_prefix('#') else {
                // A packet line without the column line: keep it for next_packet.
                r.pending = Some(text);
                break;
            };
            r.header_line(rest.trim())?;
        }
        Ok(r)
    }

    pub fn header(&self) -> &CaptureHeader {
        &self.header
    }

    fn err(&self, message: String) -> CaptureError {
        CaptureError::Line {
            path: self.path.clone(),
            line: self.line,
            message,
        }
    }

    fn next_line(&mut self) -> Result<Option<String>, CaptureError> {
        if let Some(p) = self.pending.take() {
            return Ok(Some(p));
        }
        self.buf.clear();
        let n = self
            .input
            .read_line(&mut self.buf)
            .map_err(|source| CaptureError::Io {
                path: self.path.clone(),
                source,
            })?;
        if n == 0 {
            return Ok(None);
        }
        self.line += 1;
        Ok(Some(self.buf.trim_end().to_string()))
    }

    fn header_line(&mut self, text: &str) -> Result<(), CaptureError> {
        let (key, value) = text.split_once(' ').unwrap_or((text, ""));
        match key {
            "kind" => self.header.kind = value.trim().to_string(),
            "encoder_sign" => {
                let signs: Vec<&str> = value.split_whitespace().collect();
                let parsed: Vec<i8> = signs
                    .iter()
                    .filter_map(|s| s.parse::<i8>().ok())
                    .filter(|s| *s == 1 || *s == -1)
                    .collect();
                if signs.len() != 3 || parsed.len() != 3 {
                    return Err(self.err(format!(
                        "encoder_sign `{value}`: expected three signs, each 1 or -1"
                    )));
                }
                self.header.encoder_sign = [parsed[0], parsed[1], parsed[2]];
            }
            "counts_per_rev" => {
                self.header.counts_per_rev = value
                    .trim()
                    .parse::<f64>()
                    .ok()
                    .filter(|v| v.is_finite() && *v >= 100.0)
                    .ok_or_else(|| {
                        self.err(format!(
                            "counts_per_rev `{value}`: expected a number >= 100"
                        ))
                    })?;
            }
            "rate_hz" => {
                self.header.rate_hz = Some(
                    value
                        .trim()
                        .parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite() && *v > 0.0)
                        .ok_or_else(|| {
                            self.err(format!("rate_hz `{value}`: expected a number > 0"))
                        })?,
                );
            }
            _ => {}
        }
        Ok(())
    }

    /// The next packet, skipping `#` lines; `None` at the end.
    pub fn next_packet(&mut self) -> Result<Option<CapturedPacket>, CaptureError> {
        loop {
            let Some(text) = self.next_line()? else {
                return Ok(None);
            };
            if text.starts_with('#') || text.is_empty() {
                continue;
            }
            return self.parse_packet(&text).map(Some);
        }
    }

    fn parse_packet(&self, text: &str) -> Result<CapturedPacket, CaptureError> {
        let f: Vec<&str> = text.split(',').collect();
        if f.len() != 6 {
            return Err(self.err(format!("{} fields, expected 6 ({COLUMNS})", f.len())));
        }
        let host_ns = f[1]
            .parse::<u64>()
            .map_err(|_| self.err(format!("host_ns `{}` is not a whole number", f[1])))?;
        let hex = |name: &str, v: &str, max: u64| -> Result<u64, CaptureError> {
            v.strip_prefix("0x")
                .and_then(|h| u64::from_str_radix(h, 16).ok())
                .filter(|x| *x <= max)
                .ok_or_else(|| self.err(format!("{name} `{v}` is not a hex number 0x0..={max:#x}")))
        };
        let bytes = f[5];
        if !bytes.len().is_multiple_of(2) || !bytes.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(self.err(format!(
                "bytes `{}`: expected an even number of hex digits",
                truncate(bytes)
            )));
        }
        let bytes: Vec<u8> = (0..bytes.len() / 2)
            .map(|i| u8::from_str_radix(&bytes[2 * i..2 * i + 2], 16).unwrap_or(0))
            .collect();
        let received = match f[0] {
            "tx" => None,
            "rx" if f[2].is_empty() && f[3].is_empty() => Some(None),
            "rx" => Some(Some(PacketInfo {
                len: bytes.len(),
                iso_header: hex("iso_header", f[2], u64::from(u32::MAX))? as u32,
                timestamp: hex("timestamp", f[3], u64::from(u16::MAX))? as u16,
            })),
            other => {
                return Err(self.err(format!(
                    "direction `{}`: expected rx or tx",
                    truncate(other)
                )))
            }
        };
        Ok(CapturedPacket {
            line: self.line,
            host_ns,
            received,
            bytes,
        })
    }
}

fn truncate(s: &str) -> String {
    if s.len() > 40 {
        format!(
            "{}…",
            &s[..s.char_indices().nth(40).map_or(s.len(), |(i, _)| i)]
        )
    } else {
        s.to_string()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tapped(rx: bool, bytes: &[u8]) -> Tapped {
        Tapped {
            host_ns: 42,
            received: rx.then_some(PacketInfo {
                len: bytes.len(),
                iso_header: 0x002C_00A0,
                timestamp: 0x1F40,
            }),
            bytes: bytes.to_vec(),
        }
    }

    #[test]
    fn round_trip_header_packets_and_notes() {
        let mut w = CaptureWriter::new(Vec::new()).unwrap();
        w.comment("kind firewire\nencoder_sign -1 -1 1\ncounts_per_rev 15000\nrate_hz 1000")
            .unwrap();
        w.comment("serial 10203400567").unwrap();
        let mut state = [0u8; 44];
        state[32] = 7;
        w.packet(&tapped(true, &state)).unwrap();
        w.comment("stylus docked").unwrap();
        w.packet(&tapped(false, &[0xFF, 0x07])).unwrap();
        let text = String::from_utf8(w.into_inner()).unwrap();
        assert!(text.contains("rx,42,0x002c00a0,0x1f40,7,"), "{text}");
        assert!(
            text.contains("# note stylus docked\ntx,42,,,,ff07\n"),
            "{text}"
        );
        let mut r = CaptureReader::new(text.as_bytes(), "c.txt").unwrap();
        assert_eq!(r.header().kind, "firewire");
        assert_eq!(r.header().encoder_sign, [-1, -1, 1]);
        assert_eq!(r.header().rate_hz, Some(1000.0));
        let p = r.next_packet().unwrap().unwrap();
        assert_eq!(p.bytes, state.to_vec());
        assert_eq!(p.received.unwrap().unwrap().timestamp, 0x1F40);
        let p = r.next_packet().unwrap().unwrap();
        assert_eq!((p.received, p.bytes), (None, vec![0xFF, 0x07]));
        assert!(r.next_packet().unwrap().is_none());
    }

    #[test]
    fn bad_lines_are_named() {
        assert!(matches!(
            CaptureReader::new("t,q1\n".as_bytes(), "x"),
            Err(CaptureError::NotACapture { .. })
        ));
        let e = CaptureReader::new(format!("{MAGIC}\n# encoder_sign 1 2 1\n").as_bytes(), "x")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("line 2") && e.contains("encoder_sign"), "{e}");
        for (line, says) in [
            ("rx,1,0x1,0x2,3,0g", "hex digits"),
            ("rx,1,0x1,0x20000,3,00", "timestamp"),
            ("zz,1,,,,00", "direction"),
            ("rx,x,,,,00", "host_ns"),
            ("rx,1,2", "3 fields"),
        ] {
            let text = format!("{MAGIC}\n{COLUMNS}\n{line}\n");
            let mut r = CaptureReader::new(text.as_bytes(), "x").unwrap();
            let e = r.next_packet().unwrap_err().to_string();
            assert!(e.contains("line 3") && e.contains(says), "{line}: {e}");
        }
    }
}

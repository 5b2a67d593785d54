//! Plain CDR (XCDR1), the encoding of ROS 2 messages in MCAP files and on rmw_zenoh
//! (docs/ROS2.md, CDR): a 4-byte encapsulation header (`00 01 00 00`, little-endian, is what
//! omnid writes; a reader also takes `00 00 ..`, big-endian, as some peers send), then the
//! fields in order, each primitive aligned to its size counted from the end of the header;
//! strings as a u32 length (bytes + 1) followed by the bytes and a NUL; sequences as a u32
//! count followed by the elements (no element alignment when the sequence is empty).

// One method per CDR type, named for it: documenting each would repeat its name.
#![allow(missing_docs)]

use thiserror::Error;

/// Encapsulation header: CDR, little-endian, no options.
pub const HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Encapsulation header of big-endian plain CDR (accepted when read).
pub const HEADER_BE: [u8; 2] = [0x00, 0x00];

/// Appends one CDR message to a byte buffer.
pub struct CdrWriter<'a> {
    out: &'a mut Vec<u8>,
    /// Where alignment is counted from (just after the encapsulation header).
    origin: usize,
}

impl<'a> CdrWriter<'a> {
    /// Start a message at the end of `out` (the header is written now).
    pub fn new(out: &'a mut Vec<u8>) -> Self {
        out.extend_from_slice(&HEADER);
        let origin = out.len();
        CdrWriter { out, origin }
    }

    fn align(&mut self, n: usize) {
        let pad = (n - (self.out.len() - self.origin) % n) % n;
        self.out.resize(self.out.len() + pad, 0);
    }

    pub fn u8(&mut self, v: u8) {
        self.out.push(v);
    }
    pub fn bool(&mut self, v: bool) {
        self.out.push(u8::from(v));
    }
    pub fn i32(&mut self, v: i32) {
        self.align(4);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn u32(&mut self, v: u32) {
        self.align(4);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f32(&mut self, v: f32) {
        self.align(4);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn i64(&mut self, v: i64) {
        self.align(8);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn f64(&mut self, v: f64) {
        self.align(8);
        self.out.extend_from_slice(&v.to_le_bytes());
    }
    pub fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.out.extend_from_slice(s.as_bytes());
        self.out.push(0);
    }
    /// A sequence's element count.
    pub fn count(&mut self, n: usize) {
        self.u32(n as u32);
    }
    pub fn f64s(&mut self, v: &[f64]) {
        self.count(v.len());
        for x in v {
            self.f64(*x);
        }
    }
    pub fn i64s(&mut self, v: &[i64]) {
        self.count(v.len());
        for x in v {
            self.i64(*x);
        }
    }
    pub fn f32s(&mut self, v: &[f32]) {
        self.count(v.len());
        for x in v {
            self.f32(*x);
        }
    }
    pub fn i32s(&mut self, v: &[i32]) {
        self.count(v.len());
        for x in v {
            self.i32(*x);
        }
    }
    pub fn strings(&mut self, v: &[&str]) {
        self.count(v.len());
        for s in v {
            self.string(s);
        }
    }
}

/// Why a CDR message could not be read. Offsets count from the message's first byte.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum CdrError {
    /// Not a plain CDR header.
    #[error("encapsulation header {found:02x?} is not plain CDR (00 01 00 00, or 00 00 00 00)")]
    Header {
        /// The first bytes found.
        found: Vec<u8>,
    },
    /// The message ended inside a field.
    #[error("ends at byte {len}, inside {what} at byte {at}")]
    Short {
        /// What was being read.
        what: &'static str,
        /// Where it starts.
        at: usize,
        /// The message's length.
        len: usize,
    },
    /// A string without its NUL, or not UTF-8.
    #[error("the string at byte {at} is {why}")]
    BadString {
        /// Where its length starts.
        at: usize,
        /// What is wrong with it.
        why: &'static str,
    },
    /// A sequence longer than its message could hold.
    #[error("the sequence at byte {at} claims {count} elements, more than the message holds")]
    Count {
        /// Where its count starts.
        at: usize,
        /// The count read.
        count: u32,
    },
    /// A sequence of another length than the reader needs.
    #[error("the sequence at byte {at} has {count} elements, expected {want}")]
    Length {
        /// Where its count starts.
        at: usize,
        /// The count read.
        count: u32,
        /// The count needed.
        want: usize,
    },
    /// Bytes left after the last field.
    #[error("{extra} bytes after the last field")]
    Trailing {
        /// How many.
        extra: usize,
    },
}

/// Reads one CDR message field by field.
pub struct CdrReader<'a> {
    buf: &'a [u8],
    pos: usize,
    /// The message is big-endian (header `00 00`).
    big: bool,
}

/// A primitive read in the message's byte order.
macro_rules! read_num {
    ($self:ident, $t:ty, $n:literal, $what:literal) => {{
        let b: [u8; $n] = $self.take($n, $n, $what)?.try_into().unwrap_or([0; $n]);
        Ok(if $self.big {
            <$t>::from_be_bytes(b)
        } else {
            <$t>::from_le_bytes(b)
        })
    }};
}

impl<'a> CdrReader<'a> {
    /// Check the header of `buf` and start after it.
    pub fn new(buf: &'a [u8]) -> Result<Self, CdrError> {
        // The options (bytes 2 and 3) carry nothing for plain CDR and are not checked.
        let big = match buf.get(..2) {
            Some(h) if buf.len() >= 4 && h == &HEADER[..2] => false,
            Some(h) if buf.len() >= 4 && h == HEADER_BE => true,
            _ => {
                return Err(CdrError::Header {
                    found: buf[..buf.len().min(4)].to_vec(),
                })
            }
        };
        Ok(CdrReader { buf, pos: 4, big })
    }

    fn take(&mut self, n: usize, align: usize, what: &'static str) -> Result<&'a [u8], CdrError> {
        let pad = (align - (self.pos - 4) % align) % align;
        let at = self.pos + pad;
        let end = at.checked_add(n).filter(|&e| e <= self.buf.len());
        let Some(end) = end else {
            return Err(CdrError::Short {
                what,
                at,
                len: self.buf.len(),
            });
        };
        self.pos = end;
        Ok(&self.buf[at..end])
    }

    pub fn u8(&mut self) -> Result<u8, CdrError> {
        Ok(self.take(1, 1, "a byte")?[0])
    }
    pub fn bool(&mut self) -> Result<bool, CdrError> {
        Ok(self.take(1, 1, "a bool")?[0] != 0)
    }
    pub fn i32(&mut self) -> Result<i32, CdrError> {
        read_num!(self, i32, 4, "an int32")
    }
    pub fn u32(&mut self) -> Result<u32, CdrError> {
        read_num!(self, u32, 4, "a uint32")
    }
    pub fn f32(&mut self) -> Result<f32, CdrError> {
        read_num!(self, f32, 4, "a float32")
    }
    pub fn i64(&mut self) -> Result<i64, CdrError> {
        read_num!(self, i64, 8, "an int64")
    }
    pub fn f64(&mut self) -> Result<f64, CdrError> {
        read_num!(self, f64, 8, "a float64")
    }
    pub fn string(&mut self) -> Result<&'a str, CdrError> {
        let n = self.u32()? as usize;
        let at = self.pos - 4;
        if n == 0 {
            return Err(CdrError::BadString {
                at,
                why: "of length 0 (no room for its NUL)",
            });
        }
        let bytes = self.take(n, 1, "a string")?;
        if bytes[n - 1] != 0 {
            return Err(CdrError::BadString {
                at,
                why: "not NUL-terminated",
            });
        }
        std::str::from_utf8(&bytes[..n - 1]).map_err(|_| CdrError::BadString {
            at,
            why: "not UTF-8",
        })
    }
    /// A sequence's element count, checked against what the rest of the message can hold
    /// (`min_size`: the least bytes one element takes), so a lying count never allocates.
    pub fn count(&mut self, min_size: usize) -> Result<usize, CdrError> {
        let count = self.u32()?;
        let at = self.pos - 4;
        let left = self.buf.len() - self.pos;
        if (count as usize).saturating_mul(min_size.max(1)) > left {
            return Err(CdrError::Count { at, count });
        }
        Ok(count as usize)
    }
    /// A sequence of exactly `N` elements (`min_size`: as for [`Self::count`]), checked and
    /// taken without allocating.
    fn exactly<const N: usize>(&mut self, min_size: usize) -> Result<(), CdrError> {
        let n = self.count(min_size)?;
        let at = self.pos - 4;
        if n != N {
            return Err(CdrError::Length {
                at,
                count: n as u32,
                want: N,
            });
        }
        Ok(())
    }
    pub fn f64_array<const N: usize>(&mut self) -> Result<[f64; N], CdrError> {
        self.exactly::<N>(8)?;
        let mut v = [0.0; N];
        for x in &mut v {
            *x = self.f64()?;
        }
        Ok(v)
    }
    pub fn i64_array<const N: usize>(&mut self) -> Result<[i64; N], CdrError> {
        self.exactly::<N>(8)?;
        let mut v = [0; N];
        for x in &mut v {
            *x = self.i64()?;
        }
        Ok(v)
    }
    pub fn i32_array<const N: usize>(&mut self) -> Result<[i32; N], CdrError> {
        self.exactly::<N>(4)?;
        let mut v = [0; N];
        for x in &mut v {
            *x = self.i32()?;
        }
        Ok(v)
    }
    /// A float32 sequence that must be empty.
    pub fn f32_array_empty(&mut self) -> Result<(), CdrError> {
        self.exactly::<0>(4)
    }
    pub fn f64s(&mut self) -> Result<Vec<f64>, CdrError> {
        let n = self.count(8)?;
        (0..n).map(|_| self.f64()).collect()
    }
    pub fn strings(&mut self) -> Result<Vec<&'a str>, CdrError> {
        let n = self.count(5)?;
        (0..n).map(|_| self.string()).collect()
    }
    /// The message must end here (up to 3 zero bytes of padding to a 4-byte boundary, which
    /// some writers add, are allowed).
    pub fn end(&self) -> Result<(), CdrError> {
        let rest = &self.buf[self.pos..];
        if rest.len() < 4 && rest.iter().all(|&b| b == 0) {
            Ok(())
        } else {
            Err(CdrError::Trailing { extra: rest.len() })
        }
    }
}

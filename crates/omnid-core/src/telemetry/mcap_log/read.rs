//! Reading omnid MCAP logs back: tick records in file order ([`McapTicks`]), and the same
//! rows as the CSV log's text ([`McapAsCsv`]), so every reader of logs (replay, identify,
//! plot, experiment, convert) reads MCAP through the one CSV reader and its checks. The file
//! is read as a stream (no seeking, bounded memory), so a FIFO works and a file cut short by a
//! killed run reads up to its last whole chunk.

use super::{MAGIC, TOPICS};
use crate::ros2::cdr::CdrError;
use crate::ros2::msgs;
use crate::telemetry::record::{HapticRecord, LogSchema, Mode, TickRecord};
use mcap::sans_io::linear_reader::{LinearReadEvent, LinearReader, LinearReaderOptions};
use std::io::{self, Read};
use thiserror::Error;

/// The longest record accepted (a chunk omnid writes is about 1 MiB before compression).
const MAX_RECORD_BYTES: usize = 64 << 20;

/// The most a chunk may inflate to, checked against the size its header declares before any
/// of it is decompressed; decompression then stops at the declared size (docs/MCAP.md,
/// "Reading"). A chunk omnid writes inflates to about 1 MiB.
pub const MAX_CHUNK_BYTES: u64 = 64 << 20;

/// Where a record starts: its byte offset in the file, or, for a record inside a chunk, its
/// offset in the chunk's decompressed records and the chunk's offset in the file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Place {
    /// A record of the file itself.
    File(u64),
    /// A record inside a chunk.
    Chunk {
        /// The chunk record's offset in the file.
        chunk: u64,
        /// The record's offset in the chunk's decompressed records.
        within: u64,
    },
}

impl std::fmt::Display for Place {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Place::File(at) => write!(f, "at byte {at}"),
            Place::Chunk { chunk, within } => {
                write!(f, "at byte {within} inside the chunk at byte {chunk}")
            }
        }
    }
}

/// Why an MCAP log cannot be read. Records are counted from 1 in file order, chunks'
/// contents included; the file's name is added by whoever reports it.
#[derive(Debug, Error)]
pub enum McapReadError {
    /// The file is damaged (a bad CRC, a record that does not parse, a message that does
    /// not decode).
    #[error("MCAP record {record} ({at}): {reason}")]
    Bad {
        /// Which record.
        record: u64,
        /// Where it starts.
        at: Place,
        /// What is wrong.
        reason: String,
    },
    /// The file ends before its end (a run killed mid-way).
    #[error(
        "the MCAP file ends inside record {record} (which starts at byte {at}), after {rows} \
         whole rows (a run that was killed mid-way?); --lenient reads those rows"
    )]
    Truncated {
        /// The record it ends in.
        record: u64,
        /// The file offset where that record starts.
        at: u64,
        /// Whole rows before it.
        rows: u64,
    },
    /// A well-formed MCAP file, but not an omnid log.
    #[error("an MCAP file, but not an omnid log: {0}")]
    Foreign(String),
}

/// What each channel id of the file is (an index into [`TOPICS`], or a channel omnid does not
/// read).
#[derive(Default)]
struct Channels {
    /// Each schema id's name and encoding.
    schemas: std::collections::HashMap<u16, (String, String)>,
    by_id: std::collections::HashMap<u16, Option<usize>>,
    /// The bytes each schema and channel id was first defined with: a record defining it
    /// again must be the same (the MCAP format's rule).
    schema_bytes: std::collections::HashMap<u16, Vec<u8>>,
    channel_bytes: std::collections::HashMap<u16, Vec<u8>>,
    present: [bool; TOPICS.len()],
}

/// Streams the tick records of an omnid MCAP log. After the first chunk it allocates nothing
/// per row (a replay reads it on the servo thread).
pub struct McapTicks<R: Read> {
    input: R,
    reader: LinearReader,
    /// Reads the chunk records the file reader hands over, one at a time, after their
    /// declared size was checked.
    chunks: LinearReader,
    /// A chunk is being read from `chunks`.
    in_chunk: bool,
    state: State,
    lenient: bool,
    done: bool,
}

/// Everything but the byte source: borrowed apart from the reader, so a record can be taken
/// while the reader still holds its bytes.
struct State {
    channels: Channels,
    record: u64,
    /// The file offset of the next record of the file, and of the chunk being read.
    offset: u64,
    chunk_at: u64,
    /// The offset of the next record in the chunk's decompressed records.
    within: u64,
    /// Where the record being taken starts.
    at: Place,
    /// The sizes declared by the chunks handed to the decompressor: the most it can have
    /// produced (it stops at a chunk's declared size).
    inflated: u64,
    rows: u64,
    /// The row being put together, and which of its per-tick topics have come.
    row: TickRecord,
    seen: u32,
    /// Carried values (flags 1, mode 2, amplifiers 4) have all been seen once.
    carried: u32,
}

fn blank() -> TickRecord {
    TickRecord {
        t: f64::NAN,
        q: [f64::NAN; 3],
        tau: [f64::NAN; 3],
        qf: [f64::NAN; 3],
        qd: [f64::NAN; 3],
        qdd: [f64::NAN; 3],
        reference: [f64::NAN; 3],
        tau_cmd: [f64::NAN; 3],
        tau_hat: [f64::NAN; 3],
        tau_model: [f64::NAN; 3],
        tau_ext: [f64::NAN; 3],
        enc: [0; 3],
        amps: false,
        mode: Mode::Stop,
        flags: 0,
        haptic: HapticRecord {
            tip_mm: [f64::NAN; 3],
            force: [f64::NAN; 3],
            hand: [f64::NAN; 3],
            fext: [f64::NAN; 3],
        },
        live: Default::default(),
    }
}

impl<R: Read> McapTicks<R> {
    /// Read from `input` (its first bytes must be the MCAP magic). `lenient`: a file that ends
    /// early ends after its last whole row instead of being an error.
    pub fn new(input: R, lenient: bool) -> Self {
        // A chunk's CRC is checked before any of its messages is taken, so a chunk cut short
        // or damaged yields nothing rather than unchecked rows.
        // Chunks are handed over whole, so their declared size is checked before anything is
        // decompressed, and a record inside one is known to be.
        let options = LinearReaderOptions::default()
            .with_emit_chunks(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true)
            .with_record_length_limit(MAX_RECORD_BYTES);
        let chunks = LinearReaderOptions::default()
            .with_skip_start_magic(true)
            .with_skip_end_magic(true)
            .with_prevalidate_chunk_crcs(true)
            .with_record_length_limit(MAX_RECORD_BYTES);
        McapTicks {
            input,
            reader: LinearReader::new_with_options(options),
            chunks: LinearReader::new_with_options(chunks),
            in_chunk: false,
            state: State {
                channels: Channels::default(),
                record: 0,
                offset: super::MAGIC.len() as u64,
                chunk_at: 0,
                within: 0,
                at: Place::File(0),
                inflated: 0,
                rows: 0,
                row: blank(),
                seen: 0,
                carried: 0,
            },
            lenient,
            done: false,
        }
    }

    /// The columns the log carries (known once the first row is read, or at the end).
    pub fn schema(&self) -> LogSchema {
        self.state.schema()
    }

    /// The next tick, `None` at the end of the file.
    pub fn next_tick(&mut self) -> Result<Option<TickRecord>, io::Error> {
        self.next_inner().map_err(|e| match e {
            Next::Io(e) => e,
            Next::Read(e) => io::Error::new(io::ErrorKind::InvalidData, e),
        })
    }

    fn next_inner(&mut self) -> Result<Option<TickRecord>, Next> {
        if self.done {
            return Ok(None);
        }
        let result = self.next_record();
        if result.is_err() {
            self.done = true;
        }
        result
    }

    fn next_record(&mut self) -> Result<Option<TickRecord>, Next> {
        loop {
            if self.in_chunk {
                // The chunk was handed over whole: a request for more bytes means it is done.
                match self.chunks.next_event() {
                    None | Some(Ok(LinearReadEvent::ReadRequest(_))) => self.in_chunk = false,
                    Some(Ok(LinearReadEvent::Record { data, opcode })) => {
                        let state = &mut self.state;
                        state.record += 1;
                        state.at = Place::Chunk {
                            chunk: state.chunk_at,
                            within: state.within,
                        };
                        state.within += 9 + data.len() as u64;
                        if let Some(row) = state.record_in(opcode, data, true)? {
                            return Ok(Some(row));
                        }
                    }
                    Some(Err(e)) => {
                        let state = &mut self.state;
                        state.at = Place::Chunk {
                            chunk: state.chunk_at,
                            within: state.within,
                        };
                        state.record += 1;
                        return Err(Next::Read(state.bad(e.to_string())));
                    }
                }
                continue;
            }
            let event = match self.reader.next_event() {
                None => {
                    self.done = true;
                    self.state.check_is_omnid().map_err(Next::Read)?;
                    return Ok(None);
                }
                Some(e) => e,
            };
            match event {
                Ok(LinearReadEvent::ReadRequest(n)) => {
                    let buf = self.reader.insert(n.max(1 << 16));
                    let got = loop {
                        match self.input.read(buf) {
                            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
                            other => break other,
                        }
                    }
                    .map_err(Next::Io)?;
                    self.reader.notify_read(got);
                }
                Ok(LinearReadEvent::Record { data, opcode }) => {
                    let state = &mut self.state;
                    state.record += 1;
                    state.at = Place::File(state.offset);
                    state.offset += 9 + data.len() as u64;
                    // The format has one Header, the file's first record.
                    let first = state.record == 1;
                    if first != (opcode == mcap::records::op::HEADER) {
                        return Err(Next::Read(state.bad(if first {
                            format!("the first record is opcode {opcode:#04x}, not a Header")
                        } else {
                            "a second Header record (a file has one, its first)".into()
                        })));
                    }
                    if opcode == mcap::records::op::CHUNK {
                        state.chunk(data)?;
                        // The whole record, as the chunk reader reads it from a file.
                        let buf = self.chunks.insert(9 + data.len());
                        buf[0] = opcode;
                        buf[1..9].copy_from_slice(&(data.len() as u64).to_le_bytes());
                        buf[9..].copy_from_slice(data);
                        self.chunks.notify_read(9 + data.len());
                        self.in_chunk = true;
                        continue;
                    }
                    if let Some(row) = state.record_in(opcode, data, false)? {
                        return Ok(Some(row));
                    }
                }
                Err(mcap::McapError::UnexpectedEof) => {
                    self.done = true;
                    if self.lenient {
                        self.state.check_is_omnid().map_err(Next::Read)?;
                        return Ok(None);
                    }
                    return Err(Next::Read(McapReadError::Truncated {
                        record: self.state.record + 1,
                        at: self.state.offset,
                        rows: self.state.rows,
                    }));
                }
                Err(e) => {
                    let state = &mut self.state;
                    state.record += 1;
                    state.at = Place::File(state.offset);
                    return Err(Next::Read(state.bad(e.to_string())));
                }
            }
        }
    }

    /// The most the decompressor can have produced so far: the sizes declared by the chunks
    /// it was given (it stops at a chunk's declared size).
    pub fn inflated_bytes(&self) -> u64 {
        self.state.inflated
    }
}

impl State {
    /// A chunk record of the file: refused before any of it is decompressed if it declares
    /// more than [`MAX_CHUNK_BYTES`].
    fn chunk(&mut self, data: &[u8]) -> Result<(), Next> {
        // Start and end times (8 + 8), then the uncompressed size.
        let Some(size) = data.get(16..24) else {
            return Err(Next::Read(
                self.bad("a chunk record too short for its header"),
            ));
        };
        let size = u64::from_le_bytes(size.try_into().unwrap_or_default());
        if size > MAX_CHUNK_BYTES {
            return Err(Next::Read(self.bad(format!(
                "a chunk that inflates to {size} bytes, over the {} MiB a chunk may hold",
                MAX_CHUNK_BYTES >> 20
            ))));
        }
        self.inflated += size;
        self.chunk_at = match self.at {
            Place::File(at) => at,
            Place::Chunk { chunk, .. } => chunk,
        };
        self.within = 0;
        Ok(())
    }

    /// One record, of the file or (`in_chunk`) inside a chunk; a whole row when it completes
    /// one.
    fn record_in(
        &mut self,
        opcode: u8,
        data: &[u8],
        in_chunk: bool,
    ) -> Result<Option<TickRecord>, Next> {
        use mcap::records::op;
        let refuse = |state: &Self, reason: String| Err(Next::Read(state.bad(reason)));
        match opcode {
            0x00 => return refuse(self, "opcode 0x00, which no record has".into()),
            0x80..=0xff => {
                return refuse(
                    self,
                    format!(
                        "a private record (opcode {opcode:#04x}), which an omnid log does not \
                         hold and omnid does not read"
                    ),
                )
            }
            op::SCHEMA | op::CHANNEL | op::MESSAGE => {}
            op::CHUNK if in_chunk => return refuse(self, "a chunk inside a chunk".into()),

            _ if in_chunk => {
                return refuse(
                    self,
                    format!(
                        "a record of opcode {opcode:#04x} inside a chunk, which holds only \
                         schemas, channels and messages"
                    ),
                )
            }
            // Indexes, statistics, metadata: they say nothing about the rows, and are not
            // parsed (that would allocate).
            _ => return Ok(None),
        }
        if self.known_again(opcode, data).map_err(Next::Read)? {
            return Ok(None);
        }
        let record =
            mcap::parse_record(opcode, data).map_err(|e| Next::Read(self.bad(e.to_string())))?;
        match &record {
            mcap::records::Record::Schema { header, .. } => {
                self.channels.schema_bytes.insert(header.id, data.to_vec());
            }
            mcap::records::Record::Channel(c) => {
                self.channels.channel_bytes.insert(c.id, data.to_vec());
            }
            _ => {}
        }
        self.take(record).map_err(Next::Read)
    }
    fn schema(&self) -> LogSchema {
        LogSchema {
            model: self.channels.present[super::TORQUE_MODEL.id],
            // Absent from logs written before the estimate was logged: those read as before.
            external: self.channels.present[super::TORQUE_EXTERNAL.id],
            buttons: self.channels.present[super::BUTTONS.id],
        }
    }

    /// A Schema or Channel record whose id is already known: writers repeat them in every
    /// chunk (so a chunk reads alone), and parsing one again would allocate its strings. The
    /// format requires every record of an id to be the same: one that is not is refused.
    fn known_again(&self, opcode: u8, data: &[u8]) -> Result<bool, McapReadError> {
        let Some(id) = data.get(..2).map(|b| u16::from_le_bytes([b[0], b[1]])) else {
            return Ok(false);
        };
        let (first, what) = match opcode {
            mcap::records::op::SCHEMA => (self.channels.schema_bytes.get(&id), "schema"),
            mcap::records::op::CHANNEL => (self.channels.channel_bytes.get(&id), "channel"),
            _ => return Ok(false),
        };
        match first {
            None => Ok(false),
            Some(first) if first[..] == *data => Ok(true),
            Some(first) => {
                let describe = |bytes: &[u8]| match mcap::parse_record(opcode, bytes) {
                    Ok(mcap::records::Record::Schema { header, .. }) => {
                        format!("`{}` in {:?}", header.name, header.encoding)
                    }
                    Ok(mcap::records::Record::Channel(c)) => format!(
                        "`{}` of schema {}{}",
                        c.topic,
                        c.schema_id,
                        self.channels
                            .schemas
                            .get(&c.schema_id)
                            .map(|(name, _)| format!(" ({name})"))
                            .unwrap_or_default()
                    ),
                    _ => "a record that does not parse".into(),
                };
                Err(self.bad(format!(
                    "{what} {id} defined again differently: first as {}, now as {} (a {what} \
                     id must always mean the same)",
                    describe(first),
                    describe(data)
                )))
            }
        }
    }

    fn bad(&self, reason: impl Into<String>) -> McapReadError {
        McapReadError::Bad {
            record: self.record,
            at: self.at,
            reason: reason.into(),
        }
    }

    fn check_is_omnid(&self) -> Result<(), McapReadError> {
        for t in [super::JOINT_STATES, super::TIME] {
            if !self.channels.present[t.id] {
                return Err(McapReadError::Foreign(format!(
                    "no {} channel ({} channels in all)",
                    t.name,
                    self.channels.by_id.len()
                )));
            }
        }
        Ok(())
    }

    /// Take one record; a whole row when it completes one.
    fn take(
        &mut self,
        record: mcap::records::Record<'_>,
    ) -> Result<Option<TickRecord>, McapReadError> {
        use mcap::records::Record;
        match record {
            Record::Schema { header, .. } => {
                self.channels
                    .schemas
                    .insert(header.id, (header.name, header.encoding));
            }
            Record::Channel(c) => {
                let known = TOPICS.iter().position(|t| t.name == c.topic);
                if let Some(i) = known {
                    let want = TOPICS[i].ty.name;
                    let have = self.channels.schemas.get(&c.schema_id);
                    let name = have.map(|(name, _)| name.as_str());
                    if name != Some(want) || c.message_encoding != "cdr" {
                        return Err(self.bad(format!(
                            "channel {} is {} in {:?}, not omnid's {want} in CDR",
                            c.topic,
                            name.unwrap_or("(no schema)"),
                            c.message_encoding
                        )));
                    }
                    // omnid reads its messages as the ROS 2 definitions say (docs/ROS2.md).
                    if let Some((_, encoding)) = have.filter(|(_, e)| e != "ros2msg") {
                        return Err(self.bad(format!(
                            "channel {}'s schema {want} is in {encoding:?}, not the \
                             \"ros2msg\" omnid reads",
                            c.topic
                        )));
                    }
                    self.channels.present[i] = true;
                }
                self.channels.by_id.insert(c.id, known);
            }
            Record::Message { header, data } => {
                let Some(&known) = self.channels.by_id.get(&header.channel_id) else {
                    return Err(self.bad(format!(
                        "a message on channel {}, which no Channel record declared",
                        header.channel_id
                    )));
                };
                if let Some(i) = known {
                    return self
                        .message(i, &data)
                        .map_err(|reason| self.bad(format!("{}: {reason}", TOPICS[i].name)));
                }
            }
            _ => {}
        }
        Ok(None)
    }

    fn message(&mut self, i: usize, data: &[u8]) -> Result<Option<TickRecord>, String> {
        let topic = TOPICS[i];
        let cdr = |e: CdrError| e.to_string();
        let bit = 1u32 << i;
        let r = &mut self.row;
        match topic {
            t if t == super::TIME => {
                r.t = msgs::read_float64(data).map_err(cdr)?;
                self.seen = bit;
                return Ok(None);
            }
            t if t == super::ROBOT_DESCRIPTION || t == super::EVENTS || t == super::CONTROLLER => {
                msgs::read_string(data).map_err(cdr)?;
                return Ok(None);
            }
            t if t == super::TF => {
                msgs::read_tf(data).map_err(cdr)?;
                return Ok(None);
            }
            _ => {}
        }
        if self.seen & (1 << super::TIME.id) == 0 {
            return Err("comes before its tick's /omnid/time".into());
        }
        let arr = |data: &[u8]| msgs::read_f64_array_n::<3>(data).map_err(cdr);
        match topic {
            t if t == super::ESTIMATE_POSITION => r.qf = arr(data)?,
            t if t == super::ESTIMATE_ACCELERATION => r.qdd = arr(data)?,
            t if t == super::REFERENCE => r.reference = arr(data)?,
            t if t == super::TORQUE_CONTROLLER => r.tau_cmd = arr(data)?,
            t if t == super::TORQUE_PREDICTED => r.tau_hat = arr(data)?,
            t if t == super::TORQUE_MODEL => r.tau_model = arr(data)?,
            t if t == super::TORQUE_EXTERNAL => r.tau_ext = arr(data)?,
            t if t == super::TIP_MM => r.haptic.tip_mm = arr(data)?,
            t if t == super::HEAT => r.live.heat = arr(data)?,
            t if t == super::TIP_POSE => {
                msgs::read_pose_stamped(data).map_err(cdr)?;
            }
            t if t == super::TIP_FORCE => {
                r.haptic.force = msgs::read_wrench_stamped(data).map_err(cdr)?.1
            }
            t if t == super::HAND_FORCE => {
                r.haptic.hand = msgs::read_wrench_stamped(data).map_err(cdr)?.1
            }
            t if t == super::EXTERNAL_FORCE => {
                r.haptic.fext = msgs::read_wrench_stamped(data).map_err(cdr)?.1
            }
            t if t == super::ENCODERS => r.enc = msgs::read_i64_array_n::<3>(data).map_err(cdr)?,
            t if t == super::FLAGS => {
                r.flags = msgs::read_uint32(data).map_err(cdr)?;
                self.carried |= 1;
            }
            t if t == super::MODE => {
                let s = msgs::read_string(data).map_err(cdr)?;
                r.mode = Mode::parse(s)
                    .ok_or_else(|| format!("unknown mode `{}`", crate::text::cut(s)))?;
                self.carried |= 2;
            }
            t if t == super::AMPLIFIERS => {
                r.amps = msgs::read_bool(data).map_err(cdr)?;
                self.carried |= 4;
            }
            t if t == super::BUTTONS => {
                let b = msgs::read_joy_buttons::<3>(data).map_err(cdr)?;
                r.live.buttons = [b[0] == 1, b[1] == 1];
                r.live.inkwell = b[2] == 1;
            }
            t if t == super::JOINT_STATES => {
                (r.q, r.qd, r.tau) = msgs::read_joint_state_n::<3>(data).map_err(cdr)?;
                return self.complete().map(Some);
            }
            _ => {}
        }
        self.seen |= bit;
        Ok(None)
    }

    /// `/joint_states` closes the row: every per-tick channel must have come.
    fn complete(&mut self) -> Result<TickRecord, String> {
        let schema = self.schema();
        let per_tick = [
            super::ESTIMATE_POSITION,
            super::ESTIMATE_ACCELERATION,
            super::REFERENCE,
            super::TORQUE_CONTROLLER,
            super::TORQUE_PREDICTED,
            super::TORQUE_MODEL,
            super::TORQUE_EXTERNAL,
            super::TIP_MM,
            super::TIP_FORCE,
            super::HAND_FORCE,
            super::EXTERNAL_FORCE,
            super::ENCODERS,
        ];
        for t in per_tick {
            if schema.has(t.group) && self.seen & (1 << t.id) == 0 {
                return Err(format!(
                    "the tick at t = {} has no {} message",
                    self.row.t, t.name
                ));
            }
        }
        if self.carried != 7 {
            return Err(format!(
                "the tick at t = {} comes before any /omnid/mode, /omnid/amplifiers and \
                 /omnid/safety/flags",
                self.row.t
            ));
        }
        self.seen = 0;
        self.rows += 1;
        let row = self.row;
        self.row.live.seq = self.rows;
        Ok(row)
    }
}

enum Next {
    Io(io::Error),
    Read(McapReadError),
}

/// The MCAP error inside an I/O error from [`McapTicks`] or [`McapAsCsv`], if that is what it
/// is.
pub fn mcap_error(e: &io::Error) -> Option<&McapReadError> {
    e.get_ref()
        .and_then(|inner| inner.downcast_ref::<McapReadError>())
}

/// An omnid MCAP log read as the text of the CSV log of the same run (the header of its
/// columns, then one row a tick, floats in their shortest round-trip form): every value comes
/// back bit for bit.
pub struct McapAsCsv<R: Read> {
    ticks: McapTicks<R>,
    text: Vec<u8>,
    at: usize,
    started: bool,
}

impl<R: Read> McapAsCsv<R> {
    /// Read the log from `input` (see [`McapTicks::new`] for `lenient`).
    pub fn new(input: R, lenient: bool) -> Self {
        McapAsCsv {
            ticks: McapTicks::new(input, lenient),
            text: Vec::with_capacity(1 << 16),
            at: 0,
            started: false,
        }
    }

    fn fill(&mut self) -> io::Result<()> {
        self.text.clear();
        self.at = 0;
        if !self.started {
            self.started = true;
            // The header needs the schema: known once the first row is read.
            let first = self.ticks.next_tick()?;
            let schema = self.ticks.schema();
            self.text
                .extend_from_slice(schema.columns().join(",").as_bytes());
            self.text.push(b'\n');
            if let Some(r) = first {
                crate::telemetry::recorder::format_row(&mut self.text, &r, &schema);
            }
            return Ok(());
        }
        let schema = self.ticks.schema();
        while self.text.len() < 1 << 15 {
            match self.ticks.next_tick()? {
                Some(r) => crate::telemetry::recorder::format_row(&mut self.text, &r, &schema),
                None => break,
            }
        }
        Ok(())
    }
}

impl<R: Read> Read for McapAsCsv<R> {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        if self.at == self.text.len() {
            self.fill()?;
        }
        let n = buf.len().min(self.text.len() - self.at);
        buf[..n].copy_from_slice(&self.text[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

/// Whether `head` (a file's first bytes) is the MCAP magic.
pub fn is_mcap(head: &[u8]) -> bool {
    head.len() >= MAGIC.len() && head[..MAGIC.len()] == MAGIC[..]
}

/// [`McapAsCsv`] on a thread of its own, handing over the text in blocks: a replay's servo
/// thread then only copies bytes (no chunk decompression, which takes milliseconds, and no
/// allocation: the blocks go back and forth).
pub struct McapPrefetch {
    blocks: crossbeam_channel::Receiver<io::Result<Vec<u8>>>,
    spent: crossbeam_channel::Sender<Vec<u8>>,
    current: Vec<u8>,
    at: usize,
    done: bool,
}

/// Text per block, and blocks in flight.
const BLOCK: usize = 1 << 16;
const BLOCKS: usize = 4;

impl McapPrefetch {
    /// Start decoding `input` (see [`McapTicks::new`] for `lenient`).
    pub fn new<R: Read + Send + 'static>(input: R, lenient: bool) -> io::Result<Self> {
        let (block_tx, blocks) = crossbeam_channel::bounded(BLOCKS);
        let (spent, spent_rx) = crossbeam_channel::bounded::<Vec<u8>>(BLOCKS + 2);
        for _ in 0..BLOCKS + 1 {
            let _ = spent.try_send(vec![0; BLOCK]);
        }
        std::thread::Builder::new()
            .name("omnid-mcap-read".into())
            .spawn(move || {
                let mut text = McapAsCsv::new(input, lenient);
                // Ends when the file does, on an error, or when the reader is gone.
                while let Ok(mut block) = spent_rx.recv() {
                    block.resize(BLOCK, 0);
                    let mut filled = 0;
                    let result = loop {
                        match text.read(&mut block[filled..]) {
                            Ok(0) => break Ok(()),
                            Ok(n) => {
                                filled += n;
                                if filled == BLOCK {
                                    break Ok(());
                                }
                            }
                            Err(e) => break Err(e),
                        }
                    };
                    block.truncate(filled);
                    let last = filled == 0 || result.is_err();
                    let sent = match result {
                        Ok(()) => block_tx.send(Ok(block)),
                        Err(e) if filled == 0 => block_tx.send(Err(e)),
                        // The text before the error first, then the error.
                        Err(e) => block_tx
                            .send(Ok(block))
                            .and_then(|()| block_tx.send(Err(e))),
                    };
                    if sent.is_err() || last {
                        return;
                    }
                }
            })?;
        Ok(McapPrefetch {
            blocks,
            spent,
            current: Vec::new(),
            at: 0,
            done: false,
        })
    }
}

impl McapPrefetch {
    /// The next block of text (empty at the end). Waits by polling: a blocking `recv` would
    /// allocate its waiter the first time this thread ever waits, which is only when the
    /// decoding thread falls behind (a loaded machine), so an allocation in a replay's servo
    /// tick would come and go with the load.
    fn next_block(&self) -> io::Result<Vec<u8>> {
        let mut polls = 0u32;
        loop {
            match self.blocks.try_recv() {
                Ok(block) => return block,
                Err(crossbeam_channel::TryRecvError::Disconnected) => return Ok(Vec::new()),
                Err(crossbeam_channel::TryRecvError::Empty) if polls < 64 => {
                    polls += 1;
                    std::hint::spin_loop();
                }
                Err(crossbeam_channel::TryRecvError::Empty) => {
                    std::thread::sleep(std::time::Duration::from_micros(20));
                }
            }
        }
    }
}

impl Read for McapPrefetch {
    fn read(&mut self, buf: &mut [u8]) -> io::Result<usize> {
        while self.at == self.current.len() {
            if self.done {
                return Ok(0);
            }
            let next = self.next_block()?;
            let old = std::mem::replace(&mut self.current, next);
            if old.capacity() > 0 {
                let _ = self.spent.try_send(old);
            }
            self.at = 0;
            self.done = self.current.is_empty();
        }
        let n = buf.len().min(self.current.len() - self.at);
        buf[..n].copy_from_slice(&self.current[self.at..self.at + n]);
        self.at += n;
        Ok(n)
    }
}

#[cfg(test)]
mod tests {
    //! Files that are not valid MCAP, built record by record.
    use super::*;
    use mcap::records::op;

    fn string(out: &mut Vec<u8>, s: &str) {
        out.extend_from_slice(&(s.len() as u32).to_le_bytes());
        out.extend_from_slice(s.as_bytes());
    }

    fn record(opcode: u8, body: &[u8]) -> Vec<u8> {
        let mut out = vec![opcode];
        out.extend_from_slice(&(body.len() as u64).to_le_bytes());
        out.extend_from_slice(body);
        out
    }

    fn schema(id: u16, name: &str, encoding: &str) -> Vec<u8> {
        let mut b = id.to_le_bytes().to_vec();
        string(&mut b, name);
        string(&mut b, encoding);
        string(&mut b, "float64 data\n");
        record(op::SCHEMA, &b)
    }

    fn channel(id: u16, schema_id: u16, topic: &str) -> Vec<u8> {
        let mut b = id.to_le_bytes().to_vec();
        b.extend_from_slice(&schema_id.to_le_bytes());
        string(&mut b, topic);
        string(&mut b, "cdr");
        b.extend_from_slice(&0u32.to_le_bytes()); // no metadata
        record(op::CHANNEL, &b)
    }

    /// A chunk of `records`, with `compression`; `declared` is the uncompressed size its
    /// header states.
    fn chunk(compression: &str, declared: u64, crc: u32, records: &[u8]) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(&0u64.to_le_bytes());
        b.extend_from_slice(&0u64.to_le_bytes());
        b.extend_from_slice(&declared.to_le_bytes());
        b.extend_from_slice(&crc.to_le_bytes());
        string(&mut b, compression);
        b.extend_from_slice(&(records.len() as u64).to_le_bytes());
        b.extend_from_slice(records);
        record(op::CHUNK, &b)
    }

    /// Magic, a header, `records`, a data end, a footer, magic.
    fn file(records: &[Vec<u8>]) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        let mut h = Vec::new();
        string(&mut h, "ros2");
        string(&mut h, "test");
        out.extend(record(op::HEADER, &h));
        for r in records {
            out.extend_from_slice(r);
        }
        out.extend(record(op::DATA_END, &0u32.to_le_bytes()));
        out.extend(record(op::FOOTER, &[0; 20]));
        out.extend_from_slice(MAGIC);
        out
    }

    /// Every tick of `bytes`, or the error's message; and what was inflated.
    fn read(bytes: &[u8]) -> (Result<u64, String>, u64) {
        let mut t = McapTicks::new(bytes, false);
        let mut n = 0;
        loop {
            match t.next_tick() {
                Ok(Some(_)) => n += 1,
                Ok(None) => return (Ok(n), t.inflated_bytes()),
                Err(e) => return (Err(e.to_string()), t.inflated_bytes()),
            }
        }
    }

    fn refused(bytes: &[u8]) -> String {
        let (result, _) = read(bytes);
        let e = result.expect_err("refused");
        assert!(!e.contains('\n'), "{e}");
        e
    }

    /// The file offset of record `i` (0 = the header) of a file made by [`file`].
    fn offset(records: &[Vec<u8>], i: usize) -> usize {
        let header = 9 + 8 + "ros2".len() + "test".len();
        MAGIC.len() + header + records[..i - 1].iter().map(Vec::len).sum::<usize>()
    }

    #[test]
    fn a_header_that_is_not_the_first_record_is_refused_where_it_is() {
        let records = [
            schema(1, "std_msgs/msg/Float64", "ros2msg"),
            header_record(),
        ];
        let e = refused(&file(&records));
        assert!(
            e.contains(&format!("MCAP record 3 (at byte {})", offset(&records, 2)))
                && e.contains("a second Header record"),
            "{e}"
        );
        // A file whose first record is not its Header.
        let mut no_header = MAGIC.to_vec();
        no_header.extend(schema(1, "std_msgs/msg/Float64", "ros2msg"));
        no_header.extend_from_slice(MAGIC);
        let e = refused(&no_header);
        assert!(
            e.contains(&format!("MCAP record 1 (at byte {})", MAGIC.len()))
                && e.contains("the first record is opcode 0x03, not a Header"),
            "{e}"
        );
    }

    /// A Header record as [`file`] writes it.
    fn header_record() -> Vec<u8> {
        let mut h = Vec::new();
        string(&mut h, "ros2");
        string(&mut h, "test");
        record(op::HEADER, &h)
    }

    /// Cut anywhere inside a record, the error names that record and the byte it starts at,
    /// found here by walking the file's record framing (opcode, u64 length) on its own.
    #[test]
    fn a_file_that_ends_early_names_the_record_and_its_byte() {
        let records = [
            schema(1, "std_msgs/msg/Float64", "ros2msg"),
            channel(1, 1, "/omnid/time"),
            schema(2, "std_msgs/msg/String", "ros2msg"),
        ];
        let whole = file(&records);
        for cut in [
            offset(&records, 2) + 3,
            offset(&records, 3) + 12,
            whole.len() - 30,
        ] {
            // The record the cut falls in, and where it starts.
            let (mut at, mut index) = (MAGIC.len(), 1u64);
            loop {
                let len = u64::from_le_bytes(whole[at + 1..at + 9].try_into().unwrap()) as usize;
                if cut < at + 9 + len {
                    break;
                }
                at += 9 + len;
                index += 1;
            }
            let e = refused(&whole[..cut]);
            assert!(
                e.contains(&format!(
                    "ends inside record {index} (which starts at byte {at})"
                )),
                "cut at {cut}: {e}"
            );
        }
    }

    #[test]
    fn a_channel_id_defined_again_with_another_topic_and_type_is_refused() {
        let records = [
            schema(1, "std_msgs/msg/Float64", "ros2msg"),
            channel(1, 1, "/omnid/time"),
            schema(2, "std_msgs/msg/String", "ros2msg"),
            channel(1, 2, "/chatter"),
        ];
        let e = refused(&file(&records));
        assert!(
            e.contains(&format!("MCAP record 5 (at byte {})", offset(&records, 4)))
                && e.contains("channel 1 defined again differently")
                && e.contains("`/omnid/time` of schema 1 (std_msgs/msg/Float64)")
                && e.contains("`/chatter` of schema 2 (std_msgs/msg/String)"),
            "{e}"
        );
        // Defined again the same, as writers do in every chunk: read on (to the end, where
        // it is no omnid log).
        let same = [
            schema(1, "std_msgs/msg/Float64", "ros2msg"),
            channel(1, 1, "/omnid/time"),
            chunk(
                "",
                0,
                0,
                &[
                    schema(1, "std_msgs/msg/Float64", "ros2msg"),
                    channel(1, 1, "/omnid/time"),
                ]
                .concat(),
            ),
        ];
        let e = refused(&file(&same));
        assert!(e.contains("not an omnid log"), "{e}");
        // A schema too.
        let schemas = [
            schema(1, "std_msgs/msg/Float64", "ros2msg"),
            schema(1, "std_msgs/msg/String", "ros2msg"),
        ];
        let e = refused(&file(&schemas));
        assert!(
            e.contains("MCAP record 3")
                && e.contains("schema 1 defined again differently")
                && e.contains("`std_msgs/msg/String`"),
            "{e}"
        );
    }

    #[test]
    fn a_schema_omnid_cannot_read_is_refused() {
        let records = [
            schema(1, "std_msgs/msg/Float64", "protobuf"),
            channel(1, 1, "/omnid/time"),
        ];
        let e = refused(&file(&records));
        assert!(
            e.contains(&format!("MCAP record 3 (at byte {})", offset(&records, 2)))
                && e.contains("/omnid/time")
                && e.contains("\"protobuf\"")
                && e.contains("\"ros2msg\""),
            "{e}"
        );
        // On a channel omnid does not read, any encoding is skipped.
        let other = [schema(1, "foo.Bar", "protobuf"), channel(1, 1, "/other")];
        assert!(refused(&file(&other)).contains("not an omnid log"));
    }

    #[test]
    fn a_chunk_inside_a_chunk_is_refused() {
        let inner = chunk("", 0, 0, &[]);
        let records = [chunk("", inner.len() as u64, 0, &inner)];
        let e = refused(&file(&records));
        let at = offset(&records, 1);
        assert!(
            e.contains(&format!(
                "MCAP record 3 (at byte 0 inside the chunk at byte {at})"
            )) && e.contains("a chunk inside a chunk"),
            "{e}"
        );
        // Nor anything but schemas, channels and messages.
        let statistics = record(op::STATISTICS, &[0; 46]);
        let records = [chunk("", statistics.len() as u64, 0, &statistics)];
        let e = refused(&file(&records));
        assert!(e.contains("opcode 0x0b inside a chunk"), "{e}");
    }

    #[test]
    fn opcodes_0x00_and_0x80_to_0xff_are_refused() {
        for opcode in [0x00, 0x80, 0xff] {
            let records = [
                schema(1, "std_msgs/msg/Float64", "ros2msg"),
                record(opcode, &[1, 2]),
            ];
            let e = refused(&file(&records));
            assert!(
                e.contains(&format!("MCAP record 3 (at byte {})", offset(&records, 2)))
                    && e.contains(&format!("{opcode:#04x}")),
                "{e}"
            );
            // Inside a chunk too.
            let inner = record(opcode, &[]);
            let e = refused(&file(&[chunk("", inner.len() as u64, 0, &inner)]));
            assert!(
                e.contains("MCAP record 3 (at byte 0 inside the chunk")
                    && e.contains(&format!("{opcode:#04x}")),
                "{e}"
            );
        }
    }

    /// A zstd frame of `blocks` RLE blocks of 128 KiB of `byte` each: 4 bytes a block, so
    /// 8192 blocks (32 KiB) inflate to 1 GiB.
    fn zstd_bomb(blocks: u32, byte: u8) -> Vec<u8> {
        // Magic, a descriptor with no content size, a 128 KiB window.
        let mut out = vec![0x28, 0xb5, 0x2f, 0xfd, 0x00, 0x38];
        for i in 0..blocks {
            let last = u32::from(i + 1 == blocks);
            let header = (128 << 10) << 3 | 1 << 1 | last;
            out.extend_from_slice(&header.to_le_bytes()[..3]);
            out.push(byte);
        }
        out
    }

    #[test]
    fn a_chunk_declaring_more_than_the_cap_is_refused_before_decompressing() {
        let bomb = zstd_bomb(8192, 0);
        assert!(bomb.len() < 33 << 10);
        for crc in [0, 1] {
            let records = [chunk("zstd", 1 << 30, crc, &bomb)];
            let (result, inflated) = read(&file(&records));
            let e = result.unwrap_err();
            assert!(
                e.contains(&format!("MCAP record 2 (at byte {})", offset(&records, 1)))
                    && e.contains("inflates to 1073741824 bytes, over the 64 MiB"),
                "{e}"
            );
            assert_eq!(inflated, 0, "nothing was decompressed");
        }
        // A chunk that states less than it holds: decompression stops at what it states.
        for crc in [0, 1] {
            let records = [chunk("zstd", 1 << 20, crc, &bomb)];
            let (result, inflated) = read(&file(&records));
            let e = result.unwrap_err();
            assert!(e.contains("inside the chunk at byte"), "{e}");
            assert!(inflated <= 1 << 20, "{inflated}");
        }
    }
}

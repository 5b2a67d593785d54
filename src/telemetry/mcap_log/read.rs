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

/// Why an MCAP log cannot be read. Records are counted from 1 in file order, chunks'
/// contents included; the file's name is added by whoever reports it.
#[derive(Debug, Error)]
pub enum McapReadError {
    /// The file is damaged (a bad CRC, a record that does not parse, a message that does
    /// not decode).
    #[error("MCAP record {record}: {reason}")]
    Bad {
        /// Which record.
        record: u64,
        /// What is wrong.
        reason: String,
    },
    /// The file ends before its end (a run killed mid-way).
    #[error(
        "the MCAP file ends inside record {record}, after {rows} whole rows (a run that was \
         killed mid-way?); --lenient reads those rows"
    )]
    Truncated {
        /// The record it ends in.
        record: u64,
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
    schema_names: std::collections::HashMap<u16, String>,
    by_id: std::collections::HashMap<u16, Option<usize>>,
    present: [bool; TOPICS.len()],
}

/// Streams the tick records of an omnid MCAP log. After the first chunk it allocates nothing
/// per row (a replay reads it on the servo thread).
pub struct McapTicks<R: Read> {
    input: R,
    reader: LinearReader,
    state: State,
    lenient: bool,
    done: bool,
}

/// Everything but the byte source: borrowed apart from the reader, so a record can be taken
/// while the reader still holds its bytes.
struct State {
    channels: Channels,
    record: u64,
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
        let options = LinearReaderOptions::default()
            .with_prevalidate_chunk_crcs(true)
            .with_validate_data_section_crc(true)
            .with_validate_summary_section_crc(true)
            .with_record_length_limit(MAX_RECORD_BYTES);
        McapTicks {
            input,
            reader: LinearReader::new_with_options(options),
            state: State {
                channels: Channels::default(),
                record: 0,
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
        loop {
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
                    // Only schemas, channels and messages say anything about the rows; the
                    // rest (indexes, statistics, metadata) is not parsed (that would allocate).
                    use mcap::records::op;
                    if ![op::SCHEMA, op::CHANNEL, op::MESSAGE].contains(&opcode)
                        || state.known_again(opcode, data)
                    {
                        continue;
                    }
                    let record = match mcap::parse_record(opcode, data) {
                        Ok(r) => r,
                        Err(e) => {
                            self.done = true;
                            return Err(Next::Read(state.bad(e.to_string())));
                        }
                    };
                    match state.take(record) {
                        Ok(Some(row)) => return Ok(Some(row)),
                        Ok(None) => {}
                        Err(e) => {
                            self.done = true;
                            return Err(Next::Read(e));
                        }
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
                        rows: self.state.rows,
                    }));
                }
                Err(e) => {
                    self.done = true;
                    return Err(Next::Read(McapReadError::Bad {
                        record: self.state.record + 1,
                        reason: e.to_string(),
                    }));
                }
            }
        }
    }
}

impl State {
    fn schema(&self) -> LogSchema {
        LogSchema {
            model: self.channels.present[super::TORQUE_MODEL.id],
            // Absent from logs written before the estimate was logged: those read as before.
            external: self.channels.present[super::TORQUE_EXTERNAL.id],
            buttons: self.channels.present[super::BUTTONS.id],
        }
    }

    /// A Schema or Channel record whose id is already known: writers repeat them in every
    /// chunk (so a chunk reads alone), and parsing one again would allocate its strings.
    fn known_again(&self, opcode: u8, data: &[u8]) -> bool {
        let id = || data.get(..2).map(|b| u16::from_le_bytes([b[0], b[1]]));
        match opcode {
            mcap::records::op::SCHEMA => {
                id().is_some_and(|id| self.channels.schema_names.contains_key(&id))
            }
            mcap::records::op::CHANNEL => {
                id().is_some_and(|id| self.channels.by_id.contains_key(&id))
            }
            _ => false,
        }
    }

    fn bad(&self, reason: impl Into<String>) -> McapReadError {
        McapReadError::Bad {
            record: self.record,
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
                self.channels.schema_names.insert(header.id, header.name);
            }
            Record::Channel(c) => {
                let known = TOPICS.iter().position(|t| t.name == c.topic);
                if let Some(i) = known {
                    let want = TOPICS[i].ty.name;
                    let have = self.channels.schema_names.get(&c.schema_id);
                    if have.map(String::as_str) != Some(want) || c.message_encoding != "cdr" {
                        return Err(self.bad(format!(
                            "channel {} is {} in {:?}, not omnid's {want} in CDR",
                            c.topic,
                            have.map(String::as_str).unwrap_or("(no schema)"),
                            c.message_encoding
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

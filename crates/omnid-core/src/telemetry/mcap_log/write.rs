//! The MCAP recorder: tick records to an MCAP log (see the module above for the layout). It
//! runs on the log writer's thread, never on the servo's: a chunk's compression takes
//! milliseconds.

use super::{arm3d, LogFormat, Topic, JOINT_NAMES, TOPICS};
use crate::omni::kinematics::Geometry;
use crate::ros2::msgs::{self, Header, Stamp};
use crate::telemetry::record::{LogSchema, Mode, ServoEvent, TickRecord};
use crate::telemetry::recorder::Recorder;
use std::io::{self, Write};
use std::sync::{Arc, Mutex};

/// A chunk is closed (compressed and handed to the file) once it holds this many bytes or
/// [`CHUNK_SECONDS`] of device time: what a killed run can lose.
const CHUNK_BYTES: usize = 1 << 20;
const CHUNK_SECONDS: f64 = 1.0;
/// What a Message record adds to its payload: opcode and length (9), channel id, sequence,
/// log and publish times (22).
const MESSAGE_RECORD_BYTES: usize = 31;
/// Ticks between two `/tf` and `/omnid/motor/heat` messages (62.5 Hz at 1 kHz: enough for a
/// 3-D view).
const TF_EVERY: u64 = 16;

/// The bytes the MCAP writer has produced and the file has not yet taken. The writer owns one
/// handle, the recorder the other, so each call's output can be handed on as it comes.
#[derive(Clone, Default)]
struct Pending(Arc<Mutex<Vec<u8>>>);

impl Pending {
    fn drain_into(&self, out: &mut Vec<u8>) {
        let mut b = self.0.lock().unwrap_or_else(|p| p.into_inner());
        out.extend_from_slice(&b);
        b.clear();
    }
}

impl Write for Pending {
    fn write(&mut self, buf: &[u8]) -> io::Result<usize> {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .extend_from_slice(buf);
        Ok(buf.len())
    }
    fn flush(&mut self) -> io::Result<()> {
        Ok(())
    }
}

/// What is written only when it changes (and at the first tick).
#[derive(Clone, Copy, PartialEq)]
struct Carried {
    mode: Mode,
    amps: bool,
    flags: u32,
    buttons: [bool; 3],
    controller: Option<crate::control::ControllerKind>,
}

/// Where [`TickEncoder::encode`] hands each message: its topic, log time and bytes.
pub(crate) type Put<'a> = dyn FnMut(Topic, u64, &[u8]) -> io::Result<()> + 'a;

/// Turns tick records into the messages of an omnid log, in channel order (docs/MCAP.md): the
/// MCAP recorder writes them to a file, the live view sends them to viewers.
pub struct TickEncoder {
    schema: LogSchema,
    arm: arm3d::Arm3d,
    /// Wall-clock time of device time 0, ns since the Unix epoch (set at the first tick).
    epoch_ns: Option<u64>,
    last: Option<Carried>,
    ticks: u64,
    /// Send the URDF with the next tick.
    describe: bool,
    msg: Vec<u8>,
}

impl TickEncoder {
    /// For logs of `schema`, the arm of `geometry` with its frames under `prefix` (empty: one
    /// arm, frames as ROS names them).
    pub fn new(schema: LogSchema, geometry: Geometry, prefix: &str) -> TickEncoder {
        TickEncoder {
            schema,
            arm: arm3d::Arm3d::new(geometry, prefix),
            epoch_ns: None,
            last: None,
            ticks: 0,
            describe: true,
            msg: Vec::with_capacity(512),
        }
    }

    /// Send everything that is sent once or on change (the URDF, mode, flags, amplifiers,
    /// buttons, controller) again with the next tick: for viewers that join late.
    pub fn repeat(&mut self) {
        self.last = None;
        self.describe = true;
    }

    /// Whether logs of this schema have `topic`.
    pub fn writes(&self, topic: &Topic) -> bool {
        self.schema.has(topic.group)
    }

    /// The tick's messages, each handed to `put` with its topic and log time (ns since the
    /// Unix epoch); `/robot_description` before the first tick.
    pub fn encode(&mut self, r: &TickRecord, put: &mut Put<'_>) -> io::Result<()> {
        let time = self.log_time(r.t);
        let header = Header {
            stamp: Stamp::from_nanos(time),
            frame_id: "",
        };
        if std::mem::take(&mut self.describe) {
            self.msg.clear();
            msgs::write_string(&mut self.msg, &self.arm.urdf());
            put(super::ROBOT_DESCRIPTION, time, &self.msg)?;
        }
        self.every_tick(r, time, &header, put)?;
        self.on_change(r, time, &header, put)?;
        let m = &mut self.msg;
        if let Some(ev) = r.live.event {
            m.clear();
            msgs::write_string(m, &event_text(ev));
            put(super::EVENTS, time, m)?;
        }
        if self.ticks.is_multiple_of(TF_EVERY) {
            m.clear();
            msgs::write_f64_array(m, "joint", &r.live.heat);
            put(super::HEAT, time, m)?;
            m.clear();
            msgs::write_tf(m, &self.arm.transforms(&r.q, header));
            put(super::TF, time, m)?;
        }
        m.clear();
        msgs::write_joint_state(m, &header, &JOINT_NAMES, &r.q, &r.qd, &r.tau);
        put(super::JOINT_STATES, time, m)?;
        self.ticks += 1;
        Ok(())
    }

    /// The log time of device time `t`, ns since the Unix epoch: the first tick is stamped
    /// with the wall clock, the rest follow the device's clock from there.
    fn log_time(&mut self, t: f64) -> u64 {
        let epoch = *self.epoch_ns.get_or_insert_with(|| {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(0);
            now.saturating_sub(device_ns(t))
        });
        epoch.saturating_add(device_ns(t))
    }

    /// The topics every tick carries (those of the log's schema): time, the estimate, the
    /// torques, the tip and its forces, the encoders.
    fn every_tick(
        &mut self,
        r: &TickRecord,
        time: u64,
        header: &Header<'_>,
        put: &mut Put<'_>,
    ) -> io::Result<()> {
        let based = Header {
            frame_id: self.arm.base_frame(),
            ..*header
        };
        let m = &mut self.msg;
        m.clear();
        msgs::write_float64(m, r.t);
        put(super::TIME, time, m)?;
        let arrays = [
            (super::ESTIMATE_POSITION, &r.qf),
            (super::ESTIMATE_ACCELERATION, &r.qdd),
            (super::REFERENCE, &r.reference),
            (super::TORQUE_CONTROLLER, &r.tau_cmd),
            (super::TORQUE_PREDICTED, &r.tau_hat),
            (super::TORQUE_MODEL, &r.tau_model),
            (super::TORQUE_EXTERNAL, &r.tau_ext),
        ];
        for (topic, v) in arrays {
            if self.schema.has(topic.group) {
                m.clear();
                msgs::write_f64_array(m, "joint", v);
                put(topic, time, m)?;
            }
        }
        let tip = r.haptic.tip_mm;
        m.clear();
        msgs::write_f64_array(m, "xyz_mm", &tip);
        put(super::TIP_MM, time, m)?;
        m.clear();
        msgs::write_pose_stamped(m, &based, tip.map(|v| v * 1e-3), [0.0, 0.0, 0.0, 1.0]);
        put(super::TIP_POSE, time, m)?;
        m.clear();
        msgs::write_wrench_stamped(m, &based, r.haptic.force, [0.0; 3]);
        put(super::TIP_FORCE, time, m)?;
        let wrenches = [
            (super::HAND_FORCE, r.haptic.hand),
            (super::EXTERNAL_FORCE, r.haptic.fext),
        ];
        for (topic, force) in wrenches {
            if self.schema.has(topic.group) {
                m.clear();
                msgs::write_wrench_stamped(m, &based, force, [0.0; 3]);
                put(topic, time, m)?;
            }
        }
        m.clear();
        msgs::write_i64_array(m, "joint", &r.enc);
        put(super::ENCODERS, time, m)
    }

    /// The topics written only when their value changes (and at the first tick): flags,
    /// mode, amplifiers, buttons, controller.
    fn on_change(
        &mut self,
        r: &TickRecord,
        time: u64,
        header: &Header<'_>,
        put: &mut Put<'_>,
    ) -> io::Result<()> {
        let now = Carried {
            mode: r.mode,
            amps: r.amps,
            flags: r.flags,
            buttons: [r.live.buttons[0], r.live.buttons[1], r.live.inkwell],
            controller: r.live.controller,
        };
        let last = self.last.replace(now);
        let m = &mut self.msg;
        if last.is_none_or(|l| l.flags != now.flags) {
            m.clear();
            msgs::write_uint32(m, now.flags);
            put(super::FLAGS, time, m)?;
        }
        if last.is_none_or(|l| l.mode != now.mode) {
            m.clear();
            msgs::write_string(m, now.mode.as_str());
            put(super::MODE, time, m)?;
        }
        if last.is_none_or(|l| l.amps != now.amps) {
            m.clear();
            msgs::write_bool(m, now.amps);
            put(super::AMPLIFIERS, time, m)?;
        }
        if self.schema.has(super::BUTTONS.group) && last.is_none_or(|l| l.buttons != now.buttons) {
            m.clear();
            msgs::write_joy(m, header, &[], &now.buttons.map(i32::from));
            put(super::BUTTONS, time, m)?;
        }
        if let Some(c) = now.controller {
            if last.is_none_or(|l| l.controller != now.controller) {
                m.clear();
                msgs::write_string(m, c.as_str());
                put(super::CONTROLLER, time, m)?;
            }
        }
        Ok(())
    }
}

/// Writes tick records as an MCAP log.
pub(crate) struct McapRecorder {
    encoder: TickEncoder,
    writer: Option<mcap::Writer<mcap::write::NoSeek<Pending>>>,
    pending: Pending,
    channels: [u16; TOPICS.len()],
    sequence: u32,
    /// Rows in the open chunk, its bytes so far, and the device time it began at.
    chunk_rows: u64,
    chunk_bytes: usize,
    chunk_t0: f64,
}

fn mcap_error(e: mcap::McapError) -> io::Error {
    io::Error::other(format!("MCAP writer: {e}"))
}

impl McapRecorder {
    pub(crate) fn new(schema: LogSchema, geometry: Geometry) -> Self {
        McapRecorder {
            encoder: TickEncoder::new(schema, geometry, ""),
            writer: None,
            pending: Pending::default(),
            channels: [0; TOPICS.len()],
            sequence: 0,
            chunk_rows: 0,
            chunk_bytes: 0,
            chunk_t0: 0.0,
        }
    }

    fn close_chunk(&mut self, out: &mut Vec<u8>) -> io::Result<u64> {
        if self.chunk_rows == 0 {
            return Ok(0);
        }
        if let Some(w) = self.writer.as_mut() {
            w.flush().map_err(mcap_error)?;
        }
        self.pending.drain_into(out);
        let rows = self.chunk_rows;
        self.chunk_rows = 0;
        self.chunk_bytes = 0;
        Ok(rows)
    }
}

fn event_text(ev: ServoEvent) -> String {
    match ev {
        ServoEvent::StreamStale { fallback } => format!("stream-stale: now {}", fallback.as_str()),
        ServoEvent::StreamEnded { fallback } => format!("stream-ended: now {}", fallback.as_str()),
        ServoEvent::Limit { flags } => format!("limit: flags {flags}"),
        ServoEvent::SafetyTrip(trip) => format!("safety-trip: {trip}"),
    }
}

impl Recorder for McapRecorder {
    fn header(&mut self, out: &mut Vec<u8>) -> io::Result<()> {
        let options = mcap::WriteOptions::new()
            .profile("ros2")
            .library(concat!("omnid ", env!("CARGO_PKG_VERSION")))
            .compression(Some(mcap::Compression::Zstd))
            // zstd's worker threads could land on the servo's core: compress on this thread.
            .compression_threads(0)
            .chunk_size(None)
            .disable_seeking(true);
        let mut writer = options
            .create(mcap::write::NoSeek::new(self.pending.clone()))
            .map_err(mcap_error)?;
        for (i, t) in TOPICS.iter().enumerate() {
            if !self.encoder.writes(t) {
                continue;
            }
            let schema = writer
                .add_schema(t.ty.name, "ros2msg", t.ty.definition.as_bytes())
                .map_err(mcap_error)?;
            self.channels[i] = writer
                .add_channel(schema, t.name, "cdr", &Default::default())
                .map_err(mcap_error)?;
        }
        self.writer = Some(writer);
        self.pending.drain_into(out);
        Ok(())
    }

    fn row(&mut self, r: &TickRecord, out: &mut Vec<u8>) -> io::Result<u64> {
        if self.chunk_rows == 0 {
            self.chunk_t0 = r.t;
        }
        let writer = self.writer.as_mut().expect("header written first");
        let (channels, sequence, bytes) =
            (&self.channels, &mut self.sequence, &mut self.chunk_bytes);
        self.encoder.encode(r, &mut |topic, log_time, msg| {
            *sequence = sequence.wrapping_add(1);
            *bytes += msg.len() + MESSAGE_RECORD_BYTES;
            writer
                .write_to_known_channel(
                    &mcap::records::MessageHeader {
                        channel_id: channels[topic.id],
                        sequence: *sequence,
                        log_time,
                        publish_time: log_time,
                    },
                    msg,
                )
                .map_err(mcap_error)
        })?;
        self.chunk_rows += 1;
        if self.chunk_bytes >= CHUNK_BYTES || r.t - self.chunk_t0 >= CHUNK_SECONDS {
            return self.close_chunk(out);
        }
        Ok(0)
    }

    fn finish_rows(&mut self, out: &mut Vec<u8>) -> io::Result<u64> {
        self.close_chunk(out)
    }

    fn footer(&mut self, out: &mut Vec<u8>) -> io::Result<()> {
        if let Some(mut w) = self.writer.take() {
            w.finish().map_err(mcap_error)?;
        }
        self.pending.drain_into(out);
        Ok(())
    }
}

/// Device time `t` (s) in ns, saturating (a negative or non-finite time is 0).
fn device_ns(t: f64) -> u64 {
    if t.is_finite() && t > 0.0 {
        (t * 1e9).round().min(u64::MAX as f64) as u64
    } else {
        0
    }
}

/// The recorder for `format`.
pub(crate) fn for_format(schema: LogSchema, format: LogFormat) -> Option<McapRecorder> {
    match format {
        LogFormat::Mcap { geometry } => Some(McapRecorder::new(schema, geometry)),
        LogFormat::Csv => None,
    }
}

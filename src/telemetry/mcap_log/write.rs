//! The MCAP recorder: tick records to an MCAP log (see the module above for the layout). It
//! runs on the log writer's thread, never on the servo's: a chunk's compression takes
//! milliseconds.

use super::{arm3d, LogFormat, Topic, BASE_FRAME, JOINT_NAMES, TOPICS};
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

/// Writes tick records as an MCAP log.
pub(crate) struct McapRecorder {
    schema: LogSchema,
    geometry: Geometry,
    writer: Option<mcap::Writer<mcap::write::NoSeek<Pending>>>,
    pending: Pending,
    channels: [u16; TOPICS.len()],
    sequence: u32,
    /// Wall-clock time of device time 0, ns since the Unix epoch (set at the first row).
    epoch_ns: Option<u64>,
    last: Option<Carried>,
    ticks: u64,
    /// Rows in the open chunk, its bytes so far, and the device time it began at.
    chunk_rows: u64,
    chunk_bytes: usize,
    chunk_t0: f64,
    msg: Vec<u8>,
}

fn mcap_error(e: mcap::McapError) -> io::Error {
    io::Error::other(format!("MCAP writer: {e}"))
}

impl McapRecorder {
    pub(crate) fn new(schema: LogSchema, geometry: Geometry) -> Self {
        McapRecorder {
            schema,
            geometry,
            writer: None,
            pending: Pending::default(),
            channels: [0; TOPICS.len()],
            sequence: 0,
            epoch_ns: None,
            last: None,
            ticks: 0,
            chunk_rows: 0,
            chunk_bytes: 0,
            chunk_t0: 0.0,
            msg: Vec::with_capacity(512),
        }
    }

    fn writes(&self, topic: &Topic) -> bool {
        !topic.model_only || self.schema.model
    }

    /// Write `self.msg` on `topic` at `log_time`.
    fn put(&mut self, topic: Topic, log_time: u64) -> io::Result<()> {
        let index = TOPICS
            .iter()
            .position(|t| *t == topic)
            .expect("a known topic");
        let writer = self.writer.as_mut().expect("header written first");
        self.sequence = self.sequence.wrapping_add(1);
        writer
            .write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: self.channels[index],
                    sequence: self.sequence,
                    log_time,
                    publish_time: log_time,
                },
                &self.msg,
            )
            .map_err(mcap_error)?;
        self.chunk_bytes += self.msg.len() + 31;
        Ok(())
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
            if !self.writes(t) {
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
        let epoch = *self.epoch_ns.get_or_insert_with(|| {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_nanos() as u64)
                .unwrap_or(0);
            now.saturating_sub(device_ns(r.t))
        });
        let time = epoch.saturating_add(device_ns(r.t));
        let header = Header {
            stamp: Stamp::from_nanos(time),
            frame_id: "",
        };
        let based = Header {
            frame_id: BASE_FRAME,
            ..header
        };
        if self.ticks == 0 {
            self.msg.clear();
            msgs::write_string(&mut self.msg, &arm3d::urdf(&self.geometry));
            self.put(super::ROBOT_DESCRIPTION, time)?;
        }
        if self.chunk_rows == 0 {
            self.chunk_t0 = r.t;
        }
        self.msg.clear();
        msgs::write_float64(&mut self.msg, r.t);
        self.put(super::TIME, time)?;
        let arrays = [
            (super::ESTIMATE_POSITION, &r.qf),
            (super::ESTIMATE_ACCELERATION, &r.qdd),
            (super::REFERENCE, &r.reference),
            (super::TORQUE_CONTROLLER, &r.tau_cmd),
            (super::TORQUE_PREDICTED, &r.tau_hat),
            (super::TORQUE_MODEL, &r.tau_model),
        ];
        for (topic, v) in arrays {
            if self.writes(&topic) {
                self.msg.clear();
                msgs::write_f64_array(&mut self.msg, "joint", v);
                self.put(topic, time)?;
            }
        }
        let tip = r.haptic.tip_mm;
        self.msg.clear();
        msgs::write_f64_array(&mut self.msg, "xyz_mm", &tip);
        self.put(super::TIP_MM, time)?;
        self.msg.clear();
        msgs::write_pose_stamped(
            &mut self.msg,
            &based,
            tip.map(|v| v * 1e-3),
            [0.0, 0.0, 0.0, 1.0],
        );
        self.put(super::TIP_POSE, time)?;
        self.msg.clear();
        msgs::write_wrench_stamped(&mut self.msg, &based, r.haptic.force, [0.0; 3]);
        self.put(super::TIP_FORCE, time)?;
        if self.schema.model {
            self.msg.clear();
            msgs::write_wrench_stamped(&mut self.msg, &based, r.haptic.hand, [0.0; 3]);
            self.put(super::HAND_FORCE, time)?;
        }
        self.msg.clear();
        msgs::write_i64_array(&mut self.msg, "joint", &r.enc);
        self.put(super::ENCODERS, time)?;

        let now = Carried {
            mode: r.mode,
            amps: r.amps,
            flags: r.flags,
            buttons: [r.live.buttons[0], r.live.buttons[1], r.live.inkwell],
            controller: r.live.controller,
        };
        let last = self.last.replace(now);
        let changed = |f: fn(&Carried) -> bool| last.is_none_or(|l| f(&l) != f(&now));
        if last.is_none_or(|l| l.flags != now.flags) {
            self.msg.clear();
            msgs::write_uint32(&mut self.msg, now.flags);
            self.put(super::FLAGS, time)?;
        }
        if last.is_none_or(|l| l.mode != now.mode) {
            self.msg.clear();
            msgs::write_string(&mut self.msg, now.mode.as_str());
            self.put(super::MODE, time)?;
        }
        if changed(|c| c.amps) {
            self.msg.clear();
            msgs::write_bool(&mut self.msg, now.amps);
            self.put(super::AMPLIFIERS, time)?;
        }
        if last.is_none_or(|l| l.buttons != now.buttons) {
            self.msg.clear();
            msgs::write_joy(&mut self.msg, &header, &[], &now.buttons.map(i32::from));
            self.put(super::BUTTONS, time)?;
        }
        if let Some(c) = now
            .controller
            .filter(|_| last.is_none_or(|l| l.controller != now.controller))
        {
            self.msg.clear();
            msgs::write_string(&mut self.msg, c.as_str());
            self.put(super::CONTROLLER, time)?;
        }
        if let Some(ev) = r.live.event {
            self.msg.clear();
            msgs::write_string(&mut self.msg, &event_text(ev));
            self.put(super::EVENTS, time)?;
        }
        if self.ticks % TF_EVERY == 0 {
            self.msg.clear();
            msgs::write_f64_array(&mut self.msg, "joint", &r.live.heat);
            self.put(super::HEAT, time)?;
            self.msg.clear();
            msgs::write_tf(
                &mut self.msg,
                &arm3d::transforms(&self.geometry, &r.q, header),
            );
            self.put(super::TF, time)?;
        }
        self.msg.clear();
        msgs::write_joint_state(&mut self.msg, &header, &JOINT_NAMES, &r.q, &r.qd, &r.tau);
        self.put(super::JOINT_STATES, time)?;
        self.ticks += 1;
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

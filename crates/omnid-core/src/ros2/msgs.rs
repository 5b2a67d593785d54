//! The ROS 2 standard messages omnid writes and reads: their `ros2msg` schema texts (the
//! definition followed by each dependency, as MCAP's `ros2` profile wants them) and their CDR
//! encoders and decoders (docs/ROS2.md, Messages).

// One constant, writer and reader per ROS 2 message, named for it; the fields are the
// message's own (docs/ROS2.md, Messages).
#![allow(missing_docs)]

use super::cdr::{CdrError, CdrReader, CdrWriter};

/// The 80 `=` that separate a schema's dependencies.
macro_rules! dep {
    ($name:literal, $text:expr) => {
        concat!(
            "================================================================================\n",
            "MSG: ",
            $name,
            "\n",
            $text
        )
    };
}

macro_rules! header_deps {
    () => {
        concat!(
            dep!(
                "std_msgs/Header",
                "builtin_interfaces/Time stamp\nstring frame_id\n"
            ),
            dep!("builtin_interfaces/Time", "int32 sec\nuint32 nanosec\n")
        )
    };
}
macro_rules! vector3 {
    () => {
        dep!("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z\n")
    };
}
macro_rules! quaternion {
    () => {
        dep!(
            "geometry_msgs/Quaternion",
            "float64 x\nfloat64 y\nfloat64 z\nfloat64 w\n"
        )
    };
}
macro_rules! multi_array_deps {
    () => {
        concat!(
            dep!(
                "std_msgs/MultiArrayLayout",
                "std_msgs/MultiArrayDimension[] dim\nuint32 data_offset\n"
            ),
            dep!(
                "std_msgs/MultiArrayDimension",
                "string label\nuint32 size\nuint32 stride\n"
            )
        )
    };
}

/// A message type: its name as schemas and type strings spell it, and its schema text.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MsgType {
    /// `pkg/msg/Type`.
    pub name: &'static str,
    /// The `ros2msg` text with its dependencies.
    pub definition: &'static str,
}

pub const JOINT_STATE: MsgType = MsgType {
    name: "sensor_msgs/msg/JointState",
    definition: concat!(
        "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n",
        "float64[] effort\n",
        header_deps!()
    ),
};
pub const POSE_STAMPED: MsgType = MsgType {
    name: "geometry_msgs/msg/PoseStamped",
    definition: concat!(
        "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
        header_deps!(),
        dep!(
            "geometry_msgs/Pose",
            "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n"
        ),
        dep!("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z\n"),
        quaternion!()
    ),
};
pub const WRENCH_STAMPED: MsgType = MsgType {
    name: "geometry_msgs/msg/WrenchStamped",
    definition: concat!(
        "std_msgs/Header header\ngeometry_msgs/Wrench wrench\n",
        header_deps!(),
        dep!(
            "geometry_msgs/Wrench",
            "geometry_msgs/Vector3 force\ngeometry_msgs/Vector3 torque\n"
        ),
        vector3!()
    ),
};
pub const JOY: MsgType = MsgType {
    name: "sensor_msgs/msg/Joy",
    definition: concat!(
        "std_msgs/Header header\nfloat32[] axes\nint32[] buttons\n",
        header_deps!()
    ),
};
pub const TF_MESSAGE: MsgType = MsgType {
    name: "tf2_msgs/msg/TFMessage",
    definition: concat!(
        "geometry_msgs/TransformStamped[] transforms\n",
        dep!(
            "geometry_msgs/TransformStamped",
            "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform\n"
        ),
        header_deps!(),
        dep!(
            "geometry_msgs/Transform",
            "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation\n"
        ),
        vector3!(),
        quaternion!()
    ),
};
pub const TWIST_STAMPED: MsgType = MsgType {
    name: "geometry_msgs/msg/TwistStamped",
    definition: concat!(
        "std_msgs/Header header\ngeometry_msgs/Twist twist\n",
        header_deps!(),
        dep!(
            "geometry_msgs/Twist",
            "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular\n"
        ),
        vector3!()
    ),
};
/// CRTK's arm state (crtk_msgs 1.3.0).
pub const OPERATING_STATE: MsgType = MsgType {
    name: "crtk_msgs/msg/OperatingState",
    definition: concat!(
        "std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
        header_deps!()
    ),
};
/// CRTK's stamped string (the `state_command` topic).
pub const STRING_STAMPED: MsgType = MsgType {
    name: "crtk_msgs/msg/StringStamped",
    definition: concat!("std_msgs/Header header\nstring string\n", header_deps!()),
};
pub const STRING: MsgType = MsgType {
    name: "std_msgs/msg/String",
    definition: "string data\n",
};
pub const FLOAT64: MsgType = MsgType {
    name: "std_msgs/msg/Float64",
    definition: "float64 data\n",
};
pub const UINT32: MsgType = MsgType {
    name: "std_msgs/msg/UInt32",
    definition: "uint32 data\n",
};
pub const BOOL: MsgType = MsgType {
    name: "std_msgs/msg/Bool",
    definition: "bool data\n",
};
pub const FLOAT64_MULTI_ARRAY: MsgType = MsgType {
    name: "std_msgs/msg/Float64MultiArray",
    definition: concat!(
        "std_msgs/MultiArrayLayout layout\nfloat64[] data\n",
        multi_array_deps!()
    ),
};
pub const INT64_MULTI_ARRAY: MsgType = MsgType {
    name: "std_msgs/msg/Int64MultiArray",
    definition: concat!(
        "std_msgs/MultiArrayLayout layout\nint64[] data\n",
        multi_array_deps!()
    ),
};

/// `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Stamp {
    pub sec: i32,
    pub nanosec: u32,
}

impl Stamp {
    /// From nanoseconds since the Unix epoch (seconds saturate at `i32::MAX`, year 2038).
    pub fn from_nanos(ns: u64) -> Stamp {
        Stamp {
            sec: (ns / 1_000_000_000).min(i32::MAX as u64) as i32,
            nanosec: (ns % 1_000_000_000) as u32,
        }
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Header<'a> {
    pub stamp: Stamp,
    pub frame_id: &'a str,
}

fn write_header(w: &mut CdrWriter, h: &Header) {
    w.i32(h.stamp.sec);
    w.u32(h.stamp.nanosec);
    w.string(h.frame_id);
}

fn read_header<'a>(r: &mut CdrReader<'a>) -> Result<Header<'a>, CdrError> {
    Ok(Header {
        stamp: Stamp {
            sec: r.i32()?,
            nanosec: r.u32()?,
        },
        frame_id: r.string()?,
    })
}

/// `sensor_msgs/msg/JointState`.
#[derive(Debug, Clone, PartialEq)]
pub struct JointState<'a> {
    pub header: Header<'a>,
    pub name: Vec<&'a str>,
    pub position: Vec<f64>,
    pub velocity: Vec<f64>,
    pub effort: Vec<f64>,
}

/// Append a `JointState` (the arrays borrowed, so a caller with fixed arrays allocates nothing
/// beyond `out`'s growth).
pub fn write_joint_state(
    out: &mut Vec<u8>,
    header: &Header,
    name: &[&str],
    position: &[f64],
    velocity: &[f64],
    effort: &[f64],
) {
    let mut w = CdrWriter::new(out);
    write_header(&mut w, header);
    w.strings(name);
    w.f64s(position);
    w.f64s(velocity);
    w.f64s(effort);
}

pub fn read_joint_state(buf: &[u8]) -> Result<JointState<'_>, CdrError> {
    let mut r = CdrReader::new(buf)?;
    let m = JointState {
        header: read_header(&mut r)?,
        name: r.strings()?,
        position: r.f64s()?,
        velocity: r.f64s()?,
        effort: r.f64s()?,
    };
    r.end()?;
    Ok(m)
}

/// Position, velocity and effort of `N` joints.
pub type Joints<const N: usize> = ([f64; N], [f64; N], [f64; N]);

/// A `JointState` of `N` joints, read without allocating.
pub fn read_joint_state_n<const N: usize>(buf: &[u8]) -> Result<Joints<N>, CdrError> {
    let mut r = CdrReader::new(buf)?;
    read_header(&mut r)?;
    let n = r.count(5)?;
    for _ in 0..n {
        r.string()?;
    }
    let v = (r.f64_array()?, r.f64_array()?, r.f64_array()?);
    r.end()?;
    Ok(v)
}

/// `geometry_msgs/msg/PoseStamped`: position (x, y, z) and orientation (x, y, z, w).
pub fn write_pose_stamped(out: &mut Vec<u8>, header: &Header, p: [f64; 3], q: [f64; 4]) {
    let mut w = CdrWriter::new(out);
    write_header(&mut w, header);
    for v in p.iter().chain(&q) {
        w.f64(*v);
    }
}

pub fn read_pose_stamped(buf: &[u8]) -> Result<(Header<'_>, [f64; 3], [f64; 4]), CdrError> {
    let mut r = CdrReader::new(buf)?;
    let h = read_header(&mut r)?;
    let p = [r.f64()?, r.f64()?, r.f64()?];
    let q = [r.f64()?, r.f64()?, r.f64()?, r.f64()?];
    r.end()?;
    Ok((h, p, q))
}

/// `geometry_msgs/msg/WrenchStamped`: force and torque.
pub fn write_wrench_stamped(out: &mut Vec<u8>, header: &Header, f: [f64; 3], t: [f64; 3]) {
    let mut w = CdrWriter::new(out);
    write_header(&mut w, header);
    for v in f.iter().chain(&t) {
        w.f64(*v);
    }
}

pub fn read_wrench_stamped(buf: &[u8]) -> Result<(Header<'_>, [f64; 3], [f64; 3]), CdrError> {
    let mut r = CdrReader::new(buf)?;
    let h = read_header(&mut r)?;
    let f = [r.f64()?, r.f64()?, r.f64()?];
    let t = [r.f64()?, r.f64()?, r.f64()?];
    r.end()?;
    Ok((h, f, t))
}

/// `geometry_msgs/msg/TwistStamped`: linear and angular velocity.
pub fn write_twist_stamped(out: &mut Vec<u8>, header: &Header, v: [f64; 3], w: [f64; 3]) {
    // The same layout as a wrench: two Vector3 after the header.
    write_wrench_stamped(out, header, v, w)
}

/// `crtk_msgs/msg/OperatingState`.
pub fn write_operating_state(
    out: &mut Vec<u8>,
    header: &Header,
    state: &str,
    is_homed: bool,
    is_busy: bool,
) {
    let mut w = CdrWriter::new(out);
    write_header(&mut w, header);
    w.string(state);
    w.bool(is_homed);
    w.bool(is_busy);
}

pub fn read_operating_state(buf: &[u8]) -> Result<(Header<'_>, &str, bool, bool), CdrError> {
    let mut r = CdrReader::new(buf)?;
    let h = read_header(&mut r)?;
    let v = (h, r.string()?, r.bool()?, r.bool()?);
    r.end()?;
    Ok(v)
}

/// `crtk_msgs/msg/StringStamped`.
pub fn write_string_stamped(out: &mut Vec<u8>, header: &Header, s: &str) {
    let mut w = CdrWriter::new(out);
    write_header(&mut w, header);
    w.string(s);
}

pub fn read_string_stamped(buf: &[u8]) -> Result<(Header<'_>, &str), CdrError> {
    let mut r = CdrReader::new(buf)?;
    let h = read_header(&mut r)?;
    let s = r.string()?;
    r.end()?;
    Ok((h, s))
}

/// A `JointState` command's positions: exactly `N` of them, names ignored, velocity and effort
/// free (CRTK's `servo_jp` fills position only).
pub fn read_joint_positions_n<const N: usize>(buf: &[u8]) -> Result<[f64; N], CdrError> {
    let mut r = CdrReader::new(buf)?;
    read_header(&mut r)?;
    let n = r.count(5)?;
    for _ in 0..n {
        r.string()?;
    }
    let p = r.f64_array()?;
    for _ in 0..2 {
        let n = r.count(8)?;
        for _ in 0..n {
            r.f64()?;
        }
    }
    r.end()?;
    Ok(p)
}

/// `sensor_msgs/msg/Joy`.
pub fn write_joy(out: &mut Vec<u8>, header: &Header, axes: &[f32], buttons: &[i32]) {
    let mut w = CdrWriter::new(out);
    write_header(&mut w, header);
    w.f32s(axes);
    w.i32s(buttons);
}

/// A `Joy`'s `N` buttons (no axes expected), read without allocating.
pub fn read_joy_buttons<const N: usize>(buf: &[u8]) -> Result<[i32; N], CdrError> {
    let mut r = CdrReader::new(buf)?;
    read_header(&mut r)?;
    r.f32_array_empty()?;
    let b = r.i32_array()?;
    r.end()?;
    Ok(b)
}

/// One `geometry_msgs/TransformStamped`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transform<'a> {
    pub header: Header<'a>,
    pub child_frame_id: &'a str,
    pub translation: [f64; 3],
    /// x, y, z, w.
    pub rotation: [f64; 4],
}

/// `tf2_msgs/msg/TFMessage`.
pub fn write_tf(out: &mut Vec<u8>, transforms: &[Transform]) {
    let mut w = CdrWriter::new(out);
    w.count(transforms.len());
    for t in transforms {
        write_header(&mut w, &t.header);
        w.string(t.child_frame_id);
        for v in t.translation.iter().chain(&t.rotation) {
            w.f64(*v);
        }
    }
}

pub fn read_tf(buf: &[u8]) -> Result<Vec<Transform<'_>>, CdrError> {
    let mut r = CdrReader::new(buf)?;
    let n = r.count(12 + 5 + 56)?;
    let mut v = Vec::with_capacity(n);
    for _ in 0..n {
        let header = read_header(&mut r)?;
        let child_frame_id = r.string()?;
        let translation = [r.f64()?, r.f64()?, r.f64()?];
        let rotation = [r.f64()?, r.f64()?, r.f64()?, r.f64()?];
        v.push(Transform {
            header,
            child_frame_id,
            translation,
            rotation,
        });
    }
    r.end()?;
    Ok(v)
}

/// `std_msgs/msg/String`.
pub fn write_string(out: &mut Vec<u8>, s: &str) {
    CdrWriter::new(out).string(s);
}

pub fn read_string(buf: &[u8]) -> Result<&str, CdrError> {
    let mut r = CdrReader::new(buf)?;
    let s = r.string()?;
    r.end()?;
    Ok(s)
}

/// `std_msgs/msg/Float64`.
pub fn write_float64(out: &mut Vec<u8>, v: f64) {
    CdrWriter::new(out).f64(v);
}

pub fn read_float64(buf: &[u8]) -> Result<f64, CdrError> {
    let mut r = CdrReader::new(buf)?;
    let v = r.f64()?;
    r.end()?;
    Ok(v)
}

/// `std_msgs/msg/UInt32`.
pub fn write_uint32(out: &mut Vec<u8>, v: u32) {
    CdrWriter::new(out).u32(v);
}

pub fn read_uint32(buf: &[u8]) -> Result<u32, CdrError> {
    let mut r = CdrReader::new(buf)?;
    let v = r.u32()?;
    r.end()?;
    Ok(v)
}

/// `std_msgs/msg/Bool`.
pub fn write_bool(out: &mut Vec<u8>, v: bool) {
    CdrWriter::new(out).bool(v);
}

pub fn read_bool(buf: &[u8]) -> Result<bool, CdrError> {
    let mut r = CdrReader::new(buf)?;
    let v = r.bool()?;
    r.end()?;
    Ok(v)
}

fn write_layout(w: &mut CdrWriter, label: &str, n: usize) {
    w.count(1);
    w.string(label);
    w.u32(n as u32);
    w.u32(n as u32);
    w.u32(0); // data_offset
}

fn read_layout(r: &mut CdrReader) -> Result<(), CdrError> {
    let dims = r.count(5 + 8)?;
    for _ in 0..dims {
        r.string()?;
        r.u32()?;
        r.u32()?;
    }
    r.u32()?;
    Ok(())
}

/// `std_msgs/msg/Float64MultiArray` of one dimension named `label`.
pub fn write_f64_array(out: &mut Vec<u8>, label: &str, data: &[f64]) {
    let mut w = CdrWriter::new(out);
    write_layout(&mut w, label, data.len());
    w.f64s(data);
}

/// A `Float64MultiArray` of exactly `N` values, read without allocating.
pub fn read_f64_array_n<const N: usize>(buf: &[u8]) -> Result<[f64; N], CdrError> {
    let mut r = CdrReader::new(buf)?;
    read_layout(&mut r)?;
    let v = r.f64_array()?;
    r.end()?;
    Ok(v)
}

/// `std_msgs/msg/Int64MultiArray` of one dimension named `label`.
pub fn write_i64_array(out: &mut Vec<u8>, label: &str, data: &[i64]) {
    let mut w = CdrWriter::new(out);
    write_layout(&mut w, label, data.len());
    w.i64s(data);
}

/// An `Int64MultiArray` of exactly `N` values, read without allocating.
pub fn read_i64_array_n<const N: usize>(buf: &[u8]) -> Result<[i64; N], CdrError> {
    let mut r = CdrReader::new(buf)?;
    read_layout(&mut r)?;
    let v = r.i64_array()?;
    r.end()?;
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(s: &str) -> Vec<u8> {
        let s: String = s.split_whitespace().collect();
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }

    const OMNI: Header = Header {
        stamp: Stamp {
            sec: 1_700_000_000,
            nanosec: 500,
        },
        frame_id: "omni",
    };

    // Vectors made by an independent serializer (rosbags' `serialize_cdr`, ROS 2 Jazzy
    // types), docs/ROS2.md, CDR.
    #[test]
    fn encodings_match_an_independent_serializer_byte_for_byte() {
        let mut out = Vec::new();
        write_joint_state(
            &mut out,
            &OMNI,
            &["waist", "shoulder"],
            &[0.5, -0.25],
            &[1.0, 2.0],
            &[],
        );
        assert_eq!(out, hex("0001000000f15365f4010000050000006f6d6e6900000000020000000600000077616973740000000900000073686f756c6465720000000002000000000000000000e03f000000000000d0bf0200000000000000000000000000f03f000000000000004000000000"));
        let js = read_joint_state(&out).unwrap();
        assert_eq!(js.name, ["waist", "shoulder"]);
        assert_eq!((js.position, js.effort.len()), (vec![0.5, -0.25], 0));

        out.clear();
        write_pose_stamped(&mut out, &OMNI, [1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0]);
        assert_eq!(out, hex("0001000000f15365f4010000050000006f6d6e690000000000000000000000000000f03f00000000000000400000000000000840000000000000000000000000000000000000000000000000000000000000f03f"));
        assert_eq!(read_pose_stamped(&out).unwrap().1, [1.0, 2.0, 3.0]);

        out.clear();
        write_wrench_stamped(&mut out, &OMNI, [1.0, 0.0, 0.0], [0.0, 0.0, 0.5]);
        assert_eq!(out, hex("0001000000f15365f4010000050000006f6d6e690000000000000000000000000000f03f0000000000000000000000000000000000000000000000000000000000000000000000000000e03f"));

        out.clear();
        write_joy(&mut out, &OMNI, &[], &[1]);
        assert_eq!(
            out,
            hex("0001000000f15365f4010000050000006f6d6e6900000000000000000100000001000000")
        );
        assert_eq!(read_joy_buttons::<1>(&out).unwrap(), [1]);

        out.clear();
        write_string(&mut out, "hello");
        assert_eq!(out, hex("000100000600000068656c6c6f00"));
        assert_eq!(read_string(&out).unwrap(), "hello");

        out.clear();
        let h = Header {
            stamp: Stamp { sec: 1, nanosec: 2 },
            frame_id: "",
        };
        write_joint_state(
            &mut out,
            &h,
            &["j1", "j2", "j3"],
            &[0.1, 0.2, 0.3],
            &[],
            &[],
        );
        assert_eq!(out, hex("00010000010000000200000001000000000000000300000003000000 6a3100 00 03000000 6a3200 00 03000000 6a3300 00 03000000 9a9999999999b93f 9a9999999999c93f 333333333333d33f 00000000 00000000"));
        assert_eq!(read_joint_positions_n::<3>(&out).unwrap(), [0.1, 0.2, 0.3]);

        out.clear();
        write_operating_state(&mut out, &OMNI, "ENABLED", true, false);
        assert_eq!(
            out,
            hex("0001000000f15365f4010000050000006f6d6e690000000008000000454e41424c4544000100")
        );
        let (_, state, homed, busy) = read_operating_state(&out).unwrap();
        assert_eq!((state, homed, busy), ("ENABLED", true, false));

        // A twist is laid out as a wrench (two Vector3 after the header).
        let mut twist = Vec::new();
        write_twist_stamped(&mut twist, &OMNI, [1.0, 0.0, 0.0], [0.0, 0.0, 0.5]);
        out.clear();
        write_wrench_stamped(&mut out, &OMNI, [1.0, 0.0, 0.0], [0.0, 0.0, 0.5]);
        assert_eq!(twist, out);
    }

    #[test]
    fn big_endian_messages_are_read_too() {
        // A StringStamped {stamp 1 s 2 ns, frame "", string "enable"} written big-endian by
        // hand: header 00 00 00 00, then each field's bytes most significant first.
        let be = hex("00000000 00000001 00000002 00000001 00 000000 00000007 656e61626c6500");
        let (h, s) = read_string_stamped(&be).unwrap();
        assert_eq!((h.stamp, s), (Stamp { sec: 1, nanosec: 2 }, "enable"));
        let mut le = Vec::new();
        write_string_stamped(&mut le, &h, "enable");
        assert_eq!(read_string_stamped(&le).unwrap(), (h, "enable"));
        assert!(matches!(
            read_string_stamped(&hex("00020000")),
            Err(CdrError::Header { .. })
        ));
    }

    #[test]
    fn every_reader_round_trips_its_writer() {
        let mut out = Vec::new();
        write_f64_array(&mut out, "joint", &[1.5, f64::NAN, -0.0]);
        let v = read_f64_array_n::<3>(&out).unwrap();
        assert_eq!(v[0], 1.5);
        assert!(v[1].is_nan());
        assert!(v[2] == 0.0 && v[2].is_sign_negative());
        out.clear();
        write_i64_array(&mut out, "joint", &[i64::MIN, 0, 7]);
        assert_eq!(read_i64_array_n::<3>(&out).unwrap(), [i64::MIN, 0, 7]);
        for v in [0u32, 7, u32::MAX] {
            out.clear();
            write_uint32(&mut out, v);
            assert_eq!(read_uint32(&out).unwrap(), v);
        }
        out.clear();
        write_bool(&mut out, true);
        assert!(read_bool(&out).unwrap());
        out.clear();
        write_float64(&mut out, 0.1);
        assert_eq!(read_float64(&out).unwrap(), 0.1);
        out.clear();
        let t = Transform {
            header: OMNI,
            child_frame_id: "upper_arm",
            translation: [0.0, 0.1, 0.2],
            rotation: [0.0, 0.0, 0.0, 1.0],
        };
        write_tf(&mut out, &[t, t]);
        assert_eq!(read_tf(&out).unwrap(), [t, t]);
    }

    #[test]
    fn damaged_messages_are_errors_that_say_where() {
        let mut out = Vec::new();
        write_joint_state(&mut out, &OMNI, &["a"], &[1.0], &[], &[]);
        // Every truncation is an error, never a panic.
        for cut in 0..out.len() {
            assert!(read_joint_state(&out[..cut]).is_err(), "cut at {cut}");
        }
        // A count that claims more than the message holds allocates nothing.
        let mut lie = out.clone();
        lie[24..28].copy_from_slice(&u32::MAX.to_le_bytes());
        assert!(matches!(
            read_joint_state(&lie),
            Err(CdrError::Count { at: 24, .. })
        ));
        // An encapsulation that is not plain CDR (here PL_CDR_LE, 00 03).
        let mut other = out.clone();
        other[1] = 3;
        assert!(matches!(
            read_joint_state(&other),
            Err(CdrError::Header { .. })
        ));
        out.extend_from_slice(&[1, 2, 3, 4, 5]);
        assert_eq!(read_joint_state(&out), Err(CdrError::Trailing { extra: 5 }));
    }

    #[test]
    fn schema_texts_name_each_dependency_once() {
        for t in [
            JOINT_STATE,
            POSE_STAMPED,
            WRENCH_STAMPED,
            JOY,
            TF_MESSAGE,
            FLOAT64_MULTI_ARRAY,
            INT64_MULTI_ARRAY,
        ] {
            let deps: Vec<&str> = t
                .definition
                .lines()
                .filter_map(|l| l.strip_prefix("MSG: "))
                .collect();
            let mut unique = deps.clone();
            unique.sort();
            unique.dedup();
            assert_eq!(deps.len(), unique.len(), "{}", t.name);
            // Every non-builtin field type is defined below it.
            for line in t.definition.lines() {
                let ty = line.split_whitespace().next().unwrap_or("");
                let ty = ty.trim_end_matches("[]");
                if ty.contains('/') && !line.starts_with("MSG:") {
                    assert!(deps.contains(&ty), "{}: {ty} not defined", t.name);
                }
            }
        }
    }
}

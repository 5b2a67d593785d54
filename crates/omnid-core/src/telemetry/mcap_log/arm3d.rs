//! The Omni for a 3-D viewer: a URDF written from omnid's own geometry, and the transforms
//! that pose it at joint angles q (docs/MCAP.md, 3-D view). Viewers move a URDF's links from
//! `/tf`, so every joint's transform is published, as `robot_state_publisher` would.
//!
//! Frames: `world` (z up) → `omni_base` (the OpenHaptics frame: x right, y up, z toward the
//! user; a fixed +90° turn about x) → `waist` joint at the shoulder point → `yaw_link` →
//! `shoulder` → `upper_arm` → `elbow` → `lower_arm` → fixed → `stylus_tip`. The joints follow
//! the ROS driver's convention (waist = −q1, shoulder = q2, elbow = q3 − q2), so the URDF's
//! joint angles are what ROS users know.

use crate::omni::kinematics::Geometry;
use crate::ros2::msgs::{Header, Transform};
use std::f64::consts::FRAC_PI_2;

/// Frame names, in chain order: world, base, yaw link, upper arm, lower arm, tip.
const FRAMES: [&str; 6] = [
    "world",
    "omni_base",
    "yaw_link",
    "upper_arm",
    "lower_arm",
    "stylus_tip",
];

/// One joint of the chain: the frames it joins (indices into [`FRAMES`]), origin (m),
/// rotation axis (None: fixed).
struct Joint {
    name: &'static str,
    parent: usize,
    child: usize,
    xyz: [f64; 3],
    axis: Option<[f64; 3]>,
}

fn chain(g: &Geometry) -> [Joint; 5] {
    let mm = 1e-3;
    let joint = |name, parent, xyz, axis| Joint {
        name,
        parent,
        child: parent + 1,
        xyz,
        axis,
    };
    [
        joint("base", 0, [0.0; 3], None),
        joint(
            "waist",
            1,
            [0.0, g.y_offset_mm * mm, -g.z_offset_mm * mm],
            Some([0.0, 1.0, 0.0]),
        ),
        joint("shoulder", 2, [0.0; 3], Some([-1.0, 0.0, 0.0])),
        joint("elbow", 3, [0.0, 0.0, g.l1_mm * mm], Some([-1.0, 0.0, 0.0])),
        joint("tip", 4, [0.0, -g.l2_mm * mm, 0.0], None),
    ]
}

/// The URDF joint angles (waist, shoulder, elbow) for OpenHaptics joint angles `q`.
pub(crate) fn urdf_angles(q: &[f64; 3]) -> [f64; 3] {
    [-q[0], q[1], q[2] - q[1]]
}

/// Quaternion (x, y, z, w) of a turn by `angle` about the unit `axis`.
fn quaternion(axis: [f64; 3], angle: f64) -> [f64; 4] {
    let (s, c) = (angle / 2.0).sin_cos();
    [axis[0] * s, axis[1] * s, axis[2] * s, c]
}

/// One arm drawn: its geometry and its frame names (prefixed `<arm>/` when several arms share
/// a view; `world` is everyone's).
pub(crate) struct Arm3d {
    geometry: Geometry,
    frames: [String; 6],
}

impl Arm3d {
    /// The arm of `geometry`, its frames named `<prefix>/<frame>` (no prefix: `<frame>`).
    pub(crate) fn new(geometry: Geometry, prefix: &str) -> Arm3d {
        let frames = std::array::from_fn(|i| match (i, prefix) {
            (0, _) | (_, "") => FRAMES[i].to_string(),
            _ => format!("{prefix}/{}", FRAMES[i]),
        });
        Arm3d { geometry, frames }
    }

    /// The frame the tip pose and forces are given in (the OpenHaptics frame).
    pub(crate) fn base_frame(&self) -> &str {
        &self.frames[1]
    }

    /// The transforms of every joint at `q`, stamped as `header` (a `tf2_msgs/TFMessage`'s
    /// content).
    pub(crate) fn transforms<'a>(&'a self, q: &[f64; 3], header: Header<'a>) -> [Transform<'a>; 5] {
        let angles = urdf_angles(q);
        let chain = chain(&self.geometry);
        std::array::from_fn(|i| {
            let j = &chain[i];
            let rotation = match (i, j.axis) {
                (0, _) => quaternion([1.0, 0.0, 0.0], FRAC_PI_2),
                (_, Some(axis)) => quaternion(axis, angles[i - 1]),
                (_, None) => [0.0, 0.0, 0.0, 1.0],
            };
            Transform {
                header: Header {
                    frame_id: &self.frames[j.parent],
                    ..header
                },
                child_frame_id: &self.frames[j.child],
                translation: j.xyz,
                rotation,
            }
        })
    }

    /// The arm's URDF, links drawn as cylinders of the real lengths.
    pub(crate) fn urdf(&self) -> String {
        let g = &self.geometry;
        let f = &self.frames;
        let (l1, l2) = (g.l1_mm * 1e-3, g.l2_mm * 1e-3);
        let mut s = String::from("<?xml version=\"1.0\"?>\n<robot name=\"phantom_omni\">\n");
        s += "  <material name=\"grey\"><color rgba=\"0.6 0.6 0.65 1\"/></material>\n";
        s += "  <material name=\"blue\"><color rgba=\"0.2 0.4 0.8 1\"/></material>\n";
        s += &format!("  <link name=\"{}\"/>\n", f[0]);
        s += &format!(
            "  <link name=\"{}\"><visual><origin xyz=\"0 {:.5} {:.5}\"/><geometry><box \
             size=\"0.16 0.03 0.16\"/></geometry><material name=\"grey\"/></visual></link>\n",
            f[1],
            g.y_offset_mm * 1e-3 - 0.07,
            -g.z_offset_mm * 1e-3
        );
        s += &format!(
            "  <link name=\"{}\"><visual><origin xyz=\"0 -0.03 0\" rpy=\"1.5708 0 0\"/>\
             <geometry><cylinder radius=\"0.03\" length=\"0.06\"/></geometry>\
             <material name=\"grey\"/></visual></link>\n",
            f[2]
        );
        s += &format!(
            "  <link name=\"{}\"><visual><origin xyz=\"0 0 {:.5}\"/><geometry><cylinder \
             radius=\"0.008\" length=\"{l1:.5}\"/></geometry><material name=\"blue\"/>\
             </visual></link>\n",
            f[3],
            l1 / 2.0
        );
        s += &format!(
            "  <link name=\"{}\"><visual><origin xyz=\"0 {:.5} 0\" rpy=\"1.5708 0 0\"/>\
             <geometry><cylinder radius=\"0.006\" length=\"{l2:.5}\"/></geometry>\
             <material name=\"blue\"/></visual></link>\n",
            f[4],
            -l2 / 2.0
        );
        s += &format!(
            "  <link name=\"{}\"><visual><geometry><sphere radius=\"0.006\"/></geometry>\
             <material name=\"grey\"/></visual></link>\n",
            f[5]
        );
        for j in chain(g) {
            let (kind, axis) = match j.axis {
                Some(a) => (
                    "revolute",
                    format!("<axis xyz=\"{} {} {}\"/>", a[0], a[1], a[2]),
                ),
                None => ("fixed", String::new()),
            };
            let rpy = if j.name == "base" {
                "1.5708 0 0"
            } else {
                "0 0 0"
            };
            let limit = if j.axis.is_some() {
                "<limit lower=\"-3.1416\" upper=\"3.1416\" effort=\"1\" velocity=\"10\"/>"
            } else {
                ""
            };
            s += &format!(
                "  <joint name=\"{}\" type=\"{kind}\"><parent link=\"{}\"/><child link=\"{}\"/>\
                 <origin xyz=\"{:.5} {:.5} {:.5}\" rpy=\"{rpy}\"/>{axis}{limit}</joint>\n",
                j.name, f[j.parent], f[j.child], j.xyz[0], j.xyz[1], j.xyz[2]
            );
        }
        s += "</robot>\n";
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ros2::msgs::Stamp;
    use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

    /// The tip found by composing the published transforms is the tip the kinematics give
    /// (an independent path: `tip_position_mm` is the closed form of docs/DESIGN.md §4.1).
    #[test]
    fn composed_transforms_put_the_tip_where_the_kinematics_do() {
        let g = Geometry::default();
        let header = Header {
            stamp: Stamp::default(),
            frame_id: "",
        };
        let arm = Arm3d::new(g, "");
        for q in [[0.0, 0.0, 0.0], [0.4, -0.3, 0.9], [-1.0, 0.7, -0.2]] {
            let tf = arm.transforms(&q, header);
            // Skip `world → omni_base`: the kinematics are in the OpenHaptics frame.
            let mut pose = Isometry3::identity();
            for t in &tf[1..] {
                let r = t.rotation;
                pose *= Isometry3::from_parts(
                    Translation3::from(Vector3::from(t.translation)),
                    UnitQuaternion::from_quaternion(Quaternion::new(r[3], r[0], r[1], r[2])),
                );
            }
            let tip = crate::omni::kinematics::tip_position_mm(&g, &q.into()) * 1e-3;
            let p = pose.translation.vector;
            assert!((p - tip).norm() < 1e-12, "q {q:?}: {p} vs {tip}");
        }
        // The chain the transforms name is the URDF's, with or without a prefix.
        for arm in [arm, Arm3d::new(g, "left")] {
            let u = arm.urdf();
            for t in arm.transforms(&[0.0; 3], header) {
                let joint = format!(
                    "<parent link=\"{}\"/><child link=\"{}\"/>",
                    t.header.frame_id, t.child_frame_id
                );
                assert!(u.contains(&joint), "{joint} not in the URDF");
            }
        }
        assert_eq!(Arm3d::new(g, "left").base_frame(), "left/omni_base");
    }
}
